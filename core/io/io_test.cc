#include <filesystem>
#include <fstream>
#include <random>

#include <gtest/gtest.h>

#include "core/io/calibration_io.h"
#include "core/io/image_io.h"
#include "core/io/ply_io.h"
#include "core/io/sequence.h"
#include "core/io/trajectory_io.h"

namespace prism {
namespace {
namespace fs = std::filesystem;

class IoTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("prism_io_test_" + std::to_string(::getpid()) + "_" +
                                        ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
    rng_.seed(42);
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::string P(const std::string& name) const { return (dir_ / name).string(); }

  fs::path dir_;
  std::mt19937 rng_;
};

RigCalibration TestCalibration() {
  RigCalibration c;
  c.camera = PinholeCamera::FromFov(64, 48, 60);
  c.camera.distortion = {0.01, -0.002, 0.0005, 0.0, 0.0001};
  c.lights[0] = {"red", LightType::kPoint, {-0.1, 0.05, 0}, {0, 0, -1}, {1, 0, 0}, 0.3};
  c.lights[1] = {"green", LightType::kPoint, {0.1, 0.05, 0}, {0, 0, -1}, {0, 1, 0}, 0.25};
  c.lights[2] = {"blue", LightType::kDirectional, {0, 0, 0}, Eigen::Vector3d(0.1, -0.3, -1).normalized(), {0, 0, 1},
                 0.5};
  c.crosstalk << 1.0, 0.12, 0.03, 0.1, 1.0, 0.1, 0.02, 0.15, 1.0;
  return c;
}

TEST_F(IoTest, TumTrajectoryRoundTrip) {
  Trajectory traj;
  std::normal_distribution<double> n(0, 1);
  for (int i = 0; i < 20; ++i)
    traj.push_back({1000.0 + i / 30.0, Rigid3d(Eigen::Quaterniond(n(rng_), n(rng_), n(rng_), n(rng_)),
                                               Eigen::Vector3d(n(rng_), n(rng_), n(rng_)))});
  ASSERT_TRUE(WriteTumTrajectory(P("t.txt"), traj).ok());
  auto back = ReadTumTrajectory(P("t.txt"));
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_EQ(back->size(), traj.size());
  for (size_t i = 0; i < traj.size(); ++i) {
    EXPECT_NEAR((*back)[i].timestamp_s, traj[i].timestamp_s, 1e-6);
    EXPECT_LT(((*back)[i].world_from_camera.translation - traj[i].world_from_camera.translation).norm(), 1e-7);
    EXPECT_LT(RotationAngle((*back)[i].world_from_camera.rotation * traj[i].world_from_camera.rotation.conjugate()),
              1e-7);
  }
}

TEST_F(IoTest, MalformedTrajectoryNamesTheLine) {
  std::ofstream(P("bad.txt")) << "# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 zero 0 0 0 1\n";
  auto r = ReadTumTrajectory(P("bad.txt"));
  ASSERT_FALSE(r.ok());
  EXPECT_NE(r.status().message().find(":3:"), std::string::npos) << r.status();
  EXPECT_EQ(ReadTumTrajectory(P("missing.txt")).status().code(), StatusCode::kNotFound);
}

TEST_F(IoTest, KittiTrajectoryWithTimes) {
  std::ofstream(P("poses.txt")) << "1 0 0 0 0 1 0 0 0 0 1 0\n0 -1 0 1 1 0 0 2 0 0 1 3";
  std::ofstream(P("times.txt")) << "0.0\n0.1\n";
  auto r = ReadKittiTrajectory(P("poses.txt"), P("times.txt"));
  ASSERT_TRUE(r.ok()) << r.status();
  ASSERT_EQ(r->size(), 2u);
  EXPECT_DOUBLE_EQ((*r)[1].timestamp_s, 0.1);
  EXPECT_LT(((*r)[1].world_from_camera.translation - Eigen::Vector3d(1, 2, 3)).norm(), 1e-12);
  EXPECT_NEAR(RotationAngle((*r)[1].world_from_camera.rotation), M_PI / 2, 1e-12);
  auto auto_detected = ReadTrajectoryAutoDetect(P("poses.txt"));
  ASSERT_TRUE(auto_detected.ok());
  EXPECT_EQ(auto_detected->size(), 2u);
}

TEST_F(IoTest, CalibrationYamlRoundTrip) {
  const RigCalibration c = TestCalibration();
  ASSERT_TRUE(WriteCalibrationYaml(P("camera.yaml"), c).ok());
  auto back = ReadCalibrationYaml(P("camera.yaml"));
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->camera.width, 64);
  EXPECT_DOUBLE_EQ(back->camera.fx, c.camera.fx);
  EXPECT_DOUBLE_EQ(back->camera.distortion[4], 0.0001);
  EXPECT_LT((back->crosstalk - c.crosstalk).norm(), 1e-12);
  for (int i = 0; i < 3; ++i) {
    EXPECT_EQ(back->lights[i].name, c.lights[i].name);
    EXPECT_EQ(back->lights[i].type, c.lights[i].type);
    EXPECT_LT((back->lights[i].position_in_camera - c.lights[i].position_in_camera).norm(), 1e-12);
    EXPECT_LT((back->lights[i].direction_in_camera - c.lights[i].direction_in_camera).norm(), 1e-12);
    EXPECT_DOUBLE_EQ(back->lights[i].intensity, c.lights[i].intensity);
  }
}

TEST_F(IoTest, CalibrationRejectsBadFiles) {
  std::ofstream(P("bad.yaml")) << "%YAML:1.0\n---\nwidth: 10\nheight: 10\nfx: -5\nfy: 5\ncx: 5\ncy: 5\n";
  EXPECT_FALSE(ReadCalibrationYaml(P("bad.yaml")).ok());
  std::ofstream(P("garbage.yaml")) << "\x01\x02 not yaml {{{";
  EXPECT_FALSE(ReadCalibrationYaml(P("garbage.yaml")).ok());
}

TEST_F(IoTest, DepthNormalMaskImagesRoundTrip) {
  cv::Mat depth(10, 12, CV_32F), normals(10, 12, CV_32FC3), mask(10, 12, CV_8U);
  std::uniform_real_distribution<float> u(-1, 1);
  for (int y = 0; y < 10; ++y)
    for (int x = 0; x < 12; ++x) {
      depth.at<float>(y, x) = (x == 0) ? 0.f : 0.3f + 0.01f * x + 0.1f * y;
      Eigen::Vector3f n(u(rng_), u(rng_), u(rng_));
      n.normalize();
      normals.at<cv::Vec3f>(y, x) = (y == 0) ? cv::Vec3f(0, 0, 0) : cv::Vec3f(n.x(), n.y(), n.z());
      mask.at<uint8_t>(y, x) = static_cast<uint8_t>((x * 7 + y) % 3 == 0 ? kMaskObject : kMaskBackground);
    }
  ASSERT_TRUE(WriteDepthPng(P("d.png"), depth).ok());
  ASSERT_TRUE(WriteNormalPng(P("n.png"), normals).ok());
  ASSERT_TRUE(WriteMaskPng(P("m.png"), mask).ok());
  auto d = ReadDepthPng(P("d.png"));
  auto n = ReadNormalPng(P("n.png"));
  auto m = ReadMaskPng(P("m.png"));
  ASSERT_TRUE(d.ok() && n.ok() && m.ok());
  for (int y = 0; y < 10; ++y)
    for (int x = 0; x < 12; ++x) {
      EXPECT_NEAR(d->at<float>(y, x), depth.at<float>(y, x), /*half depth step=*/0.5 / kTumDepthScale + 1e-6);
      const cv::Vec3f a = n->at<cv::Vec3f>(y, x), b = normals.at<cv::Vec3f>(y, x);
      if (y == 0) {
        EXPECT_EQ(a, cv::Vec3f(0, 0, 0));
      } else {
        const Eigen::Vector3d ea(a[0], a[1], a[2]), eb(b[0], b[1], b[2]);
        const double angle_deg = std::atan2(ea.cross(eb).norm(), ea.dot(eb)) * 180 / M_PI;
        EXPECT_LT(angle_deg, /*max_normal_quantisation_deg=*/0.01);
      }
      EXPECT_EQ(m->at<uint8_t>(y, x), mask.at<uint8_t>(y, x));
    }
}

TEST_F(IoTest, CorruptImageIsAnError) {
  std::ofstream(P("corrupt.png"), std::ios::binary) << "\x89PNG\r\n\x1a\n garbage";
  EXPECT_FALSE(ReadRgbImage(P("corrupt.png")).ok());
  EXPECT_FALSE(ReadDepthPng(P("nothing.png")).ok());
}

TEST_F(IoTest, SequenceRoundTrip) {
  const RigCalibration c = TestCalibration();
  auto writer = SequenceWriter::Create(P("seq"), c);
  ASSERT_TRUE(writer.ok()) << writer.status();
  Trajectory gt;
  for (int i = 0; i < 3; ++i) {
    const double t = 10.0 + i / 30.0;
    cv::Mat rgb(48, 64, CV_8UC3, cv::Scalar(10 * i, 20, 30)), depth(48, 64, CV_32F, cv::Scalar(0.5 + i));
    cv::Mat normals(48, 64, CV_32FC3, cv::Scalar(0, 0, -1)), mask(48, 64, CV_8U, cv::Scalar(kMaskObject));
    rgb.at<cv::Vec3b>(0, 0) = cv::Vec3b(255, 0, 0);  // pure red at (0, 0): checks channel order
    ASSERT_TRUE(writer->WriteFrame(t, rgb, depth, normals, mask).ok());
    gt.push_back({std::round(t * 1e6) / 1e6, Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(i, 0, 0))});
  }
  ASSERT_TRUE(writer->Finish(gt, true, true, true).ok());

  auto seq = LoadSequence(P("seq"));
  ASSERT_TRUE(seq.ok()) << seq.status();
  ASSERT_EQ(seq->frames.size(), 3u);
  EXPECT_TRUE(seq->has_calibration);
  EXPECT_EQ(seq->groundtruth.size(), 3u);
  auto rgb = seq->ReadRgb(2);
  ASSERT_TRUE(rgb.ok());
  EXPECT_EQ(rgb->at<cv::Vec3b>(0, 0), cv::Vec3b(255, 0, 0));
  EXPECT_EQ(rgb->at<cv::Vec3b>(5, 5), cv::Vec3b(20, 20, 30));
  auto depth = seq->ReadDepth(1);
  ASSERT_TRUE(depth.ok());
  EXPECT_NEAR(depth->at<float>(3, 3), 1.5f, 1e-4);
  auto normals = seq->ReadNormals(0);
  ASSERT_TRUE(normals.ok());
  EXPECT_NEAR(normals->at<cv::Vec3f>(3, 3)[2], -1.f, 1e-4);
  auto pose = seq->GroundTruthPose(1);
  ASSERT_TRUE(pose.ok());
  EXPECT_NEAR(pose->translation.x(), 1.0, 1e-9);
  EXPECT_FALSE(seq->ReadRgb(3).ok());
  EXPECT_EQ(LoadSequence(P("nope")).status().code(), StatusCode::kNotFound);
}

TEST_F(IoTest, PointCloudPlyRoundTripAndAscii) {
  PointCloud cloud;
  for (int i = 0; i < 100; ++i) {
    cloud.positions.emplace_back(i * 0.1f, -i * 0.2f, 1.f);
    cloud.normals.emplace_back(0.f, 0.f, 1.f);
    cloud.colors.emplace_back(static_cast<uint8_t>(i), 2, 3);
    cloud.confidences.push_back(i * 0.5f);
  }
  ASSERT_TRUE(WritePointCloudPly(P("c.ply"), cloud).ok());
  auto back = ReadPointCloudPly(P("c.ply"));
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_EQ(back->size(), 100u);
  EXPECT_EQ(back->positions[42], cloud.positions[42]);
  EXPECT_EQ(back->colors[42], cloud.colors[42]);
  EXPECT_EQ(back->confidences[99], 49.5f);

  std::ofstream(P("a.ply")) << "ply\nformat ascii 1.0\nelement vertex 3\nproperty double x\nproperty double y\n"
                               "property double z\nelement face 1\nproperty list uchar int vertex_indices\n"
                               "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";
  auto mesh = ReadTriangleMesh(P("a.ply"));
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  EXPECT_EQ(mesh->faces.size(), 1u);
  std::ofstream(P("trunc.ply")) << "ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\n"
                                   "property float y\nproperty float z\nend_header\nabc";
  EXPECT_FALSE(ReadPointCloudPly(P("trunc.ply")).ok());
}

TEST_F(IoTest, OffAndObjMeshes) {
  std::ofstream(P("m.off")) << "OFF\n# comment\n4 2 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n3 0 2 3\n";
  auto off = ReadTriangleMesh(P("m.off"));
  ASSERT_TRUE(off.ok()) << off.status();
  EXPECT_EQ(off->vertices.size(), 4u);
  EXPECT_EQ(off->faces.size(), 3u);  // the quad is split in two
  std::ofstream(P("m.obj")) << "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/1/1 2/2/2 3/3/3\n";
  auto obj = ReadTriangleMesh(P("m.obj"));
  ASSERT_TRUE(obj.ok()) << obj.status();
  EXPECT_EQ(obj->faces[0], Eigen::Vector3i(0, 1, 2));
  std::ofstream(P("bad.off")) << "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n";
  EXPECT_FALSE(ReadTriangleMesh(P("bad.off")).ok());
}

}  // namespace
}  // namespace prism
