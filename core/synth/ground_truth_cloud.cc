#include "core/synth/ground_truth_cloud.h"

#include <cmath>
#include <unordered_map>

#include "core/io/image_io.h"

namespace prism::synth {

Status GroundTruthCloudOptions::Check() const {
  if (frame_step < 1) return InvalidArgumentError("GroundTruthCloudOptions.frame_step must be >= 1");
  if (!(voxel_m > 0)) return InvalidArgumentError("GroundTruthCloudOptions.voxel_m must be > 0");
  return Status::Ok();
}

StatusOr<PointCloud> GroundTruthCloud(const Sequence& seq, const GroundTruthCloudOptions& options) {
  PRISM_RETURN_IF_ERROR(options.Check());
  if (!seq.has_calibration) return FailedPreconditionError("sequence has no camera.yaml");
  struct Voxel {
    Eigen::Vector3d position = Eigen::Vector3d::Zero(), normal = Eigen::Vector3d::Zero(),
                    color = Eigen::Vector3d::Zero();
    int count = 0;
  };
  std::unordered_map<uint64_t, Voxel> voxels;
  auto key = [&](const Eigen::Vector3d& p) {
    const auto q = [&](double v) {
      return static_cast<uint64_t>(static_cast<int64_t>(std::floor(v / options.voxel_m)) & 0x1FFFFF);
    };
    return (q(p.x()) << 42) | (q(p.y()) << 21) | q(p.z());
  };
  const PinholeCamera& cam = seq.calibration.camera;
  for (size_t i = 0; i < seq.frames.size(); i += options.frame_step) {
    auto pose = seq.GroundTruthPose(i);
    if (!pose.ok()) continue;
    PRISM_ASSIGN_OR_RETURN(cv::Mat depth, seq.ReadDepth(i));
    PRISM_ASSIGN_OR_RETURN(cv::Mat normals, seq.ReadNormals(i));
    PRISM_ASSIGN_OR_RETURN(cv::Mat rgb, seq.ReadRgb(i));
    cv::Mat mask;
    if (options.object_only) {
      PRISM_ASSIGN_OR_RETURN(mask, seq.ReadMask(i));
    }
    for (int y = 0; y < depth.rows; ++y)
      for (int x = 0; x < depth.cols; ++x) {
        const float d = depth.at<float>(y, x);
        if (!(d > 0)) continue;
        if (options.object_only && mask.at<uint8_t>(y, x) != kMaskObject) continue;
        const Eigen::Vector3d p = *pose * (cam.Unproject(Eigen::Vector2d(x, y)) * d);
        const cv::Vec3f n = normals.at<cv::Vec3f>(y, x);
        const cv::Vec3b c = rgb.at<cv::Vec3b>(y, x);
        Voxel& v = voxels[key(p)];
        v.position += p;
        v.normal += pose->rotation * Eigen::Vector3d(n[0], n[1], n[2]);
        v.color += Eigen::Vector3d(c[0], c[1], c[2]);
        v.count++;
      }
  }
  if (voxels.empty()) return FailedPreconditionError("no frame of the sequence has ground-truth depth and a pose");
  PointCloud cloud;
  for (const auto& [k, v] : voxels) {
    (void)k;
    cloud.positions.push_back((v.position / v.count).cast<float>());
    const Eigen::Vector3d n = v.normal.norm() > 0 ? Eigen::Vector3d(v.normal.normalized()) : Eigen::Vector3d::UnitZ();
    cloud.normals.push_back(n.cast<float>());
    const Eigen::Vector3d c = (v.color / v.count).array().round();
    cloud.colors.emplace_back(static_cast<uint8_t>(c.x()), static_cast<uint8_t>(c.y()), static_cast<uint8_t>(c.z()));
  }
  return cloud;
}

}  // namespace prism::synth
