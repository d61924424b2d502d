// Semi-dense inverse depth of one keyframe, refined by small-baseline stereo (LSD-SLAM, Engel et al.
// 2013/2014): every high-gradient keyframe pixel keeps a Gaussian estimate of its inverse depth. For
// each tracked frame, the pixel's 5-sample patch along its epipolar line is searched for in the
// frame along the epipolar segment its current +-2 sigma interval maps to; the match becomes an
// observation whose variance combines the geometric error (epipolar line misplacement against the
// gradient direction) and the photometric error (image noise over the gradient along the line), and
// is fused (Kalman update) or counted as an outlier. Matching runs on the local-mean normalised
// image J = 128 I / (box_mean(I) + floor), which cancels the smooth shading change caused by the
// lights that move with the camera.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "core/geometry/camera.h"
#include "core/geometry/point_cloud.h"
#include "core/geometry/rigid3.h"
#include "core/io/inverse_depth.h"
#include "core/util/status.h"

namespace prism {

class ThreadPool;

struct DepthFilterOptions {
  // Grey-level gradient a keyframe pixel needs for a depth estimate, [0, 255]: lower = denser, noisier.
  double min_gradient = 4.0;
  // Minimum |cos| between the gradient direction and the epipolar line; below it the match is too
  // ambiguous along the line, in [0, 1).
  double min_gradient_line_cosine = 0.3;
  // Epipolar search: the 5 samples of a keyframe patch (1 px apart along the epipolar line) against
  // 5 samples along the frame's epipolar line, as far apart as the keyframe's pixel step maps to there,
  // the search stepping by that distance (each position shares 4 samples with the previous one); SSD on
  // J. A match is accepted when its mean squared difference per sample is below this (J grey
  // levels^2), > 0 ...
  double max_match_error = 300.0;
  // ... and the best match outside +-2 px of it is at least this factor worse, >= 1.
  double min_match_ratio = 1.5;
  // Pixels searched along an epipolar line, >= 4: more = faster motion handled, slower mapping.
  int max_search_px = 64;
  // Standard deviation of J's noise, grey levels, > 0 (photometric disparity error).
  double image_noise_sigma = 4.0;
  // Standard deviation of the epipolar line's position from pose error, pixels, > 0.
  double epipolar_sigma_px = 0.5;
  // A pixel without an estimate (a wide seed) takes its first match only when that observation's
  // relative standard deviation is at most this (small baselines wait), > 0.
  double seed_max_relative_sigma = 1.0;
  // The epipolar search covers the estimate +- this many standard deviations, in [1, 10].
  double search_sigmas = 2.0;
  // An observation further than this many standard deviations (of the estimate and the observation
  // combined) from the estimate is an outlier, > 0. A match lies within the searched +- search_sigmas,
  // so with search_sigmas <= outlier_sigmas (the defaults) no observation is ever an outlier: a wrong
  // estimate is pulled towards the end of the segment instead. (LSD-SLAM also searches +-2 sigma but
  // gates at 1 sigma, and widens the variance of an inconsistent estimate instead of counting.)
  double outlier_sigmas = 2.5;
  // Propagation into a new keyframe adds this relative standard deviation (prediction noise), >= 0.
  double propagation_relative_sigma = 0.01;
  // Half size of the box for J's local mean, pixels, in [1, 32]; floor added to it, > 0.
  int local_mean_radius_px = 5;
  double local_mean_floor = 8.0;
  // Pixels whose local mean grey level is below this are not estimated (dark background), in [0, 255].
  double min_local_mean = 25.0;
  // Pixels where J's local mean changes fast are not estimated either: there J = I / mean carries the
  // mean's own pattern (a bright object's outline beside a dim ground; the co-moving shading), which
  // stays put in the image while the surface slides under it. The test: |grad mean| / (mean + floor) >
  // this, the gradient by central differences over local_mean_radius_px, per pixel. 0 = off, >= 0:
  // lower (> 0) = fewer false depths, less coverage. SlamOptions::depth sets 0.03 with the dim side only.
  double max_local_mean_log_gradient = 0.0;
  // Only the dim side of such an edge (the mean curving up along its gradient, sampled at the box's
  // radius on either side): the ground beside a bright object, not the object's own rim.
  bool local_mean_edge_dim_side_only = false;
  // Regularisation: an estimate is replaced by the inverse-variance weighted mean of the 3x3
  // neighbours within this many sigmas of it, > 0; estimates with fewer than `min_neighbours` such
  // neighbours are dropped, in [0, 8].
  double regularise_sigmas = 2.0;
  int min_neighbours = 2;
  // Light edges (off when light_edge_radius_px is 0). The three lights move with the camera, so the
  // edges of their cast and attached shadows slide over the surface as it moves: they are not points
  // of the surface, and a depth triangulated on one is wrong. With a light per colour channel each
  // light's own image is the colour image unmixed by the crosstalk matrix; a pixel is not estimated
  // when, within light_edge_radius_px, one light's share of the light at a pixel (3x3 mean) is both
  // below light_edge_low_share and above light_edge_high_share (that light's shadow edge passes
  // by). Albedo texture changes every light's image in proportion and so does not trigger it.
  // Radius in [0, 16]; 0 <= low < high <= 1.
  int light_edge_radius_px = 0;
  double light_edge_low_share = 0.05;
  double light_edge_high_share = 0.12;
  // Points that move with the camera (cast-shadow edges, the shading of the co-moving lights): a search
  // votes "attached" when the frame at the pixel's own keyframe position (the patch along the keyframe's
  // line, unmoved) matches it better than camera_attached_error_ratio times the best match on the
  // segment, that match being at least camera_attached_min_flow_px away. An estimate with
  // camera_attached_min_votes such votes is dropped for the rest of the keyframe. 0 = off, >= 0;
  // flow > 0; ratio in (0, 1].
  int camera_attached_min_votes = 0;
  double camera_attached_min_flow_px = 2.0;
  double camera_attached_error_ratio = 0.5;
  // Searches that would add little are skipped: before the search, the observation a frame would give
  // is predicted at the current estimate (the same variance model as a match, with the keyframe's
  // gradient along the line and the segment's inverse depth per pixel); an estimate with at least one
  // observation is not searched when that prediction exceeds skip_information_ratio times its variance
  // (it would lower the variance by less than 1 / (1 + ratio)). As the baseline grows within a keyframe
  // the predicted variance shrinks, so a skipped estimate is searched again once a frame can improve it.
  // 0 = every estimate searched, >= 0: lower (> 0) = more skipped, faster mapping, worse ATE and depth (for
  // slow machines, where the mapping falls behind).
  double skip_information_ratio = 0;
  // Observations an estimate needs before it is used, >= 1: more = fewer, surer points.
  int min_observations = 2;
  // Largest relative inverse-depth sigma of a used estimate, > 0: larger = denser, noisier depth.
  double max_relative_sigma = 0.1;

  Status Check() const;
};

struct DepthUpdateStats {
  int searched = 0;  // pixels whose line was searched
  int fused = 0;     // observations fused
  int outliers = 0;  // observations rejected as outliers
  int no_match = 0;  // searches without an acceptable match
  int dropped = 0;   // estimates dropped (too many outliers)
  int skipped = 0;   // searches skipped as uninformative (skip_information_ratio)
};

class KeyframeDepth {
 public:
  // rgb: CV_8UC3 (R, G, B) of the camera's size (no distortion). crosstalk: the rig's (channel c, light
  // l) response matrix, for the light edges (DepthFilterOptions::light_edge_radius_px); must be
  // invertible when they are on.
  static StatusOr<KeyframeDepth> Create(const cv::Mat& rgb, const PinholeCamera& camera,
                                        const DepthFilterOptions& options,
                                        const Eigen::Matrix3d& crosstalk = Eigen::Matrix3d::Identity());

  // A copy without estimates, as Create gives for the same image (the image-derived parts shared).
  KeyframeDepth Blank() const;
  // Whether rgb holds the same bytes as the image this was created from.
  bool HasImage(const cv::Mat& rgb) const;

  // Seeds every candidate pixel (gradient, bright enough) where `dense_inverse_depth` (CV_32F, 0 = none)
  // is set, with the given relative standard deviation; counts as `observations` fused observations.
  void Seed(const cv::Mat& dense_inverse_depth, double relative_sigma, int observations);
  // Propagates the estimates of `previous` into this keyframe: this_from_previous maps points of the
  // previous keyframe's camera into this one. Where two land on one pixel the nearer wins unless they
  // agree (then fused). Candidate pixels left without an estimate are seeded at the mean inverse depth
  // with relative sigma `fill_relative_sigma` (0 observations: searched, not output).
  void PropagateFrom(const KeyframeDepth& previous, const Rigid3d& this_from_previous, double fill_relative_sigma);

  // One stereo update from a tracked frame: frame_from_keyframe from the tracker. `frame_grey_j` from
  // NormalisedGrey. Parallel over rows when `pool` is given.
  DepthUpdateStats Update(const cv::Mat& frame_grey_j, const Rigid3d& frame_from_keyframe, ThreadPool* pool);
  // Smooths and removes isolated estimates (see DepthFilterOptions::regularise_sigmas).
  void Regularise();

  // The output estimates (min_observations, max_relative_sigma).
  InverseDepthMap ToInverseDepthMap() const;
  // Every estimate with at least `min_observations` observations (for tracking).
  InverseDepthMap ToInverseDepthMap(int min_observations, double max_relative_sigma) const;
  // Mean inverse depth over estimates with >= 1 observation (0 if none); kept up to date by every
  // change of the estimates (one pass over the image per change, not per call).
  double MeanInverseDepth() const { return mean_idepth_; }
  // Number of output estimates, and of estimates with >= 1 observation.
  int NumValid() const;
  int NumCandidates() const { return static_cast<int>(pixels_.size()); }

  // The keyframe's local-mean normalised grey image J (CV_32F).
  const cv::Mat& grey_j() const { return grey_j_; }
  const cv::Mat& rgb() const { return rgb_; }
  const PinholeCamera& camera() const { return camera_; }
  const DepthFilterOptions& options() const { return options_; }

  // CV_8U, 255 where a light's shadow edge passes within options.light_edge_radius_px (see
  // DepthFilterOptions; all 0 when the radius is 0). rgb CV_8UC3 (R, G, B); crosstalk invertible.
  static cv::Mat LightEdgeMask(const cv::Mat& rgb, const Eigen::Matrix3d& crosstalk, const DepthFilterOptions& options);
  // J = 128 I / (box_mean(I) + floor) of an RGB image (grey = channel mean); also the raw local mean.
  static void NormalisedGrey(const cv::Mat& rgb, const DepthFilterOptions& options, cv::Mat* grey_j,
                             cv::Mat* local_mean);

 private:
  struct Pixel {
    float idepth = 0;
    float var = 0;  // 0 = no estimate
    uint16_t observations = 0;
    uint16_t outliers = 0;
    uint16_t attached = 0;  // camera-attached votes (DepthFilterOptions::camera_attached_min_votes)
  };
  // UpdateRows's state for one frame and its passes over a row (depth_filter_update.cc).
  class RowUpdate;
  // A patch is 2 kPatchHalf + 1 = 5 samples along the epipolar line, 1 px apart in the keyframe.
  static constexpr int kPatchHalf = 2;

  KeyframeDepth() = default;
  void UpdateRows(int y0, int y1, const cv::Mat& frame, const Rigid3d& frame_from_keyframe, double mean_idepth,
                  DepthUpdateStats* out_stats);
  double ComputeMeanInverseDepth() const;

  PinholeCamera camera_;
  DepthFilterOptions options_;
  cv::Mat rgb_;
  cv::Mat grey_j_;  // CV_32F
  cv::Mat grad_x_, grad_y_;
  // The candidate pixels (high gradient, bright enough): their indices (y * width + x), ascending; where
  // each row's begin (height + 1 entries); and per image pixel its candidate number, -1 for none.
  // Shared by Blank() copies. Only candidates ever hold an estimate, so the estimates are stored per
  // candidate, in image order: the passes over them read one contiguous array.
  struct Candidates {
    std::vector<uint32_t> index;
    std::vector<uint32_t> row_begin;
    std::vector<int32_t> slot;
  };
  std::shared_ptr<const Candidates> candidates_;
  std::vector<Pixel> pixels_;  // per candidate (Candidates::index)
  double mean_idepth_ = 0;     // MeanInverseDepth()
};

}  // namespace prism
