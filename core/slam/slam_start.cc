// SlamSystem's start: the initialisation from the first frames, and the start check with its second start.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <future>
#include <limits>
#include <string>

#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/video/tracking.hpp>

#include "core/photometric/depth_prior.h"
#include "core/slam/slam_system.h"
#include "core/slam/slam_system_impl.h"
#include "core/util/logging.h"
#include "core/util/thread_pool.h"

namespace prism {

using slam_internal::AllPointLights;
using slam_internal::PairScales;
using slam_internal::PairSpread;
using slam_internal::QualityOf;
using slam_internal::ScopedSeconds;
using slam_internal::SecondsSince;

namespace {

cv::Mat ToGrey8(const cv::Mat& rgb) {
  cv::Mat grey;
  cv::cvtColor(rgb, grey, cv::COLOR_RGB2GRAY);
  return grey;
}

// The initialisation's KLT image (SlamOptions::init_track_normalised) and, when `local_mean` is
// given, the raw box mean of the depth filter's normalisation.
cv::Mat KltImage(const cv::Mat& rgb, const SlamOptions& options, cv::Mat* local_mean) {
  if (!options.init_track_normalised) {
    cv::Mat grey = ToGrey8(rgb);
    if (local_mean != nullptr) {
      const int k = 2 * options.depth.local_mean_radius_px + 1;
      cv::blur(grey, *local_mean, cv::Size(k, k), cv::Point(-1, -1), cv::BORDER_REFLECT);
    }
    return grey;
  }
  cv::Mat j, mean, j8;
  KeyframeDepth::NormalisedGrey(rgb, options.depth, &j, &mean);
  j.convertTo(j8, CV_8U);  // J is about 128 on average; saturates at 255
  if (local_mean != nullptr) *local_mean = mean;
  return j8;
}

}  // namespace

void SlamSystem::StepStartCheck(double timestamp, const cv::Mat& rgb, StatusOr<SlamFrameResult>* result) {
  const ScopedSeconds timer(&start_check_report_.seconds);
  StartCheck& c = *start_check_;
  const SlamOptions o = impl_->options;  // a copy: impl_ may be replaced below
  const size_t n = static_cast<size_t>(o.start_check_keyframes);
  c.AddFrame(timestamp, rgb);
  if (!c.retry) {
    if (impl_->keyframes.size() < n) {
      if (static_cast<int>(c.frames.size()) >= o.start_check_max_frames) {
        PRISM_LOG(INFO) << "slam: start check: fewer than " << n << " keyframes after " << c.frames.size()
                        << " frames; not checked";
        start_check_.reset();
      }
      return;
    }
    const auto check_start = std::chrono::steady_clock::now();
    std::vector<double> first;
    if (o.start_check_async) {
      // The pair scales run on their own thread from this frame on; taken at the first frame after they
      // are done (the next keyframe waits for them).
      Impl::PendingStartCheck* pending = impl_->pending_start_check.get();
      if (pending == nullptr) {
        impl_->ApplyPendingAdjustment();
        impl_->StartPairShadingScales(n);
        c.check_frame = c.frames.size() - 1;
        return;
      }
      if (pending->done.wait_for(std::chrono::seconds(0)) != std::future_status::ready) return;
      first = TakeStartCheckScales();
    } else {
      impl_->ApplyPendingAdjustment();
      first = impl_->PairShadingScales(n);
      c.check_frame = c.frames.size() - 1;
    }
    if (first.size() < 3) {
      PRISM_LOG(INFO) << "slam: start check: " << first.size() << " keyframe pairs gave a shading scale; not checked";
      start_check_.reset();
      return;
    }
    start_check_report_.checked = true;
    start_check_report_.first_spread = PairSpread(first);
    if (start_check_report_.first_spread <= o.start_check_max_pair_spread) {
      start_check_report_.passed = true;
      PRISM_LOG(INFO) << "slam: start check passed: the first " << n << " keyframes' pair shading scales spread by "
                      << start_check_report_.first_spread << " (" << 1000 * SecondsSince(check_start) << " ms)";
      start_check_.reset();
      return;
    }
    if (impl_->init_parallax_px >= o.start_check_retry_parallax_fraction * impl_->rig.camera.width) {
      PRISM_LOG(WARNING) << "slam: start check failed: the first " << n << " keyframes' pair shading scales spread by "
                         << start_check_report_.first_spread << " (limit " << o.start_check_max_pair_spread
                         << "), but its initialisation already had the second "
                         << "start's baseline (" << impl_->init_parallax_px << " px); the first start is kept";
      start_check_.reset();
      return;
    }
    PRISM_LOG(WARNING) << "slam: start check failed: the first " << n << " keyframes' pair shading scales spread by "
                       << start_check_report_.first_spread << " (limit " << o.start_check_max_pair_spread
                       << "); starting again from frame 0 with a longer initialisation baseline ("
                       << o.start_check_retry_parallax_fraction << " of the width) alongside";
    SlamOptions retry_options = o;
    retry_options.init_min_parallax_fraction = o.start_check_retry_parallax_fraction;
    StatusOr<std::unique_ptr<Impl>> retry = NewImpl(impl_->rig, retry_options, impl_->pool);
    if (!retry.ok()) {
      PRISM_LOG(WARNING) << "slam: start check: " << retry.status();
      start_check_.reset();
      return;
    }
    c.retry = std::move(*retry);
    c.retry->start_check_running = true;
    start_check_report_.retried = true;
    if (o.start_check_async) {
      // On its own thread: the frames so far, then each new one, while the first start goes on here.
      c.StartSecondStartThread(n, static_cast<size_t>(o.start_check_max_frames), start_check_report_.first_spread);
      return;
    }
    // The second start runs over the frames up to the one the first was checked at, at once (inline that
    // is this frame; on its thread an earlier one), then frame by frame, checked after each as if it had
    // run alongside the first from the check's frame on.
    for (size_t i = 0; i < c.check_frame; ++i) {
      ++start_check_report_.second_frames_on_caller;
      StatusOr<SlamFrameResult> r = c.retry->Process(c.frames[i].timestamp, c.frames[i].rgb);
      if (!r.ok()) {
        PRISM_LOG(WARNING) << "slam: start check: second start: " << r.status();
      }
    }
    for (size_t i = c.check_frame; i < c.frames.size(); ++i) {
      ++start_check_report_.second_frames_on_caller;
      StatusOr<SlamFrameResult> second = c.retry->Process(c.frames[i].timestamp, c.frames[i].rgb);
      if (!StepSecondStart(i, &second)) continue;
      // Closed at frame i. Kept, the second start goes on over the frames after it (as the only start, as
      // if it had been kept there); the caller gets this frame's result from it.
      if (start_check_report_.second_kept) {
        for (size_t j = i + 1; j < c.frames.size(); ++j)
          second = impl_->Process(c.frames[j].timestamp, c.frames[j].rgb);
        *result = std::move(second);
      }
      start_check_.reset();
      return;
    }
    return;
  }
  if (c.second_start.valid()) {
    if (!c.keeping && c.second_start.wait_for(std::chrono::seconds(0)) != std::future_status::ready) return;
    CloseSecondStart(result);
    return;
  }
  ++start_check_report_.second_frames_on_caller;
  StatusOr<SlamFrameResult> second = c.retry->Process(timestamp, rgb);
  if (!StepSecondStart(c.frames.size() - 1, &second)) return;
  if (start_check_report_.second_kept) *result = std::move(second);
  start_check_.reset();
}

std::vector<double> SlamSystem::TakeStartCheckScales() {
  std::unique_ptr<Impl::PendingStartCheck> pending = std::move(impl_->pending_start_check);
  pending->done.get();  // waits; rethrows what the thread threw
  start_check_report_.thread_seconds = pending->thread_seconds;
  start_check_report_.seconds += pending->wait_seconds;
  return std::move(pending->scales);
}

SlamSystem::StartCheck::~StartCheck() {
  {
    std::lock_guard<std::mutex> lock(mutex);
    stop = true;
  }
  more.notify_all();
  if (second_start.valid()) second_start.wait();
}

void SlamSystem::StartCheck::AddFrame(double timestamp, const cv::Mat& rgb) {
  {
    std::lock_guard<std::mutex> lock(mutex);
    frames.push_back({timestamp, rgb.clone()});
  }
  more.notify_one();
}

void SlamSystem::StartCheck::StartSecondStartThread(size_t num_keyframes, size_t max_frames, double first_spread) {
  second_start = std::async(std::launch::async, [this, num_keyframes, max_frames, first_spread] {
    SetCurrentThreadName("slam-2nd-start");
    SecondStartEnd end;
    for (size_t i = 0;; ++i) {
      Frame f;
      {
        std::unique_lock<std::mutex> lock(mutex);
        more.wait(lock, [&] { return stop || i < frames.size() || (catch_up && i == frames.size()); });
        if (stop || i == frames.size()) return end;  // abandoned; or caught up (kept, or at Finish)
        f = frames[i];
      }
      StatusOr<SlamFrameResult> r = retry->Process(f.timestamp, f.rgb);
      if (!r.ok()) {
        PRISM_LOG(WARNING) << "slam: start check: second start: " << r.status();
      }
      if (end.result) {  // kept: catching up
        end.last = std::move(r);
        continue;
      }
      if (i < check_frame) continue;
      end.enough_keyframes = retry->keyframes.size() >= num_keyframes;
      if (!end.enough_keyframes && i + 1 < max_frames) continue;
      if (end.enough_keyframes) {
        retry->ApplyPendingAdjustment();
        end.scales = retry->PairShadingScales(num_keyframes);
      }
      end.decided = true;
      end.frame = i;
      const bool keep =
          end.enough_keyframes && r.ok() && end.scales.size() >= 3 && PairSpread(end.scales) < first_spread;
      end.result = std::move(r);
      if (!keep) return end;
      end.last = end.result;
      retry->start_check_running = false;  // as the only start from here on
      keeping = true;                      // the caller stops the first start and waits for this one
    }
  });
}

void SlamSystem::CloseSecondStart(StatusOr<SlamFrameResult>* result) {
  StartCheck& c = *start_check_;
  {
    std::lock_guard<std::mutex> lock(c.mutex);
    c.catch_up = true;
  }
  c.more.notify_one();
  StartCheck::SecondStartEnd end = c.second_start.get();
  if (end.decided) {
    StatusOr<SlamFrameResult> second = std::move(*end.result);
    StepSecondStart(end.frame, &second, end.enough_keyframes ? &end.scales : nullptr);
    // Kept, it has caught up with every frame on its thread: the newest frame's result is its own.
    if (start_check_report_.second_kept && result != nullptr) *result = std::move(*end.last);
  } else {
    PRISM_LOG(WARNING) << "slam: start check: the second start had fewer than " << impl_->options.start_check_keyframes
                       << " keyframes at the last frame; the first start is kept";
  }
  start_check_.reset();
}

bool SlamSystem::StepSecondStart(size_t frame, StatusOr<SlamFrameResult>* second, const std::vector<double>* scales) {
  StartCheck& c = *start_check_;
  const SlamOptions o = impl_->options;  // a copy: impl_ may be replaced below
  const size_t n = static_cast<size_t>(o.start_check_keyframes);
  if (c.retry->keyframes.size() < n) {
    if (static_cast<int>(frame + 1) >= o.start_check_max_frames) {
      PRISM_LOG(WARNING) << "slam: start check: the second start has fewer than " << n << " keyframes after "
                         << frame + 1 << " frames; the first start is kept";
      return true;
    }
    return false;
  }
  std::vector<double> again;
  if (scales != nullptr) {
    again = *scales;
  } else {
    c.retry->ApplyPendingAdjustment();
    again = c.retry->PairShadingScales(n);
  }
  const double spread = again.size() >= 3 ? PairSpread(again) : std::numeric_limits<double>::infinity();
  start_check_report_.second_checked = true;
  start_check_report_.second_spread = spread;
  if (spread < start_check_report_.first_spread && second->ok()) {
    PRISM_LOG(WARNING) << "slam: start check: the second start is kept (pair spread " << spread << " against "
                       << start_check_report_.first_spread << ")";
    impl_ = std::move(c.retry);
    impl_->start_check_running = false;
    start_check_report_.second_kept = true;
  } else {
    PRISM_LOG(WARNING) << "slam: start check: the first start is kept (pair spread " << start_check_report_.first_spread
                       << " against " << spread << " for the second)";
  }
  return true;
}

void SlamSystem::Impl::StartPairShadingScales(size_t num_keyframes) {
  auto job = std::make_unique<PendingStartCheck>();
  PendingStartCheck* p = job.get();
  // The thread reads its own copies and the rig (a copy too): nothing the frames change.
  job->done = std::async(std::launch::async, [p, rig = rig, pairs = ShadingPairs(num_keyframes, true)] {
    SetCurrentThreadName("slam-start-chk");
    const auto start = std::chrono::steady_clock::now();
    if (AllPointLights(rig))
      for (const auto& [k, scale] : PairScales(rig, pairs)) p->scales.push_back(scale);
    p->thread_seconds = SecondsSince(start);
  });
  pending_start_check = std::move(job);
}

void SlamSystem::Impl::WaitForStartCheck() {
  if (!pending_start_check) return;
  const auto start = std::chrono::steady_clock::now();
  pending_start_check->done.wait();
  pending_start_check->wait_seconds += SecondsSince(start);
}

bool SlamSystem::Impl::StartCheckCloses(const std::vector<double>& scales) const {
  return scales.size() < 3 || PairSpread(scales) <= options.start_check_max_pair_spread ||
         init_parallax_px >= options.start_check_retry_parallax_fraction * rig.camera.width;
}

void SlamSystem::Impl::ResetInit(int64_t frame_id, double timestamp, const cv::Mat& rgb) {
  init_frames.clear();
  init_frames.push_back({frame_id, timestamp, rgb.clone()});
  cv::Mat local_mean, feature_mask;
  const bool masked = options.init_min_feature_local_mean > 0;
  init_prev_grey = KltImage(rgb, options, masked ? &local_mean : nullptr);
  if (masked) cv::compare(local_mean, options.init_min_feature_local_mean, feature_mask, cv::CMP_GE);
  init_points0.clear();
  cv::goodFeaturesToTrack(init_prev_grey, init_points0, 800, 0.01, std::max(4, rig.camera.width / 64), feature_mask);
  init_points = init_points0;
}

StatusOr<SlamFrameResult> SlamSystem::Impl::Initialise(int64_t frame_id, double timestamp, const cv::Mat& rgb) {
  FrameRecord rec;
  rec.result.frame_id = frame_id;
  rec.result.timestamp = timestamp;
  rec.result.state = SlamState::kInitializing;
  if (init_frames.empty()) {
    ResetInit(frame_id, timestamp, rgb);
    rec.result.message = "initialising: waiting for parallax";
    frames.push_back(rec);
    return rec.result;
  }
  init_frames.push_back({frame_id, timestamp, rgb.clone()});
  cv::Mat grey = KltImage(rgb, options, nullptr);
  std::vector<cv::Point2f> next;
  std::vector<uint8_t> status;
  std::vector<float> err;
  if (!init_points.empty()) {
    cv::calcOpticalFlowPyrLK(init_prev_grey, grey, init_points, next, status, err, cv::Size(21, 21), 3);
  }
  std::vector<cv::Point2f> p0, p1;
  for (size_t i = 0; i < next.size(); ++i) {
    if (!status[i]) continue;
    if (next[i].x < 0 || next[i].y < 0 || next[i].x > rgb.cols - 1 || next[i].y > rgb.rows - 1) continue;
    p0.push_back(init_points0[i]);
    p1.push_back(next[i]);
  }
  init_points0.swap(p0);
  init_points.swap(p1);
  init_prev_grey = grey;
  frames.push_back(rec);

  std::string why;
  if (init_points.size() < 40) {
    why = "too few features tracked since the first frame (restarted initialisation)";
    // The frames so far stay kInitializing with identity poses and no keyframe.
    ResetInit(frame_id, timestamp, rgb);
  } else if (static_cast<int>(init_frames.size()) >= options.init_min_frames && TryInitialise(&why)) {
    initialized = true;
    // TryInitialise filled in the buffered frames' records; return this frame's.
    init_frames.clear();
    return frames.back().result;
  }
  if (!initialized && static_cast<int>(init_frames.size()) >= options.init_max_frames) {
    why += " (no initialisation within init_max_frames, restarted from this frame)";
    ResetInit(frame_id, timestamp, rgb);
  }
  frames.back().result.message = "initialising: " + why;
  return frames.back().result;
}

namespace {

// Median distance between where each inlier would appear in the second frame after the rotation alone
// and where it was tracked, pixels: the parallax that triangulates, whatever the path (an arc round the
// objects keeps them still in the image while the rays between the two views open up).
double RotationCompensatedParallax(const PinholeCamera& cam, const Eigen::Matrix3d& R,
                                   const std::vector<cv::Point2f>& p0, const std::vector<cv::Point2f>& p1,
                                   const cv::Mat& inlier_mask) {
  std::vector<double> disp;
  for (size_t i = 0; i < p0.size(); ++i) {
    if (!inlier_mask.at<uint8_t>(static_cast<int>(i))) continue;
    const Eigen::Vector3d ray = R * cam.Unproject(Eigen::Vector2d(p0[i].x, p0[i].y));
    if (ray.z() <= 0) continue;
    disp.push_back((cam.Project(ray) - Eigen::Vector2d(p1[i].x, p1[i].y)).norm());
  }
  if (disp.empty()) return 0;
  std::nth_element(disp.begin(), disp.begin() + disp.size() / 2, disp.end());
  return disp[disp.size() / 2];
}

}  // namespace

bool SlamSystem::Impl::EstimateInitMotion(double* parallax, Eigen::Matrix3d* R, Eigen::Vector3d* t,
                                          cv::Mat* inlier_mask, std::string* why) const {
  const PinholeCamera& cam = rig.camera;
  std::vector<double> disp;
  for (size_t i = 0; i < init_points.size(); ++i) disp.push_back(cv::norm(init_points[i] - init_points0[i]));
  std::nth_element(disp.begin(), disp.begin() + disp.size() / 2, disp.end());
  const double raw = disp[disp.size() / 2];
  const double needed = options.init_min_parallax_fraction * cam.width;
  cv::Mat K = (cv::Mat_<double>(3, 3) << cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1);
  cv::Mat E =
      cv::findEssentialMat(init_points0, init_points, K, cv::RANSAC, 0.999, 1.0 * cam.width / 512.0, *inlier_mask);
  if (E.rows != 3 || E.cols != 3) {
    *why = raw < needed ? "waiting for parallax" : "essential matrix estimation failed";
    return false;
  }
  cv::Mat Rm, tm;
  const int good = cv::recoverPose(E, init_points0, init_points, K, Rm, tm, *inlier_mask);
  const int inliers = cv::countNonZero(*inlier_mask);
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) (*R)(r, c) = Rm.at<double>(r, c);
    (*t)(r) = tm.at<double>(r, 0);
  }
  *parallax = raw;
  if (raw < needed) {
    *parallax = RotationCompensatedParallax(cam, *R, init_points0, init_points, *inlier_mask);
    if (*parallax < needed) {
      *why = "waiting for parallax";
      return false;
    }
  }
  // Features on shading (terminators, shadow edges, highlights) move with the lights, not with the
  // surface, so only a part of them is consistent with one rigid motion: ask for enough RANSAC inliers,
  // nearly all in front of both cameras.
  if (inliers < 30 || inliers < 0.15 * static_cast<double>(init_points.size()) || good < 0.9 * inliers) {
    *why = "relative pose ambiguous (" + std::to_string(good) + " of " + std::to_string(init_points.size()) +
           " features consistent, " + std::to_string(inliers) + " RANSAC inliers, parallax " +
           std::to_string(*parallax) + " px)";
    return false;
  }
  return true;
}

bool SlamSystem::Impl::TryInitialise(std::string* why) {
  const PinholeCamera& cam = rig.camera;
  double parallax = 0;
  Eigen::Matrix3d R;
  Eigen::Vector3d t;
  cv::Mat inlier_mask;
  if (!EstimateInitMotion(&parallax, &R, &t, &inlier_mask, why)) return false;
  // Triangulate (midpoint of the two rays) in the first camera.
  std::vector<Eigen::Vector3d> points;
  std::vector<cv::Point2f> pixels;
  TriangulateInitFeatures(R, t, inlier_mask, &points, &pixels);
  if (points.size() < 30) {
    *why = "too few triangulated points";
    return false;
  }
  std::vector<double> depths;
  for (const auto& p : points) depths.push_back(p.z());
  std::nth_element(depths.begin(), depths.begin() + depths.size() / 2, depths.end());
  const double median_depth = depths[depths.size() / 2];
  const double scale = 1.0 / median_depth;

  // Sparse inverse depth at the features, densified to seed the first keyframe's depth filter.
  InverseDepthMap sparse;
  sparse.inverse_depth = cv::Mat::zeros(cam.height, cam.width, CV_32F);
  sparse.variance = cv::Mat::zeros(cam.height, cam.width, CV_32F);
  for (size_t i = 0; i < points.size(); ++i) {
    const int x = static_cast<int>(std::lround(pixels[i].x)), y = static_cast<int>(std::lround(pixels[i].y));
    if (x < 0 || y < 0 || x >= cam.width || y >= cam.height) continue;
    const float rho = static_cast<float>(1.0 / (points[i].z() * scale));
    sparse.inverse_depth.at<float>(y, x) = rho;
    sparse.variance.at<float>(y, x) = 0.01f * rho * rho;
  }
  DensifyOptions dens;
  dens.sigma_px = std::max(2.0, cam.width / 100.0);
  dens.levels = 6;
  const cv::Mat dense = DensifyInverseDepth(sparse, dens);

  const InitFrame& first = init_frames.front();
  DepthFilterOptions init_depth = options.depth;
  if (!options.init_depth_edge_test) init_depth.max_local_mean_log_gradient = 0;
  StatusOr<KeyframeDepth> kd = KeyframeDepth::Create(first.rgb, cam, init_depth, rig.crosstalk);
  if (!kd.ok()) {
    *why = kd.status().ToString();
    return false;
  }
  auto depth = std::make_unique<KeyframeDepth>(std::move(kd).value());
  depth->Seed(dense, 0.25, 1);

  // The buffered frames' normalised images J and depth updates below run on options.init_threads threads
  // when the SLAM's own pool has fewer: before the first keyframe nothing else runs beside the tracking
  // (the window adjustment and the start check come later), and both are the same to the bit on any
  // number of threads (KeyframeDepth::Update splits by rows).
  std::unique_ptr<ThreadPool> own_pool;
  ThreadPool* init_pool = pool;
  if (options.init_threads > (pool ? pool->num_threads() : 1)) {
    own_pool = std::make_unique<ThreadPool>(options.init_threads);
    init_pool = own_pool.get();
  }
  std::vector<cv::Mat> init_j(init_frames.size());  // frame 0's is not needed (the keyframe)
  const auto make_j = [&](std::ptrdiff_t i) {
    cv::Mat mean;
    if (i > 0) KeyframeDepth::NormalisedGrey(init_frames[static_cast<size_t>(i)].rgb, options.depth, &init_j[i], &mean);
  };
  if (init_pool) {
    init_pool->ParallelFor(0, static_cast<std::ptrdiff_t>(init_frames.size()), make_j);
  } else {
    for (size_t i = 0; i < init_frames.size(); ++i) make_j(static_cast<std::ptrdiff_t>(i));
  }

  // Track the buffered frames against the first one and refine its depth by stereo with each (two
  // passes: the second re-tracks on the refined depth).
  std::vector<Rigid3d> poses(init_frames.size());
  // Each buffered frame's alignment in the last pass (its record's SlamTrackingQuality; frame 0 is the
  // keyframe itself).
  std::vector<SlamTrackingQuality> quality(init_frames.size());
  const Rigid3d last_guess(Eigen::Quaterniond(R), t * scale);
  if (!TrackInitialisationFrames(init_depth, dense, init_j, init_pool, last_guess, &depth, &poses, &quality, why))
    return false;
  // Fraction of candidates with converged depth.
  const double converged = static_cast<double>(depth->NumValid()) / std::max(1, depth->NumCandidates());
  if (converged < options.init_min_converged_fraction) {
    *why = "first keyframe's depth did not converge (" + std::to_string(static_cast<int>(100 * converged)) + "%)";
    return false;
  }

  Keyframe k;
  k.id = 0;
  k.frame_id = first.frame_id;
  k.timestamp = first.timestamp;
  k.rgb = first.rgb;
  keyframes.push_back(k);
  current_depth = std::move(depth);
  if (!RefreshTracker().ok()) {
    // Not initialised after all: no keyframe (the next attempt makes keyframe 0 again).
    keyframes.pop_back();
    current_depth.reset();
    *why = "too few points with depth for the tracker in the first keyframe";
    return false;
  }
  for (size_t i = 0; i < init_frames.size(); ++i) {
    FrameRecord& f = frames[static_cast<size_t>(init_frames[i].frame_id)];
    f.frame_from_keyframe = poses[i];
    f.result.keyframe_id = 0;
    f.result.state = SlamState::kTracking;
    f.result.message.clear();
    f.result.tracking = quality[i];
    f.result.world_from_camera = WorldFromFrame(f);
  }
  frames[static_cast<size_t>(first.frame_id)].result.new_keyframe = true;
  frames_since_keyframe = static_cast<int>(init_frames.size()) - 1;
  has_last = true;
  last_frame_from_kf = poses.back();
  has_prev = init_frames.size() >= 2;
  prev_frame_from_kf = poses[poses.size() - 2];
  init_parallax_px = parallax;
  PRISM_LOG(INFO) << "slam: initialised on frames " << first.frame_id << ".." << init_frames.back().frame_id
                  << ", parallax " << parallax << " px, " << points.size() << " points, converged " << 100 * converged
                  << "%";
  return true;
}

void SlamSystem::Impl::TriangulateInitFeatures(const Eigen::Matrix3d& R, const Eigen::Vector3d& t,
                                               const cv::Mat& inlier_mask, std::vector<Eigen::Vector3d>* points,
                                               std::vector<cv::Point2f>* pixels) const {
  const PinholeCamera& cam = rig.camera;
  for (size_t i = 0; i < init_points.size(); ++i) {
    if (!inlier_mask.at<uint8_t>(static_cast<int>(i))) continue;
    const Eigen::Vector3d a = cam.Unproject(Eigen::Vector2d(init_points0[i].x, init_points0[i].y));
    const Eigen::Vector3d b = R.transpose() * cam.Unproject(Eigen::Vector2d(init_points[i].x, init_points[i].y));
    const Eigen::Vector3d c = -R.transpose() * t;  // second centre in the first camera
    // Solve s a - u b = c in least squares.
    Eigen::Matrix<double, 3, 2> A;
    A.col(0) = a;
    A.col(1) = -b;
    const Eigen::Vector2d su = A.colPivHouseholderQr().solve(c);
    if (!(su(0) > 0 && su(1) > 0)) continue;
    const Eigen::Vector3d p = 0.5 * (su(0) * a + c + su(1) * b);
    if (!(p.z() > 0)) continue;
    points->push_back(p);
    pixels->push_back(init_points0[i]);
  }
}

bool SlamSystem::Impl::TrackInitialisationFrames(const DepthFilterOptions& init_depth, const cv::Mat& dense,
                                                 const std::vector<cv::Mat>& init_j, ThreadPool* init_pool,
                                                 const Rigid3d& last_guess,
                                                 std::unique_ptr<KeyframeDepth>* depth_in_out,
                                                 std::vector<Rigid3d>* poses_out,
                                                 std::vector<SlamTrackingQuality>* quality_out, std::string* why) {
  const PinholeCamera& cam = rig.camera;
  const InitFrame& first = init_frames.front();
  std::unique_ptr<KeyframeDepth>& depth = *depth_in_out;
  std::vector<Rigid3d>& poses = *poses_out;
  std::vector<SlamTrackingQuality>& quality = *quality_out;
  for (int pass = 0; pass < 1 + options.init_rounds; ++pass) {
    if (pass >= 2) {
      // A further round: the depth estimated again from the seed, by stereo with every buffered frame at
      // the poses of the previous pass, then the frames tracked again on it.
      StatusOr<KeyframeDepth> fresh = KeyframeDepth::Create(first.rgb, cam, init_depth, rig.crosstalk);
      if (!fresh.ok()) {
        *why = fresh.status().ToString();
        return false;
      }
      auto redo = std::make_unique<KeyframeDepth>(std::move(fresh).value());
      redo->Seed(dense, 0.25, 1);
      redo->Seed(depth->ToInverseDepthMap(1, 0.5).inverse_depth, 0.25, 1);
      for (size_t i = 1; i < init_frames.size(); ++i) redo->Update(init_j[i], poses[i], init_pool);
      redo->Regularise();
      depth = std::move(redo);
    }
    Tracker* init = init_tracker.get();
    if (!init->SetKeyframe(first.rgb, depth->ToInverseDepthMap(1, 0.5)).ok()) {
      *why = "too few points to track on the first keyframe";
      return false;
    }
    Rigid3d prev, prev2;
    for (size_t i = 1; i < init_frames.size(); ++i) {
      // Constant velocity (pass 1 starts from pass 0's first pose); the last frame of pass 0 starts from
      // the essential-matrix pose.
      Rigid3d guess = i == 1 ? (pass >= 1 ? poses[1] : Rigid3d()) : (prev * prev2.Inverse()) * prev;
      const bool from_essential = pass == 0 && i + 1 == init_frames.size();
      if (from_essential) guess = last_guess;
      StatusOr<TrackingResult> tr = init->Track(init_frames[i].rgb, guess);
      const double mean_idepth = depth->MeanInverseDepth();
      bool retried = false;
      if (tr.ok() && tr->ok && !from_essential && !PlausibleStep(tr->frame_from_keyframe, guess, mean_idepth)) {
        StatusOr<TrackingResult> retry = init->Track(init_frames[i].rgb, prev);
        if (!(retry.ok() && retry->ok && PlausibleStep(retry->frame_from_keyframe, guess, mean_idepth))) {
          *why = "tracking the initialisation frames failed: implausible jump at buffered frame " + std::to_string(i);
          return false;
        }
        tr = retry;
        retried = true;
      }
      if (!tr.ok() || !tr->ok) {
        *why = "tracking the initialisation frames failed" + (tr.ok() ? ": " + tr->lost_reason : std::string());
        return false;
      }
      poses[i] = tr->frame_from_keyframe;
      // The previous buffered frame's pose (frame 1's is the keyframe's own).
      quality[i] = QualityOf(*tr, retried, guess, prev, mean_idepth);
      prev2 = prev;
      prev = poses[i];
      if (pass == 0) {
        depth->Update(init_j[i], poses[i], init_pool);
        // Keep the tracker's copy of the refined depth fresh, as during tracking (on the rough first depth
        // the residuals grew from frame to frame until one frame jumped).
        if (i % static_cast<size_t>(options.tracker_refresh_frames) == 0 && i + 1 < init_frames.size()) {
          depth->Regularise();
          if (!init->SetKeyframe(first.rgb, depth->ToInverseDepthMap(1, 0.5)).ok()) {
            *why = "too few points to track on the first keyframe";
            return false;
          }
        }
      }
    }
    if (pass == 0) depth->Regularise();
  }
  return true;
}

}  // namespace prism
