#include "core/slam/depth_filter.h"

#include <algorithm>
#include <cmath>

#include <opencv2/imgproc.hpp>

#include "core/slam/image_bytes.h"

namespace prism {

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
