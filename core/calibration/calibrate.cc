#include "core/calibration/calibrate.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <limits>
#include <sstream>

#include <opencv2/calib3d.hpp>
#include <opencv2/core/eigen.hpp>

#include "core/io/image_io.h"

namespace prism::calibration {

Status CalibrateOptions::Check() const {
  PRISM_RETURN_IF_ERROR(board.Check());
  PRISM_RETURN_IF_ERROR(light_fit.Check());
  std::ostringstream e;
  if (!(min_intrinsics_views >= 3 && min_intrinsics_views <= 1000))
    e << "CalibrateOptions.min_intrinsics_views = " << min_intrinsics_views << "; violated: in [3, 1000]";
  else if (!(min_light_views >= 1 && min_light_views <= 1000))
    e << "CalibrateOptions.min_light_views = " << min_light_views << "; violated: in [1, 1000]";
  else if (!(min_corners >= 6 && min_corners <= 10000))
    e << "CalibrateOptions.min_corners = " << min_corners << "; violated: in [6, 10000]";
  else if (!(white_albedo > 0 && white_albedo <= 1))
    e << "CalibrateOptions.white_albedo = " << white_albedo << "; violated: in (0, 1]";
  else if (!(saturation_level >= 1 && saturation_level <= 255))
    e << "CalibrateOptions.saturation_level = " << saturation_level << "; violated: in [1, 255]";
  else if (!(max_saturated_fraction >= 0 && max_saturated_fraction <= 1))
    e << "CalibrateOptions.max_saturated_fraction = " << max_saturated_fraction << "; violated: in [0, 1]";
  else if (!(dark_level >= 0 && dark_level <= 255))
    e << "CalibrateOptions.dark_level = " << dark_level << "; violated: in [0, 255]";
  else if (!(sample_spacing_m > 0 && sample_spacing_m <= 0.1))
    e << "CalibrateOptions.sample_spacing_m = " << sample_spacing_m << "; violated: in (0, 0.1]";
  else if (!(sample_inset_m > 0 && sample_inset_m <= 0.1))
    e << "CalibrateOptions.sample_inset_m = " << sample_inset_m << "; violated: in (0, 0.1]";
  else if (!(max_reprojection_rms_px > 0 && max_reprojection_rms_px <= 100))
    e << "CalibrateOptions.max_reprojection_rms_px = " << max_reprojection_rms_px << "; violated: in (0, 100]";
  else if (!(max_light_rms_levels > 0 && max_light_rms_levels <= 255))
    e << "CalibrateOptions.max_light_rms_levels = " << max_light_rms_levels << "; violated: in (0, 255]";
  if (e.str().empty()) return Status::Ok();
  return InvalidArgumentError(e.str());
}

namespace {

namespace fs = std::filesystem;

StatusOr<std::vector<fs::path>> ListImages(const fs::path& dir) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) return NotFoundError("missing folder " + dir.string());
  std::vector<fs::path> files;
  for (const fs::directory_entry& e : fs::directory_iterator(dir, ec)) {
    std::string ext = e.path().extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
    if (e.is_regular_file() && (ext == ".png" || ext == ".jpg" || ext == ".jpeg")) files.push_back(e.path());
  }
  if (ec) return UnavailableError("cannot list " + dir.string() + ": " + ec.message());
  std::sort(files.begin(), files.end());
  if (files.empty()) return NotFoundError("no images (*.png, *.jpg) in " + dir.string());
  return files;
}

std::string Relative(const fs::path& file, const fs::path& root) { return fs::relative(file, root).string(); }

StatusOr<cv::Mat> ReadSized(const fs::path& file, const fs::path& root, cv::Size* size) {
  StatusOr<cv::Mat> rgb = ReadRgbImage(file.string());
  if (!rgb.ok()) return rgb.status();
  if (size->area() == 0) *size = rgb->size();
  if (rgb->size() != *size) {
    std::ostringstream e;
    e << Relative(file, root) << " is " << rgb->cols << "x" << rgb->rows << ", the other images " << size->width << "x"
      << size->height << ": all images must come from the same camera mode";
    return InvalidArgumentError(e.str());
  }
  return rgb;
}

// Level below which 99% of the image's pixels (brightest channel) lie.
int Percentile99(const cv::Mat& rgb) {
  std::array<int, 256> histogram{};
  for (int y = 0; y < rgb.rows; ++y) {
    const cv::Vec3b* p = rgb.ptr<cv::Vec3b>(y);
    for (int x = 0; x < rgb.cols; ++x) ++histogram[std::max({p[x][0], p[x][1], p[x][2]})];
  }
  const double target = 0.99 * rgb.total();
  double count = 0;
  for (int v = 0; v < 256; ++v)
    if ((count += histogram[v]) >= target) return v;
  return 255;
}

Status CalibrateIntrinsics(const std::vector<fs::path>& files, const fs::path& root, const CalibrateOptions& options,
                           const cv::Ptr<cv::aruco::CharucoBoard>& board, cv::Size* size, CalibrationReport* report) {
  std::vector<std::vector<cv::Point2f>> corners;
  std::vector<std::vector<int>> ids;
  for (const fs::path& f : files) {
    StatusOr<cv::Mat> rgb = ReadSized(f, root, size);
    if (!rgb.ok()) return rgb.status();
    BoardDetection d = DetectBoard(*rgb, board);
    if (static_cast<int>(d.ids.size()) < options.min_corners) {
      report->skipped.push_back(Relative(f, root));
      continue;
    }
    corners.push_back(std::move(d.corners));
    ids.push_back(std::move(d.ids));
  }
  report->intrinsics_images = static_cast<int>(files.size());
  report->intrinsics_views = static_cast<int>(corners.size());
  const fs::path dir = files.front().parent_path();
  if (corners.empty())
    return NotFoundError("no ChArUco board (" + options.board.Describe() + ") found in any of the " +
                         std::to_string(files.size()) + " images in " + dir.string() +
                         "; check the board options (--squares, --square-mm, --marker-mm, --dictionary)");
  if (report->intrinsics_views < options.min_intrinsics_views)
    return FailedPreconditionError("too few views: the board (at least " + std::to_string(options.min_corners) +
                                   " corners) was found in " + std::to_string(corners.size()) + " of " +
                                   std::to_string(files.size()) + " images in " + dir.string() + "; the minimum is " +
                                   std::to_string(options.min_intrinsics_views));
  cv::Mat k, dist, std_intrinsics, std_extrinsics, per_view;
  std::vector<cv::Mat> rvecs, tvecs;
  const int flags = options.fit_k3 ? 0 : cv::CALIB_FIX_K3;
  report->reprojection_rms_px = cv::aruco::calibrateCameraCharuco(corners, ids, board, *size, k, dist, rvecs, tvecs,
                                                                  std_intrinsics, std_extrinsics, per_view, flags);
  // A lens without distortion still gets some from the fit (noise in the corners): when no coefficient
  // differs from zero by kDistortionSignificanceSigma of its standard deviation, the pinhole model is fitted
  // instead, and the frames are not resampled for a distortion the lens does not have.
  constexpr double kDistortionSignificanceSigma = 3.0;
  report->distortion_significant = false;
  for (int i = 0; i < static_cast<int>(dist.total()) && i < 5; ++i) {
    const double sigma = std_intrinsics.at<double>(4 + i);
    if (std::abs(dist.at<double>(i)) > kDistortionSignificanceSigma * sigma) report->distortion_significant = true;
  }
  if (!report->distortion_significant) {
    for (int i = 0; i < 5; ++i)
      report->distortion_fitted[i] = i < static_cast<int>(dist.total()) ? dist.at<double>(i) : 0.0;
    dist = cv::Mat::zeros(1, 5, CV_64F);
    report->reprojection_rms_px = cv::aruco::calibrateCameraCharuco(
        corners, ids, board, *size, k, dist, rvecs, tvecs, std_intrinsics, std_extrinsics, per_view,
        cv::CALIB_FIX_K1 | cv::CALIB_FIX_K2 | cv::CALIB_FIX_K3 | cv::CALIB_ZERO_TANGENT_DIST);
  }
  if (!(report->reprojection_rms_px <= options.max_reprojection_rms_px)) {
    std::ostringstream e;
    e << "the board does not fit the images: reprojection error " << report->reprojection_rms_px << " px (at most "
      << options.max_reprojection_rms_px << "); check that the board options (" << options.board.Describe()
      << ") match the printed board and that the images are sharp";
    return FailedPreconditionError(e.str());
  }
  PinholeCamera& cam = report->rig.camera;
  cam.width = size->width;
  cam.height = size->height;
  cam.fx = k.at<double>(0, 0);
  cam.fy = k.at<double>(1, 1);
  cam.cx = k.at<double>(0, 2);
  cam.cy = k.at<double>(1, 2);
  for (int i = 0; i < 5; ++i) cam.distortion[i] = i < static_cast<int>(dist.total()) ? dist.at<double>(i) : 0.0;
  for (int i = 0; i < 4; ++i) report->intrinsics_std[i] = std_intrinsics.at<double>(i);
  for (int i = 0; i < 5; ++i) report->distortion_std[i] = std_intrinsics.at<double>(4 + i);
  return cam.Check();
}

Eigen::Vector3d Bilinear(const cv::Mat& rgb, const Eigen::Vector2d& p, int* max_level) {
  const int x0 = static_cast<int>(std::floor(p.x())), y0 = static_cast<int>(std::floor(p.y()));
  const double fx = p.x() - x0, fy = p.y() - y0;
  Eigen::Vector3d v = Eigen::Vector3d::Zero();
  *max_level = 0;
  for (int dy = 0; dy < 2; ++dy) {
    const cv::Vec3b* row = rgb.ptr<cv::Vec3b>(y0 + dy);
    for (int dx = 0; dx < 2; ++dx) {
      const double w = (dx ? fx : 1 - fx) * (dy ? fy : 1 - fy);
      const cv::Vec3b& px = row[x0 + dx];
      for (int c = 0; c < 3; ++c) {
        v[c] += w * px[c];
        *max_level = std::max<int>(*max_level, px[c]);
      }
    }
  }
  return v / 255.0;
}

// A white sample counts only this far from ink in the image, pixels: the bilinear read (1 px) and the
// pixel's own area (0.5 px) stay on white paper, with a margin for the lens's blur.
constexpr double kMinInkDistancePx = 2.0;

// The white-paper samples of one light image; false (and no samples) when the board is not found.
StatusOr<bool> AddLightSamples(const cv::Mat& rgb, const std::string& name, int lit, const CalibrateOptions& options,
                               const cv::Ptr<cv::aruco::CharucoBoard>& board, const PinholeCamera& cam,
                               const std::vector<WhitePoint>& white, std::vector<LightSample>* samples) {
  const BoardDetection d = DetectBoard(rgb, board);
  if (static_cast<int>(d.ids.size()) < options.min_corners) return false;
  cv::Mat k, dist(1, 5, CV_64F), rvec, tvec;
  cv::eigen2cv(cam.K(), k);
  for (int i = 0; i < 5; ++i) dist.at<double>(i) = cam.distortion[i];
  if (!cv::aruco::estimatePoseCharucoBoard(d.corners, d.ids, board, k, dist, rvec, tvec)) return false;
  cv::Mat r;
  cv::Rodrigues(rvec, r);
  Eigen::Matrix3d cam_from_board_rotation;
  Eigen::Vector3d cam_from_board_translation;
  cv::cv2eigen(r, cam_from_board_rotation);
  cv::cv2eigen(tvec, cam_from_board_translation);
  const Eigen::Vector3d normal = -cam_from_board_rotation.col(2);  // the printed side faces the board's -z
  int used = 0, saturated = 0;
  for (const WhitePoint& w : white) {
    const Eigen::Vector2d& q = w.point;
    const Eigen::Vector3d x = cam_from_board_rotation * Eigen::Vector3d(q.x(), q.y(), 0) + cam_from_board_translation;
    if (x.z() <= 0) continue;
    const Eigen::Vector2d px = cam.Project(x);
    if (!cam.InImage(px, 2)) continue;
    // The ink distance seen in the image: the shorter of the board's two axes, foreshortened.
    double ink_px = std::numeric_limits<double>::infinity();
    for (int axis = 0; axis < 2; ++axis) {
      const Eigen::Vector3d step = cam_from_board_rotation.col(axis) * w.ink_distance_m;
      if ((x + step).z() > 0) ink_px = std::min(ink_px, (cam.Project(x + step) - px).norm());
    }
    if (ink_px < kMinInkDistancePx) continue;
    int level = 0;
    const Eigen::Vector3d value = Bilinear(rgb, px, &level);
    ++used;
    if (level >= options.saturation_level) {
      ++saturated;
      continue;
    }
    samples->push_back({lit, x, normal.dot(x) < 0 ? normal : Eigen::Vector3d(-normal), value});
  }
  if (used > 0 && saturated > options.max_saturated_fraction * used) {
    std::ostringstream e;
    e << name << " is saturated: " << std::lround(100.0 * saturated / used)
      << "% of the board's white paper is at level " << options.saturation_level << " or above (at most "
      << std::lround(100 * options.max_saturated_fraction)
      << "%); lower the exposure or gain, or move the board further away";
    return Status(FailedPreconditionError(e.str()));
  }
  return true;
}

Status CalibrateLights(const fs::path& root, const CalibrateOptions& options,
                       const cv::Ptr<cv::aruco::CharucoBoard>& board, cv::Size* size, CalibrationReport* report) {
  const std::vector<WhitePoint> white =
      WhitePaperPoints(options.board, options.sample_spacing_m, options.sample_inset_m);
  std::vector<LightSample> samples;
  for (int f = 0; f < 4; ++f) {
    const fs::path dir = root / "lights" / kLightFolders[f];
    const bool optional = kLightFolderLit[f] == 7;
    std::error_code ec;
    if (optional && !fs::exists(dir, ec)) continue;
    StatusOr<std::vector<fs::path>> files = ListImages(dir);
    if (!files.ok()) return files.status();
    int dark = 0, brightest = 0;
    for (const fs::path& file : *files) {
      StatusOr<cv::Mat> rgb = ReadSized(file, root, size);
      if (!rgb.ok()) return rgb.status();
      const int level = Percentile99(*rgb);
      brightest = std::max(brightest, level);
      if (level < options.dark_level) {
        ++dark;
        report->skipped.push_back(Relative(file, root));
        continue;
      }
      StatusOr<bool> found = AddLightSamples(*rgb, Relative(file, root), kLightFolderLit[f], options, board,
                                             report->rig.camera, white, &samples);
      if (!found.ok()) return found.status();
      if (*found) ++report->light_views[f];
      else report->skipped.push_back(Relative(file, root));
    }
    if (dark == static_cast<int>(files->size()))
      return FailedPreconditionError(std::string("the ") + kLightFolders[f] + " light never lit the board: all " +
                                     std::to_string(dark) + " images in " + dir.string() +
                                     " are dark (99th-percentile level " + std::to_string(brightest) + " < " +
                                     std::to_string(options.dark_level) + "); is that light connected and on?");
    const int needed = optional ? 1 : options.min_light_views;
    if (report->light_views[f] < needed)
      return FailedPreconditionError("too few views under the " + std::string(kLightFolders[f]) +
                                     " light: the board was found in " + std::to_string(report->light_views[f]) +
                                     " of " + std::to_string(files->size()) + " images in " + dir.string() +
                                     "; the minimum is " + std::to_string(needed));
  }
  StatusOr<LightFitResult> fit = FitLights(samples, options.light_fit);
  if (!fit.ok()) return fit.status();
  report->light_fit = *fit;
  const double rms_levels = 255 * fit->rms;
  if (!fit->converged || !(rms_levels <= options.max_light_rms_levels)) {
    std::ostringstream e;
    e << "the light images do not follow the near-light model: the fit "
      << (fit->converged ? "converged" : "did not converge") << " with residual " << rms_levels
      << " levels RMS (at most " << options.max_light_rms_levels
      << "); check for ambient light, automatic exposure or gain, glossy paper, or a light in the wrong folder";
    return FailedPreconditionError(e.str());
  }
  // G(c, l) = crosstalk(c, l) * white_albedo * intensity_l with crosstalk(l, l) = 1.
  RigCalibration& rig = report->rig;
  const Eigen::Matrix3d& g = fit->gain;
  static const char* kChannels[3] = {"red", "green", "blue"};
  for (int l = 0; l < 3; ++l) {
    int strongest = l;
    g.col(l).maxCoeff(&strongest);
    if (strongest != l)
      return FailedPreconditionError(std::string("the ") + kLightFolders[l] + " light's images (lights/" +
                                     kLightFolders[l] + ") are brightest in the camera's " + kChannels[strongest] +
                                     " channel, not its " + kChannels[l] + " one: are the light folders swapped?");
  }
  // Board poses that leave a light's depth and intensity nearly interchangeable show as a large
  // position uncertainty (on rendered boards the error then reaches about its one-sigma).
  constexpr double kUncertainLightM = 0.003;
  for (int l = 0; l < 3; ++l) {
    const double sigma = fit->position_std[l].maxCoeff();
    if (sigma <= kUncertainLightM) continue;
    std::ostringstream w;
    w << "the " << kLightFolders[l] << " light's position is uncertain (one-sigma " << std::lround(1000 * sigma)
      << " mm): add board poses nearer the camera (0.45-0.6 m) and tilted towards that light";
    report->warnings.push_back(w.str());
  }
  auto var = [&](int c0, int l0, int c1, int l1) { return fit->covariance(9 + 3 * l0 + c0, 9 + 3 * l1 + c1); };
  for (int l = 0; l < 3; ++l) {
    Light& light = rig.lights[l];
    light.name = kLightFolders[l];
    light.type = LightType::kPoint;
    light.position_in_camera = fit->position_in_camera[l];
    light.color = Eigen::Vector3d::Unit(l);
    light.intensity = g(l, l) / options.white_albedo;
    report->intensity_std[l] = fit->gain_std(l, l) / options.white_albedo;
    for (int c = 0; c < 3; ++c) {
      rig.crosstalk(c, l) = g(c, l) / g(l, l);
      // Delta method for a ratio a / b.
      const double a = g(c, l), b = g(l, l);
      const double v =
          var(c, l, c, l) / (b * b) + a * a * var(l, l, l, l) / (b * b * b * b) - 2 * a * var(c, l, l, l) / (b * b * b);
      report->crosstalk_std(c, l) = c == l ? 0.0 : std::sqrt(std::max(0.0, v));
    }
  }
  return rig.Check();
}

}  // namespace

StatusOr<CalibrationReport> CalibrateRig(const std::string& folder, const CalibrateOptions& options) {
  PRISM_RETURN_IF_ERROR(options.Check());
  const fs::path root(folder);
  std::error_code ec;
  if (!fs::is_directory(root, ec)) return NotFoundError("no calibration folder " + folder);
  const cv::Ptr<cv::aruco::CharucoBoard> board = MakeBoard(options.board);
  CalibrationReport report;
  StatusOr<std::vector<fs::path>> files = ListImages(root / "intrinsics");
  if (!files.ok()) return files.status();
  cv::Size size;
  PRISM_RETURN_IF_ERROR(CalibrateIntrinsics(*files, root, options, board, &size, &report));
  PRISM_RETURN_IF_ERROR(CalibrateLights(root, options, board, &size, &report));
  return report;
}

}  // namespace prism::calibration
