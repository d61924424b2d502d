#include "server/server_options.h"

#include <cmath>
#include <cstdlib>
#include <fstream>
#include <sstream>

#include "core/slam/slam_config.h"
#include "core/util/key_value_text.h"

namespace prism::server {
namespace {

bool ParseInt(const std::string& s, long long* out) {
  char* end = nullptr;
  *out = std::strtoll(s.c_str(), &end, 10);
  return !s.empty() && end && *end == '\0';
}
bool ParseDouble(const std::string& s, double* out) {
  char* end = nullptr;
  *out = std::strtod(s.c_str(), &end);
  return !s.empty() && end && *end == '\0';
}

}  // namespace

const char* ServerOptionsHelp() {
  return R"(  bind ENDPOINT           ZeroMQ endpoint (default tcp://127.0.0.1:5555; tcp://127.0.0.1:* = free port)
  data-dir DIR            where sessions persist poses, chunks, map.ply and summary (required)
  metrics HOST:PORT|off   HTTP /metrics (Prometheus text), /healthz, /readyz and /allocate (default 127.0.0.1:0 =
                          free port; served on a thread of its own)
  http-max-connections N  HTTP connections open at once; more wait in the backlog (default 1024)
  http-idle-timeout-s S   close an HTTP connection silent for S seconds (default 5)
  http-max-request-bytes B  largest HTTP request line + headers; larger gets 431 (default 16384)
  handshake-timeout-ms MS drop a ZeroMQ peer that has not finished its handshake (default 10000)
  advertise ENDPOINT      endpoint GET /allocate hands to clients (default: the bound one)
  max-sessions N          concurrent sessions before RESOURCE_EXHAUSTED (default 4)
  dense-workers N         dense keyframe jobs at once over all sessions (default 1)
  threads N               process-wide worker pool for the dense loops (default 0 = all cores)
  dense-nice N            niceness of the dense threads, 0-19: poses get the CPU first (default 5)
  idle-timeout-ms MS      close sessions silent for this long (default 30000)
  max-frame-bytes B       largest frame payload (default 16777216)
  max-message-bytes B     ZMQ_MAXMSGSIZE: larger messages drop their peer (default 0 = max-frame-bytes + 64 KiB)
  heartbeat-ivl-ms MS     ZMTP heartbeat interval (default 1000)
  heartbeat-timeout-ms MS ZMTP heartbeat timeout (default 5000)
  send-hwm N              ZMQ_SNDHWM (default 1000)
  max-frame-rate-hz HZ    average frames/s per session, bursts up to frame-queue (default 60; 0 = off)
  max-session-memory-mb M a session's map + held chunks beyond this ends it with an error (default 1024)
  max-pending-chunks-in-memory N  chunks held in memory per session for a slow client; more wait on disk (default 16)
  chunk-credits N         map chunks in flight when the client grants none (default 8)
  frame-queue N           frames queued per session (default 8; also the initial frame credits)
  input-policy live|upload  full frame queue: drop the oldest (live) or reject (upload) (default live)
  keyframe-queue N        finished keyframes queued per session for the dense stage (default 4)
  skip-depth-update-backlog N  when N frames wait for an upload session's SLAM, the next frame is
                          tracked without its stereo depth update (behind: poses first; default 0 = never)
  skip-depth-update-backlog-live N  the same for live sessions (default 2; 0 = never)
  slam-adjustment-max-wait-live MS  a live session's new keyframe waits at most MS for the SLAM's window
                          adjustment still running (default 0; negative: as the SLAM options say, by
                          default as long as it takes)
  voxel-m M               map voxel edge, metres (default 0.002)
  remap-at-end true|false at a session's end, rebuild the map at the final keyframe poses and send it as
                          one chunk that replaces the map (default true; the keyframe clouds it needs
                          are kept within a quarter of max-session-memory-mb)
  metric-scale-at-end true|false  with remap-at-end, rebuild the map at the SLAM's metric scale from the
                          co-moving lights instead of the dense stage's (default true; 2-7 s more at a
                          session's end)
  shutdown-deadline-ms MS on SIGTERM, time to finish queued work before stopping (default 10000)
  curve-keys FILE         CURVE: this server's key pair (from `prism-server keygen`); default off = plain TCP
  allowed-clients FILE    CURVE: client public keys admitted, one per line (required with curve-keys)
  slam-config FILE        SLAM options for every session, one 'key = value' per line (core/slam/slam_config.h;
                          the same keys as prism-slam --slam-config and its slam_config.txt)
  slam.KEY VALUE          one SLAM option, e.g. slam.loop_closure false or slam.tracker.min_gradient 5
)";
}

Status ServerOptions::Check() const {
  auto bad = [](const std::string& f, const std::string& v, const std::string& rule) {
    return InvalidArgumentError("ServerOptions." + f + " = " + v + "; violated: " + rule);
  };
  if (bind.rfind("tcp://", 0) != 0 && bind.rfind("ipc://", 0) != 0)
    return bad("bind", "'" + bind + "'", "a tcp:// or ipc:// endpoint");
  if (data_dir.empty()) return bad("data_dir", "''", "non-empty (--data-dir)");
  if (!advertise.empty() && advertise.rfind("tcp://", 0) != 0)
    return bad("advertise", "'" + advertise + "'", "a tcp:// endpoint or empty");
  if (max_sessions < 1 || max_sessions > 1024) return bad("max_sessions", std::to_string(max_sessions), "in [1, 1024]");
  if (dense_workers < 1 || dense_workers > 64) return bad("dense_workers", std::to_string(dense_workers), "in [1, 64]");
  if (threads < 0 || threads > 256) return bad("threads", std::to_string(threads), "in [0, 256]");
  if (dense_nice < 0 || dense_nice > 19) return bad("dense_nice", std::to_string(dense_nice), "in [0, 19]");
  if (idle_timeout_ms < 100) return bad("idle_timeout_ms", std::to_string(idle_timeout_ms), ">= 100");
  if (max_frame_bytes < 1024 || max_frame_bytes > (1ull << 30))
    return bad("max_frame_bytes", std::to_string(max_frame_bytes), "in [1024, 2^30]");
  if (max_message_bytes != 0 && max_message_bytes < MinMessageLimit())
    return bad("max_message_bytes", std::to_string(max_message_bytes), "0 (automatic) or >= max_frame_bytes + 64 KiB");
  if (heartbeat_ivl_ms < 10 || heartbeat_timeout_ms < heartbeat_ivl_ms)
    return bad("heartbeat_timeout_ms", std::to_string(heartbeat_timeout_ms), ">= heartbeat_ivl_ms >= 10");
  if (send_hwm < 1) return bad("send_hwm", std::to_string(send_hwm), ">= 1");
  if (http_max_connections < 16 || http_max_connections > 65536)
    return bad("http_max_connections", std::to_string(http_max_connections), "in [16, 65536]");
  if (http_idle_timeout_s < 1 || http_idle_timeout_s > 3600)
    return bad("http_idle_timeout_s", std::to_string(http_idle_timeout_s), "in [1, 3600]");
  if (http_max_request_bytes < 1024 || http_max_request_bytes > (1 << 20))
    return bad("http_max_request_bytes", std::to_string(http_max_request_bytes), "in [1024, 1048576]");
  if (handshake_timeout_ms < 100) return bad("handshake_timeout_ms", std::to_string(handshake_timeout_ms), ">= 100");
  if (max_frame_rate_hz < 0 || max_frame_rate_hz > 1000)
    return bad("max_frame_rate_hz", std::to_string(max_frame_rate_hz), "in [0, 1000] (0 = no limit)");
  if (max_session_memory_mb < 16 || max_session_memory_mb > 65536)
    return bad("max_session_memory_mb", std::to_string(max_session_memory_mb), "in [16, 65536]");
  if (max_pending_chunks_in_memory < 1 || max_pending_chunks_in_memory > 4096)
    return bad("max_pending_chunks_in_memory", std::to_string(max_pending_chunks_in_memory), "in [1, 4096]");
  if (default_chunk_credits < 1) return bad("default_chunk_credits", std::to_string(default_chunk_credits), ">= 1");
  if (shutdown_deadline_ms < 0) return bad("shutdown_deadline_ms", std::to_string(shutdown_deadline_ms), ">= 0");
  if (skip_depth_update_backlog_live < 0 || skip_depth_update_backlog_live > 1024)
    return bad("skip_depth_update_backlog_live", std::to_string(skip_depth_update_backlog_live), "in [0, 1024]");
  if (!std::isfinite(slam_adjustment_max_wait_ms_live))
    return bad("slam_adjustment_max_wait_ms_live", std::to_string(slam_adjustment_max_wait_ms_live), "finite");
  if (!curve_keys.empty() && allowed_clients.empty())
    return bad("allowed_clients", "''", "a file of client public keys when curve_keys is set");
  if (curve_keys.empty() && !allowed_clients.empty())
    return bad("curve_keys", "''", "a key file when allowed_clients is set");
  return pipeline.Check();
}

Status ApplyServerOption(const std::string& key_in, const std::string& value, ServerOptions* o) {
  // SLAM options: the keys of core/slam/slam_config.h, shared with prism-slam.
  if (key_in.rfind("slam.", 0) == 0) return SetSlamOption(key_in.substr(5), value, &o->pipeline.slam);
  std::string key = key_in;
  for (char& c : key)
    if (c == '_') c = '-';
  long long i = 0;
  double d = 0;
  const bool is_int = ParseInt(value, &i), is_double = ParseDouble(value, &d);
  auto bad = [&] { return InvalidArgumentError("bad value for " + key + ": '" + value + "'"); };
  if (key == "bind") o->bind = value;
  else if (key == "data-dir") o->data_dir = value;
  else if (key == "metrics") o->metrics_bind = value;
  else if (key == "advertise") o->advertise = value;
  else if (key == "max-sessions") {
    if (!is_int) return bad();
    o->max_sessions = static_cast<int>(i);
  } else if (key == "dense-workers") {
    if (!is_int) return bad();
    o->dense_workers = static_cast<int>(i);
  } else if (key == "dense-nice") {
    if (!is_int) return bad();
    o->dense_nice = static_cast<int>(i);
  } else if (key == "threads") {
    if (!is_int) return bad();
    o->threads = static_cast<int>(i);
  } else if (key == "idle-timeout-ms") {
    if (!is_int) return bad();
    o->idle_timeout_ms = static_cast<int>(i);
  } else if (key == "max-frame-bytes") {
    if (!is_int || i < 0) return bad();
    o->max_frame_bytes = static_cast<uint64_t>(i);
  } else if (key == "max-message-bytes") {
    if (!is_int) return bad();
    o->max_message_bytes = i;
  } else if (key == "heartbeat-ivl-ms") {
    if (!is_int) return bad();
    o->heartbeat_ivl_ms = static_cast<int>(i);
  } else if (key == "heartbeat-timeout-ms") {
    if (!is_int) return bad();
    o->heartbeat_timeout_ms = static_cast<int>(i);
  } else if (key == "http-max-connections") {
    if (!is_int) return bad();
    o->http_max_connections = static_cast<int>(i);
  } else if (key == "http-idle-timeout-s") {
    if (!is_int) return bad();
    o->http_idle_timeout_s = static_cast<int>(i);
  } else if (key == "http-max-request-bytes") {
    if (!is_int) return bad();
    o->http_max_request_bytes = static_cast<int>(i);
  } else if (key == "handshake-timeout-ms") {
    if (!is_int) return bad();
    o->handshake_timeout_ms = static_cast<int>(i);
  } else if (key == "send-hwm") {
    if (!is_int) return bad();
    o->send_hwm = static_cast<int>(i);
  } else if (key == "max-frame-rate-hz") {
    if (!is_double) return bad();
    o->max_frame_rate_hz = d;
  } else if (key == "max-session-memory-mb") {
    if (!is_int) return bad();
    o->max_session_memory_mb = static_cast<int>(i);
  } else if (key == "max-pending-chunks-in-memory") {
    if (!is_int) return bad();
    o->max_pending_chunks_in_memory = static_cast<int>(i);
  } else if (key == "chunk-credits") {
    if (!is_int) return bad();
    o->default_chunk_credits = static_cast<int>(i);
  } else if (key == "frame-queue") {
    if (!is_int) return bad();
    o->pipeline.frame_queue_capacity = static_cast<int>(i);
  } else if (key == "skip-depth-update-backlog") {
    if (!is_int) return bad();
    o->pipeline.skip_depth_update_backlog = static_cast<int>(i);
  } else if (key == "skip-depth-update-backlog-live") {
    if (!is_int) return bad();
    o->skip_depth_update_backlog_live = static_cast<int>(i);
  } else if (key == "slam-adjustment-max-wait-live") {
    if (!is_double) return bad();
    o->slam_adjustment_max_wait_ms_live = d;
  } else if (key == "keyframe-queue") {
    if (!is_int) return bad();
    o->pipeline.keyframe_queue_capacity = static_cast<int>(i);
  } else if (key == "voxel-m") {
    if (!is_double) return bad();
    o->pipeline.dense.map.voxel_m = d;
  } else if (key == "remap-at-end") {
    if (value == "true" || value == "1") o->pipeline.remap_at_end = true;
    else if (value == "false" || value == "0") o->pipeline.remap_at_end = false;
    else return bad();
  } else if (key == "metric-scale-at-end") {
    if (value == "true" || value == "1") o->pipeline.metric_scale_at_end = true;
    else if (value == "false" || value == "0") o->pipeline.metric_scale_at_end = false;
    else return bad();
  } else if (key == "curve-keys") o->curve_keys = value;
  else if (key == "allowed-clients") o->allowed_clients = value;
  else if (key == "slam-config") return ApplySlamConfigFile(value, &o->pipeline.slam);
  else if (key == "shutdown-deadline-ms") {
    if (!is_int) return bad();
    o->shutdown_deadline_ms = static_cast<int>(i);
  } else if (key == "input-policy") {
    if (value == "live") o->pipeline.input_policy = OverflowPolicy::kDropOldest;
    else if (value == "upload") o->pipeline.input_policy = OverflowPolicy::kReject;
    else return bad();
  } else {
    return InvalidArgumentError("unknown option '" + key_in + "'");
  }
  return Status::Ok();
}

Status LoadServerConfig(const std::string& path, ServerOptions* options) {
  std::ifstream in(path);
  if (!in) return NotFoundError("cannot read config file '" + path + "'");
  std::ostringstream text;
  text << in.rdbuf();
  return ForEachKeyValueLine(text.str(), path, "=:", [&](const std::string& key, const std::string& value) {
    return ApplyServerOption(key, value, options);
  });
}

}  // namespace prism::server
