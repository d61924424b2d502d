#include "core/fusion/fusion_testing.h"

#include <cmath>
#include <filesystem>
#include <fstream>
#include <random>

#include <opencv2/imgcodecs.hpp>

#include "core/eval/depth_metrics.h"
#include "core/eval/normal_metrics.h"
#include "core/io/image_io.h"
#include "core/photometric/depth_prior.h"
#include "core/photometric/photometric_stereo.h"
#include "core/synth/trajectory.h"

namespace prism {

StatusOr<FusionTestFrame> MakeFusionTestFrame(const std::string& preset, const FusionTestFrameOptions& options) {
  synth::PresetOptions po;
  po.width = options.width;
  po.height = options.height;
  po.frames = options.frames;
  po.seed = options.seed;
  PRISM_ASSIGN_OR_RETURN(synth::SynthSetup setup, synth::MakePreset(preset, po));
  if (options.frame_index < 0 || options.frame_index >= options.frames)
    return InvalidArgumentError("FusionTestFrameOptions.frame_index out of range");
  PRISM_RETURN_IF_ERROR(options.semi_dense.Check());
  const Trajectory trajectory = synth::MakeTrajectory(setup.trajectory);
  FusionTestFrame f;
  f.preset = preset;
  f.rig = setup.rig;
  f.world_from_camera = trajectory[options.frame_index].world_from_camera;
  f.frame = synth::RenderFrame(setup.scene, setup.rig, f.world_from_camera, setup.render,
                               /*noise_seed=*/options.seed * 1000003u + options.frame_index);
  f.slam_scale = options.semi_dense.scale;
  f.semi_dense = synth::SimulateSemiDenseDepth(f.frame.depth, f.frame.rgb, options.semi_dense);
  f.prior_inverse_depth = DensifyInverseDepth(f.semi_dense, DensifyOptions());
  return f;
}

cv::Mat PerturbNormals(const cv::Mat& normals, const NormalNoiseOptions& o) {
  std::mt19937 rng(o.seed);
  std::normal_distribution<float> gauss(0.f, 1.f);
  std::uniform_real_distribution<double> phase(0, 2 * M_PI);
  // Smooth bias: a tilt vector field (x, y components) made of two plane waves per component.
  const double k = 2 * M_PI / o.bias_wavelength_px;
  const double ax = phase(rng), bx = phase(rng), ay = phase(rng), by = phase(rng);
  const double bias = o.bias_deg * M_PI / 180.0;
  // Per-axis sigma so that the RMS of the 2D tilt is noise_deg.
  const float sigma = static_cast<float>(o.noise_deg * M_PI / 180.0 / std::sqrt(2.0));
  cv::Mat out(normals.size(), CV_32FC3, cv::Scalar(0, 0, 0));
  for (int y = 0; y < normals.rows; ++y)
    for (int x = 0; x < normals.cols; ++x) {
      const cv::Vec3f n = normals.at<cv::Vec3f>(y, x);
      const float gx = gauss(rng), gy = gauss(rng);
      if (n.dot(n) < 0.25f) continue;
      const Eigen::Vector3f nn(n[0], n[1], n[2]);
      // Two tangent directions of the normal.
      Eigen::Vector3f t1 = nn.cross(std::abs(nn.x()) < 0.9f ? Eigen::Vector3f::UnitX() : Eigen::Vector3f::UnitY());
      t1.normalize();
      const Eigen::Vector3f t2 = nn.cross(t1);
      // Bias tilt in image axes (projected onto the tangent plane), then random tilt.
      const Eigen::Vector3f b(
          static_cast<float>(bias * 0.5 * (std::sin(k * x + ax) + std::sin(0.7 * k * y + bx))),
          static_cast<float>(bias * 0.5 * (std::sin(0.8 * k * y + ay) + std::sin(0.6 * k * x + by))), 0.f);
      const Eigen::Vector3f bt = b - b.dot(nn) * nn;
      Eigen::Vector3f m = nn + bt + sigma * (gx * t1 + gy * t2);
      m.normalize();
      out.at<cv::Vec3f>(y, x) = cv::Vec3f(m.x(), m.y(), m.z());
    }
  return out;
}

StatusOr<DiligentBallFrame> MakeDiligentBallFrame(const std::string& dir, double focal_px) {
  constexpr int kRows = 512, kCols = 612;
  if (!std::filesystem::exists(dir + "/normal_gt_512x612x3_f32le.bin"))
    return NotFoundError("no DiLiGenT ball in " + dir);
  std::vector<Eigen::Vector3d> intensity;
  {
    std::ifstream in(dir + "/light_intensities.txt");
    double r, g, b;
    while (in >> r >> g >> b) intensity.emplace_back(r, g, b);
  }
  if (intensity.size() != 96u) return DataLossError("light_intensities.txt: expected 96 lines");
  cv::Mat gt(kRows, kCols, CV_32FC3);
  {
    std::ifstream in(dir + "/normal_gt_512x612x3_f32le.bin", std::ios::binary);
    in.read(reinterpret_cast<char*>(gt.data), static_cast<std::streamsize>(kRows) * kCols * 3 * 4);
    if (!in.good()) return DataLossError("normal_gt_512x612x3_f32le.bin: short read");
  }
  const cv::Mat mask_rgb = cv::imread(dir + "/mask.png", cv::IMREAD_GRAYSCALE);
  if (mask_rgb.empty()) return DataLossError("mask.png unreadable");
  const int lights[3] = {9, 24, 85};  // as in photometric_test.cc
  std::vector<cv::Mat> channels;
  for (int c = 0; c < 3; ++c) {
    char name[32];
    std::snprintf(name, sizeof(name), "/%03d.png", lights[c]);
    const cv::Mat img = cv::imread(dir + name, cv::IMREAD_UNCHANGED);  // 16-bit BGR
    if (img.type() != CV_16UC3) return DataLossError(std::string(name) + ": not 16-bit colour");
    std::vector<cv::Mat> bgr;
    cv::split(img, bgr);
    cv::Mat ch;
    bgr[2 - c].convertTo(ch, CV_64F, 1.0 / (65535.0 * intensity[lights[c] - 1][c]));
    channels.push_back(ch);
  }
  double max_v = 0;
  for (auto& ch : channels) max_v = std::max(max_v, cv::norm(ch, cv::NORM_INF));
  // Lighting matrix from 2% of the ground truth (DiLiGenT axes: x right, y up, z to the camera).
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(0, 1);
  std::vector<Eigen::Vector3d> colors, fit_normals;
  auto color_at = [&](int y, int x) -> Eigen::Vector3d {
    return Eigen::Vector3d(channels[0].at<double>(y, x), channels[1].at<double>(y, x), channels[2].at<double>(y, x)) /
           max_v;
  };
  for (int y = 0; y < kRows; ++y)
    for (int x = 0; x < kCols; ++x) {
      if (mask_rgb.at<uint8_t>(y, x) == 0 || u(rng) > 0.02) continue;
      const cv::Vec3f n = gt.at<cv::Vec3f>(y, x);
      colors.push_back(color_at(y, x));
      fit_normals.emplace_back(n[0], n[1], n[2]);
    }
  Eigen::Matrix3d m;
  if (!FitLightingMatrix(colors, fit_normals, &m)) return InternalError("lighting matrix fit failed");
  const Eigen::Matrix3d m_inv = m.inverse();

  DiligentBallFrame out;
  FusionTestFrame& f = out.frame;
  f.preset = "diligent-ball";
  f.rig.camera.width = kCols;
  f.rig.camera.height = kRows;
  f.rig.camera.fx = f.rig.camera.fy = focal_px;
  f.rig.camera.cx = 0.5 * (kCols - 1);
  f.rig.camera.cy = 0.5 * (kRows - 1);
  f.slam_scale = 1.0;
  // Sphere fitted to the mask: centroid and equal-area radius; unit radius, centre on the centroid's ray.
  double su = 0, sv = 0, area = 0;
  for (int y = 0; y < kRows; ++y)
    for (int x = 0; x < kCols; ++x)
      if (mask_rgb.at<uint8_t>(y, x) != 0) {
        su += x;
        sv += y;
        area += 1;
      }
  const double radius_px = std::sqrt(area / M_PI);
  const Eigen::Vector3d ray0 = f.rig.camera.Unproject(Eigen::Vector2d(su / area, sv / area)).normalized();
  const double distance = std::sqrt(std::pow(focal_px / radius_px, 2) + 1.0);
  const Eigen::Vector3d centre = distance * ray0;
  f.frame.depth = cv::Mat(kRows, kCols, CV_32F, cv::Scalar(0));
  f.frame.normals = cv::Mat(kRows, kCols, CV_32FC3, cv::Scalar(0, 0, 0));
  f.frame.mask = cv::Mat(kRows, kCols, CV_8U, cv::Scalar(0));
  f.frame.rgb = cv::Mat(kRows, kCols, CV_8UC3, cv::Scalar(0, 0, 0));
  out.ps_normals = cv::Mat(kRows, kCols, CV_32FC3, cv::Scalar(0, 0, 0));
  cv::Mat sphere_normals(kRows, kCols, CV_32FC3, cv::Scalar(0, 0, 0));
  for (int y = 0; y < kRows; ++y)
    for (int x = 0; x < kCols; ++x) {
      if (mask_rgb.at<uint8_t>(y, x) == 0) continue;
      const Eigen::Vector3d c = color_at(y, x);
      for (int k = 0; k < 3; ++k) f.frame.rgb.at<cv::Vec3b>(y, x)[k] = cv::saturate_cast<uint8_t>(255.0 * c[k]);
      // Ray-sphere intersection (the near one).
      const Eigen::Vector3d d = f.rig.camera.Unproject(Eigen::Vector2d(x, y)).normalized();
      const double b = d.dot(centre), disc = b * b - (centre.squaredNorm() - 1.0);
      if (disc < 0) continue;
      const Eigen::Vector3d p = (b - std::sqrt(disc)) * d;
      f.frame.depth.at<float>(y, x) = static_cast<float>(p.z());
      f.frame.mask.at<uint8_t>(y, x) = 255;
      const Eigen::Vector3d sn = p - centre;
      sphere_normals.at<cv::Vec3f>(y, x) =
          cv::Vec3f(static_cast<float>(sn.x()), static_cast<float>(sn.y()), static_cast<float>(sn.z()));
      const cv::Vec3f g = gt.at<cv::Vec3f>(y, x);
      f.frame.normals.at<cv::Vec3f>(y, x) = cv::Vec3f(g[0], -g[1], -g[2]);  // to x right, y down, z forward
      Eigen::Vector3d n = m_inv * c;
      if (n.norm() < 1e-12) continue;
      n.normalize();
      out.ps_normals.at<cv::Vec3f>(y, x) =
          cv::Vec3f(static_cast<float>(n.x()), static_cast<float>(-n.y()), static_cast<float>(-n.z()));
    }
  out.sphere_vs_gt_median_deg = ComputeNormalError(sphere_normals, f.frame.normals, f.frame.mask).value().median_deg;
  synth::SemiDenseOptions sd;
  sd.scale = 1.0;
  // The same noise in pixel footprints as the synthetic frames (1% of depth at a 550 px focal length):
  // at 3800 px a 1% depth error would be 38 footprints, far more than any SLAM's error on such a view.
  sd.relative_noise = 0.01 * 550.0 / focal_px;
  f.semi_dense = synth::SimulateSemiDenseDepth(f.frame.depth, f.frame.rgb, sd);
  f.prior_inverse_depth = DensifyInverseDepth(f.semi_dense, DensifyOptions());
  return out;
}

FusionInput MakeFusionInput(const FusionTestFrame& frame, const cv::Mat& normals) {
  FusionInput in;
  in.camera = frame.rig.camera;
  in.normals = normals;
  in.semi_dense = frame.semi_dense;
  in.prior_inverse_depth = frame.prior_inverse_depth;
  return in;
}

namespace {

double Rmse(const cv::Mat& estimate_m, const cv::Mat& gt_m, const cv::Mat& mask, DepthScaleAlignment alignment) {
  DepthEvalOptions o;
  o.scale_alignment = alignment;
  const StatusOr<DepthErrorStats> s = ComputeDepthError(estimate_m, gt_m, mask, o);
  return s.ok() ? s->rmse_m : std::numeric_limits<double>::quiet_NaN();
}

}  // namespace

FusionScore ScoreFusion(const FusionTestFrame& f, const cv::Mat& input_normals, const FusionResult& result) {
  FusionScore s;
  const cv::Mat object = f.frame.mask == kMaskObject;
  // Semi-dense depth in metres: scale / rho.
  cv::Mat input_m(f.semi_dense.inverse_depth.size(), CV_32F, cv::Scalar(0));
  for (int y = 0; y < input_m.rows; ++y)
    for (int x = 0; x < input_m.cols; ++x) {
      const float rho = f.semi_dense.inverse_depth.at<float>(y, x);
      if (rho > 0) input_m.at<float>(y, x) = static_cast<float>(f.slam_scale / rho);
    }
  cv::Mat fused_m = result.depth * f.slam_scale;
  s.input_depth_rmse_m = Rmse(input_m, f.frame.depth, object, DepthScaleAlignment::kNone);
  s.fused_depth_rmse_m = Rmse(fused_m, f.frame.depth, object, DepthScaleAlignment::kNone);
  s.input_depth_rmse_median_aligned_m = Rmse(input_m, f.frame.depth, object, DepthScaleAlignment::kMedianRatio);
  s.fused_depth_rmse_median_aligned_m = Rmse(fused_m, f.frame.depth, object, DepthScaleAlignment::kMedianRatio);
  const int object_pixels = cv::countNonZero(object);
  s.coverage =
      object_pixels > 0 ? static_cast<double>(cv::countNonZero(object & (result.depth > 0))) / object_pixels : 0;
  auto normal_error = [&](const cv::Mat& n, double* median, double* mean) {
    const StatusOr<AngularErrorStats> e = ComputeNormalError(n, f.frame.normals, object);
    *median = e.ok() ? e->median_deg : std::numeric_limits<double>::quiet_NaN();
    if (mean != nullptr) *mean = e.ok() ? e->mean_deg : std::numeric_limits<double>::quiet_NaN();
  };
  normal_error(input_normals, &s.input_normal_median_deg, &s.input_normal_mean_deg);
  normal_error(result.normals, &s.fused_normal_median_deg, &s.fused_normal_mean_deg);
  normal_error(result.corrected_normals, &s.corrected_normal_median_deg, nullptr);
  return s;
}

}  // namespace prism
