// Smooth 6-DoF camera paths around a target: an orbit arc at a fixed height, optionally preceded by
// a forward approach, with smooth seeded jitter. The camera always roughly faces the target.
#pragma once

#include <cstdint>

#include <Eigen/Core>

#include "core/io/trajectory_io.h"
#include "core/util/status.h"

namespace prism::synth {

enum class TrajectoryStart {
  kSideways,  // the orbit starts at once: the first motion is sideways (tangential)
  kForward,   // the camera first moves towards the target, then orbits
};

struct TrajectoryOptions {
  // Point the camera looks at, world frame, metres.
  Eigen::Vector3d target = Eigen::Vector3d(0, 0, 0.08);
  // Horizontal distance from the target during the orbit, metres, > 0.
  double radius_m = 0.5;
  // Camera height above the target, metres.
  double height_m = 0.3;
  // Azimuth where the orbit starts, degrees (0 = camera on the +x side of the target).
  double start_azimuth_deg = -90.0;
  // Total azimuth swept by the orbit phase, degrees (sign = direction), |.| <= 720.
  double arc_deg = 120.0;
  TrajectoryStart start = TrajectoryStart::kSideways;
  // kForward: duration of the approach, seconds, and the distance covered along the view direction.
  double forward_duration_s = 1.0;
  double forward_distance_m = 0.15;
  // Smooth jitter amplitudes: camera position (metres) and viewing direction/roll (degrees).
  double jitter_position_m = 0.01;
  double jitter_rotation_deg = 1.0;
  // Frames per second and number of frames, >= 2.
  double fps = 30.0;
  int frames = 300;
  // Timestamp of the first frame, seconds (rounded to microseconds like the file names).
  double start_timestamp_s = 1000.0;
  uint32_t seed = 1;

  Status Check() const;
};

// Poses world_from_camera (OpenCV camera axes; world z up appears as image up).
Trajectory MakeTrajectory(const TrajectoryOptions& options);

// Length of the camera path (sum of the distances between consecutive positions), metres.
double PathLength(const Trajectory& trajectory);

}  // namespace prism::synth
