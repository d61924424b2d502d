#include "tools/client/client_output.h"

#include <cstdio>
#include <fstream>
#include <iostream>

#include "core/geometry/point_cloud.h"
#include "core/io/ply_io.h"

namespace prism {

namespace pc = client;

void ClientOutput::OnEvent(const pc::Event& e) {
  if (e.kind == pc::Event::Kind::kPose) {
    refined_poses_ += e.pose.refined ? 1 : 0;
    poses_[e.pose.frame_sequence_number] = e.pose;
    if (!e.pose.refined) tracking_ = e.pose.state;
    if (view_) view_->SetPose(e.pose);
  } else if (e.kind == pc::Event::Kind::kChunk) {
    char name[64];
    std::snprintf(name, sizeof(name), "/chunks/%06llu.drc", static_cast<unsigned long long>(e.chunk.sequence_number));
    std::ofstream(out_dir_ + name, std::ios::binary)
        .write(reinterpret_cast<const char*>(e.chunk.draco.data()), static_cast<std::streamsize>(e.chunk.draco.size()));
    ++chunks_;
    chunk_bytes_ += e.chunk.draco.size();
    chunk_points_ += e.chunk.points.size();
    chunk_records_.push_back({e.chunk.sequence_number, e.chunk.keyframe_id, e.chunk.points.size(), e.chunk.draco.size(),
                              e.chunk.replaces_map});
    remapped_ = remapped_ || e.chunk.replaces_map;
    if (view_) view_->AddChunk(e.chunk);
    std::cerr << "prism-client: chunk " << e.chunk.sequence_number;
    if (e.chunk.replaces_map) std::cerr << " (the map rebuilt at the final keyframe poses)";
    else std::cerr << " (keyframe " << e.chunk.keyframe_id << ")";
    std::cerr << ": " << e.chunk.points.size() << " points, " << e.chunk.draco.size() << " bytes\n";
  } else if (e.kind == pc::Event::Kind::kError) {
    ++errors_;
    std::cerr << "prism-client: server error: " << e.error.ToString() << "\n";
    if (e.error.code == pc::Code::kNotFound || e.error.code == pc::Code::kInternal ||
        e.error.code == pc::Code::kUnavailable)
      fatal_ = e.error.ToString();
  }
}

StatusOr<nlohmann::ordered_json> ClientOutput::Write(const pc::Session& session, const pc::Summary& summary) const {
  // Trajectory, scaled to metres by the final session scale when known.
  const double s = summary.metres_per_unit > 0 ? summary.metres_per_unit : 1.0;
  {
    std::ofstream traj(out_dir_ + "/trajectory.txt");
    traj << "# timestamp tx ty tz qx qy qz qw (world_from_camera, metres per unit " << s << ")\n";
    char line[256];
    for (const auto& [sequence, p] : poses_) {
      if (p.state != pc::TrackingState::kTracking) continue;  // provisional (initialising) or lost
      std::snprintf(line, sizeof(line), "%.6f %.9g %.9g %.9g %.9g %.9g %.9g %.9g\n", p.timestamp_ns * 1e-9,
                    p.translation[0] * s, p.translation[1] * s, p.translation[2] * s, p.rotation_xyzw[0],
                    p.rotation_xyzw[1], p.rotation_xyzw[2], p.rotation_xyzw[3]);
      traj << line;
    }
  }
  {
    // As prism-slam's tracking.txt: each frame aligned against a keyframe, as the server tracked it.
    std::ofstream tracking(out_dir_ + "/tracking.txt");
    tracking << "# timestamp keyframe_id residual_rms visible_fraction inlier_fraction iterations retried step "
                "rotation_deg guess_correction\n";
    char line[256];
    for (const auto& [sequence, p] : poses_) {
      if (!p.has_tracking) continue;
      const pc::TrackingQuality& q = p.tracking;
      std::snprintf(line, sizeof(line), "%.6f %lld %g %g %g %u %d %g %g %g\n", p.timestamp_ns * 1e-9,
                    static_cast<long long>(p.keyframe_id), q.residual_rms, q.visible_fraction, q.inlier_fraction,
                    q.iterations, q.retried ? 1 : 0, q.step, q.rotation_deg, q.guess_correction);
      tracking << line;
    }
  }
  {
    // Which chunk replaced the map (the .drc files alone do not say): prism-client view reads it.
    nlohmann::ordered_json list = nlohmann::ordered_json::array();
    for (const ChunkRecord& c : chunk_records_)
      list.push_back({{"sequence", c.sequence},
                      {"keyframe_id", c.keyframe_id},
                      {"points", c.points},
                      {"bytes", c.bytes},
                      {"replaces_map", c.replaces_map}});
    std::ofstream(out_dir_ + "/chunks.json") << list.dump(1) << "\n";
  }
  const std::vector<pc::Point> map = session.Map();
  PointCloud cloud;
  for (const pc::Point& p : map) {
    cloud.positions.emplace_back(p.position[0], p.position[1], p.position[2]);
    cloud.normals.emplace_back(p.normal[0], p.normal[1], p.normal[2]);
    cloud.colors.emplace_back(p.color[0], p.color[1], p.color[2]);
  }
  PRISM_RETURN_IF_ERROR(WritePointCloudPly(out_dir_ + "/map.ply", cloud));

  nlohmann::ordered_json j;
  j["session"] = session.session_id();
  j["poses"] = poses_.size();
  j["refined_poses"] = refined_poses_;
  j["chunks"] = chunks_;
  j["chunk_bytes"] = chunk_bytes_;
  j["chunk_points"] = chunk_points_;
  j["map_points"] = map.size();
  j["map_replaced"] = remapped_;
  j["errors"] = errors_;
  j["uplink_bytes"] = session.bytes_sent();
  j["server_keyframes"] = summary.keyframes;
  j["server_keyframes_failed"] = summary.keyframes_failed;
  j["server_map_points"] = summary.map_points;
  j["server_frames_dropped"] = summary.frames_dropped;
  j["server_frames_depth_update_skipped"] = summary.frames_depth_update_skipped;
  j["metres_per_unit"] = summary.metres_per_unit;
  j["shading_check"] = summary.shading_check == pc::Summary::ShadingCheck::kConsistent  ? "consistent"
                       : summary.shading_check == pc::Summary::ShadingCheck::kDistorted ? "distorted"
                                                                                        : "not_run";
  j["shading_pair_spread"] = summary.shading_pair_spread;
  j["start_check"] = pc::StartCheckName(summary.start_check);
  j["start_pair_spread"] = summary.start_pair_spread;
  j["reconnects"] = session.reconnects();
  j["reason"] = summary.reason;
  return j;
}

Status ClientOutput::WriteSummary(const nlohmann::ordered_json& j) const {
  const std::string json = j.dump(-1, ' ', false, nlohmann::ordered_json::error_handler_t::replace) + "\n";
  std::cout << json;
  std::ofstream out(out_dir_ + "/summary.json");
  out << json;
  if (!out) return UnavailableError("cannot write '" + out_dir_ + "/summary.json'");
  return Status::Ok();
}

}  // namespace prism
