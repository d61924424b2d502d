#include "core/synth/synthesize.h"

#include <atomic>
#include <chrono>
#include <mutex>

#include <opencv2/core.hpp>

#include "core/io/sequence.h"
#include "core/util/thread_pool.h"

namespace prism::synth {

StatusOr<SynthesizeSummary> SynthesizeSequence(const SynthSetup& setup, uint32_t seed, const std::string& out_dir,
                                               ThreadPool* pool) {
  const auto start = std::chrono::steady_clock::now();
  PRISM_ASSIGN_OR_RETURN(SequenceWriter writer, SequenceWriter::Create(out_dir, setup.rig));
  const Trajectory traj = MakeTrajectory(setup.trajectory);

  std::mutex error_mutex;
  Status first_error;  // Guarded by error_mutex.
  std::atomic<bool> failed{false};
  auto render = [&](std::ptrdiff_t i) {
    if (failed) return;
    const RenderedFrame f =
        RenderFrame(setup.scene, setup.rig, traj[i].world_from_camera, setup.render, FrameNoiseSeed(seed, i));
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
  fs.release();

  summary.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return summary;
}

}  // namespace prism::synth
