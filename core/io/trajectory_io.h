// Trajectories: TUM format (`timestamp tx ty tz qx qy qz qw`, pose = world_from_camera) and KITTI
// odometry format (12 numbers per line, row-major [R|t] of camera i in the frame of camera 0).
#pragma once

#include <string>
#include <vector>

#include "core/geometry/rigid3.h"
#include "core/util/status.h"

namespace prism {

struct TimedPose {
  double timestamp_s = 0.0;
  Rigid3d world_from_camera;
};
using Trajectory = std::vector<TimedPose>;

// Lines starting with '#' and blank lines are skipped; anything else malformed is an error naming
// the line. Poses are returned in file order.
StatusOr<Trajectory> ReadTumTrajectory(const std::string& path);
Status WriteTumTrajectory(const std::string& path, const Trajectory& trajectory);

// KITTI poses; `times_path` may be empty, then timestamps are the line indices (0, 1, 2, ...).
StatusOr<Trajectory> ReadKittiTrajectory(const std::string& poses_path, const std::string& times_path = "");

// Reads TUM, or KITTI when the first data line has 12 numbers.
StatusOr<Trajectory> ReadTrajectoryAutoDetect(const std::string& path);

}  // namespace prism
