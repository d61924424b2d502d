// KeyframeDepth::Update: one stereo update of the estimates from a tracked frame (see depth_filter.h): per
// candidate the epipolar search in the frame, the match tests and the fusion of the observation.
#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include "core/slam/depth_filter.h"
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

}  // namespace

// UpdateRows for one frame: the pose and the options as the passes read them, scratch arrays grown only,
// and the counts (written to the chunk's entry once at the end: the chunks' entries share cache lines,
// and counting in them from two threads made the update barely faster on two threads than on one).
// Per row, first for all its candidates at once (a loop that vectorises) the epipolar direction in the
// keyframe (unit, towards the projection of the frame's centre) and the cosine between it and the image
// gradient; then for those that pass, again at once, the search interval in the frame; then the
// searches, one pixel at a time.
class KeyframeDepth::RowUpdate {
 public:
  RowUpdate(KeyframeDepth* depth, const cv::Mat& frame, const Rigid3d& frame_from_keyframe);
  // Whether the baseline over the depth (|t| * rho at the mean inverse depth) is too small for stereo.
  bool BaselineTooSmall(double mean_idepth) const {
    const float min_baseline = 0.003f;  // |t| * rho: baseline over depth
    return translation_.norm() * static_cast<float>(mean_idepth) < min_baseline;
  }
  void Row(int y);
  const DepthUpdateStats& counts() const { return counts_; }

 private:
  // One row's candidates: the first one's number, how many, their pixel indices and estimates.
  struct RowCandidates {
    int y = 0;
    uint32_t k0 = 0;
    int count = 0;
    const uint32_t* index = nullptr;
    const Pixel* pixels = nullptr;
    int offset = 0;   // y * width
    float ray_y = 0;  // the row's normalised image coordinate
  };
  // Per passing candidate: the search interval's ends and centre in the frame, the keyframe step's
  // image there and its length, and R ray.
  struct SearchGeometry {
    float pa_x, pa_y, pb_x, pb_y, pm_x, pm_y, m_x, m_y, m_norm, a_x, a_y, a_z;
  };
  // One candidate's search along its epipolar segment in the frame.
  struct LineSearch {
    float kp[2 * kPatchHalf + 1];  // the keyframe patch along the keyframe's line
    float grad_along = 0;          // the keyframe's gradient along the line at the pixel
    Eigen::Vector2f start, e;      // where the positions start on the frame's line, and its direction
    float step = 0;                // between positions (and samples), pixels
    int n = 0;                     // positions 1 .. n cover the segment (0 and n + 1: a neighbour each side)
    int best = -1;                 // the first smallest error's position (-1: none)
    float best_err = 0;
  };

  void Reserve(int n_row);
  void Directions(const RowCandidates& row);
  int ListPassing(int n_row);
  void SearchIntervals(const RowCandidates& row, int n_pass);
  void SearchAndFuse(const RowCandidates& row, int j, const SearchGeometry& g);
  bool SearchLine(int x, int y, const Eigen::Vector2f& dk, const SearchGeometry& g, LineSearch* search);
  bool DropsAsCameraAttached(int x, int y, const Eigen::Vector2f& dk, const LineSearch& search, Pixel* pixel);
  bool MatchedInverseDepth(const LineSearch& search, const SearchGeometry& g, float* rho_obs, float* alpha);
  void Fuse(float rho_obs, float var_obs, Pixel* pixel);
  static void ScorePositions(const float* samples, const int* outside_before, const float* patch, int positions,
                             float* errors);

  // The inverse depth along the keyframe ray a = R ray whose projection in the frame is q (from the
  // better conditioned image axis).
  __attribute__((always_inline)) float InverseDepthAt(const Eigen::Vector3f& a, const Eigen::Vector2f& q) const {
    const Eigen::Vector3f& t = translation_;
    const float qx = (q.x() - cx_) / fx_, qy = (q.y() - cy_) / fy_;
    const float den_x = qx * t.z() - t.x(), den_y = qy * t.z() - t.y();
    if (std::abs(den_x) * fx_ > std::abs(den_y) * fy_) return (a.x() - qx * a.z()) / den_x;
    return (a.y() - qy * a.z()) / den_y;
  }

  KeyframeDepth* const depth_;
  const Eigen::Matrix3f rotation_;
  const Eigen::Vector3f translation_;
  const Eigen::Vector3f centre_;  // frame centre in the keyframe
  const float fx_, fy_, cx_, cy_;
  const float min_cos_, max_err_, ratio_, sigma_l2_, sigma_i2_, outlier2_;
  const int max_search_;
  const float search_sigmas_, seed_max_rel_var_;
  const int attached_votes_;
  const float attached_flow_, attached_ratio_, skip_ratio_;
  const bool skip_on_;
  const LineSamplerImage keyframe_image_, frame_image_;

  DepthUpdateStats counts_;
  std::vector<float> errors_, samples_;
  std::vector<int> outside_before_;
  std::vector<float> row_dk_x_, row_dk_y_, row_gcos_, row_galong_;
  std::vector<uint8_t> row_pass_, geo_ok_, geo_skip_;
  std::vector<int> row_list_;
  std::vector<SearchGeometry> geo_values_;
};

KeyframeDepth::RowUpdate::RowUpdate(KeyframeDepth* depth, const cv::Mat& frame, const Rigid3d& frame_from_keyframe)
    : depth_(depth),
      rotation_(frame_from_keyframe.rotation.toRotationMatrix().cast<float>()),
      translation_(frame_from_keyframe.translation.cast<float>()),
      centre_(-(rotation_.transpose() * translation_)),
      fx_(static_cast<float>(depth->camera_.fx)),
      fy_(static_cast<float>(depth->camera_.fy)),
      cx_(static_cast<float>(depth->camera_.cx)),
      cy_(static_cast<float>(depth->camera_.cy)),
      min_cos_(static_cast<float>(depth->options_.min_gradient_line_cosine)),
      max_err_(static_cast<float>(depth->options_.max_match_error) * (2 * kPatchHalf + 1)),
      ratio_(static_cast<float>(depth->options_.min_match_ratio)),
      sigma_l2_(static_cast<float>(depth->options_.epipolar_sigma_px * depth->options_.epipolar_sigma_px)),
      sigma_i2_(static_cast<float>(depth->options_.image_noise_sigma * depth->options_.image_noise_sigma)),
      outlier2_(static_cast<float>(depth->options_.outlier_sigmas * depth->options_.outlier_sigmas)),
      max_search_(depth->options_.max_search_px),
      search_sigmas_(static_cast<float>(depth->options_.search_sigmas)),
      seed_max_rel_var_(
          static_cast<float>(depth->options_.seed_max_relative_sigma * depth->options_.seed_max_relative_sigma)),
      attached_votes_(depth->options_.camera_attached_min_votes),
      attached_flow_(static_cast<float>(depth->options_.camera_attached_min_flow_px)),
      attached_ratio_(static_cast<float>(depth->options_.camera_attached_error_ratio)),
      skip_ratio_(static_cast<float>(depth->options_.skip_information_ratio)),
      skip_on_(skip_ratio_ > 0),
      keyframe_image_(ViewOf(depth->grey_j_)),
      frame_image_(ViewOf(frame)) {}

void KeyframeDepth::RowUpdate::Row(int y) {
  const Candidates& candidates = *depth_->candidates_;
  RowCandidates row;
  row.y = y;
  row.k0 = candidates.row_begin[y];
  row.count = static_cast<int>(candidates.row_begin[y + 1] - row.k0);
  Reserve(row.count);
  row.index = candidates.index.data() + row.k0;
  row.pixels = depth_->pixels_.data() + row.k0;
  row.offset = y * depth_->camera_.width;
  row.ray_y = (y - cy_) / fy_;
  Directions(row);
  const int n_pass = ListPassing(row.count);
  SearchIntervals(row, n_pass);
  for (int l = 0; l < n_pass; ++l) {
    counts_.skipped += geo_skip_[l];
    if (!geo_ok_[l]) continue;
    SearchAndFuse(row, row_list_[l], geo_values_[l]);
  }
}

void KeyframeDepth::RowUpdate::Reserve(int n_row) {
  if (row_dk_x_.size() < static_cast<size_t>(n_row)) {
    row_dk_x_.resize(static_cast<size_t>(n_row));
    row_dk_y_.resize(static_cast<size_t>(n_row));
    row_gcos_.resize(static_cast<size_t>(n_row));
    row_galong_.resize(static_cast<size_t>(n_row));
    row_pass_.resize(static_cast<size_t>(n_row));
    geo_skip_.resize(static_cast<size_t>(n_row));
    row_list_.resize(static_cast<size_t>(n_row));
    geo_ok_.resize(static_cast<size_t>(n_row));
    geo_values_.resize(static_cast<size_t>(n_row));
  }
}

// For all the row's candidates at once: the unit epipolar direction, the gradient's cosine with it and
// its component along it, and whether the candidate passes (an estimate, a direction, the cosine).
void KeyframeDepth::RowUpdate::Directions(const RowCandidates& row) {
  const float* gxr = depth_->grad_x_.ptr<float>(row.y);
  const float* gyr = depth_->grad_y_.ptr<float>(row.y);
  const Eigen::Vector3f c = centre_;
  const float fx = fx_, fy = fy_, cx = cx_, min_cos = min_cos_;
  const float min_dk_norm = 1e-9f;
  const int n_row = row.count, row_offset = row.offset;
  const uint32_t* row_index = row.index;
  const Pixel* pix = row.pixels;
  float* row_dk_x = row_dk_x_.data();
  float* row_dk_y = row_dk_y_.data();
  float* row_gcos = row_gcos_.data();
  float* row_galong = row_galong_.data();
  uint8_t* row_pass = row_pass_.data();
  const float ray_y = row.ray_y;
  const float dk_y_unscaled = fy * (c.y() - ray_y * c.z());
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
}

// The passing candidates' numbers in the row, in order; returns how many.
int KeyframeDepth::RowUpdate::ListPassing(int n_row) {
  int n_pass = 0;
  for (int j = 0; j < n_row; ++j) {  // without a branch: each j written, kept when it passes
    row_list_[static_cast<size_t>(n_pass)] = j;
    n_pass += row_pass_[j];
  }
  return n_pass;
}

// For all the passing candidates at once (vectorised as Directions) the search interval's ends and
// centre projected into the frame (pa, pb, pm) and the keyframe step dk mapped into the frame (m), the
// operations of the one-pixel form (a = R ray summed as Eigen's product of fixed size does,
// R(i,0) x + (R(i,1) y + R(i,2) z) with z = 1; the projections as a `project` lambda would); and whether
// each is searched (geo_ok_) or skipped as uninformative (geo_skip_).
void KeyframeDepth::RowUpdate::SearchIntervals(const RowCandidates& row, int n_pass) {
  const Eigen::Matrix3f& R = rotation_;
  const float r00 = R(0, 0), r01 = R(0, 1), r02 = R(0, 2), r10 = R(1, 0), r11 = R(1, 1), r12 = R(1, 2);
  const float r20 = R(2, 0), r21 = R(2, 1), r22 = R(2, 2);
  const float tx = translation_.x(), ty = translation_.y(), tz = translation_.z();
  const float fx = fx_, fy = fy_, cx = cx_, cy = cy_;
  const float search_sigmas = search_sigmas_, sigma_l2 = sigma_l2_, sigma_i2 = sigma_i2_;
  const float skip_ratio = skip_ratio_;
  const bool skip_on = skip_on_;
  const int y = row.y, row_offset = row.offset;
  const float ray_y = row.ray_y;
  const uint32_t* row_index = row.index;
  const Pixel* pix = row.pixels;
  const int* list = row_list_.data();
  const float* row_dk_x = row_dk_x_.data();
  const float* row_dk_y = row_dk_y_.data();
  const float* row_gcos = row_gcos_.data();
  const float* row_galong = row_galong_.data();
  uint8_t* geo_skip = geo_skip_.data();
  uint8_t* geo_ok = geo_ok_.data();
  SearchGeometry* geo = geo_values_.data();
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
    // segment's inverse depth per pixel, and the variance model of a match (SearchAndFuse) with the
    // keyframe's gradient along the line for the patch's.
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
}

// Candidate j of the row: the search, the camera-attached vote, the match tests, and the fusion of the
// observation with its variance (geometric and photometric error, scaled to inverse depth).
void KeyframeDepth::RowUpdate::SearchAndFuse(const RowCandidates& row, int j, const SearchGeometry& g) {
  const int x = static_cast<int>(row.index[j]) - row.offset;
  const int y = row.y;
  Pixel& px = depth_->pixels_[row.k0 + static_cast<uint32_t>(j)];
  const Eigen::Vector2f dk(row_dk_x_[j], row_dk_y_[j]);
  const float gcos = row_gcos_[j];
  LineSearch search;
  if (!SearchLine(x, y, dk, g, &search)) return;
  if (attached_votes_ > 0 && search.best >= 0 && DropsAsCameraAttached(x, y, dk, search, &px)) return;
  float rho_obs, alpha;
  if (!MatchedInverseDepth(search, g, &rho_obs, &alpha)) return;
  const float geo = sigma_l2_ / (gcos * gcos);
  const float photo = 2 * sigma_i2_ / std::max(search.grad_along * search.grad_along, 1e-2f);
  const float var_obs = alpha * alpha * (geo + photo + 0.1f);
  Fuse(rho_obs, var_obs, &px);
}

// The keyframe patch, the frame's line sampled over the segment (at most max_search_px long, about the
// estimate) and every position's error, and the best position; false when the patch leaves the
// keyframe or the line's step is degenerate.
bool KeyframeDepth::RowUpdate::SearchLine(int x, int y, const Eigen::Vector2f& dk, const SearchGeometry& g,
                                          LineSearch* search) {
  const LineSamplerImage& keyframe_image = keyframe_image_;
  const int max_search = max_search_;
  // Keyframe patch along the line.
  float* kp = search->kp;
  if (!InsideForBilinear(keyframe_image, x - kPatchHalf * std::abs(dk.x()) - 1,
                         y - kPatchHalf * std::abs(dk.y()) - 1) ||
      !InsideForBilinear(keyframe_image, x + kPatchHalf * std::abs(dk.x()) + 1, y + kPatchHalf * std::abs(dk.y()) + 1))
    return false;
  for (int i = -kPatchHalf; i <= kPatchHalf; ++i)
    kp[i + kPatchHalf] = SampleBilinear(keyframe_image, x + i * dk.x(), y + i * dk.y());
  search->grad_along = 0.5f * (kp[kPatchHalf + 1] - kp[kPatchHalf - 1]);

  const Eigen::Vector2f pa(g.pa_x, g.pa_y), pb(g.pb_x, g.pb_y), pm(g.pm_x, g.pm_y);
  // The keyframe step dk mapped into the frame (at the current estimate): the patch direction there.
  const Eigen::Vector2f m(g.m_x, g.m_y);
  const float m_norm = g.m_norm;
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
  ++counts_.searched;
  // The patch's samples lie on the frame's epipolar line too (the keyframe's epipolar line maps onto
  // it, so m is parallel to e), mu apart. The search steps by |mu|, so that each position shares four
  // of its five samples with the previous one (as in LSD-SLAM): one bilinear sample per position.
  const float mu = m.dot(e);
  const float step = std::abs(mu);
  // |mu| equals |m| (>= 0.4) up to rounding; the guard bounds the positions (len / step) for any input.
  if (!(step >= 0.25f)) return false;
  float kq[2 * kPatchHalf + 1];  // the keyframe patch in the order of increasing line parameter
  for (int i = 0; i <= 2 * kPatchHalf; ++i) kq[i] = mu > 0 ? kp[i] : kp[2 * kPatchHalf - i];
  // Positions s in [0, n + 1] at line parameter (s - 1) * step from `start` (a neighbour on each
  // side of the segment for the parabola); sample k at (k - 1 - kPatchHalf) * step, so position s
  // uses samples s .. s + 2 kPatchHalf.
  const int n = static_cast<int>(std::floor(len / step)) + 1;
  const int num_samples = n + 2 + 2 * kPatchHalf;
  // Samples outside the frame are 0 and counted: outside_before[k] of the samples before k are
  // outside, so a position is scored only where its window has none (no test per tap, so the
  // scoring loop vectorises; the same sums in the same order as one tap at a time).
  // Grown only (every entry used below is written first): no refill per pixel.
  if (samples_.size() < static_cast<size_t>(num_samples)) samples_.resize(static_cast<size_t>(num_samples));
  if (outside_before_.size() < static_cast<size_t>(num_samples) + 1)
    outside_before_.resize(static_cast<size_t>(num_samples) + 1);
  LineSamples line;
  line.start_x = start.x();
  line.start_y = start.y();
  line.e_x = e.x();
  line.e_y = e.y();
  line.step = step;
  line.k_offset = -1 - kPatchHalf;
  line.num = num_samples;
  SampleAlongLine(frame_image_, line, samples_.data(), outside_before_.data());
  if (errors_.size() < static_cast<size_t>(n) + 2) errors_.resize(static_cast<size_t>(n) + 2);
  ScorePositions(samples_.data(), outside_before_.data(), kq, n + 2, errors_.data());
  int best = -1;
  float best_err = std::numeric_limits<float>::infinity();
  // The first smallest error, selected without a branch (which mispredicted often).
  for (int s = 1; s <= n; ++s) {
    const float err = errors_[static_cast<size_t>(s)];
    const bool smaller = err < best_err;
    best = smaller ? s : best;
    best_err = smaller ? err : best_err;
  }
  search->start = start;
  search->e = e;
  search->step = step;
  search->n = n;
  search->best = best;
  search->best_err = best_err;
  return true;
}

// The camera-attached vote (DepthFilterOptions::camera_attached_min_votes): true when it drops the
// estimate.
bool KeyframeDepth::RowUpdate::DropsAsCameraAttached(int x, int y, const Eigen::Vector2f& dk, const LineSearch& search,
                                                     Pixel* pixel) {
  Pixel& px = *pixel;
  const float* kp = search.kp;
  // The camera-attached hypothesis: the keyframe patch where it was, in the frame.
  const Eigen::Vector2f matched = search.start + ((search.best - 1.0f) * search.step) * search.e;
  const float fx0 = x - kPatchHalf * std::abs(dk.x()) - 1, fy0 = y - kPatchHalf * std::abs(dk.y()) - 1;
  const float fx1 = x + kPatchHalf * std::abs(dk.x()) + 1, fy1 = y + kPatchHalf * std::abs(dk.y()) + 1;
  if ((matched - Eigen::Vector2f(x, y)).norm() >= attached_flow_ && InsideForBilinear(frame_image_, fx0, fy0) &&
      InsideForBilinear(frame_image_, fx1, fy1)) {
    float err = 0;
    for (int i = -kPatchHalf; i <= kPatchHalf; ++i) {
      const float d = SampleBilinear(frame_image_, x + i * dk.x(), y + i * dk.y()) - kp[i + kPatchHalf];
      err += d * d;
    }
    if (err < attached_ratio_ * search.best_err && ++px.attached >= attached_votes_) {
      px.var = 0;
      px.observations = 0;
      px.outliers = 0;
      ++counts_.dropped;
      return true;
    }
  }
  return false;
}

// The match's inverse depth (at the sub-sample minimum of the errors) and the inverse depth per pixel
// along the line there (alpha); false, counted as no match, when the best error is too large, a far
// position scores nearly as well, or the depth is not in front of the camera.
bool KeyframeDepth::RowUpdate::MatchedInverseDepth(const LineSearch& search, const SearchGeometry& g,
                                                   float* rho_obs_out, float* alpha_out) {
  const int best = search.best, n = search.n;
  const float best_err = search.best_err, step = search.step;
  const Eigen::Vector2f& start = search.start;
  const Eigen::Vector2f& e = search.e;
  if (best < 0 || best_err > max_err_) {
    ++counts_.no_match;
    return false;
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
    second = far ? std::min(second, errors_[static_cast<size_t>(s)]) : second;
  }
  if (second < ratio_ * best_err) {
    ++counts_.no_match;
    return false;
  }
  float offset = 0;
  const float em = errors_[best - 1], ep = errors_[best + 1];
  if (std::isfinite(em) && std::isfinite(ep)) {
    const float denom = em - 2 * best_err + ep;
    if (denom > 1e-9f) offset = std::clamp(0.5f * (em - ep) / denom, -0.5f, 0.5f);
  }
  const Eigen::Vector3f a(g.a_x, g.a_y, g.a_z);
  const Eigen::Vector2f qb = start + ((best - 1.0f + offset) * step) * e;
  const float rho_obs = InverseDepthAt(a, qb);
  const float alpha = std::abs(InverseDepthAt(a, qb + 0.5f * e) - InverseDepthAt(a, qb - 0.5f * e));
  if (!(rho_obs > 0) || !std::isfinite(alpha)) {
    ++counts_.no_match;
    return false;
  }
  *rho_obs_out = rho_obs;
  *alpha_out = alpha;
  return true;
}

// The observation into the estimate: a wide seed takes its first match when precise enough; one too far
// from the estimate is an outlier (and enough of them drop the estimate); else the Kalman update.
void KeyframeDepth::RowUpdate::Fuse(float rho_obs, float var_obs, Pixel* pixel) {
  Pixel& px = *pixel;
  if (px.observations == 0) {
    // A wide seed: the first match replaces it, once the baseline makes it precise enough.
    if (var_obs > seed_max_rel_var_ * rho_obs * rho_obs) {
      ++counts_.no_match;
      return;
    }
    px.idepth = rho_obs;
    px.var = var_obs;
    px.observations = 1;
    ++counts_.fused;
    return;
  }
  const float diff = rho_obs - px.idepth;
  if (diff * diff > outlier2_ * (px.var + var_obs)) {
    ++px.outliers;
    ++counts_.outliers;
    if (px.outliers >= 3 && px.outliers > px.observations) {
      px.var = 0;
      px.observations = 0;
      px.outliers = 0;
      ++counts_.dropped;
    }
    return;
  }
  const float sum = px.var + var_obs;
  px.idepth = (px.idepth * var_obs + rho_obs * px.var) / sum;
  px.var = px.var * var_obs / sum;
  if (px.observations < 60000) ++px.observations;
  ++counts_.fused;
}

// The sum of squared differences between the patch `patch` (2 kPatchHalf + 1 values) and the
// samples at each of `positions` positions s (samples s .. s + 2 kPatchHalf), the taps summed in
// order; infinity where one of those samples is outside the frame (outside_before counts them).
void KeyframeDepth::RowUpdate::ScorePositions(const float* samples, const int* outside_before, const float* patch,
                                              int positions, float* errors) {
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
  RowUpdate update(this, frame, frame_from_keyframe);
  if (update.BaselineTooSmall(mean_idepth)) return;
  for (int y = y0; y < y1; ++y) update.Row(y);
  *out_stats = update.counts();
}

}  // namespace prism
