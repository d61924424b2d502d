#include "core/mapping/synthetic_keyframe.h"

#include "core/util/check.h"

namespace prism {

PointCloud BackProjectFrame(const PinholeCamera& camera, const synth::RenderedFrame& frame, int stride) {
  PRISM_CHECK_GE(stride, 1);
  PRISM_CHECK(frame.depth.type() == CV_32F && frame.depth.cols == camera.width && frame.depth.rows == camera.height)
      << "depth image does not match the camera";
  const bool has_normals = !frame.normals.empty();
  const bool has_rgb = !frame.rgb.empty();
  PRISM_CHECK(!has_normals || (frame.normals.type() == CV_32FC3 && frame.normals.size() == frame.depth.size()));
  PRISM_CHECK(!has_rgb || (frame.rgb.type() == CV_8UC3 && frame.rgb.size() == frame.depth.size()));

  PointCloud cloud;
  const size_t capacity = static_cast<size_t>((camera.width + stride - 1) / stride) *
                          static_cast<size_t>((camera.height + stride - 1) / stride);
  cloud.positions.reserve(capacity);
  if (has_normals) cloud.normals.reserve(capacity);
  if (has_rgb) cloud.colors.reserve(capacity);
  cloud.confidences.reserve(capacity);
  for (int v = 0; v < camera.height; v += stride) {
    const float* depth_row = frame.depth.ptr<float>(v);
    for (int u = 0; u < camera.width; u += stride) {
      const float depth_m = depth_row[u];
      if (!(depth_m > 0.0f)) continue;
      const Eigen::Vector3d ray = camera.Unproject(Eigen::Vector2d(u, v));
      cloud.positions.push_back((ray * depth_m).cast<float>());
      if (has_normals) {
        const cv::Vec3f& n = frame.normals.at<cv::Vec3f>(v, u);
        cloud.normals.emplace_back(n[0], n[1], n[2]);
      }
      if (has_rgb) {
        const cv::Vec3b& c = frame.rgb.at<cv::Vec3b>(v, u);
        cloud.colors.emplace_back(c[0], c[1], c[2]);
      }
      cloud.confidences.push_back(1.0f);
    }
  }
  return cloud;
}

PointCloud RenderKeyframeCloud(const synth::SynthSetup& setup, const Rigid3d& world_from_camera, uint64_t noise_seed,
                               int stride) {
  const synth::RenderedFrame frame =
      synth::RenderFrame(setup.scene, setup.rig, world_from_camera, setup.render, noise_seed);
  return BackProjectFrame(setup.rig.camera, frame, stride);
}

}  // namespace prism
