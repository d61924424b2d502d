// Interoperability with PCL: the PLY and PCD files Prism writes open in PCL's own readers
// (pcl::io::loadPLYFile / loadPCDFile into PointXYZRGBNormal) with the same values, and the PCD files
// PCL writes (binary, ASCII) open in Prism's reader.
#include <unistd.h>

#include <filesystem>
#include <random>
#include <string>

#include <gtest/gtest.h>
#include <pcl/io/pcd_io.h>
#include <pcl/io/ply_io.h>
#include <pcl/point_types.h>

#include "core/io/pcd_io.h"
#include "core/io/ply_io.h"

namespace prism {
namespace {
namespace fs = std::filesystem;

PointCloud RandomCloud(size_t n) {
  std::mt19937 rng(11);
  std::normal_distribution<float> g(0.f, 1.f);
  std::uniform_int_distribution<int> c(0, 255);
  PointCloud cloud;
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Vector3f d = Eigen::Vector3f(g(rng), g(rng), g(rng)).normalized();
    cloud.positions.push_back(Eigen::Vector3f(0.5f, 0.1f, 2.f) + 0.25f * d);
    cloud.normals.push_back(d);
    // Include colours whose packed float is a NaN pattern (opaque-looking high bytes are not used by
    // PCL's rgb, but 0xFF.... in rgba is): the packing must go through bits, not float values.
    cloud.colors.emplace_back(c(rng), c(rng), c(rng));
  }
  cloud.colors[0] = {255, 255, 255};
  return cloud;
}

void ExpectPclMatches(const PointCloud& ours, const pcl::PointCloud<pcl::PointXYZRGBNormal>& pcl) {
  ASSERT_EQ(pcl.size(), ours.size());
  for (size_t i = 0; i < ours.size(); ++i) {
    const auto& p = pcl[i];
    ASSERT_EQ(Eigen::Vector3f(p.x, p.y, p.z), ours.positions[i]) << "point " << i;
    ASSERT_EQ(Eigen::Vector3f(p.normal_x, p.normal_y, p.normal_z), ours.normals[i]) << "point " << i;
    using Rgb = Eigen::Matrix<uint8_t, 3, 1>;
    ASSERT_EQ(Rgb(p.r, p.g, p.b), ours.colors[i]) << "point " << i;
  }
}

class PclFormatsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("prism_pcl_formats_test_" + std::to_string(getpid()));
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override {
    if (!HasFailure()) fs::remove_all(dir_);
  }
  std::string P(const std::string& name) const { return (dir_ / name).string(); }
  fs::path dir_;
};

TEST_F(PclFormatsTest, PclReadsOurPlyAndPcd) {
  const PointCloud cloud = RandomCloud(500);
  ASSERT_TRUE(WritePointCloudPly(P("c.ply"), cloud).ok());
  ASSERT_TRUE(WritePointCloudPcd(P("b.pcd"), cloud, PcdEncoding::kBinary).ok());
  ASSERT_TRUE(WritePointCloudPcd(P("a.pcd"), cloud, PcdEncoding::kAscii).ok());
  pcl::PointCloud<pcl::PointXYZRGBNormal> pcl;
  {
    SCOPED_TRACE("binary PLY");
    ASSERT_EQ(pcl::io::loadPLYFile(P("c.ply"), pcl), 0);
    ExpectPclMatches(cloud, pcl);
  }
  {
    SCOPED_TRACE("binary PCD");
    ASSERT_EQ(pcl::io::loadPCDFile(P("b.pcd"), pcl), 0);
    ExpectPclMatches(cloud, pcl);
  }
  {
    SCOPED_TRACE("ASCII PCD");
    ASSERT_EQ(pcl::io::loadPCDFile(P("a.pcd"), pcl), 0);
    ExpectPclMatches(cloud, pcl);
  }
}

TEST_F(PclFormatsTest, WeReadPclsPcd) {
  const PointCloud cloud = RandomCloud(300);
  pcl::PointCloud<pcl::PointXYZRGBNormal> pcl;
  for (size_t i = 0; i < cloud.size(); ++i) {
    pcl::PointXYZRGBNormal p;
    p.x = cloud.positions[i].x();
    p.y = cloud.positions[i].y();
    p.z = cloud.positions[i].z();
    p.normal_x = cloud.normals[i].x();
    p.normal_y = cloud.normals[i].y();
    p.normal_z = cloud.normals[i].z();
    p.r = cloud.colors[i][0];
    p.g = cloud.colors[i][1];
    p.b = cloud.colors[i][2];
    pcl.push_back(p);
  }
  ASSERT_EQ(pcl::io::savePCDFileBinary(P("pcl_b.pcd"), pcl), 0);
  ASSERT_EQ(pcl::io::savePCDFileASCII(P("pcl_a.pcd"), pcl), 0);
  ASSERT_EQ(pcl::io::savePLYFileBinary(P("pcl.ply"), pcl), 0);
  for (const std::string name : {"pcl_b.pcd", "pcl_a.pcd"}) {
    StatusOr<PointCloud> back = ReadPointCloudPcd(P(name));
    ASSERT_TRUE(back.ok()) << name << ": " << back.status();
    ASSERT_EQ(back->size(), cloud.size()) << name;
    for (size_t i = 0; i < cloud.size(); ++i) {
      // PCL's ASCII writer prints 8 significant digits: a float comes back within one ulp-ish step.
      ASSERT_LT((back->positions[i] - cloud.positions[i]).norm(), 1e-6f) << name << " point " << i;
      ASSERT_LT((back->normals[i] - cloud.normals[i]).norm(), 1e-6f) << name << " point " << i;
      ASSERT_EQ(back->colors[i], cloud.colors[i]) << name << " point " << i;
    }
  }
  StatusOr<PointCloud> ply = ReadPointCloudPly(P("pcl.ply"));
  ASSERT_TRUE(ply.ok()) << ply.status();
  ASSERT_EQ(ply->size(), cloud.size());
  EXPECT_EQ(ply->positions[7], cloud.positions[7]);
  ASSERT_TRUE(ply->HasColors());
  EXPECT_EQ(ply->colors[7], cloud.colors[7]);
}

}  // namespace
}  // namespace prism
