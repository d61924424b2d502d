#include "core/synth/synthesize.h"

#include <atomic>
#include <chrono>
#include <cstdlib>
#include <mutex>

#include <opencv2/core.hpp>

#include "core/io/sequence.h"
#include "core/util/thread_pool.h"

namespace prism::synth {

RigCalibration RigAtFrame(const SynthSetup& setup, const Trajectory& traj, size_t i) {
  if (!setup.lights_fixed_in_world || traj.empty()) return setup.rig;
  // The lights stay where the rig had them at the first frame.
  RigCalibration rig = setup.rig;
  const Rigid3d camera_from_first = traj[i].world_from_camera.Inverse() * traj[0].world_from_camera;
  for (Light& l : rig.lights) {
    l.position_in_camera = camera_from_first * l.position_in_camera;
    l.direction_in_camera = camera_from_first.rotation * l.direction_in_camera;
  }
  return rig;
}

RenderedFrame RenderSequenceFrame(const SynthSetup& setup, const Trajectory& traj, size_t i, uint64_t noise_seed) {
  RenderedFrame f =
      RenderFrame(setup.scene, RigAtFrame(setup, traj, i), traj[i].world_from_camera, setup.render, noise_seed);
  if (setup.blur_samples <= 1 || setup.exposure <= 0 || i == 0) return f;
  // Motion blur: the mean radiance over the last `exposure` of the motion from the previous frame.
  cv::Mat sum;
  f.radiance.copyTo(sum);
  const Rigid3d& a = traj[i - 1].world_from_camera;
  const Rigid3d& b = traj[i].world_from_camera;
  for (int k = 1; k < setup.blur_samples; ++k) {
    const double t = 1.0 - setup.exposure * k / (setup.blur_samples - 1);
    Rigid3d pose;
    pose.rotation = a.rotation.slerp(t, b.rotation);
    pose.translation = (1 - t) * a.translation + t * b.translation;
    sum += RenderFrame(setup.scene, RigAtFrame(setup, traj, i), pose, setup.render, noise_seed).radiance;
  }
  f.radiance = sum / static_cast<double>(setup.blur_samples);
  f.rgb = QuantiseRadiance(f.radiance, setup.render, noise_seed);
  return f;
}

StatusOr<SynthesizeSummary> SynthesizeSequence(const SynthSetup& setup, uint32_t seed, const std::string& out_dir,
                                               ThreadPool* pool) {
  const auto start = std::chrono::steady_clock::now();
  // With lights fixed in the world no light moves with the camera: camera.yaml says so (intensity 0).
  RigCalibration written = setup.rig;
  if (setup.lights_fixed_in_world)
    for (Light& l : written.lights) l.intensity = 0;
  PRISM_ASSIGN_OR_RETURN(SequenceWriter writer, SequenceWriter::Create(out_dir, written));
  const Trajectory traj = setup.Poses();

  std::mutex error_mutex;
  Status first_error;  // Guarded by error_mutex.
  std::atomic<bool> failed{false};
  auto render = [&](std::ptrdiff_t i) {
    if (failed) return;
    const RenderedFrame f = RenderSequenceFrame(setup, traj, i, FrameNoiseSeed(seed, i));
    const Status s = writer.WriteFrame(traj[i].timestamp_s, f.rgb, f.depth, f.normals, f.mask);
    if (!s.ok()) {
      std::lock_guard<std::mutex> lock(error_mutex);
      if (!failed) first_error = s;
      failed = true;
    }
  };
  if (pool) pool->ParallelFor(0, static_cast<std::ptrdiff_t>(traj.size()), render);
  else
    for (size_t i = 0; i < traj.size(); ++i) render(static_cast<std::ptrdiff_t>(i));
  if (failed) return first_error;
  PRISM_RETURN_IF_ERROR(writer.Finish(traj, true, true, true));

  SynthesizeSummary summary;
  summary.frames = static_cast<int>(traj.size());
  summary.path_length_m = PathLength(traj);
  Eigen::Vector3d centre;
  setup.scene.ObjectBounds(&centre, &summary.object_radius_m);

  cv::FileStorage fs(out_dir + "/scene.yaml", cv::FileStorage::WRITE);
  if (!fs.isOpened()) return UnavailableError("cannot write '" + out_dir + "/scene.yaml'");
  fs << "preset" << setup.preset << "description" << setup.description << "seed" << static_cast<int>(seed);
  fs << "frames" << summary.frames << "fps" << setup.trajectory.fps;
  fs << "object_centre"
     << "[:" << centre.x() << centre.y() << centre.z() << "]";
  fs << "object_radius_m" << summary.object_radius_m;
  fs << "path_length_m" << summary.path_length_m;
  fs << "ambient" << setup.render.ambient << "noise_sigma" << setup.render.noise_sigma;
  fs << "cast_shadows" << static_cast<int>(setup.render.cast_shadows);
  fs << "supersampling" << setup.render.supersampling;
  for (const auto& [key, value] : setup.notes) {
    char* end = nullptr;
    const double number = std::strtod(value.c_str(), &end);
    if (!value.empty() && *end == '\0') fs << key << number;
    else fs << key << value;
  }
  fs.release();

  summary.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return summary;
}

}  // namespace prism::synth
