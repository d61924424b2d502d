#include "core/io/sequence.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "core/io/image_io.h"

namespace prism {
namespace fs = std::filesystem;
namespace {

constexpr double kMaxAssociationS = 0.02;

struct IndexEntry {
  double timestamp_s;
  std::string file;
};

// Reads a TUM index ("timestamp file" per line). Missing file -> empty list when optional.
StatusOr<std::vector<IndexEntry>> ReadIndex(const std::string& path, bool required) {
  std::ifstream in(path);
  if (!in) {
    if (required) return NotFoundError("cannot open '" + path + "'");
    return std::vector<IndexEntry>{};
  }
  std::vector<IndexEntry> out;
  std::string line;
  int line_no = 0;
  while (std::getline(in, line)) {
    ++line_no;
    const size_t p = line.find_first_not_of(" \t\r");
    if (p == std::string::npos || line[p] == '#') continue;
    std::istringstream ls(line);
    IndexEntry e;
    if (!(ls >> e.timestamp_s >> e.file) || !std::isfinite(e.timestamp_s))
      return InvalidArgumentError(path + ":" + std::to_string(line_no) + ": expected 'timestamp file'");
    if (e.file.find("..") != std::string::npos || (!e.file.empty() && e.file[0] == '/'))
      return InvalidArgumentError(path + ":" + std::to_string(line_no) + ": file must be relative to the sequence");
    out.push_back(e);
  }
  std::sort(out.begin(), out.end(),
            [](const IndexEntry& a, const IndexEntry& b) { return a.timestamp_s < b.timestamp_s; });
  return out;
}

// Nearest entry within kMaxAssociationS, or empty string.
std::string Nearest(const std::vector<IndexEntry>& index, double t) {
  if (index.empty()) return "";
  auto it =
      std::lower_bound(index.begin(), index.end(), t, [](const IndexEntry& e, double v) { return e.timestamp_s < v; });
  const IndexEntry* best = nullptr;
  if (it != index.end()) best = &*it;
  if (it != index.begin()) {
    const IndexEntry* prev = &*(it - 1);
    if (!best || std::abs(prev->timestamp_s - t) < std::abs(best->timestamp_s - t)) best = prev;
  }
  if (!best || std::abs(best->timestamp_s - t) > kMaxAssociationS) return "";
  return best->file;
}

Status WriteIndex(const std::string& path, const std::string& folder, const std::vector<double>& stamps,
                  const std::string& comment) {
  std::ofstream out(path);
  if (!out) return UnavailableError("cannot write '" + path + "'");
  out << "# " << comment << "\n# timestamp filename\n";
  char stamp[64];
  for (double t : stamps) {
    std::snprintf(stamp, sizeof(stamp), "%.6f", t);
    out << stamp << " " << folder << "/" << SequenceWriter::FrameName(t) << "\n";
  }
  if (!out) return UnavailableError("write failed for '" + path + "'");
  return Status::Ok();
}

}  // namespace

StatusOr<cv::Mat> Sequence::ReadRgb(size_t i) const {
  if (i >= frames.size()) return OutOfRangeError("frame index out of range");
  return ReadRgbImage(Path(frames[i].rgb_file));
}
StatusOr<cv::Mat> Sequence::ReadDepth(size_t i) const {
  if (i >= frames.size()) return OutOfRangeError("frame index out of range");
  if (frames[i].depth_file.empty()) return NotFoundError("frame has no depth image");
  return ReadDepthPng(Path(frames[i].depth_file));
}
StatusOr<cv::Mat> Sequence::ReadNormals(size_t i) const {
  if (i >= frames.size()) return OutOfRangeError("frame index out of range");
  if (frames[i].normal_file.empty()) return NotFoundError("frame has no normal map");
  return ReadNormalPng(Path(frames[i].normal_file));
}
StatusOr<cv::Mat> Sequence::ReadMask(size_t i) const {
  if (i >= frames.size()) return OutOfRangeError("frame index out of range");
  if (frames[i].mask_file.empty()) return NotFoundError("frame has no mask");
  return ReadMaskPng(Path(frames[i].mask_file));
}

StatusOr<Rigid3d> Sequence::GroundTruthPose(size_t i) const {
  if (i >= frames.size()) return OutOfRangeError("frame index out of range");
  const double t = frames[i].timestamp_s;
  const TimedPose* best = nullptr;
  for (const TimedPose& p : groundtruth)
    if (!best || std::abs(p.timestamp_s - t) < std::abs(best->timestamp_s - t)) best = &p;
  if (!best || std::abs(best->timestamp_s - t) > kMaxAssociationS)
    return NotFoundError("no ground-truth pose within 20 ms of frame " + std::to_string(i));
  return best->world_from_camera;
}

StatusOr<Sequence> LoadSequence(const std::string& dir) {
  if (!fs::is_directory(dir)) return NotFoundError("sequence directory '" + dir + "' does not exist");
  Sequence seq;
  seq.root = dir;
  PRISM_ASSIGN_OR_RETURN(auto rgb, ReadIndex(dir + "/rgb.txt", /*required=*/true));
  if (rgb.empty()) return InvalidArgumentError(dir + "/rgb.txt lists no frames");
  PRISM_ASSIGN_OR_RETURN(auto depth, ReadIndex(dir + "/depth.txt", false));
  PRISM_ASSIGN_OR_RETURN(auto normals, ReadIndex(dir + "/normals.txt", false));
  PRISM_ASSIGN_OR_RETURN(auto mask, ReadIndex(dir + "/mask.txt", false));
  for (const IndexEntry& e : rgb) {
    SequenceFrame f;
    f.timestamp_s = e.timestamp_s;
    f.rgb_file = e.file;
    f.depth_file = Nearest(depth, e.timestamp_s);
    f.normal_file = Nearest(normals, e.timestamp_s);
    f.mask_file = Nearest(mask, e.timestamp_s);
    seq.frames.push_back(f);
  }
  if (fs::exists(dir + "/groundtruth.txt")) {
    PRISM_ASSIGN_OR_RETURN(seq.groundtruth, ReadTumTrajectory(dir + "/groundtruth.txt"));
  }
  if (fs::exists(dir + "/camera.yaml")) {
    PRISM_ASSIGN_OR_RETURN(seq.calibration, ReadCalibrationYaml(dir + "/camera.yaml"));
    seq.has_calibration = true;
  }
  return seq;
}

std::string SequenceWriter::FrameName(double timestamp_s) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.6f.png", timestamp_s);
  return buf;
}

StatusOr<SequenceWriter> SequenceWriter::Create(const std::string& dir, const RigCalibration& calibration) {
  PRISM_RETURN_IF_ERROR(calibration.Check());
  std::error_code ec;
  for (const char* sub : {"", "/rgb", "/depth", "/normals", "/mask"}) {
    fs::create_directories(dir + sub, ec);
    if (ec) return UnavailableError("cannot create '" + dir + sub + "': " + ec.message());
  }
  PRISM_RETURN_IF_ERROR(WriteCalibrationYaml(dir + "/camera.yaml", calibration));
  return SequenceWriter(dir);
}

Status SequenceWriter::WriteFrame(double timestamp_s, const cv::Mat& rgb, const cv::Mat& depth, const cv::Mat& normals,
                                  const cv::Mat& mask) const {
  const std::string name = FrameName(timestamp_s);
  if (!rgb.empty()) PRISM_RETURN_IF_ERROR(WriteRgbImage(dir_ + "/rgb/" + name, rgb));
  if (!depth.empty()) PRISM_RETURN_IF_ERROR(WriteDepthPng(dir_ + "/depth/" + name, depth));
  if (!normals.empty()) PRISM_RETURN_IF_ERROR(WriteNormalPng(dir_ + "/normals/" + name, normals));
  if (!mask.empty()) PRISM_RETURN_IF_ERROR(WriteMaskPng(dir_ + "/mask/" + name, mask));
  return Status::Ok();
}

Status SequenceWriter::Finish(const Trajectory& groundtruth, bool has_depth, bool has_normals, bool has_mask) const {
  std::vector<double> stamps;
  for (const TimedPose& p : groundtruth) stamps.push_back(p.timestamp_s);
  PRISM_RETURN_IF_ERROR(WriteIndex(dir_ + "/rgb.txt", "rgb", stamps, "colour images (RGB, 8-bit)"));
  if (has_depth)
    PRISM_RETURN_IF_ERROR(WriteIndex(dir_ + "/depth.txt", "depth", stamps, "depth images (16-bit, 5000 per metre)"));
  if (has_normals)
    PRISM_RETURN_IF_ERROR(WriteIndex(dir_ + "/normals.txt", "normals", stamps,
                                     "normal maps, camera frame, 16-bit: (n+1)/2*65535, (0,0,0) = none"));
  if (has_mask)
    PRISM_RETURN_IF_ERROR(WriteIndex(dir_ + "/mask.txt", "mask", stamps, "masks: 255 object, 64 ground, 0 none"));
  return WriteTumTrajectory(dir_ + "/groundtruth.txt", groundtruth);
}

}  // namespace prism
