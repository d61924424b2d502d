#include "core/synth/trajectory.h"

#include <cmath>
#include <random>
#include <sstream>

namespace prism::synth {
namespace {

// Sum of three sinusoids with seeded frequencies (0.1-0.6 Hz) and phases: smooth, zero-mean-ish.
struct SmoothJitter {
  double freq[3], phase[3], weight[3];
  explicit SmoothJitter(std::mt19937& rng) {
    std::uniform_real_distribution<double> f(0.1, 0.6), p(0, 2 * M_PI), w(0.5, 1.0);
    double sum = 0;
    for (int i = 0; i < 3; ++i) {
      freq[i] = f(rng);
      phase[i] = p(rng);
      weight[i] = w(rng);
      sum += weight[i];
    }
    for (double& x : weight) x /= sum;
  }
  double operator()(double t) const {
    double v = 0;
    for (int i = 0; i < 3; ++i) v += weight[i] * std::sin(2 * M_PI * freq[i] * t + phase[i]);
    return v;
  }
};

}  // namespace

Status TrajectoryOptions::Check() const {
  std::ostringstream e;
  if (!(radius_m > 0)) e << "TrajectoryOptions.radius_m = " << radius_m << "; violated: > 0";
  else if (!(std::abs(arc_deg) <= 720)) e << "TrajectoryOptions.arc_deg = " << arc_deg << "; violated: |.| <= 720";
  else if (!(fps > 0 && fps <= 1000)) e << "TrajectoryOptions.fps = " << fps << "; violated: in (0, 1000]";
  else if (frames < 2 || frames > 1000000) e << "TrajectoryOptions.frames = " << frames << "; violated: in [2, 1e6]";
  else if (!(forward_duration_s >= 0)) e << "TrajectoryOptions.forward_duration_s must be >= 0";
  else if (!(jitter_position_m >= 0 && jitter_rotation_deg >= 0)) e << "TrajectoryOptions: jitter must be >= 0";
  if (e.str().empty()) return Status::Ok();
  return InvalidArgumentError(e.str());
}

Trajectory MakeTrajectory(const TrajectoryOptions& o) {
  std::mt19937 rng(o.seed);
  SmoothJitter jx(rng), jy(rng), jz(rng), jtx(rng), jty(rng), jtz(rng), jroll(rng);
  const double duration = (o.frames - 1) / o.fps;
  const double forward_s = o.start == TrajectoryStart::kForward ? std::min(o.forward_duration_s, duration) : 0.0;
  const double orbit_s = std::max(1e-9, duration - forward_s);
  const double deg = M_PI / 180.0;
  // Jitter fades in over the first half second so the very first motion is the nominal one.
  auto fade = [](double t) { return std::min(1.0, t / 0.5); };

  Trajectory traj;
  traj.reserve(o.frames);
  for (int i = 0; i < o.frames; ++i) {
    const double t = i / o.fps;
    double azimuth = o.start_azimuth_deg * deg;
    double extra_distance = 0.0;
    if (t < forward_s) {
      // Constant-speed approach along the view direction, arriving at the orbit radius.
      extra_distance = o.forward_distance_m * (1.0 - t / forward_s);
    } else {
      azimuth += o.arc_deg * deg * (t - forward_s) / orbit_s;
    }
    const Eigen::Vector3d offset(std::cos(azimuth) * o.radius_m, std::sin(azimuth) * o.radius_m, o.height_m);
    Eigen::Vector3d eye = o.target + offset + extra_distance * offset.normalized();
    Eigen::Vector3d target = o.target;
    const double a = fade(t);
    eye += a * o.jitter_position_m * Eigen::Vector3d(jx(t), jy(t), jz(t));
    const double look_jitter = std::tan(o.jitter_rotation_deg * deg) * (target - eye).norm();
    target += a * look_jitter * Eigen::Vector3d(jtx(t), jty(t), jtz(t));
    Rigid3d pose = LookAt(eye, target, Eigen::Vector3d::UnitZ());
    const double roll = a * o.jitter_rotation_deg * deg * jroll(t);
    pose.rotation = pose.rotation * Eigen::Quaterniond(Eigen::AngleAxisd(roll, Eigen::Vector3d::UnitZ()));
    const double stamp = std::round((o.start_timestamp_s + t) * 1e6) / 1e6;
    traj.push_back({stamp, pose});
  }
  return traj;
}

double PathLength(const Trajectory& trajectory) {
  double len = 0;
  for (size_t i = 1; i < trajectory.size(); ++i)
    len += (trajectory[i].world_from_camera.translation - trajectory[i - 1].world_from_camera.translation).norm();
  return len;
}

}  // namespace prism::synth
