#include "server/server_options.h"

#include <cmath>
#include <cstdlib>
#include <fstream>
#include <sstream>
#include <type_traits>

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

Status Bad(const std::string& key, const std::string& value) {
  return InvalidArgumentError("bad value for " + key + ": '" + value + "'");
}

std::string Text(double v) {
  std::ostringstream out;
  out << v;
  return out.str();
}

// A key whose value is an integer field; `field` gives the field of an options object. Fields that are
// not int (uint64_t, int64_t) are assigned the parsed value as it is, as before.
template <typename Field>
ServerOptionKey IntKey(const char* key, const char* value_name, const char* help, Field field) {
  return {key, value_name, help,
          [key, field](const std::string& value, ServerOptions* o) {
            long long i = 0;
            using T = std::remove_reference_t<decltype(field(*o))>;
            if (!ParseInt(value, &i) || (std::is_unsigned_v<T> && i < 0)) return Bad(key, value);
            field(*o) = static_cast<T>(i);
            return Status::Ok();
          },
          [field](const ServerOptions& o) {
            ServerOptions copy = o;
            return std::to_string(field(copy));
          }};
}

template <typename Field>
ServerOptionKey DoubleKey(const char* key, const char* value_name, const char* help, Field field) {
  return {key, value_name, help,
          [key, field](const std::string& value, ServerOptions* o) {
            double d = 0;
            if (!ParseDouble(value, &d)) return Bad(key, value);
            field(*o) = d;
            return Status::Ok();
          },
          [field](const ServerOptions& o) {
            ServerOptions copy = o;
            return Text(field(copy));
          }};
}

template <typename Field>
ServerOptionKey BoolKey(const char* key, const char* help, Field field) {
  return {key, "true|false", help,
          [key, field](const std::string& value, ServerOptions* o) {
            if (value == "true" || value == "1") field(*o) = true;
            else if (value == "false" || value == "0") field(*o) = false;
            else return Bad(key, value);
            return Status::Ok();
          },
          [field](const ServerOptions& o) {
            ServerOptions copy = o;
            return std::string(field(copy) ? "true" : "false");
          }};
}

template <typename Field>
ServerOptionKey StringKey(const char* key, const char* value_name, const char* help, Field field) {
  return {key, value_name, help,
          [field](const std::string& value, ServerOptions* o) {
            field(*o) = value;
            return Status::Ok();
          },
          [field](const ServerOptions& o) {
            ServerOptions copy = o;
            return field(copy);
          }};
}

std::vector<ServerOptionKey> MakeKeys() {
  using O = ServerOptions;
  return {
      StringKey("bind", "ENDPOINT", "ZeroMQ endpoint (tcp://127.0.0.1:* = a free port)",
                [](O& o) -> std::string& { return o.bind; }),
      StringKey("data-dir", "DIR", "where sessions persist poses, chunks, map.ply and summary (required)",
                [](O& o) -> std::string& { return o.data_dir; }),
      StringKey("metrics", "ADDR",
                "HOST:PORT or off: HTTP /metrics (Prometheus), /healthz, /readyz and\n"
                "/allocate on a thread of its own (port 0 = a free port)",
                [](O& o) -> std::string& { return o.metrics_bind; }),
      IntKey("http-max-connections", "N", "HTTP connections open at once; more wait in the backlog",
             [](O& o) -> int& { return o.http_max_connections; }),
      IntKey("http-idle-timeout-s", "S", "close an HTTP connection silent for S seconds",
             [](O& o) -> int& { return o.http_idle_timeout_s; }),
      IntKey("http-max-request-bytes", "B", "largest HTTP request line + headers; larger gets 431",
             [](O& o) -> int& { return o.http_max_request_bytes; }),
      IntKey("handshake-timeout-ms", "MS", "drop a ZeroMQ peer that has not finished its handshake",
             [](O& o) -> int& { return o.handshake_timeout_ms; }),
      StringKey("advertise", "ENDPOINT", "endpoint GET /allocate hands to clients (default: the bound one)",
                [](O& o) -> std::string& { return o.advertise; }),
      IntKey("max-sessions", "N", "concurrent sessions before RESOURCE_EXHAUSTED",
             [](O& o) -> int& { return o.max_sessions; }),
      IntKey("dense-workers", "N", "dense keyframe jobs at once over all sessions",
             [](O& o) -> int& { return o.dense_workers; }),
      IntKey("threads", "N", "process-wide worker pool for the dense loops (0 = all cores)",
             [](O& o) -> int& { return o.threads; }),
      IntKey("dense-nice", "N", "niceness of the dense threads, 0-19: poses get the CPU first",
             [](O& o) -> int& { return o.dense_nice; }),
      IntKey("idle-timeout-ms", "MS", "close sessions silent for this long",
             [](O& o) -> int& { return o.idle_timeout_ms; }),
      IntKey("max-frame-bytes", "B", "largest frame payload", [](O& o) -> uint64_t& { return o.max_frame_bytes; }),
      IntKey("max-message-bytes", "B", "ZMQ_MAXMSGSIZE: larger messages drop their peer (0 = max-frame-bytes + 64 KiB)",
             [](O& o) -> int64_t& { return o.max_message_bytes; }),
      IntKey("heartbeat-ivl-ms", "MS", "ZMTP heartbeat interval", [](O& o) -> int& { return o.heartbeat_ivl_ms; }),
      IntKey("heartbeat-timeout-ms", "MS", "ZMTP heartbeat timeout",
             [](O& o) -> int& { return o.heartbeat_timeout_ms; }),
      IntKey("send-hwm", "N", "ZMQ_SNDHWM", [](O& o) -> int& { return o.send_hwm; }),
      DoubleKey("max-frame-rate-hz", "HZ", "average frames/s per session, bursts up to frame-queue (0 = off)",
                [](O& o) -> double& { return o.max_frame_rate_hz; }),
      IntKey("max-session-memory-mb", "M", "a session's map + held chunks beyond this ends it with an error",
             [](O& o) -> int& { return o.max_session_memory_mb; }),
      IntKey("max-pending-chunks-in-memory", "N",
             "chunks held in memory per session for a slow client; more wait on disk",
             [](O& o) -> int& { return o.max_pending_chunks_in_memory; }),
      IntKey("chunk-credits", "N", "map chunks in flight when the client grants none",
             [](O& o) -> int& { return o.default_chunk_credits; }),
      IntKey("frame-queue", "N", "frames queued per session (also the initial frame credits)",
             [](O& o) -> int& { return o.pipeline.frame_queue_capacity; }),
      {"input-policy", "live|upload", "full frame queue: drop the oldest (live) or reject (upload)",
       [](const std::string& value, O* o) {
         if (value == "live") o->pipeline.input_policy = OverflowPolicy::kDropOldest;
         else if (value == "upload") o->pipeline.input_policy = OverflowPolicy::kReject;
         else return Bad("input-policy", value);
         return Status::Ok();
       },
       [](const O& o) { return std::string(o.pipeline.input_policy == OverflowPolicy::kReject ? "upload" : "live"); }},
      IntKey("keyframe-queue", "N", "finished keyframes queued per session for the dense stage",
             [](O& o) -> int& { return o.pipeline.keyframe_queue_capacity; }),
      DoubleKey("covered-keyframe-fraction", "F",
                "with another keyframe of the session waiting, a keyframe the map already\n"
                "covers to more than F skips the dense stage (in (0, 1]; 1 = never)",
                [](O& o) -> double& { return o.pipeline.covered_keyframe_fraction; }),
      IntKey("skip-depth-update-backlog", "N",
             "when N frames wait for an upload session's SLAM, the next frame is tracked\n"
             "without its stereo depth update (behind: poses first; 0 = never)",
             [](O& o) -> int& { return o.pipeline.skip_depth_update_backlog; }),
      IntKey("skip-depth-update-backlog-live", "N", "the same for live sessions (0 = never)",
             [](O& o) -> int& { return o.skip_depth_update_backlog_live; }),
      DoubleKey("slam-adjustment-max-wait-live", "MS",
                "a live session's new keyframe waits at most MS for the SLAM's window\n"
                "adjustment still running (negative: as the SLAM options say)",
                [](O& o) -> double& { return o.slam_adjustment_max_wait_ms_live; }),
      DoubleKey("voxel-m", "M", "map voxel edge, metres", [](O& o) -> double& { return o.pipeline.dense.map.voxel_m; }),
      BoolKey("remap-at-end",
              "at a session's end, rebuild the map at the final keyframe poses and send it\n"
              "as one chunk that replaces the map (the keyframe clouds it needs are kept\n"
              "within a quarter of max-session-memory-mb)",
              [](O& o) -> bool& { return o.pipeline.remap_at_end; }),
      BoolKey("metric-scale-at-end",
              "with remap-at-end, estimate the SLAM's metric scale from the co-moving\n"
              "lights and rebuild the map at it when it agrees with the dense stage's\n"
              "(2-7 s more at the end)",
              [](O& o) -> bool& { return o.pipeline.metric_scale_at_end; }),
      IntKey("shutdown-deadline-ms", "MS", "on SIGTERM, time to finish queued work before stopping",
             [](O& o) -> int& { return o.shutdown_deadline_ms; }),
      StringKey("curve-keys", "FILE", "CURVE: this server's key pair (prism-server keygen); none = plain TCP",
                [](O& o) -> std::string& { return o.curve_keys; }),
      StringKey("allowed-clients", "FILE", "CURVE: client public keys admitted, one per line (with curve-keys)",
                [](O& o) -> std::string& { return o.allowed_clients; }),
      {"slam-config", "FILE",
       "SLAM options for every session, 'key = value' lines (core/slam/slam_config.h;\n"
       "the keys of prism-slam --slam-config and of its slam_config.txt)",
       [](const std::string& value, O* o) { return ApplySlamConfigFile(value, &o->pipeline.slam); },
       [](const O&) { return std::string(); }},
  };
}

}  // namespace

const std::vector<ServerOptionKey>& ServerOptionKeys() {
  static const std::vector<ServerOptionKey> keys = MakeKeys();
  return keys;
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
  for (const ServerOptionKey& k : ServerOptionKeys())
    if (key == k.key) return k.set(value, o);
  return InvalidArgumentError("unknown option '" + key_in + "'");
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
