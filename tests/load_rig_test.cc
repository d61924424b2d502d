// The SDK's LoadRig (client-sdk/src/rig_yaml.cc, yaml-cpp) reads camera.yaml as core/io's
// ReadCalibrationYaml does, and refuses the same malformed files with a message naming the field.
#include <prism/client/client.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>

#include <gtest/gtest.h>

#include "core/io/calibration_io.h"
#include "tools/client_rig.h"

namespace prism {
namespace {

namespace fs = std::filesystem;

class LoadRigTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("prism_load_rig_test_" + std::to_string(getpid()));
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::string Write(const std::string& name, const std::string& text) const {
    const std::string path = (dir_ / name).string();
    std::ofstream(path) << text;
    return path;
  }
  fs::path dir_;
};

RigCalibration ExampleCalibration() {
  RigCalibration c;
  c.camera.width = 640;
  c.camera.height = 480;
  c.camera.fx = 520.5;
  c.camera.fy = 521.25;
  c.camera.cx = 319.5;
  c.camera.cy = 241.0;
  c.camera.distortion = {-0.25, 0.08, 0.001, -0.002, 0.01};
  const char* names[3] = {"red", "green", "blue"};
  for (int l = 0; l < 3; ++l) {
    c.lights[l].name = names[l];
    c.lights[l].position_in_camera = Eigen::Vector3d(0.1 * (l - 1), 0.05 * l, -0.01);
    c.lights[l].color = Eigen::Vector3d::Unit(l);
    c.lights[l].intensity = 0.1 + 0.01 * l;
  }
  c.lights[2].type = LightType::kDirectional;
  c.lights[2].direction_in_camera = Eigen::Vector3d(0, -0.6, -0.8);
  c.crosstalk << 1, 0.12, 0.02, 0.1, 1, 0.14, 0.03, 0.12, 1;
  return c;
}

void ExpectSameRig(const client::Rig& a, const client::Rig& b) {
  EXPECT_EQ(a.camera.width, b.camera.width);
  EXPECT_EQ(a.camera.height, b.camera.height);
  EXPECT_DOUBLE_EQ(a.camera.fx, b.camera.fx);
  EXPECT_DOUBLE_EQ(a.camera.fy, b.camera.fy);
  EXPECT_DOUBLE_EQ(a.camera.cx, b.camera.cx);
  EXPECT_DOUBLE_EQ(a.camera.cy, b.camera.cy);
  EXPECT_EQ(a.camera.distortion, b.camera.distortion);
  for (int l = 0; l < 3; ++l) {
    EXPECT_EQ(a.lights[l].name, b.lights[l].name);
    EXPECT_EQ(a.lights[l].directional, b.lights[l].directional);
    EXPECT_EQ(a.lights[l].position_in_camera, b.lights[l].position_in_camera);
    EXPECT_EQ(a.lights[l].direction_in_camera, b.lights[l].direction_in_camera);
    EXPECT_EQ(a.lights[l].color, b.lights[l].color);
    EXPECT_DOUBLE_EQ(a.lights[l].intensity, b.lights[l].intensity);
  }
  EXPECT_EQ(a.crosstalk, b.crosstalk);
}

TEST_F(LoadRigTest, ReadsWhatCoreWritesAsCoreReadsIt) {
  const std::string path = (dir_ / "camera.yaml").string();
  ASSERT_TRUE(WriteCalibrationYaml(path, ExampleCalibration()).ok());
  StatusOr<RigCalibration> core = ReadCalibrationYaml(path);
  ASSERT_TRUE(core.ok()) << core.status();
  client::Rig rig;
  const client::Status s = client::LoadRig(path, &rig);
  ASSERT_TRUE(s.ok()) << s.ToString();
  ExpectSameRig(rig, ToClientRig(*core));
}

TEST_F(LoadRigTest, OptionalFieldsTakeCoresDefaults) {
  // No distortion, no crosstalk, lights without type, direction or color.
  const std::string path = Write("minimal.yaml",
                                 "%YAML:1.0\n---\nwidth: 320\nheight: 240\nfx: 300.\nfy: 300.\ncx: 159.5\ncy: 119.5\n"
                                 "lights:\n"
                                 "   - { name: red, position: [ -0.2, 0., 0. ], intensity: 0.1 }\n"
                                 "   - { name: green, position: [ 0.2, 0., 0. ], intensity: 0.1 }\n"
                                 "   - { name: blue, position: [ 0., -0.2, 0. ], intensity: 0.1 }\n");
  StatusOr<RigCalibration> core = ReadCalibrationYaml(path);
  ASSERT_TRUE(core.ok()) << core.status();
  client::Rig rig;
  ASSERT_TRUE(client::LoadRig(path, &rig).ok());
  ExpectSameRig(rig, ToClientRig(*core));
}

TEST_F(LoadRigTest, MalformedFilesAreRefusedNamingTheField) {
  const std::string head = "%YAML:1.0\n---\nwidth: 320\nheight: 240\nfx: 300.\nfy: 300.\ncx: 159.5\ncy: 119.5\n";
  const std::string lights =
      "lights:\n   - { name: red, position: [ -0.2, 0., 0. ], intensity: 0.1 }\n"
      "   - { name: green, position: [ 0.2, 0., 0. ], intensity: 0.1 }\n"
      "   - { name: blue, position: [ 0., -0.2, 0. ], intensity: 0.1 }\n";
  struct Case {
    std::string name, text, needle;
  };
  const Case cases[] = {
      {"no_lights", head, "lights"},
      {"two_lights", head + "lights:\n   - { name: red }\n   - { name: green }\n", "3 entries"},
      {"no_fx", "%YAML:1.0\n---\nwidth: 320\nheight: 240\nfy: 300.\ncx: 1.\ncy: 1.\n" + lights, "fx"},
      {"zero_size", "%YAML:1.0\n---\nwidth: 0\nheight: 240\nfx: 1.\nfy: 1.\ncx: 1.\ncy: 1.\n" + lights, "width"},
      {"bad_type", head + "lights:\n   - { name: red, type: spot }\n   - { name: g }\n   - { name: b }\n", "spot"},
      {"short_vector", head + "lights:\n   - { name: red, position: [ 1., 2. ] }\n   - { name: g }\n   - { name: b }\n",
       "3-vector"},
      {"singular_crosstalk",
       head + lights +
           "crosstalk: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1., 1., 1., 1., 1., 1., 0., 0., "
           "1. ]\n",
       "invertible"},
      {"four_distortion",
       head + lights + "distortion: !!opencv-matrix\n   rows: 1\n   cols: 4\n   dt: d\n   data: [ 0., 0., 0., 0. ]\n",
       "distortion"},
      {"not_yaml", "this is not: [ yaml\n", "calibration"},
  };
  for (const Case& c : cases) {
    client::Rig rig;
    const client::Status s = client::LoadRig(Write(c.name + ".yaml", c.text), &rig);
    EXPECT_EQ(s.code, client::Code::kInvalidArgument) << c.name << ": " << s.ToString();
    EXPECT_NE(s.message.find(c.needle), std::string::npos) << c.name << ": " << s.message;
    EXPECT_FALSE(ReadCalibrationYaml((dir_ / (c.name + ".yaml")).string()).ok()) << c.name << ": core accepts it";
  }
  client::Rig rig;
  const client::Status missing = client::LoadRig((dir_ / "absent.yaml").string(), &rig);
  EXPECT_EQ(missing.code, client::Code::kNotFound) << missing.ToString();
}

}  // namespace
}  // namespace prism
