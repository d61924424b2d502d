#include "tools/view/view_server.h"

#include <arpa/inet.h>
#include <microhttpd.h>
#include <netinet/in.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <thread>

#include "tools/capture/live_stream.h"

namespace prism {
namespace {

namespace fs = std::filesystem;

// The files the page cannot work without (relative to the web folder); the build copies the libraries
// from web/node_modules (scripts/setup.sh installs them from npm).
constexpr const char* kRequiredFiles[] = {"index.html",
                                          "view.js",
                                          "lib/three/build/three.module.js",
                                          "lib/three/build/three.core.js",
                                          "lib/three/examples/jsm/controls/OrbitControls.js",
                                          "lib/draco/draco_decoder_nodejs.js",
                                          "lib/draco/draco_decoder.wasm"};
// Connections at once (a few browser tabs, each polling) and how long an idle one is kept, s.
constexpr unsigned kMaxConnections = 64;
constexpr unsigned kConnectionTimeoutS = 30;
// The web folder's files are read into memory at start; a folder larger than this is refused.
constexpr size_t kMaxWebBytes = 64u << 20;

std::string ContentType(const std::string& path) {
  const std::string ext = fs::path(path).extension().string();
  if (ext == ".html") return "text/html; charset=utf-8";
  if (ext == ".js" || ext == ".mjs") return "text/javascript; charset=utf-8";
  if (ext == ".css") return "text/css; charset=utf-8";
  if (ext == ".wasm") return "application/wasm";
  if (ext == ".json") return "application/json";
  if (ext == ".png") return "image/png";
  return "application/octet-stream";
}

struct StoredPose {
  double timestamp_s = 0;
  std::array<double, 3> translation{0, 0, 0};
  std::array<double, 4> rotation_xyzw{0, 0, 0, 1};
  std::string state;
  bool keyframe = false;
  uint64_t revision = 0;
};

struct StoredChunk {
  uint64_t sequence = 0, keyframe_id = 0;
  size_t points = 0;
  bool replaces_map = false;
  std::vector<uint8_t> draco;
};

}  // namespace

struct ViewServer::Impl {
  MHD_Daemon* daemon = nullptr;
  std::map<std::string, std::string> files;  // URL path -> content; read once at Start, then const
  std::atomic<uint64_t> state_requests{0};

  std::mutex mutex;
  ViewStatus status;                                // Guarded by mutex.
  client::Camera camera;                            // Guarded by mutex.
  double metres_per_unit = 0;                       // Guarded by mutex.
  std::map<uint64_t, StoredPose> poses;             // Guarded by mutex: by frame.
  uint64_t pose_revision = 0;                       // Guarded by mutex.
  std::vector<StoredChunk> chunks;                  // Guarded by mutex: from the last replaces_map on.
  uint64_t chunks_received = 0, chunks_voided = 0;  // Guarded by mutex.
  uint64_t max_sequence = 0;                        // Guarded by mutex: the highest chunk received.

  static MHD_Result Reply(MHD_Connection* c, unsigned code, const std::string& type, const void* data, size_t size,
                          MHD_ResponseMemoryMode mode) {
    MHD_Response* r = MHD_create_response_from_buffer(size, const_cast<void*>(data), mode);
    if (!r) return MHD_NO;
    MHD_add_response_header(r, "Content-Type", type.c_str());
    MHD_add_response_header(r, "Cache-Control", "no-store");
    const MHD_Result result = MHD_queue_response(c, code, r);
    MHD_destroy_response(r);
    return result;
  }
  static MHD_Result Text(MHD_Connection* c, unsigned code, const std::string& type, const std::string& body) {
    return Reply(c, code, type, body.data(), body.size(), MHD_RESPMEM_MUST_COPY);
  }

  std::string StateJson() {
    std::lock_guard<std::mutex> lock(mutex);
    nlohmann::ordered_json j;
    j["mode"] = status.mode;
    j["session"] = status.session;
    j["source"] = status.source;
    j["state"] = status.state;
    j["frames_per_s"] = status.frames_per_s;
    j["frames_sent"] = status.frames_sent;
    j["frames_dropped"] = status.frames_dropped;
    j["poses"] = status.poses;
    j["tracking"] = status.tracking;
    j["map_points"] = status.map_points;
    j["seconds"] = status.seconds;
    j["metres_per_unit"] = metres_per_unit > 0 ? metres_per_unit : 1.0;
    j["camera"] = {{"width", camera.width}, {"height", camera.height}, {"fx", camera.fx},
                   {"fy", camera.fy},       {"cx", camera.cx},         {"cy", camera.cy}};
    nlohmann::json list = nlohmann::json::array();
    size_t points = 0;
    for (const StoredChunk& c : chunks) {
      list.push_back({{"sequence", c.sequence},
                      {"keyframe_id", c.keyframe_id},
                      {"points", c.points},
                      {"replaces_map", c.replaces_map},
                      {"bytes", c.draco.size()}});
      points += c.points;
    }
    j["chunks"] = list;
    j["chunk_points"] = points;
    j["chunks_received"] = chunks_received;
    j["chunks_voided"] = chunks_voided;
    j["pose_revision"] = pose_revision;
    return j.dump();
  }

  std::string PosesJson(uint64_t since) {
    std::lock_guard<std::mutex> lock(mutex);
    nlohmann::json list = nlohmann::json::array();
    for (const auto& [frame, p] : poses) {
      if (p.revision <= since) continue;
      list.push_back({{"frame", frame},
                      {"t", p.timestamp_s},
                      {"p", p.translation},
                      {"q", p.rotation_xyzw},
                      {"state", p.state},
                      {"keyframe", p.keyframe}});
    }
    nlohmann::json j;
    j["revision"] = pose_revision;
    j["poses"] = list;
    return j.dump();
  }

  MHD_Result Handle(MHD_Connection* c, const std::string& url, const std::string& method) {
    if (method != "GET" && method != "HEAD") return Text(c, MHD_HTTP_METHOD_NOT_ALLOWED, "text/plain", "GET only\n");
    if (url == "/api/state") {
      ++state_requests;
      return Text(c, MHD_HTTP_OK, "application/json", StateJson());
    }
    if (url == "/api/poses") {
      const char* since = MHD_lookup_connection_value(c, MHD_GET_ARGUMENT_KIND, "since");
      return Text(c, MHD_HTTP_OK, "application/json", PosesJson(since ? std::strtoull(since, nullptr, 10) : 0));
    }
    constexpr const char kChunkPrefix[] = "/api/chunks/";
    if (url.rfind(kChunkPrefix, 0) == 0) {
      const uint64_t sequence = std::strtoull(url.c_str() + sizeof(kChunkPrefix) - 1, nullptr, 10);
      std::vector<uint8_t> bytes;
      bool received = false;
      {
        std::lock_guard<std::mutex> lock(mutex);
        for (const StoredChunk& chunk : chunks)
          if (chunk.sequence == sequence) bytes = chunk.draco;
        received = chunks_received > 0 && sequence <= max_sequence;
      }
      // A chunk voided by one that replaced the map since the page listed it: nothing to draw, not an
      // error (a 4xx would be one in the page's console).
      if (bytes.empty() && received) return Text(c, MHD_HTTP_NO_CONTENT, "text/plain", "");
      if (bytes.empty()) return Text(c, MHD_HTTP_NOT_FOUND, "text/plain", "no such chunk\n");
      return Reply(c, MHD_HTTP_OK, "application/octet-stream", bytes.data(), bytes.size(), MHD_RESPMEM_MUST_COPY);
    }
    const auto it = files.find(url == "/" ? "/index.html" : url);
    if (it == files.end()) return Text(c, MHD_HTTP_NOT_FOUND, "text/plain", "not found\n");
    // The cached files live as long as the daemon.
    return Reply(c, MHD_HTTP_OK, ContentType(it->first), it->second.data(), it->second.size(), MHD_RESPMEM_PERSISTENT);
  }
};

namespace {

MHD_Result OnRequest(void* cls, MHD_Connection* connection, const char* url, const char* method, const char*,
                     const char*, size_t*, void** request_context) {
  // libmicrohttpd calls once for the headers, then again to answer; GETs carry no body.
  static int first_call_marker;
  if (*request_context == nullptr) {
    *request_context = &first_call_marker;
    return MHD_YES;
  }
  return static_cast<ViewServer::Impl*>(cls)->Handle(connection, url, method);
}

Status LoadFiles(const std::string& web_dir, std::map<std::string, std::string>* files) {
  size_t total = 0;
  std::error_code ec;
  for (auto it = fs::recursive_directory_iterator(web_dir, ec); !ec && it != fs::recursive_directory_iterator();
       it.increment(ec)) {
    if (!it->is_regular_file()) continue;
    std::ifstream in(it->path(), std::ios::binary);
    std::ostringstream s;
    s << in.rdbuf();
    total += s.str().size();
    if (total > kMaxWebBytes)
      return FailedPreconditionError("the live view's folder '" + web_dir + "' holds more than " +
                                     std::to_string(kMaxWebBytes >> 20) + " MiB");
    (*files)["/" + fs::relative(it->path(), web_dir).generic_string()] = s.str();
  }
  if (ec) return UnavailableError("cannot read '" + web_dir + "': " + ec.message());
  return Status::Ok();
}

}  // namespace

StatusOr<std::string> ViewServer::FindWebDir() {
  std::vector<std::string> candidates;
  if (const char* env = std::getenv("PRISM_WEB_DIR"); env && *env) candidates.push_back(env);
  std::error_code ec;
  const fs::path self = fs::read_symlink("/proc/self/exe", ec);
  if (!ec) candidates.push_back((self.parent_path().parent_path() / "share/prism/web").string());
#ifdef PRISM_WEB_INSTALL_DIR
  candidates.push_back(PRISM_WEB_INSTALL_DIR);
#endif
  std::string tried;
  for (const std::string& dir : candidates) {
    if (!fs::exists(dir + "/index.html", ec)) {
      tried += (tried.empty() ? "" : ", ") + dir;
      continue;
    }
    for (const char* f : kRequiredFiles)
      if (!fs::exists(dir + "/" + f, ec))
        return FailedPreconditionError("the live view's '" + dir + "/" + f +
                                       "' is missing: three.js and the Draco decoder come from npm (bash "
                                       "scripts/setup.sh installs them into web/node_modules), then rebuild");
    return dir;
  }
  return FailedPreconditionError("the live view's page is not installed (looked in " + tried +
                                 "; set PRISM_WEB_DIR, or build the project after bash scripts/setup.sh)");
}

StatusOr<std::unique_ptr<ViewServer>> ViewServer::Start(const std::string& address, const std::string& web_dir) {
  const size_t colon = address.rfind(':');
  if (colon == std::string::npos)
    return InvalidArgumentError("--view must be HOST:PORT (e.g. 127.0.0.1:8080, port 0 = a free one), got '" + address +
                                "'");
  const std::string host = address.substr(0, colon), port_text = address.substr(colon + 1);
  char* end = nullptr;
  const long port = std::strtol(port_text.c_str(), &end, 10);
  if (port_text.empty() || *end != '\0' || port < 0 || port > 65535)
    return InvalidArgumentError("--view port must be in [0, 65535], got '" + port_text + "'");
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(static_cast<uint16_t>(port));
  const std::string bind_host = host == "localhost" ? "127.0.0.1" : host;
  if (inet_pton(AF_INET, bind_host.c_str(), &addr.sin_addr) != 1)
    return InvalidArgumentError("--view host must be an IPv4 address (127.0.0.1, 0.0.0.0 for every interface), got '" +
                                host + "'");

  std::unique_ptr<ViewServer> server(new ViewServer());
  server->impl_ = std::make_unique<Impl>();
  Impl* impl = server->impl_.get();
  PRISM_RETURN_IF_ERROR(LoadFiles(web_dir, &impl->files));
  impl->daemon =
      MHD_start_daemon(MHD_USE_EPOLL_INTERNAL_THREAD, 0, nullptr, nullptr, &OnRequest, impl, MHD_OPTION_SOCK_ADDR,
                       reinterpret_cast<const sockaddr*>(&addr), MHD_OPTION_CONNECTION_LIMIT, kMaxConnections,
                       MHD_OPTION_CONNECTION_TIMEOUT, kConnectionTimeoutS, MHD_OPTION_END);
  if (!impl->daemon)
    return UnavailableError("cannot serve the live view on " + address + ": " + std::strerror(errno) +
                            " (in use, or not an address of this machine?)");
  const MHD_DaemonInfo* info = MHD_get_daemon_info(impl->daemon, MHD_DAEMON_INFO_BIND_PORT);
  const std::string shown_host = bind_host == "0.0.0.0" ? "127.0.0.1" : bind_host;
  server->url_ = "http://" + shown_host + ":" + std::to_string(info ? info->port : port) + "/";
  return server;
}

bool ViewServer::WaitForPage(int timeout_ms, const std::atomic<bool>& stop) const {
  const auto until = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
  while (impl_->state_requests == 0 && !stop && std::chrono::steady_clock::now() < until)
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  return impl_->state_requests > 0;
}

ViewServer::~ViewServer() {
  if (impl_ && impl_->daemon) MHD_stop_daemon(impl_->daemon);
}

void ViewServer::SetCamera(const client::Camera& camera) {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  impl_->camera = camera;
}

void ViewServer::SetStatus(const ViewStatus& status) {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  impl_->status = status;
}

void ViewServer::SetMetresPerUnit(double metres_per_unit) {
  if (!(metres_per_unit > 0)) return;
  std::lock_guard<std::mutex> lock(impl_->mutex);
  impl_->metres_per_unit = metres_per_unit;
}

void ViewServer::AddChunk(const client::MapChunk& chunk) {
  AddChunkBytes(chunk.sequence_number, chunk.keyframe_id, chunk.points.size(), chunk.replaces_map, chunk.draco);
}

void ViewServer::AddChunkBytes(uint64_t sequence, uint64_t keyframe_id, size_t points, bool replaces_map,
                               std::vector<uint8_t> draco) {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  ++impl_->chunks_received;
  impl_->max_sequence = std::max(impl_->max_sequence, sequence);
  if (replaces_map) {  // every earlier chunk is void (protocol.md, "Map chunks")
    impl_->chunks_voided += impl_->chunks.size();
    impl_->chunks.clear();
  } else if (!impl_->chunks.empty() && impl_->chunks.front().replaces_map &&
             sequence < impl_->chunks.front().sequence) {
    ++impl_->chunks_voided;  // older than the map that replaced it
    return;
  }
  impl_->chunks.push_back({sequence, keyframe_id, points, replaces_map, std::move(draco)});
}

void ViewServer::SetPose(uint64_t frame, double timestamp_s, const std::array<double, 3>& translation,
                         const std::array<double, 4>& rotation_xyzw, const std::string& state, bool keyframe) {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  StoredPose& p = impl_->poses[frame];
  p.timestamp_s = timestamp_s;
  p.translation = translation;
  p.rotation_xyzw = rotation_xyzw;
  p.state = state;
  p.keyframe = keyframe;
  p.revision = ++impl_->pose_revision;
}

void ViewServer::SetPose(const client::Pose& pose) {
  SetPose(pose.frame_sequence_number, static_cast<double>(pose.timestamp_ns) * 1e-9, pose.translation,
          pose.rotation_xyzw, client::TrackingStateName(pose.state), pose.is_keyframe);
  SetMetresPerUnit(pose.metres_per_unit);
}

}  // namespace prism
