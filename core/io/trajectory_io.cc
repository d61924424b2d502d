#include "core/io/trajectory_io.h"

#include <cmath>
#include <fstream>
#include <iomanip>
#include <sstream>

namespace prism {
namespace {

// Splits a data line into numbers; false when a token is not a finite number.
bool ParseNumbers(const std::string& line, std::vector<double>* out) {
  out->clear();
  std::istringstream in(line);
  std::string tok;
  while (in >> tok) {
    char* end = nullptr;
    const double v = std::strtod(tok.c_str(), &end);
    if (end == tok.c_str() || *end != '\0' || !std::isfinite(v)) return false;
    out->push_back(v);
  }
  return true;
}

bool IsDataLine(const std::string& line) {
  const size_t p = line.find_first_not_of(" \t\r");
  return p != std::string::npos && line[p] != '#';
}

}  // namespace

StatusOr<Trajectory> ReadTumTrajectory(const std::string& path) {
  std::ifstream in(path);
  if (!in) return NotFoundError("cannot open trajectory file '" + path + "'");
  Trajectory traj;
  std::string line;
  std::vector<double> v;
  int line_no = 0;
  while (std::getline(in, line)) {
    ++line_no;
    if (!IsDataLine(line)) continue;
    // Some tools separate with commas.
    for (char& c : line)
      if (c == ',') c = ' ';
    if (!ParseNumbers(line, &v) || v.size() != 8)
      return InvalidArgumentError(path + ":" + std::to_string(line_no) + ": expected 'timestamp tx ty tz qx qy qz qw'");
    const Eigen::Quaterniond q(v[7], v[4], v[5], v[6]);
    if (q.norm() < 1e-6) return InvalidArgumentError(path + ":" + std::to_string(line_no) + ": zero quaternion");
    traj.push_back({v[0], Rigid3d(q, Eigen::Vector3d(v[1], v[2], v[3]))});
  }
  if (traj.empty()) return InvalidArgumentError("trajectory file '" + path + "' has no poses");
  return traj;
}

Status WriteTumTrajectory(const std::string& path, const Trajectory& trajectory) {
  std::ofstream out(path);
  if (!out) return UnavailableError("cannot write trajectory file '" + path + "'");
  out << "# timestamp tx ty tz qx qy qz qw (world_from_camera)\n";
  out << std::setprecision(9);
  for (const TimedPose& p : trajectory) {
    const Eigen::Quaterniond& q = p.world_from_camera.rotation;
    const Eigen::Vector3d& t = p.world_from_camera.translation;
    out << std::fixed << std::setprecision(6) << p.timestamp_s << std::defaultfloat << std::setprecision(9) << " "
        << t.x() << " " << t.y() << " " << t.z() << " " << q.x() << " " << q.y() << " " << q.z() << " " << q.w()
        << "\n";
  }
  if (!out) return UnavailableError("write failed for '" + path + "'");
  return Status::Ok();
}

StatusOr<Trajectory> ReadKittiTrajectory(const std::string& poses_path, const std::string& times_path) {
  std::ifstream in(poses_path);
  if (!in) return NotFoundError("cannot open KITTI poses file '" + poses_path + "'");
  std::vector<double> times;
  if (!times_path.empty()) {
    std::ifstream tin(times_path);
    if (!tin) return NotFoundError("cannot open times file '" + times_path + "'");
    std::string line;
    std::vector<double> v;
    while (std::getline(tin, line)) {
      if (!IsDataLine(line)) continue;
      if (!ParseNumbers(line, &v) || v.size() != 1)
        return InvalidArgumentError(times_path + ": expected one timestamp per line");
      times.push_back(v[0]);
    }
  }
  Trajectory traj;
  std::string line;
  std::vector<double> v;
  int line_no = 0;
  while (std::getline(in, line)) {
    ++line_no;
    if (!IsDataLine(line)) continue;
    if (!ParseNumbers(line, &v) || v.size() != 12)
      return InvalidArgumentError(poses_path + ":" + std::to_string(line_no) + ": expected 12 numbers");
    Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 4; ++c) m(r, c) = v[r * 4 + c];
    const double t = times.empty() ? static_cast<double>(traj.size()) : 0.0;
    traj.push_back({t, Rigid3d::FromMatrix(m)});
  }
  if (traj.empty()) return InvalidArgumentError("KITTI poses file '" + poses_path + "' has no poses");
  if (!times.empty()) {
    if (times.size() != traj.size())
      return InvalidArgumentError("times file has " + std::to_string(times.size()) + " lines but poses file has " +
                                  std::to_string(traj.size()));
    for (size_t i = 0; i < traj.size(); ++i) traj[i].timestamp_s = times[i];
  }
  return traj;
}

StatusOr<Trajectory> ReadTrajectoryAutoDetect(const std::string& path) {
  std::ifstream in(path);
  if (!in) return NotFoundError("cannot open trajectory file '" + path + "'");
  std::string line;
  std::vector<double> v;
  while (std::getline(in, line)) {
    if (!IsDataLine(line)) continue;
    for (char& c : line)
      if (c == ',') c = ' ';
    if (ParseNumbers(line, &v) && v.size() == 12) return ReadKittiTrajectory(path);
    break;
  }
  return ReadTumTrajectory(path);
}

}  // namespace prism
