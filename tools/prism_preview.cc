// prism-preview: renders a point cloud (PLY) to a PNG picture, so a result can be looked at without a
// 3D viewer (z-buffered point splats, shaded by the normals when present, else by the colours).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <limits>
#include <string>
#include <vector>

#include <Eigen/Eigenvalues>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/geometry/camera.h"
#include "core/geometry/rigid3.h"
#include "core/io/ply_io.h"
#include "core/io/trajectory_io.h"
#include "tools/cli.h"
#include "tools/json_output.h"

namespace {

using namespace prism;

constexpr char kNotes[] =
    R"(The virtual camera looks at the cloud's centre (median point) from the given azimuth and elevation,
at a distance that frames the central 98% of the points. Points are z-buffered splats; with normals
they are shaded by a headlight (Lambert) tinted by their colour, else they show their colour.)";

int Fail(const std::string& m) {
  std::cerr << "prism-preview: " << m << "\n";
  return 1;
}

double Quantile(std::vector<double> v, double q) {
  if (v.empty()) return 0;
  const size_t k = std::min(v.size() - 1, static_cast<size_t>(q * (v.size() - 1)));
  std::nth_element(v.begin(), v.begin() + k, v.end());
  return v[k];
}

}  // namespace

int main(int argc, char** argv) {
  std::string cloud_path, out_path, trajectory_path, size = "800x800";
  int width = 800, height = 800, splat = 1;
  double azimuth = 30, elevation = 25;
  CLI::App app{"", "prism-preview"};
  cli::Setup(&app, "renders a point cloud (PLY) to a PNG picture",
             {"prism-preview --cloud FILE.ply --out FILE.png [options]"}, kNotes);
  app.add_option("--cloud", cloud_path, "the cloud, PLY")->type_name("FILE")->required();
  app.add_option("--out", out_path, "the picture, PNG")->type_name("FILE")->required();
  app.add_option("--size", size, "picture size, sides in [16, 8192]")->type_name("WxH");
  app.add_option("--azimuth", azimuth, "camera azimuth about the cloud's flattest axis (its \"up\"), degrees")
      ->type_name("DEG");
  app.add_option("--elevation", elevation, "camera elevation above the plane of its two main axes, degrees")
      ->type_name("DEG");
  app.add_option("--splat", splat, "splat radius, pixels, 0-10")->type_name("PX")->check(CLI::Range(0, 10));
  app.add_option("--trajectory", trajectory_path,
                 "look from the camera pose in the middle of this TUM trajectory (the\n"
                 "cloud's world frame, e.g. prism-client's trajectory.txt), pulled back to\n"
                 "frame the cloud")
      ->type_name("FILE");
  if (const int exit = cli::Parse(&app, argc, argv, /*usage_exit=*/1); exit != cli::kContinue) return exit;
  if (std::sscanf(size.c_str(), "%dx%d", &width, &height) != 2 || width < 16 || height < 16 || width > 8192 ||
      height > 8192)
    return Fail("--size must be WxH with sides in [16, 8192]");
  StatusOr<PointCloud> cloud = ReadPointCloudPly(cloud_path);
  if (!cloud.ok()) return Fail(cloud.status().ToString());
  if (cloud->empty()) return Fail("'" + cloud_path + "' has no points");

  // Robust centre and extent.
  std::vector<double> xs, ys, zs;
  for (const auto& p : cloud->positions) xs.push_back(p.x()), ys.push_back(p.y()), zs.push_back(p.z());
  const Eigen::Vector3d centre(Quantile(xs, 0.5), Quantile(ys, 0.5), Quantile(zs, 0.5));
  std::vector<double> dist;
  for (const auto& p : cloud->positions) dist.push_back((p.cast<double>() - centre).norm());
  const double radius = std::max(1e-6, Quantile(dist, 0.98));

  // Principal frame: the smallest-variance axis of the cloud is "up" for the azimuth/elevation
  // (scenes on a ground plane look natural; the sign makes the camera look from the side the
  // normals face, when there are normals).
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (const auto& p : cloud->positions) {
    const Eigen::Vector3d d = p.cast<double>() - centre;
    if (d.norm() <= radius) cov += d * d.transpose();
  }
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(cov);
  Eigen::Vector3d up = eig.eigenvectors().col(0);
  if (cloud->HasNormals()) {
    Eigen::Vector3d mean_n = Eigen::Vector3d::Zero();
    for (const auto& n : cloud->normals) mean_n += n.cast<double>();
    if (mean_n.dot(up) < 0) up = -up;
  } else if (up.z() < 0) {
    up = -up;
  }
  const Eigen::Vector3d ax = eig.eigenvectors().col(2);
  const Eigen::Vector3d ay = up.cross(ax).normalized();
  const double az = azimuth * M_PI / 180, el = elevation * M_PI / 180;
  Eigen::Vector3d dir = std::cos(el) * (std::cos(az) * ax + std::sin(az) * ay) + std::sin(el) * up;
  if (!trajectory_path.empty()) {
    StatusOr<Trajectory> traj = ReadTumTrajectory(trajectory_path);
    if (!traj.ok()) return Fail(traj.status().ToString());
    if (traj->empty()) return Fail("'" + trajectory_path + "' has no poses");
    const Rigid3d& pose = (*traj)[traj->size() / 2].world_from_camera;
    const Eigen::Vector3d d = pose.translation - centre;
    if (d.norm() > 1e-9) dir = d.normalized();
    up = -(pose.rotation * Eigen::Vector3d::UnitY());  // the camera's up
  }
  const double hfov = 40.0;
  const double distance = radius / std::sin(0.5 * hfov * M_PI / 180) * 1.05;
  const Eigen::Vector3d eye = centre + distance * dir;
  const Rigid3d world_from_camera = LookAt(eye, centre, -up);
  const Rigid3d camera_from_world = world_from_camera.Inverse();
  const PinholeCamera cam = PinholeCamera::FromFov(width, height, hfov);

  cv::Mat image(height, width, CV_8UC3, cv::Scalar(255, 255, 255));
  cv::Mat zbuf(height, width, CV_32F, cv::Scalar(std::numeric_limits<float>::infinity()));
  for (size_t i = 0; i < cloud->size(); ++i) {
    const Eigen::Vector3d pc = camera_from_world * cloud->positions[i].cast<double>();
    if (pc.z() <= 1e-6) continue;
    const Eigen::Vector2d uv = cam.Project(pc);
    const int u = static_cast<int>(std::lround(uv.x())), v = static_cast<int>(std::lround(uv.y()));
    Eigen::Vector3d colour(0.8, 0.8, 0.8);
    if (cloud->HasColors()) colour = cloud->colors[i].cast<double>() / 255.0;
    if (cloud->HasNormals()) {
      const Eigen::Vector3d n = camera_from_world.rotation * cloud->normals[i].cast<double>();
      const double shade = 0.25 + 0.75 * std::abs(n.dot(-pc.normalized()));
      colour = shade * (0.35 * Eigen::Vector3d::Ones() + 0.65 * colour);
    }
    for (int dy = -splat; dy <= splat; ++dy) {
      for (int dx = -splat; dx <= splat; ++dx) {
        const int x = u + dx, y = v + dy;
        if (x < 0 || y < 0 || x >= width || y >= height) continue;
        float& z = zbuf.at<float>(y, x);
        if (pc.z() >= z) continue;
        z = static_cast<float>(pc.z());
        image.at<cv::Vec3b>(y, x) =
            cv::Vec3b(cv::saturate_cast<uint8_t>(255 * colour.z()), cv::saturate_cast<uint8_t>(255 * colour.y()),
                      cv::saturate_cast<uint8_t>(255 * colour.x()));  // BGR
      }
    }
  }
  if (!cv::imwrite(out_path, image)) return Fail("cannot write '" + out_path + "'");
  std::cout << JsonText(Json{{"points", cloud->size()}, {"out", out_path}});
  return 0;
}
