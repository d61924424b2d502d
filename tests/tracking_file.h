// prism-slam's and prism-client's tracking.txt (one line per frame aligned against a keyframe; see
// tools/prism_slam.cc), read for the suites that check it.
#pragma once

#include <fstream>
#include <sstream>
#include <string>
#include <vector>

namespace prism::test {

struct TrackingRow {
  double timestamp = 0;
  int keyframe_id = -1;
  double residual_rms = 0, visible_fraction = 0, inlier_fraction = 0;
  int iterations = 0, retried = 0;
  double step = 0, rotation_deg = 0, guess_correction = 0;
  std::string line;  // as read, for messages
};

// The rows of the file; false when it cannot be opened or a line does not parse (*bad_line: that line).
inline bool ReadTrackingFile(const std::string& path, std::vector<TrackingRow>* rows, std::string* bad_line) {
  std::ifstream in(path);
  if (!in.good()) return false;
  std::string line;
  while (std::getline(in, line)) {
    if (line.empty() || line[0] == '#') continue;
    std::istringstream f(line);
    TrackingRow r;
    r.line = line;
    if (!(f >> r.timestamp >> r.keyframe_id >> r.residual_rms >> r.visible_fraction >> r.inlier_fraction >>
          r.iterations >> r.retried >> r.step >> r.rotation_deg >> r.guess_correction)) {
      *bad_line = line;
      return false;
    }
    rows->push_back(r);
  }
  return true;
}

}  // namespace prism::test
