#include "core/slam/depth_filter.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include <opencv2/imgproc.hpp>

#include "core/slam/image_bytes.h"
#include "core/slam/line_sampler.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace {

// A CV_32F image as the line sampler reads it.
LineSamplerImage ViewOf(const cv::Mat& image) {
  LineSamplerImage v;
  v.data = image.ptr<float>(0);
  v.stride = image.step1();
  v.u_end = static_cast<float>(image.cols - 1);
  v.v_end = static_cast<float>(image.rows - 1);
  return v;
}

constexpr int kPatchHalf = 2;  // 5 samples

// The sum of squared differences between the patch `patch` (2 kPatchHalf + 1 values) and the
// samples at each of `positions` positions s (samples s .. s + 2 kPatchHalf), the taps summed in
// order; infinity where one of those samples is outside the frame (outside_before counts them).
void ScorePositions(const float* samples, const int* outside_before, const float* patch, int positions, float* errors) {
  constexpr int kTaps = 2 * kPatchHalf + 1;
  const float p0 = patch[0], p1 = patch[1], p2 = patch[2], p3 = patch[3], p4 = patch[4];
  static_assert(kTaps == 5, "the taps below");
#pragma omp simd
  for (int s = 0; s < positions; ++s) {
    const float d0 = samples[s] - p0, d1 = samples[s + 1] - p1, d2 = samples[s + 2] - p2;
    const float d3 = samples[s + 3] - p3, d4 = samples[s + 4] - p4;
    float err = 0;
    err += d0 * d0;
    err += d1 * d1;
    err += d2 * d2;
    err += d3 * d3;
    err += d4 * d4;
    errors[s] = outside_before[s + kTaps] == outside_before[s] ? err : std::numeric_limits<float>::infinity();
  }
}

}  // namespace

Status DepthFilterOptions::Check() const {
  if (!(min_gradient >= 0 && min_gradient <= 255))
    return InvalidArgumentError("DepthFilterOptions: min_gradient must be in [0, 255]");
  if (!(min_gradient_line_cosine >= 0 && min_gradient_line_cosine < 1))
    return InvalidArgumentError("DepthFilterOptions: min_gradient_line_cosine must be in [0, 1)");
  if (!(max_match_error > 0)) return InvalidArgumentError("DepthFilterOptions: max_match_error must be > 0");
  if (!(min_match_ratio >= 1)) return InvalidArgumentError("DepthFilterOptions: min_match_ratio must be >= 1");
  if (max_search_px < 4) return InvalidArgumentError("DepthFilterOptions: max_search_px must be >= 4");
  if (!(image_noise_sigma > 0)) return InvalidArgumentError("DepthFilterOptions: image_noise_sigma must be > 0");
  if (!(epipolar_sigma_px > 0)) return InvalidArgumentError("DepthFilterOptions: epipolar_sigma_px must be > 0");
  if (!(seed_max_relative_sigma > 0))
    return InvalidArgumentError("DepthFilterOptions: seed_max_relative_sigma must be > 0");
  if (!(outlier_sigmas > 0)) return InvalidArgumentError("DepthFilterOptions: outlier_sigmas must be > 0");
  if (!(propagation_relative_sigma >= 0))
    return InvalidArgumentError("DepthFilterOptions: propagation_relative_sigma must be >= 0");
  if (local_mean_radius_px < 1 || local_mean_radius_px > 32)
    return InvalidArgumentError("DepthFilterOptions: local_mean_radius_px must be in [1, 32]");
  if (!(local_mean_floor > 0)) return InvalidArgumentError("DepthFilterOptions: local_mean_floor must be > 0");
  if (!(max_local_mean_log_gradient >= 0))
    return InvalidArgumentError("DepthFilterOptions: max_local_mean_log_gradient must be >= 0");
  if (!(min_local_mean >= 0 && min_local_mean <= 255))
    return InvalidArgumentError("DepthFilterOptions: min_local_mean must be in [0, 255]");
  if (!(regularise_sigmas > 0)) return InvalidArgumentError("DepthFilterOptions: regularise_sigmas must be > 0");
  if (min_neighbours < 0 || min_neighbours > 8)
    return InvalidArgumentError("DepthFilterOptions: min_neighbours must be in [0, 8]");
  if (min_observations < 0) return InvalidArgumentError("DepthFilterOptions: min_observations must be >= 0");
  if (!(max_relative_sigma > 0)) return InvalidArgumentError("DepthFilterOptions: max_relative_sigma must be > 0");
  if (!(search_sigmas >= 1 && search_sigmas <= 10))
    return InvalidArgumentError("DepthFilterOptions: search_sigmas must be in [1, 10]");
  if (camera_attached_min_votes < 0)
    return InvalidArgumentError("DepthFilterOptions: camera_attached_min_votes must be >= 0");
  if (!(camera_attached_min_flow_px > 0))
    return InvalidArgumentError("DepthFilterOptions: camera_attached_min_flow_px must be > 0");
  if (!(camera_attached_error_ratio > 0 && camera_attached_error_ratio <= 1))
    return InvalidArgumentError("DepthFilterOptions: camera_attached_error_ratio must be in (0, 1]");
  if (!(skip_information_ratio >= 0))
    return InvalidArgumentError("DepthFilterOptions: skip_information_ratio must be >= 0");
  if (light_edge_radius_px < 0 || light_edge_radius_px > 16)
    return InvalidArgumentError("DepthFilterOptions: light_edge_radius_px must be in [0, 16]");
  if (!(light_edge_low_share >= 0 && light_edge_low_share < light_edge_high_share && light_edge_high_share <= 1))
    return InvalidArgumentError("DepthFilterOptions: need 0 <= light_edge_low_share < light_edge_high_share <= 1");
  return Status::Ok();
}

void KeyframeDepth::NormalisedGrey(const cv::Mat& rgb, const DepthFilterOptions& options, cv::Mat* grey_j,
                                   cv::Mat* local_mean) {
  cv::Mat grey(rgb.rows, rgb.cols, CV_32F);
  for (int y = 0; y < rgb.rows; ++y) {
    const uint8_t* in = rgb.ptr<uint8_t>(y);
    float* out = grey.ptr<float>(y);
    for (int x = 0; x < rgb.cols; ++x) out[x] = (in[3 * x] + in[3 * x + 1] + in[3 * x + 2]) * (1.0f / 3.0f);
  }
  const int k = 2 * options.local_mean_radius_px + 1;
  cv::blur(grey, *local_mean, cv::Size(k, k), cv::Point(-1, -1), cv::BORDER_REFLECT);
  grey_j->create(rgb.rows, rgb.cols, CV_32F);
  const float floor = static_cast<float>(options.local_mean_floor);
  for (int y = 0; y < rgb.rows; ++y) {
    const float* g = grey.ptr<float>(y);
    const float* m = local_mean->ptr<float>(y);
    float* o = grey_j->ptr<float>(y);
    for (int x = 0; x < rgb.cols; ++x) o[x] = 128.0f * g[x] / (m[x] + floor);
  }
}

cv::Mat KeyframeDepth::LightEdgeMask(const cv::Mat& rgb, const Eigen::Matrix3d& crosstalk,
                                     const DepthFilterOptions& options) {
  cv::Mat edge = cv::Mat::zeros(rgb.rows, rgb.cols, CV_8U);
  if (options.light_edge_radius_px <= 0) return edge;
  // Each light's image: L = crosstalk^-1 c per pixel, smoothed over 3x3 against the noise (the mean
  // is taken first: both are linear).
  const Eigen::Matrix3d unmix = crosstalk.inverse();
  cv::Mat lights;
  cv::boxFilter(rgb, lights, CV_32F, cv::Size(3, 3), cv::Point(-1, -1), true, cv::BORDER_REFLECT);
  cv::Matx33f m;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) m(r, c) = static_cast<float>(unmix(r, c));
  cv::transform(lights, lights, m);
  std::vector<cv::Mat> light(3);
  cv::split(lights, light);
  // The sum has a floor of 10 grey levels: in the dark the shares are noise.
  cv::Mat total = cv::max(light[0], 0.0f) + cv::max(light[1], 0.0f) + cv::max(light[2], 0.0f) + 10.0f;
  const int k = 2 * options.light_edge_radius_px + 1;
  const cv::Mat box = cv::getStructuringElement(cv::MORPH_RECT, cv::Size(k, k));
  for (const cv::Mat& l : light) {
    const cv::Mat share = l / total;
    cv::Mat most, least;
    cv::dilate(share, most, box);
    cv::erode(share, least, box);
    edge |= (most > options.light_edge_high_share) & (least < options.light_edge_low_share);
  }
  return edge;
}

StatusOr<KeyframeDepth> KeyframeDepth::Create(const cv::Mat& rgb, const PinholeCamera& camera,
                                              const DepthFilterOptions& options, const Eigen::Matrix3d& crosstalk) {
  PRISM_RETURN_IF_ERROR(options.Check());
  PRISM_RETURN_IF_ERROR(camera.Check());
  if (camera.HasDistortion())
    return InvalidArgumentError("KeyframeDepth: undistort the images first (camera has distortion)");
  if (rgb.type() != CV_8UC3 || rgb.cols != camera.width || rgb.rows != camera.height)
    return InvalidArgumentError("KeyframeDepth: the image must be CV_8UC3 of the camera's size");
  KeyframeDepth kd;
  kd.camera_ = camera;
  kd.options_ = options;
  kd.rgb_ = rgb.clone();
  cv::Mat local_mean;
  NormalisedGrey(rgb, options, &kd.grey_j_, &local_mean);
  const int w = rgb.cols, h = rgb.rows;
  kd.grad_x_ = cv::Mat::zeros(h, w, CV_32F);
  kd.grad_y_ = cv::Mat::zeros(h, w, CV_32F);
  const float min_g2 = static_cast<float>(options.min_gradient * options.min_gradient);
  const float min_mean = static_cast<float>(options.min_local_mean);
  const int border = kPatchHalf + 2;
  if (options.light_edge_radius_px > 0 && std::abs(crosstalk.determinant()) < 1e-9)
    return InvalidArgumentError("KeyframeDepth: the crosstalk matrix must be invertible for the light edges");
  // Empty when the light edges are off (no mask to allocate and read per keyframe).
  const cv::Mat light_edge = options.light_edge_radius_px > 0 ? LightEdgeMask(rgb, crosstalk, options) : cv::Mat();
  // Where the local mean changes fast (DepthFilterOptions::max_local_mean_log_gradient): 255.
  cv::Mat mean_edge;
  if (options.max_local_mean_log_gradient > 0) {
    mean_edge = cv::Mat::zeros(h, w, CV_8U);
    const int r = options.local_mean_radius_px;
    const float limit = static_cast<float>(options.max_local_mean_log_gradient);
    const float floor = static_cast<float>(options.local_mean_floor);
    for (int y = r; y < h - r; ++y) {
      const float* m = local_mean.ptr<float>(y);
      const float* mu = local_mean.ptr<float>(y - r);
      const float* md = local_mean.ptr<float>(y + r);
      uint8_t* e = mean_edge.ptr<uint8_t>(y);
      for (int x = r; x < w - r; ++x) {
        const float gx = (m[x + r] - m[x - r]) / (2.0f * r), gy = (md[x] - mu[x]) / (2.0f * r);
        const float g = std::sqrt(gx * gx + gy * gy);
        e[x] = g > limit * (m[x] + floor) ? 255 : 0;
        if (e[x] && options.local_mean_edge_dim_side_only) {
          // The dim side of the mean's ramp curves up along the gradient, the bright side down.
          const int dx = static_cast<int>(std::lround(r * gx / g)), dy = static_cast<int>(std::lround(r * gy / g));
          const int xa = std::clamp(x + dx, 0, w - 1), ya = std::clamp(y + dy, 0, h - 1);
          const int xb = std::clamp(x - dx, 0, w - 1), yb = std::clamp(y - dy, 0, h - 1);
          if (local_mean.at<float>(ya, xa) + local_mean.at<float>(yb, xb) - 2 * m[x] <= 0) e[x] = 0;
        }
      }
    }
  }
  auto candidates = std::make_shared<Candidates>();
  candidates->row_begin.assign(static_cast<size_t>(h) + 1, 0);
  // Every pixel's index is written at the end of the list and kept (the count advanced) when it is a
  // candidate: no branch per test (they mispredicted), no growth checks.
  std::vector<uint32_t>& index = candidates->index;
  index.resize(static_cast<size_t>(w) * h);
  size_t count = 0;
  for (int y = 1; y < h - 1; ++y) {
    candidates->row_begin[static_cast<size_t>(y)] = static_cast<uint32_t>(count);
    const float* up = kd.grey_j_.ptr<float>(y - 1);
    const float* row = kd.grey_j_.ptr<float>(y);
    const float* down = kd.grey_j_.ptr<float>(y + 1);
    const float* m = local_mean.ptr<float>(y);
    float* gx = kd.grad_x_.ptr<float>(y);
    float* gy = kd.grad_y_.ptr<float>(y);
    const uint8_t* le = light_edge.empty() ? nullptr : light_edge.ptr<uint8_t>(y);
    const uint8_t* me = mean_edge.empty() ? nullptr : mean_edge.ptr<uint8_t>(y);
    for (int x = 1; x < w - 1; ++x) {
      gx[x] = 0.5f * (row[x + 1] - row[x - 1]);
      gy[x] = 0.5f * (down[x] - up[x]);
      const bool inside = !(x < border || y < border || x >= w - border || y >= h - border);
      const bool keep =
          inside && !(m[x] < min_mean) && !(gx[x] * gx[x] + gy[x] * gy[x] < min_g2) && !(le && le[x]) && !(me && me[x]);
      index[count] = static_cast<uint32_t>(y * w + x);
      count += keep;
    }
  }
  index.resize(count);
  index.shrink_to_fit();
  // Rows 0 and h - 1 hold none.
  candidates->row_begin[static_cast<size_t>(h) - 1] = static_cast<uint32_t>(candidates->index.size());
  candidates->row_begin[static_cast<size_t>(h)] = static_cast<uint32_t>(candidates->index.size());
  candidates->slot.assign(static_cast<size_t>(w) * h, -1);
  for (size_t k = 0; k < candidates->index.size(); ++k)
    candidates->slot[candidates->index[k]] = static_cast<int32_t>(k);
  kd.pixels_.assign(candidates->index.size(), Pixel{});
  kd.candidates_ = std::move(candidates);
  return kd;
}

KeyframeDepth KeyframeDepth::Blank() const {
  KeyframeDepth kd;
  kd.camera_ = camera_;
  kd.options_ = options_;
  kd.rgb_ = rgb_;
  kd.grey_j_ = grey_j_;
  kd.grad_x_ = grad_x_;
  kd.grad_y_ = grad_y_;
  kd.candidates_ = candidates_;
  kd.pixels_.assign(pixels_.size(), Pixel{});
  return kd;
}

bool KeyframeDepth::HasImage(const cv::Mat& rgb) const { return SameImageBytes(rgb, rgb_); }

void KeyframeDepth::Seed(const cv::Mat& dense_inverse_depth, double relative_sigma, int observations) {
  const int w = camera_.width;
  for (int y = 0; y < camera_.height; ++y) {
    const float* d = dense_inverse_depth.ptr<float>(y);
    for (uint32_t k = candidates_->row_begin[y]; k < candidates_->row_begin[y + 1]; ++k) {
      const uint32_t i = candidates_->index[k];
      const float di = d[i - static_cast<uint32_t>(y * w)];
      if (!(di > 0)) continue;
      Pixel& p = pixels_[k];
      p.idepth = di;
      const float s = static_cast<float>(relative_sigma) * di;
      p.var = s * s;
      p.observations = static_cast<uint16_t>(observations);
      p.outliers = 0;
    }
  }
  mean_idepth_ = ComputeMeanInverseDepth();
}

void KeyframeDepth::PropagateFrom(const KeyframeDepth& previous, const Rigid3d& this_from_previous,
                                  double fill_relative_sigma) {
  const int w = camera_.width, h = camera_.height;
  const Eigen::Matrix3f R = this_from_previous.rotation.toRotationMatrix().cast<float>();
  const Eigen::Vector3f t = this_from_previous.translation.cast<float>();
  const float fx = static_cast<float>(camera_.fx), fy = static_cast<float>(camera_.fy);
  const float cx = static_cast<float>(camera_.cx), cy = static_cast<float>(camera_.cy);
  const float pfx = static_cast<float>(previous.camera_.fx), pfy = static_cast<float>(previous.camera_.fy);
  const float pcx = static_cast<float>(previous.camera_.cx), pcy = static_cast<float>(previous.camera_.cy);
  const float noise = static_cast<float>(options_.propagation_relative_sigma);
  const int pw = previous.camera_.width;
  for (int y = 0; y < previous.camera_.height; ++y) {
    for (uint32_t k = previous.candidates_->row_begin[y]; k < previous.candidates_->row_begin[y + 1]; ++k) {
      const uint32_t i = previous.candidates_->index[k];
      const int x = static_cast<int>(i) - y * pw;
      const Pixel& src = previous.pixels_[k];
      if (!(src.var > 0) || src.observations == 0) continue;
      const Eigen::Vector3f ray((x - pcx) / pfx, (y - pcy) / pfy, 1.0f);
      const Eigen::Vector3f p = R * (ray / src.idepth) + t;
      if (!(p.z() > 1e-6f)) continue;
      const float u = fx * p.x() / p.z() + cx, v = fy * p.y() / p.z() + cy;
      const int iu = static_cast<int>(std::lround(u)), iv = static_cast<int>(std::lround(v));
      if (iu < 0 || iv < 0 || iu >= w || iv >= h) continue;
      const int32_t slot = candidates_->slot[static_cast<size_t>(iv) * w + iu];
      if (slot < 0) continue;
      const float rho = 1.0f / p.z();
      const float ratio = rho / src.idepth;
      const float var = src.var * ratio * ratio * ratio * ratio + (noise * rho) * (noise * rho);
      Pixel& dst = pixels_[static_cast<size_t>(slot)];
      const uint16_t obs = static_cast<uint16_t>(std::min<int>(src.observations, 20));
      if (!(dst.var > 0)) {
        dst = Pixel{rho, var, obs, 0};
        continue;
      }
      const float diff = rho - dst.idepth;
      if (diff * diff < 4.0f * (var + dst.var)) {
        const float sum = var + dst.var;
        dst.idepth = (dst.idepth * var + rho * dst.var) / sum;
        dst.var = var * dst.var / sum;
        dst.observations = std::max(dst.observations, obs);
      } else if (rho > dst.idepth) {  // nearer: the other one is occluded
        dst = Pixel{rho, var, obs, 0};
      }
    }
  }
  mean_idepth_ = ComputeMeanInverseDepth();  // the fill below adds no observed estimate
  const double mean = mean_idepth_;
  if (mean > 0 && fill_relative_sigma > 0) {
    const float s = static_cast<float>(fill_relative_sigma * mean);
    for (Pixel& p : pixels_)
      if (!(p.var > 0)) p = Pixel{static_cast<float>(mean), s * s, 0, 0};
  }
}

DepthUpdateStats KeyframeDepth::Update(const cv::Mat& frame_grey_j, const Rigid3d& frame_from_keyframe,
                                       ThreadPool* pool) {
  DepthUpdateStats total;
  if (frame_grey_j.type() != CV_32F || frame_grey_j.cols != camera_.width || frame_grey_j.rows != camera_.height)
    return total;
  double mean = MeanInverseDepth();
  if (!(mean > 0)) {
    // Only seeds: their mean.
    double s = 0;
    int n = 0;
    for (const Pixel& p : pixels_)
      if (p.var > 0) s += p.idepth, ++n;
    mean = n ? s / n : 0;
  }
  if (!(mean > 0)) return total;
  const int h = camera_.height;
  const int chunk = 16;
  const int num_chunks = (h + chunk - 1) / chunk;
  std::vector<DepthUpdateStats> stats(num_chunks);
  auto run = [&](std::ptrdiff_t i) {
    UpdateRows(static_cast<int>(i) * chunk, std::min(h, static_cast<int>(i + 1) * chunk), frame_grey_j,
               frame_from_keyframe, mean, &stats[i]);
  };
  if (pool) {
    pool->ParallelFor(0, num_chunks, run);
  } else {
    for (int i = 0; i < num_chunks; ++i) run(i);
  }
  mean_idepth_ = ComputeMeanInverseDepth();
  for (const DepthUpdateStats& s : stats) {
    total.searched += s.searched;
    total.fused += s.fused;
    total.outliers += s.outliers;
    total.no_match += s.no_match;
    total.dropped += s.dropped;
    total.skipped += s.skipped;
  }
  return total;
}

void KeyframeDepth::UpdateRows(int y0, int y1, const cv::Mat& frame, const Rigid3d& frame_from_keyframe,
                               double mean_idepth, DepthUpdateStats* out_stats) {
  // Counted here and written once at the end: the chunks' entries share cache lines, and counting in
  // them from two threads (increments in the inner loops) made the update barely faster on two threads
  // than on one (false sharing; fifty-fourth round).
  DepthUpdateStats counts;
  DepthUpdateStats* const stats = &counts;
  const int w = camera_.width;
  const Eigen::Matrix3f R = frame_from_keyframe.rotation.toRotationMatrix().cast<float>();
  const Eigen::Vector3f t = frame_from_keyframe.translation.cast<float>();
  const Eigen::Vector3f c = -(R.transpose() * t);  // frame centre in the keyframe
  const float fx = static_cast<float>(camera_.fx), fy = static_cast<float>(camera_.fy);
  const float cx = static_cast<float>(camera_.cx), cy = static_cast<float>(camera_.cy);
  const float min_baseline = 0.003f;  // |t| * rho: baseline over depth
  if (t.norm() * static_cast<float>(mean_idepth) < min_baseline) return;
  const float min_cos = static_cast<float>(options_.min_gradient_line_cosine);
  const float max_err = static_cast<float>(options_.max_match_error) * (2 * kPatchHalf + 1);
  const float ratio = static_cast<float>(options_.min_match_ratio);
  const float sigma_l2 = static_cast<float>(options_.epipolar_sigma_px * options_.epipolar_sigma_px);
  const float sigma_i2 = static_cast<float>(options_.image_noise_sigma * options_.image_noise_sigma);
  const float outlier2 = static_cast<float>(options_.outlier_sigmas * options_.outlier_sigmas);
  const int max_search = options_.max_search_px;
  const float search_sigmas = static_cast<float>(options_.search_sigmas);
  const float seed_max_rel_var =
      static_cast<float>(options_.seed_max_relative_sigma * options_.seed_max_relative_sigma);
  const int attached_votes = options_.camera_attached_min_votes;
  const float attached_flow = static_cast<float>(options_.camera_attached_min_flow_px);
  const float attached_ratio = static_cast<float>(options_.camera_attached_error_ratio);
  const float skip_ratio = static_cast<float>(options_.skip_information_ratio);
  const bool skip_on = skip_ratio > 0;

  const LineSamplerImage keyframe_image = ViewOf(grey_j_), frame_image = ViewOf(frame);
  std::vector<float> errors, samples;
  std::vector<int> outside_before;
  const std::vector<uint32_t>& candidates = candidates_->index;
  // Per row, first for all its candidates at once (a loop that vectorises): the epipolar direction in
  // the keyframe (unit, towards the projection of the frame's centre) and the cosine between it and
  // the image gradient; then for those that pass, again at once, the search interval in the frame;
  // then the searches, one pixel at a time.
  std::vector<float> row_dk_x, row_dk_y, row_gcos, row_galong;
  std::vector<uint8_t> row_pass, geo_ok, geo_skip;
  std::vector<int> row_list;
  // Per passing candidate: the search interval's ends and centre in the frame, the keyframe step's
  // image there and its length, and R ray.
  struct SearchGeometry {
    float pa_x, pa_y, pb_x, pb_y, pm_x, pm_y, m_x, m_y, m_norm, a_x, a_y, a_z;
  };
  std::vector<SearchGeometry> geo_values;
  const float r00 = R(0, 0), r01 = R(0, 1), r02 = R(0, 2), r10 = R(1, 0), r11 = R(1, 1), r12 = R(1, 2);
  const float r20 = R(2, 0), r21 = R(2, 1), r22 = R(2, 2);
  const float tx = t.x(), ty = t.y(), tz = t.z();
  const float min_dk_norm = 1e-9f;
  for (int y = y0; y < y1; ++y) {
    const float* gxr = grad_x_.ptr<float>(y);
    const float* gyr = grad_y_.ptr<float>(y);
    const uint32_t k0 = candidates_->row_begin[y], k1 = candidates_->row_begin[y + 1];
    const int n_row = static_cast<int>(k1 - k0);
    if (row_dk_x.size() < static_cast<size_t>(n_row)) {
      row_dk_x.resize(static_cast<size_t>(n_row));
      row_dk_y.resize(static_cast<size_t>(n_row));
      row_gcos.resize(static_cast<size_t>(n_row));
      row_galong.resize(static_cast<size_t>(n_row));
      row_pass.resize(static_cast<size_t>(n_row));
      geo_skip.resize(static_cast<size_t>(n_row));
      row_list.resize(static_cast<size_t>(n_row));
      geo_ok.resize(static_cast<size_t>(n_row));
      geo_values.resize(static_cast<size_t>(n_row));
    }
    SearchGeometry* geo = geo_values.data();
    const uint32_t* row_index = candidates.data() + k0;
    const Pixel* pix = pixels_.data() + k0;  // the row's estimates
    const float ray_y = (y - cy) / fy;
    const float dk_y_unscaled = fy * (c.y() - ray_y * c.z());
    const int row_offset = y * w;
    // The operations of the one-pixel form (Eigen's norm and dot of 2-vectors in the same order).
#pragma omp simd
    for (int j = 0; j < n_row; ++j) {
      const int x = static_cast<int>(row_index[j]) - row_offset;
      const float ray_x = (static_cast<float>(x) - cx) / fx;
      const float dkx = fx * (c.x() - ray_x * c.z()), dky = dk_y_unscaled;
      const float dk_norm = std::sqrt(dkx * dkx + dky * dky);
      const float ux = dkx / dk_norm, uy = dky / dk_norm;
      const float gx = gxr[x], gy = gyr[x];
      const float g_norm = std::sqrt(gx * gx + gy * gy);
      const float galong = std::abs(gx * ux + gy * uy);
      const float gcos = galong / std::max(g_norm, 1e-6f);
      row_dk_x[j] = ux;
      row_dk_y[j] = uy;
      row_gcos[j] = gcos;
      row_galong[j] = galong;
      row_pass[j] = (pix[j].var > 0) & (dk_norm > min_dk_norm) & !(gcos < min_cos);
    }
    // Those that pass, then for all of them at once (vectorised as above) the search interval's ends and
    // centre projected into the frame (pa, pb, pm) and the keyframe step dk mapped into the frame (m),
    // the operations of the one-pixel form (a = R ray summed as Eigen's product of fixed size does,
    // R(i,0) x + (R(i,1) y + R(i,2) z) with z = 1; the projections as the `project` lambda was).
    int n_pass = 0;
    for (int j = 0; j < n_row; ++j) {  // without a branch: each j written, kept when it passes
      row_list[static_cast<size_t>(n_pass)] = j;
      n_pass += row_pass[j];
    }
    const int* list = row_list.data();
#pragma omp simd
    for (int l = 0; l < n_pass; ++l) {
      const int j = list[l];
      const int x = static_cast<int>(row_index[j]) - row_offset;
      const float ray_x = (static_cast<float>(x) - cx) / fx;
      const float ax = r00 * ray_x + (r01 * ray_y + r02 * 1.0f);
      const float ay = r10 * ray_x + (r11 * ray_y + r12 * 1.0f);
      const float az = r20 * ray_x + (r21 * ray_y + r22 * 1.0f);
      const Pixel& pxl = pix[j];
      const float rho = pxl.idepth;
      const float sigma = std::sqrt(pxl.var);
      const float lo = std::max(rho - search_sigmas * sigma, 0.05f * rho);
      float hi = rho + search_sigmas * sigma;
      if (tz < 0) hi = std::min(hi, 0.99f * (-az / tz));
      bool ok = hi > lo;
      const float qax = ax + lo * tx, qay = ay + lo * ty, qaz = az + lo * tz;
      const float qbx = ax + hi * tx, qby = ay + hi * ty, qbz = az + hi * tz;
      const float qmx = ax + rho * tx, qmy = ay + rho * ty, qmz = az + rho * tz;
      ok = ok & (qaz > 1e-6f) & (qbz > 1e-6f) & (qmz > 1e-6f);
      const float pmx = fx * qmx / qmz + cx, pmy = fy * qmy / qmz + cy;
      const float r2x = (static_cast<float>(x) + row_dk_x[j] - cx) / fx;
      const float r2y = (static_cast<float>(y) + row_dk_y[j] - cy) / fy;
      const float a2x = r00 * r2x + (r01 * r2y + r02 * 1.0f);
      const float a2y = r10 * r2x + (r11 * r2y + r12 * 1.0f);
      const float a2z = r20 * r2x + (r21 * r2y + r22 * 1.0f);
      const float q2x = a2x + rho * tx, q2y = a2y + rho * ty, q2z = a2z + rho * tz;
      ok = ok & (q2z > 1e-6f);
      const float mx = (fx * q2x / q2z + cx) - pmx, my = (fy * q2y / q2z + cy) - pmy;
      const float m_norm = std::sqrt(mx * mx + my * my);
      ok = ok & !(m_norm < 0.4f || m_norm > 2.5f);
      const float pax = fx * qax / qaz + cx, pay = fy * qay / qaz + cy;
      const float pbx = fx * qbx / qbz + cx, pby = fy * qby / qbz + cy;
      // The observation this frame would give, predicted at the estimate (skip_information_ratio): the
      // segment's inverse depth per pixel, and the variance model of a match below with the keyframe's
      // gradient along the line for the patch's.
      const float seg_x = pbx - pax, seg_y = pby - pay;
      const float seg_len = std::sqrt(seg_x * seg_x + seg_y * seg_y);
      const float alpha_pred = (hi - lo) / std::max(seg_len, 1e-6f);
      const float gcos_j = row_gcos[j], ga_j = row_galong[j];
      const float var_pred =
          alpha_pred * alpha_pred *
          (sigma_l2 / std::max(gcos_j * gcos_j, 1e-6f) + 2 * sigma_i2 / std::max(ga_j * ga_j, 1e-2f) + 0.1f);
      const bool skip = skip_on & ok & (pxl.observations > 0) & (var_pred > skip_ratio * pxl.var);
      geo_skip[l] = skip;
      geo_ok[l] = ok & !skip;
      geo[l].pa_x = pax;
      geo[l].pa_y = pay;
      geo[l].pb_x = pbx;
      geo[l].pb_y = pby;
      geo[l].pm_x = pmx;
      geo[l].pm_y = pmy;
      geo[l].m_x = mx;
      geo[l].m_y = my;
      geo[l].m_norm = m_norm;
      geo[l].a_x = ax;
      geo[l].a_y = ay;
      geo[l].a_z = az;
    }
    for (int l = 0; l < n_pass; ++l) {
      stats->skipped += geo_skip[l];
      if (!geo_ok[l]) continue;
      const int j = list[l];
      const int x = static_cast<int>(row_index[j]) - row_offset;
      Pixel& px = pixels_[k0 + static_cast<uint32_t>(j)];
      const Eigen::Vector2f dk(row_dk_x[j], row_dk_y[j]);
      const float gcos = row_gcos[j];
      // Keyframe patch along the line.
      float kp[2 * kPatchHalf + 1];
      if (!InsideForBilinear(keyframe_image, x - kPatchHalf * std::abs(dk.x()) - 1,
                             y - kPatchHalf * std::abs(dk.y()) - 1) ||
          !InsideForBilinear(keyframe_image, x + kPatchHalf * std::abs(dk.x()) + 1,
                             y + kPatchHalf * std::abs(dk.y()) + 1))
        continue;
      for (int i = -kPatchHalf; i <= kPatchHalf; ++i)
        kp[i + kPatchHalf] = SampleBilinear(keyframe_image, x + i * dk.x(), y + i * dk.y());
      const float grad_along = 0.5f * (kp[kPatchHalf + 1] - kp[kPatchHalf - 1]);

      const Eigen::Vector3f a(geo[l].a_x, geo[l].a_y, geo[l].a_z);
      const Eigen::Vector2f pa(geo[l].pa_x, geo[l].pa_y), pb(geo[l].pb_x, geo[l].pb_y), pm(geo[l].pm_x, geo[l].pm_y);
      // The keyframe step dk mapped into the frame (at the current estimate): the patch direction there.
      const Eigen::Vector2f m(geo[l].m_x, geo[l].m_y);
      const float m_norm = geo[l].m_norm;
      Eigen::Vector2f seg = pb - pa;
      float len = seg.norm();
      Eigen::Vector2f e = len > 1e-6f ? Eigen::Vector2f(seg / len) : Eigen::Vector2f(m / m_norm);
      Eigen::Vector2f start = pa;
      if (len > max_search) {
        const float centre = (pm - pa).dot(e);
        float s0 = std::clamp(centre - 0.5f * max_search, 0.0f, len - max_search);
        start = pa + s0 * e;
        len = static_cast<float>(max_search);
      }
      ++stats->searched;
      // The patch's samples lie on the frame's epipolar line too (the keyframe's epipolar line maps onto
      // it, so m is parallel to e), mu apart. The search steps by |mu|, so that each position shares four
      // of its five samples with the previous one (as in LSD-SLAM): one bilinear sample per position.
      const float mu = m.dot(e);
      const float step = std::abs(mu);
      // |mu| equals |m| (>= 0.4) up to rounding; the guard bounds the positions (len / step) for any input.
      if (!(step >= 0.25f)) continue;
      float kq[2 * kPatchHalf + 1];  // the keyframe patch in the order of increasing line parameter
      for (int i = 0; i <= 2 * kPatchHalf; ++i) kq[i] = mu > 0 ? kp[i] : kp[2 * kPatchHalf - i];
      // Positions s in [0, n + 1] at line parameter (s - 1) * step from `start` (a neighbour on each
      // side of the segment for the parabola); sample k at (k - 1 - kPatchHalf) * step, so position s
      // uses samples s .. s + 2 kPatchHalf.
      const int n = static_cast<int>(std::floor(len / step)) + 1;
      const int num_samples = n + 2 + 2 * kPatchHalf;
      // Samples outside the frame are 0 and counted: outside_before[k] of the samples before k are
      // outside, so a position is scored only where its window has none (no test per tap, so the
      // scoring loop below vectorises; the same sums in the same order as one tap at a time).
      // Grown only (every entry used below is written first): no refill per pixel.
      if (samples.size() < static_cast<size_t>(num_samples)) samples.resize(static_cast<size_t>(num_samples));
      if (outside_before.size() < static_cast<size_t>(num_samples) + 1)
        outside_before.resize(static_cast<size_t>(num_samples) + 1);
      LineSamples line;
      line.start_x = start.x();
      line.start_y = start.y();
      line.e_x = e.x();
      line.e_y = e.y();
      line.step = step;
      line.k_offset = -1 - kPatchHalf;
      line.num = num_samples;
      SampleAlongLine(frame_image, line, samples.data(), outside_before.data());
      if (errors.size() < static_cast<size_t>(n) + 2) errors.resize(static_cast<size_t>(n) + 2);
      ScorePositions(samples.data(), outside_before.data(), kq, n + 2, errors.data());
      int best = -1;
      float best_err = std::numeric_limits<float>::infinity();
      // The first smallest error, selected without a branch (which mispredicted often: 8% of this
      // function's time in perf).
      for (int s = 1; s <= n; ++s) {
        const float err = errors[static_cast<size_t>(s)];
        const bool smaller = err < best_err;
        best = smaller ? s : best;
        best_err = smaller ? err : best_err;
      }
      if (attached_votes > 0 && best >= 0) {
        // The camera-attached hypothesis: the keyframe patch where it was, in the frame.
        const Eigen::Vector2f matched = start + ((best - 1.0f) * step) * e;
        const float fx0 = x - kPatchHalf * std::abs(dk.x()) - 1, fy0 = y - kPatchHalf * std::abs(dk.y()) - 1;
        const float fx1 = x + kPatchHalf * std::abs(dk.x()) + 1, fy1 = y + kPatchHalf * std::abs(dk.y()) + 1;
        if ((matched - Eigen::Vector2f(x, y)).norm() >= attached_flow && InsideForBilinear(frame_image, fx0, fy0) &&
            InsideForBilinear(frame_image, fx1, fy1)) {
          float err = 0;
          for (int i = -kPatchHalf; i <= kPatchHalf; ++i) {
            const float d = SampleBilinear(frame_image, x + i * dk.x(), y + i * dk.y()) - kp[i + kPatchHalf];
            err += d * d;
          }
          if (err < attached_ratio * best_err && ++px.attached >= attached_votes) {
            px.var = 0;
            px.observations = 0;
            px.outliers = 0;
            ++stats->dropped;
            continue;
          }
        }
      }
      if (best < 0 || best_err > max_err) {
        ++stats->no_match;
        continue;
      }
      // The best score more than 2 px away from the best: |s - best| >= d_min, the first distance with
      // d * step > 2 (the test is monotone in d).
      int d_min = 1;
      while (!(static_cast<float>(d_min) * step > 2.0f)) ++d_min;
      // One pass over all positions with the near ones masked (a fixed trip count: the two loops on
      // either side of the best, of varying lengths, mispredicted their exits; the minimum is the same).
      float second = std::numeric_limits<float>::infinity();
      for (int s = 1; s <= n; ++s) {
        const bool far = s <= best - d_min || s >= best + d_min;
        second = far ? std::min(second, errors[static_cast<size_t>(s)]) : second;
      }
      if (second < ratio * best_err) {
        ++stats->no_match;
        continue;
      }
      float offset = 0;
      const float em = errors[best - 1], ep = errors[best + 1];
      if (std::isfinite(em) && std::isfinite(ep)) {
        const float denom = em - 2 * best_err + ep;
        if (denom > 1e-9f) offset = std::clamp(0.5f * (em - ep) / denom, -0.5f, 0.5f);
      }
      auto rho_at = [&](const Eigen::Vector2f& q) __attribute__((always_inline)) {
        const float qx = (q.x() - cx) / fx, qy = (q.y() - cy) / fy;
        const float den_x = qx * t.z() - t.x(), den_y = qy * t.z() - t.y();
        if (std::abs(den_x) * fx > std::abs(den_y) * fy) return (a.x() - qx * a.z()) / den_x;
        return (a.y() - qy * a.z()) / den_y;
      };
      const Eigen::Vector2f qb = start + ((best - 1.0f + offset) * step) * e;
      const float rho_obs = rho_at(qb);
      const float alpha = std::abs(rho_at(qb + 0.5f * e) - rho_at(qb - 0.5f * e));
      if (!(rho_obs > 0) || !std::isfinite(alpha)) {
        ++stats->no_match;
        continue;
      }
      const float geo = sigma_l2 / (gcos * gcos);
      const float photo = 2 * sigma_i2 / std::max(grad_along * grad_along, 1e-2f);
      const float var_obs = alpha * alpha * (geo + photo + 0.1f);
      if (px.observations == 0) {
        // A wide seed: the first match replaces it, once the baseline makes it precise enough.
        if (var_obs > seed_max_rel_var * rho_obs * rho_obs) {
          ++stats->no_match;
          continue;
        }
        px.idepth = rho_obs;
        px.var = var_obs;
        px.observations = 1;
        ++stats->fused;
        continue;
      }
      const float diff = rho_obs - px.idepth;
      if (diff * diff > outlier2 * (px.var + var_obs)) {
        ++px.outliers;
        ++stats->outliers;
        if (px.outliers >= 3 && px.outliers > px.observations) {
          px.var = 0;
          px.observations = 0;
          px.outliers = 0;
          ++stats->dropped;
        }
        continue;
      }
      const float sum = px.var + var_obs;
      px.idepth = (px.idepth * var_obs + rho_obs * px.var) / sum;
      px.var = px.var * var_obs / sum;
      if (px.observations < 60000) ++px.observations;
      ++stats->fused;
    }
  }
  *out_stats = counts;
}

void KeyframeDepth::Regularise() {
  const int w = camera_.width, h = camera_.height;
  const std::vector<int32_t>& slot = candidates_->slot;
  const size_t num = pixels_.size();
  // Scratch kept per thread (two weights and the new estimate per candidate): no fresh pages per call.
  thread_local std::vector<Pixel> out;
  thread_local std::vector<float> inverse_var, weighted_idepth;
  out.resize(num);
  // Each estimate's weight 1 / var and weighted inverse depth idepth / var, once per candidate instead of
  // once per neighbour (the same quotients). Entries of candidates without an estimate (1 / 0) are read
  // below but never used.
  inverse_var.resize(num);
  weighted_idepth.resize(num);
  for (size_t k = 0; k < num; ++k) {  // for every candidate (a loop that vectorises); used for estimates only
    const Pixel& q = pixels_[k];
    inverse_var[k] = 1.0f / q.var;
    weighted_idepth[k] = q.idepth / q.var;
  }
  const float k2 = static_cast<float>(options_.regularise_sigmas * options_.regularise_sigmas);
  for (int y = 0; y < h; ++y) {
    for (uint32_t k = candidates_->row_begin[y]; k < candidates_->row_begin[y + 1]; ++k) {
      const size_t i = candidates_->index[k];
      const int x = static_cast<int>(i) - y * w;
      const Pixel& p = pixels_[k];
      Pixel& o = out[k];
      o = p;
      if (y < 1 || y >= h - 1 || x < 1 || x >= w - 1) continue;  // the image's border is kept as it is
      if (!(p.var > 0) || p.observations == 0) continue;
      float sw = inverse_var[k], swd = weighted_idepth[k];
      int agree = 0;
      // The neighbours without a branch (which mispredicted): one that is not a candidate, has no
      // estimate or disagrees adds 0 to the sums (which leaves them as they are: the same sums in the same
      // order); a non-candidate reads the pixel's own entries in its place.
      for (int dy = -1; dy <= 1; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
          if (!dx && !dy) continue;
          const int32_t j = slot[static_cast<size_t>(y + dy) * w + x + dx];
          const size_t jj = j < 0 ? k : static_cast<size_t>(j);
          const Pixel& q = pixels_[jj];
          const float d = q.idepth - p.idepth;
          const bool ok = j >= 0 && q.var > 0 && q.observations != 0 && !(d * d > k2 * (p.var + q.var));
          agree += ok;
          sw += ok ? inverse_var[jj] : 0.0f;
          swd += ok ? weighted_idepth[jj] : 0.0f;
        }
      }
      if (agree < options_.min_neighbours) {
        o = Pixel{};
        continue;
      }
      o.idepth = swd / sw;  // the variance is kept (the neighbours are not independent observations)
    }
  }
  pixels_.swap(out);
  mean_idepth_ = ComputeMeanInverseDepth();
}

InverseDepthMap KeyframeDepth::ToInverseDepthMap() const {
  return ToInverseDepthMap(options_.min_observations, options_.max_relative_sigma);
}

InverseDepthMap KeyframeDepth::ToInverseDepthMap(int min_observations, double max_relative_sigma) const {
  InverseDepthMap m;
  m.inverse_depth = cv::Mat::zeros(camera_.height, camera_.width, CV_32F);
  m.variance = cv::Mat::zeros(camera_.height, camera_.width, CV_32F);
  const float r2 = static_cast<float>(max_relative_sigma * max_relative_sigma);
  float* d = m.inverse_depth.ptr<float>(0);  // both continuous (just created)
  float* v = m.variance.ptr<float>(0);
  const std::vector<uint32_t>& index = candidates_->index;
  for (size_t k = 0; k < pixels_.size(); ++k) {
    const Pixel& p = pixels_[k];
    const uint32_t i = index[k];
    // Without a branch: a candidate left out writes the 0 its pixel already has.
    const bool keep =
        p.var > 0 && p.observations >= std::max(min_observations, 1) && !(p.var > r2 * p.idepth * p.idepth);
    d[i] = keep ? p.idepth : 0.0f;
    v[i] = keep ? p.var : 0.0f;
  }
  return m;
}

double KeyframeDepth::ComputeMeanInverseDepth() const {
  double s = 0;
  int n = 0;
  // In image order, as a pass over every pixel. Without a branch: adding 0 leaves the sum as it is, so
  // this is the sum of the estimates alone, in the same order.
  for (const Pixel& p : pixels_) {
    const bool has = p.var > 0 && p.observations > 0;
    s += has ? static_cast<double>(p.idepth) : 0.0;
    n += has;
  }
  return n ? s / n : 0.0;
}

int KeyframeDepth::NumValid() const {
  const float r2 = static_cast<float>(options_.max_relative_sigma * options_.max_relative_sigma);
  int n = 0;
  for (const Pixel& p : pixels_)
    n += p.var > 0 && p.observations >= std::max(options_.min_observations, 1) && p.var <= r2 * p.idepth * p.idepth;
  return n;
}

}  // namespace prism
