// The live 3D view's HTTP side (prism-client stream --view, prism-client view DIR). It serves the page
// (web/: index.html, view.js, and three.js and the Draco decoder from npm, installed with the tools)
// and the data the page polls:
//   GET /api/state         JSON: the session's status, the camera, the current map chunks (those from
//                          the last chunk that replaced the map on) and the poses' revision
//   GET /api/poses?since=R JSON: the poses added or refined after revision R
//   GET /api/chunks/N.drc  the Draco bytes of chunk N, as the server sent them
// libmicrohttpd runs it on a thread of its own; the streaming thread updates the model through the
// setters below, under a mutex, so no HTTP peer can hold up the stream.
#pragma once

#include <prism/client/client.h>

#include <array>
#include <atomic>
#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "core/util/status.h"

namespace prism {

struct ViewStatus {
  std::string mode = "live";  // "live" (a stream) or "folder" (prism-client view DIR)
  std::string session, source;
  std::string state = "opening";  // "opening", "streaming", "closing", "finished", "failed: ..."
  double frames_per_s = 0;
  uint64_t frames_sent = 0, frames_dropped = 0, poses = 0;
  std::string tracking = "unknown";
  size_t map_points = 0;
  double seconds = 0;
};

class ViewServer {
 public:
  // Serves web_dir on address "HOST:PORT" (an IPv4 address; PORT 0 = a free port). INVALID_ARGUMENT
  // for a malformed address, UNAVAILABLE when it cannot be bound (in use, not this machine's).
  static StatusOr<std::unique_ptr<ViewServer>> Start(const std::string& address, const std::string& web_dir);
  // The folder of the page: $PRISM_WEB_DIR, else share/prism/web beside the running binary's bin/ (the
  // build tree and an installed prefix), else the install prefix's. FAILED_PRECONDITION, saying how to
  // install them, when three.js or the Draco decoder are missing.
  static StatusOr<std::string> FindWebDir();
  ~ViewServer();
  ViewServer(const ViewServer&) = delete;
  ViewServer& operator=(const ViewServer&) = delete;

  // "http://HOST:PORT/".
  const std::string& url() const { return url_; }
  // Waits until a page has asked for the state (a browser has the view open), at most timeout_ms, or
  // until `stop` is set; true when one has.
  bool WaitForPage(int timeout_ms, const std::atomic<bool>& stop) const;

  // The model, from the streaming thread.
  void SetCamera(const client::Camera& camera);
  void SetStatus(const ViewStatus& status);
  // Metres per SLAM unit for the poses (the latest estimate; 1 when the poses are in metres already).
  void SetMetresPerUnit(double metres_per_unit);
  void AddChunk(const client::MapChunk& chunk);
  // Chunk bytes read from a folder (prism-client view): `points` as the file decodes.
  void AddChunkBytes(uint64_t sequence, uint64_t keyframe_id, size_t points, bool replaces_map,
                     std::vector<uint8_t> draco);
  // A frame's pose (a later call for the same frame replaces it): world_from_camera, SLAM units.
  void SetPose(uint64_t frame, double timestamp_s, const std::array<double, 3>& translation,
               const std::array<double, 4>& rotation_xyzw, const std::string& state, bool keyframe);
  void SetPose(const client::Pose& pose);

  struct Impl;  // public for libmicrohttpd's C callbacks

 private:
  ViewServer() = default;
  std::unique_ptr<Impl> impl_;
  std::string url_;
};

}  // namespace prism
