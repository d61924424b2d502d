// Round trips of the exchange formats: PCD (binary, ASCII, PCL's conventions), Draco .drc (lossless
// and quantised; Debian's draco_decoder reads ours), COLMAP text models, OpenCV and ROS camera files.
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <random>
#include <sstream>
#include <string>

#include <gtest/gtest.h>

#include "core/io/calibration_io.h"
#include "core/io/camera_info_io.h"
#include "core/io/colmap_io.h"
#include "core/io/draco_io.h"
#include "core/io/pcd_io.h"
#include "core/io/ply_io.h"

namespace prism {
namespace {
namespace fs = std::filesystem;

class FormatsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("prism_formats_test_" + std::to_string(getpid()) + "_" +
                                        ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override {
    if (!HasFailure()) fs::remove_all(dir_);
  }
  std::string P(const std::string& name) const { return (dir_ / name).string(); }
  static void Write(const std::string& path, const std::string& text) { std::ofstream(path) << text; }
  fs::path dir_;
};

// A seeded random cloud on a 0.3 m sphere with unit normals and colours.
PointCloud RandomCloud(size_t n, bool normals = true, bool colors = true) {
  std::mt19937 rng(7);
  std::normal_distribution<float> g(0.f, 1.f);
  std::uniform_int_distribution<int> c(0, 255);
  PointCloud cloud;
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Vector3f d = Eigen::Vector3f(g(rng), g(rng), g(rng)).normalized();
    cloud.positions.push_back(Eigen::Vector3f(0.1f, -0.2f, 1.5f) + 0.3f * d);
    if (normals) cloud.normals.push_back(d);
    if (colors) cloud.colors.emplace_back(c(rng), c(rng), c(rng));
  }
  return cloud;
}

void ExpectSameCloud(const PointCloud& a, const PointCloud& b, float position_tolerance, float normal_tolerance) {
  ASSERT_EQ(a.size(), b.size());
  ASSERT_EQ(a.HasNormals(), b.HasNormals());
  ASSERT_EQ(a.HasColors(), b.HasColors());
  float max_position = 0, max_normal = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    max_position = std::max(max_position, (a.positions[i] - b.positions[i]).norm());
    if (a.HasNormals()) max_normal = std::max(max_normal, (a.normals[i] - b.normals[i]).norm());
    if (a.HasColors()) {
      ASSERT_EQ(a.colors[i], b.colors[i]) << "point " << i;
    }
  }
  EXPECT_LE(max_position, position_tolerance);
  EXPECT_LE(max_normal, normal_tolerance);
}

TEST_F(FormatsTest, PcdBinaryAndAsciiRoundTripsExactly) {
  const PointCloud cloud = RandomCloud(1000);
  for (PcdEncoding encoding : {PcdEncoding::kBinary, PcdEncoding::kAscii}) {
    ASSERT_TRUE(WritePointCloudPcd(P("c.pcd"), cloud, encoding).ok());
    StatusOr<PointCloud> back = ReadPointCloudPcd(P("c.pcd"));
    ASSERT_TRUE(back.ok()) << back.status();
    // ASCII writes 9 significant digits: float positions and normals come back bit-exact.
    ExpectSameCloud(cloud, *back, 0.f, 0.f);
  }
  const PointCloud bare = RandomCloud(10, false, false);
  ASSERT_TRUE(WritePointCloudPcd(P("bare.pcd"), bare).ok());
  StatusOr<PointCloud> back = ReadPointCloudPcd(P("bare.pcd"));
  ASSERT_TRUE(back.ok()) << back.status();
  ExpectSameCloud(bare, *back, 0.f, 0.f);
}

TEST_F(FormatsTest, PcdReadsPclConventionsAndRejectsBrokenFiles) {
  // As PCL writes an ASCII PointXYZRGB: rgb is TYPE F, but the value is the packed colour as an integer;
  // extra fields (here intensity with COUNT 2) are skipped.
  Write(P("pcl.pcd"),
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z rgb intensity\nSIZE 4 4 4 4 4\n"
        "TYPE F F F F F\nCOUNT 1 1 1 1 2\nWIDTH 2\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n"
        "1 2 3 16711680 0.5 0.5\n-1.5 0 2.25 65280 1 1\n");
  StatusOr<PointCloud> c = ReadPointCloudPcd(P("pcl.pcd"));
  ASSERT_TRUE(c.ok()) << c.status();
  ASSERT_EQ(c->size(), 2u);
  EXPECT_EQ(c->positions[1], Eigen::Vector3f(-1.5f, 0.f, 2.25f));
  using Rgb = Eigen::Matrix<uint8_t, 3, 1>;
  EXPECT_EQ(c->colors[0], Rgb(255, 0, 0));
  EXPECT_EQ(c->colors[1], Rgb(0, 255, 0));
  EXPECT_FALSE(c->HasNormals());

  ASSERT_TRUE(WritePointCloudPcd(P("t.pcd"), RandomCloud(100)).ok());
  fs::resize_file(P("t.pcd"), fs::file_size(P("t.pcd")) - 10);
  EXPECT_EQ(ReadPointCloudPcd(P("t.pcd")).status().code(), StatusCode::kDataLoss);
  Write(P("noxyz.pcd"), "VERSION 0.7\nFIELDS a b\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nWIDTH 1\nPOINTS 1\nDATA ascii\n1 2\n");
  EXPECT_EQ(ReadPointCloudPcd(P("noxyz.pcd")).status().code(), StatusCode::kInvalidArgument);
  Write(P("comp.pcd"),
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nPOINTS 1\nDATA binary_compressed\n");
  EXPECT_NE(ReadPointCloudPcd(P("comp.pcd")).status().message().find("binary_compressed"), std::string::npos);
  Write(P("badsize.pcd"),
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nPOINTS 1\nDATA ascii\n");
  EXPECT_EQ(ReadPointCloudPcd(P("badsize.pcd")).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(ReadPointCloudPcd(P("missing.pcd")).status().code(), StatusCode::kNotFound);
}

TEST_F(FormatsTest, DracoLosslessAndQuantisedRoundTrips) {
  const PointCloud cloud = RandomCloud(2000);
  DracoFileOptions lossless;
  lossless.position_bits = 0;
  lossless.normal_bits = 0;
  ASSERT_TRUE(WritePointCloudDraco(P("lossless.drc"), cloud, lossless).ok());
  StatusOr<PointCloud> back = ReadPointCloudDraco(P("lossless.drc"));
  ASSERT_TRUE(back.ok()) << back.status();
  ExpectSameCloud(cloud, *back, 0.f, 0.f);

  ASSERT_TRUE(WritePointCloudDraco(P("q.drc"), cloud).ok());  // 14-bit positions, 10-bit normals
  back = ReadPointCloudDraco(P("q.drc"));
  ASSERT_TRUE(back.ok()) << back.status();
  // The bounding box is 0.6 m: a 14-bit step is 0.6 / 16383 m per axis.
  const float max_position_error_m = 0.6f / 16383.f * std::sqrt(3.f);
  ExpectSameCloud(cloud, *back, max_position_error_m, /*max_normal_error=*/0.01f);
  EXPECT_LT(fs::file_size(P("q.drc")), fs::file_size(P("lossless.drc")) / 2);

  DracoFileOptions kd;
  kd.keep_order = false;
  ASSERT_TRUE(WritePointCloudDraco(P("kd.drc"), cloud, kd).ok());
  back = ReadPointCloudDraco(P("kd.drc"));
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->size(), cloud.size());

  if (access("/usr/bin/draco_decoder", X_OK) == 0) {
    const std::string command =
        "/usr/bin/draco_decoder -i " + P("q.drc") + " -o " + P("decoded.ply") + " > /dev/null 2>&1";
    ASSERT_EQ(std::system(command.c_str()), 0);
    StatusOr<PointCloud> decoded = ReadPointCloudPly(P("decoded.ply"));
    ASSERT_TRUE(decoded.ok()) << decoded.status();
    EXPECT_EQ(decoded->size(), cloud.size());
  }
  Write(P("bad.drc"), "DRACO but not really");
  EXPECT_EQ(ReadPointCloudDraco(P("bad.drc")).status().code(), StatusCode::kDataLoss);
  DracoFileOptions bad;
  bad.position_bits = 31;
  EXPECT_EQ(WritePointCloudDraco(P("x.drc"), cloud, bad).code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(WritePointCloudDraco(P("x.drc"), PointCloud()).code(), StatusCode::kInvalidArgument);
}

TEST_F(FormatsTest, ColmapTextRoundTripWithPixelConvention) {
  ColmapModel model;
  PinholeCamera pinhole;
  pinhole.width = 512;
  pinhole.height = 384;
  pinhole.fx = 500;
  pinhole.fy = 510;
  pinhole.cx = 255.5;
  pinhole.cy = 191.5;
  PinholeCamera opencv = pinhole;
  opencv.distortion = {0.1, -0.05, 0.001, -0.002, 0};
  PinholeCamera full = opencv;
  full.distortion[4] = 0.01;
  model.cameras = {{1, pinhole}, {2, opencv}, {3, full}};
  for (uint32_t i = 1; i <= 5; ++i) {
    ColmapImage im;
    im.image_id = i;
    im.camera_id = 1 + (i % 3);
    im.name = "rgb/" + std::to_string(1000 + i) + ".png";
    im.cam_from_world = Rigid3d(Eigen::Quaterniond(Eigen::AngleAxisd(0.1 * i, Eigen::Vector3d(1, 2, 3).normalized())),
                                Eigen::Vector3d(0.1 * i, -0.2, 0.3 * i));
    model.images.push_back(im);
  }
  model.points = RandomCloud(50, /*normals=*/false);
  ASSERT_TRUE(WriteColmapText(P("sparse"), model).ok());

  // COLMAP's principal point is 0.5 px further (pixel centres at +0.5).
  std::ifstream cameras(P("sparse/cameras.txt"));
  std::stringstream text;
  text << cameras.rdbuf();
  EXPECT_NE(text.str().find("1 PINHOLE 512 384 500 510 256 192"), std::string::npos) << text.str();
  EXPECT_NE(text.str().find("3 FULL_OPENCV"), std::string::npos) << text.str();

  StatusOr<ColmapModel> back = ReadColmapText(P("sparse"));
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_EQ(back->cameras.size(), 3u);
  for (const auto& [id, c] : model.cameras) {
    const PinholeCamera& b = back->cameras.at(id);
    EXPECT_EQ(b.width, c.width);
    EXPECT_DOUBLE_EQ(b.cx, c.cx);
    EXPECT_DOUBLE_EQ(b.cy, c.cy);
    EXPECT_DOUBLE_EQ(b.fy, c.fy);
    for (int k = 0; k < 5; ++k) EXPECT_DOUBLE_EQ(b.distortion[k], c.distortion[k]) << "camera " << id;
  }
  ASSERT_EQ(back->images.size(), model.images.size());
  for (size_t i = 0; i < model.images.size(); ++i) {
    EXPECT_EQ(back->images[i].name, model.images[i].name);
    EXPECT_EQ(back->images[i].camera_id, model.images[i].camera_id);
    EXPECT_LT((back->images[i].cam_from_world.translation - model.images[i].cam_from_world.translation).norm(), 1e-12);
    EXPECT_LT(back->images[i].cam_from_world.rotation.angularDistance(model.images[i].cam_from_world.rotation), 1e-12);
  }
  ExpectSameCloud(model.points, back->points, 1e-6f, 0.f);

  ColmapModel bad = model;
  bad.images[0].name = "with space.png";
  EXPECT_EQ(WriteColmapText(P("bad"), bad).code(), StatusCode::kInvalidArgument);
  bad = model;
  bad.images[1].camera_id = 9;
  EXPECT_EQ(WriteColmapText(P("bad"), bad).code(), StatusCode::kInvalidArgument);
  bad = model;
  bad.images[1].image_id = bad.images[0].image_id;
  EXPECT_EQ(WriteColmapText(P("bad"), bad).code(), StatusCode::kInvalidArgument);
}

// DSO's and LSD-SLAM's camera.txt: absolute RadTan (EuRoC's cam0 as DSO users write it), relative
// Pinhole (DSO's convention: scaled by the image size, centre shifted by half a pixel), RadTan without
// the model name, and what Prism's model cannot take.
TEST_F(FormatsTest, DsoAndLsdSlamCameraTxt) {
  Write(P("euroc.txt"),
        "RadTan 458.654 457.296 367.215 248.375 -0.28340811 0.07395907 0.00019359 1.76187114e-05\n752 480\ncrop\n"
        "640 480\n");
  StatusOr<PinholeCamera> euroc = ReadCameraIntrinsics(P("euroc.txt"));
  ASSERT_TRUE(euroc.ok()) << euroc.status();
  EXPECT_EQ(euroc->width, 752);
  EXPECT_EQ(euroc->height, 480);
  EXPECT_DOUBLE_EQ(euroc->fx, 458.654);
  EXPECT_DOUBLE_EQ(euroc->cy, 248.375);
  EXPECT_DOUBLE_EQ(euroc->distortion[0], -0.28340811);
  EXPECT_DOUBLE_EQ(euroc->distortion[3], 1.76187114e-05);
  EXPECT_DOUBLE_EQ(euroc->distortion[4], 0.0);

  Write(P("relative.txt"), "Pinhole 0.5 0.625 0.5 0.5 0\n640 480\nnone\n640 480\n");
  StatusOr<PinholeCamera> rel = ReadCameraIntrinsics(P("relative.txt"));
  ASSERT_TRUE(rel.ok()) << rel.status();
  EXPECT_DOUBLE_EQ(rel->fx, 320.0);
  EXPECT_DOUBLE_EQ(rel->fy, 300.0);
  EXPECT_DOUBLE_EQ(rel->cx, 319.5);
  EXPECT_DOUBLE_EQ(rel->cy, 239.5);
  EXPECT_FALSE(rel->HasDistortion());

  Write(P("unnamed.txt"), "\n  400 400 320 240 0.1 -0.05 0.001 0.002\n640 480\n");
  StatusOr<PinholeCamera> unnamed = ReadDsoCameraTxt(P("unnamed.txt"));
  ASSERT_TRUE(unnamed.ok()) << unnamed.status();
  EXPECT_DOUBLE_EQ(unnamed->distortion[1], -0.05);

  const std::pair<std::string, std::string> bad[] = {
      {"0.349 0.549 0.5 0.5 0.88\n640 480\n", "FOV camera model is not Prism's"},  // TUM monoVO's ATAN
      {"KannalaBrandt 400 400 320 240 0.1 0.01 0 0\n640 480\n", "KannalaBrandt"},
      {"RadTan 400 400 320 240 0.1\n640 480\n", "the RadTan model has 8 numbers, got 5"},
      {"RadTan 400 400 320 240 0.1 0 0 0\n640\n", ":2: expected 'width height'"},
      {"RadTan 400 400 320 240 0.1 0 0 0\n", "needs the intrinsics line and the 'width height' line"},
      {"Weird 1 2 3\n640 480\n", "unknown camera model"},
  };
  for (const auto& [text, expect] : bad) {
    Write(P("bad.txt"), text);
    StatusOr<PinholeCamera> c = ReadCameraIntrinsics(P("bad.txt"));
    EXPECT_EQ(c.status().code(), StatusCode::kInvalidArgument) << text;
    EXPECT_NE(c.status().message().find(expect), std::string::npos) << c.status();
  }
}

TEST_F(FormatsTest, RosCameraInfoAndOpenCvCalibrationFiles) {
  // As camera_calibration_parsers writes it (ROS wiki example values).
  Write(P("ros.yaml"),
        "image_width: 640\nimage_height: 480\ncamera_name: narrow_stereo\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
        "  data: [430.215550, 0.000000, 306.691343, 0.000000, 430.531693, 227.224800, 0.000000, 0.000000, 1.000000]\n"
        "distortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n"
        "  data: [-0.337586, 0.111014, -0.000599, 0.000116, 0.000000]\nrectification_matrix:\n  rows: 3\n  cols: 3\n"
        "  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\nprojection_matrix:\n  rows: 3\n  cols: 4\n"
        "  data: [326.2, 0, 302.6, 0, 0, 380.3, 224.7, 0, 0, 0, 1, 0]\n");
  StatusOr<PinholeCamera> ros = ReadRosCameraInfoYaml(P("ros.yaml"));
  ASSERT_TRUE(ros.ok()) << ros.status();
  EXPECT_EQ(ros->width, 640);
  EXPECT_EQ(ros->height, 480);
  EXPECT_DOUBLE_EQ(ros->fx, 430.215550);
  EXPECT_DOUBLE_EQ(ros->cy, 227.224800);
  EXPECT_DOUBLE_EQ(ros->distortion[0], -0.337586);
  EXPECT_DOUBLE_EQ(ros->distortion[3], 0.000116);

  // As OpenCV's calibration sample writes it (FileStorage, opencv-matrix nodes).
  Write(P("opencv.yaml"),
        "%YAML:1.0\n---\ncalibration_time: \"Sat 21 Nov 2026\"\nimage_width: 1280\nimage_height: 720\n"
        "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        "   data: [ 9.1e+02, 0., 6.395e+02, 0., 9.12e+02, 3.595e+02, 0., 0., 1. ]\n"
        "distortion_coefficients: !!opencv-matrix\n   rows: 5\n   cols: 1\n   dt: d\n"
        "   data: [ 0.05, -0.1, 0.001, 0.002, 0.03 ]\navg_reprojection_error: 0.21\n");
  StatusOr<PinholeCamera> opencv = ReadOpenCvCameraYaml(P("opencv.yaml"));
  ASSERT_TRUE(opencv.ok()) << opencv.status();
  EXPECT_EQ(opencv->width, 1280);
  EXPECT_DOUBLE_EQ(opencv->fy, 912.0);
  EXPECT_DOUBLE_EQ(opencv->cx, 639.5);
  EXPECT_DOUBLE_EQ(opencv->distortion[4], 0.03);

  // Writers round-trip, and the auto-detecting reader tells the files apart.
  ASSERT_TRUE(WriteRosCameraInfoYaml(P("ros_out.yaml"), *opencv).ok());
  ASSERT_TRUE(WriteOpenCvCameraYaml(P("opencv_out.yaml"), *ros).ok());
  for (const auto& [path, expected] :
       {std::make_pair(P("ros_out.yaml"), *opencv), std::make_pair(P("opencv_out.yaml"), *ros),
        std::make_pair(P("ros.yaml"), *ros), std::make_pair(P("opencv.yaml"), *opencv)}) {
    StatusOr<PinholeCamera> c = ReadCameraIntrinsics(path);
    ASSERT_TRUE(c.ok()) << path << ": " << c.status();
    EXPECT_EQ(c->width, expected.width) << path;
    EXPECT_DOUBLE_EQ(c->fx, expected.fx) << path;
    EXPECT_DOUBLE_EQ(c->cy, expected.cy) << path;
    for (int k = 0; k < 5; ++k) EXPECT_DOUBLE_EQ(c->distortion[k], expected.distortion[k]) << path;
  }
  // Prism's own camera.yaml is recognised too.
  RigCalibration rig;
  rig.camera = *ros;
  for (int l = 0; l < 3; ++l) rig.lights[l].name = l == 0 ? "red" : l == 1 ? "green" : "blue";
  rig.lights[0].position_in_camera = Eigen::Vector3d(-0.2, 0, 0);
  rig.lights[1].position_in_camera = Eigen::Vector3d(0.2, 0, 0);
  rig.lights[2].position_in_camera = Eigen::Vector3d(0, -0.2, 0);
  ASSERT_TRUE(WriteCalibrationYaml(P("camera.yaml"), rig).ok());
  StatusOr<PinholeCamera> prism = ReadCameraIntrinsics(P("camera.yaml"));
  ASSERT_TRUE(prism.ok()) << prism.status();
  EXPECT_DOUBLE_EQ(prism->fx, ros->fx);

  // What Prism's model cannot represent is refused with the reason.
  Write(P("rational.yaml"),
        "image_width: 640\nimage_height: 480\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
        "  data: [400, 0, 320, 0, 400, 240, 0, 0, 1]\ndistortion_model: rational_polynomial\n"
        "distortion_coefficients:\n  rows: 1\n  cols: 8\n  data: [0.1, 0.01, 0, 0, 0.001, 0.2, 0, 0]\n");
  StatusOr<PinholeCamera> rational = ReadRosCameraInfoYaml(P("rational.yaml"));
  EXPECT_EQ(rational.status().code(), StatusCode::kInvalidArgument);
  EXPECT_NE(rational.status().message().find("coefficient 5"), std::string::npos) << rational.status();
  Write(P("fisheye.yaml"),
        "image_width: 640\nimage_height: 480\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
        "  data: [400, 0, 320, 0, 400, 240, 0, 0, 1]\ndistortion_model: equidistant\n"
        "distortion_coefficients:\n  rows: 1\n  cols: 4\n  data: [0.1, 0.01, 0, 0]\n");
  EXPECT_NE(ReadRosCameraInfoYaml(P("fisheye.yaml")).status().message().find("equidistant"), std::string::npos);
  Write(P("skew.yaml"),
        "image_width: 640\nimage_height: 480\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
        "  data: [400, 3, 320, 0, 400, 240, 0, 0, 1]\n");
  EXPECT_EQ(ReadRosCameraInfoYaml(P("skew.yaml")).status().code(), StatusCode::kInvalidArgument);
  Write(P("other.yaml"), "%YAML:1.0\n---\nfoo: 1\n");
  EXPECT_EQ(ReadCameraIntrinsics(P("other.yaml")).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(ReadCameraIntrinsics(P("missing.yaml")).status().code(), StatusCode::kNotFound);
}

}  // namespace
}  // namespace prism
