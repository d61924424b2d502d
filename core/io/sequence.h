// A sequence on disk in the TUM RGB-D layout, so real TUM sequences load unchanged:
//   rgb.txt + rgb/<timestamp>.png          colour frames ("timestamp rgb/<file>" per line)
//   depth.txt + depth/<timestamp>.png      16-bit depth, 5000 per metre (optional)
//   groundtruth.txt                        "timestamp tx ty tz qx qy qz qw", world_from_camera (optional)
// Prism adds (all optional for reading):
//   camera.yaml                            rig calibration (calibration_io.h)
//   normals.txt + normals/<timestamp>.png  ground-truth normal maps in the camera frame (image_io.h)
//   mask.txt + mask/<timestamp>.png        255 = object, 64 = ground, 0 = no surface
// Depth, normals and masks are associated with colour frames by nearest timestamp within 20 ms.
#pragma once

#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "core/io/calibration_io.h"
#include "core/io/trajectory_io.h"
#include "core/util/status.h"

namespace prism {

struct SequenceFrame {
  double timestamp_s = 0.0;
  std::string rgb_file;     // relative to the sequence root
  std::string depth_file;   // empty when absent
  std::string normal_file;  // empty when absent
  std::string mask_file;    // empty when absent
};

struct Sequence {
  std::string root;
  bool has_calibration = false;
  RigCalibration calibration;
  std::vector<SequenceFrame> frames;  // sorted by timestamp
  Trajectory groundtruth;             // empty when absent

  std::string Path(const std::string& relative) const { return root + "/" + relative; }
  StatusOr<cv::Mat> ReadRgb(size_t i) const;
  StatusOr<cv::Mat> ReadDepth(size_t i) const;
  StatusOr<cv::Mat> ReadNormals(size_t i) const;
  StatusOr<cv::Mat> ReadMask(size_t i) const;
  // Ground-truth pose at the frame's timestamp (nearest within 20 ms), or NOT_FOUND.
  StatusOr<Rigid3d> GroundTruthPose(size_t i) const;
};

// Loads the index files (not the images). Needs rgb.txt; the rest is optional.
StatusOr<Sequence> LoadSequence(const std::string& dir);

// Writes a sequence frame by frame. WriteFrame may be called from several threads at once (each
// call writes its own files); Finish writes the index files in timestamp order.
class SequenceWriter {
 public:
  // Creates dir and its sub-folders and writes camera.yaml.
  static StatusOr<SequenceWriter> Create(const std::string& dir, const RigCalibration& calibration);

  // rgb CV_8UC3 (RGB), depth CV_32F metres, normals CV_32FC3, mask CV_8U; empty Mats are skipped.
  Status WriteFrame(double timestamp_s, const cv::Mat& rgb, const cv::Mat& depth, const cv::Mat& normals,
                    const cv::Mat& mask) const;
  // Writes rgb.txt, depth.txt, normals.txt, mask.txt (for the given timestamps) and groundtruth.txt.
  Status Finish(const Trajectory& groundtruth, bool has_depth, bool has_normals, bool has_mask) const;

  static std::string FrameName(double timestamp_s);  // "%.6f.png"

 private:
  explicit SequenceWriter(std::string dir) : dir_(std::move(dir)) {}
  std::string dir_;
};

}  // namespace prism
