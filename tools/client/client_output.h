// What prism-client keeps of a session and writes to its --out folder: every event is handed to
// OnEvent (chunks go to chunks/<sequence>.drc at once, poses are kept, the latest per frame wins), and
// Write puts trajectory.txt, tracking.txt, map.ply, chunks.json and summary.json beside them.
#pragma once

#include <prism/client/client.h>

#include <cstdint>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "tools/view/view_server.h"

namespace prism {

class ClientOutput {
 public:
  // out_dir must exist (with chunks/). view may be null; it then gets every pose and chunk too.
  ClientOutput(std::string out_dir, ViewServer* view) : out_dir_(std::move(out_dir)), view_(view) {}

  // Keeps a pose, writes a chunk, counts an error (on the thread that polls the session).
  void OnEvent(const client::Event& e);
  // A session-ending error seen in the events (NOT_FOUND, INTERNAL, UNAVAILABLE), "" when none.
  const std::string& fatal() const { return fatal_; }
  size_t poses() const { return poses_.size(); }
  size_t chunks() const { return chunks_; }
  // The latest pose's tracking state.
  client::TrackingState tracking() const { return tracking_; }

  // trajectory.txt (tracked frames, metres by the summary's scale), tracking.txt, map.ply (the
  // session's running map) and chunks.json; returns the summary.json object with the session's
  // fields filled in, for the caller to add its own and write with WriteSummary.
  StatusOr<nlohmann::ordered_json> Write(const client::Session& session, const client::Summary& summary) const;
  Status WriteSummary(const nlohmann::ordered_json& j) const;

 private:
  std::string out_dir_;
  ViewServer* view_;
  std::map<uint64_t, client::Pose> poses_;  // by frame sequence number: the latest (refined) pose wins
  struct ChunkRecord {
    uint64_t sequence, keyframe_id;
    size_t points, bytes;
    bool replaces_map;
  };
  std::vector<ChunkRecord> chunk_records_;
  size_t refined_poses_ = 0, chunks_ = 0, chunk_bytes_ = 0, chunk_points_ = 0, errors_ = 0;
  client::TrackingState tracking_ = client::TrackingState::kUnknown;
  bool remapped_ = false;  // a chunk replaced the map (rebuilt at the final keyframe poses)
  std::string fatal_;
};

}  // namespace prism
