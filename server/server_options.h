// prism-server's options: flags and a config file ("key = value" lines, '#' comments; the keys are the
// long flag names without "--"). The defaults here are the single source of truth.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "core/pipeline/session_pipeline.h"
#include "core/util/status.h"

namespace prism::server {

struct ServerOptions {
  // ZeroMQ endpoint of the ROUTER socket; "tcp://127.0.0.1:*" picks a free port (printed at start).
  std::string bind = "tcp://127.0.0.1:5555";
  // Sessions persist their poses and map chunks as produced, and their merged map and summary when they
  // end, under data_dir/sessions/<id>/ (server/session_store.h); resumes read them back. Required.
  std::string data_dir;
  // HTTP metrics (/metrics, Prometheus text) and health (/healthz): "HOST:PORT" (port 0 = any free
  // port) or "off".
  std::string metrics_bind = "127.0.0.1:0";
  // HTTP listener limits: connections open at once (in [16, 65536]), seconds a connection may stay
  // silent (in [1, 3600]), bytes of a request's line and headers (in [1 KiB, 1 MiB]; larger gets 431).
  int http_max_connections = 1024;
  int http_idle_timeout_s = 5;
  int http_max_request_bytes = 16 * 1024;
  // A ZeroMQ peer that has not finished the ZMTP handshake after this long is dropped, ms, >= 100.
  int handshake_timeout_ms = 10000;
  // The ZeroMQ endpoint GET /allocate tells clients to connect to, e.g. the pod's own DNS name behind a
  // Kubernetes headless Service; "" = the bound endpoint. A tcp:// endpoint or "".
  std::string advertise;
  // Concurrent sessions; OpenSession beyond is refused with RESOURCE_EXHAUSTED, in [1, 1024].
  int max_sessions = 4;
  // Dense keyframe jobs running at once over all sessions, in [1, 64].
  int dense_workers = 1;
  // Threads of the process-wide pool the dense jobs' inner loops share (0 = all cores), in [0, 256].
  int threads = 0;
  // Niceness of the dense workers and that pool, in [0, 19]: higher gives the SLAM threads (poses) the
  // CPU first when cores are short, and the map lags instead.
  int dense_nice = 5;
  // A session without any message from its client for this long is closed, ms, >= 100.
  int idle_timeout_ms = 30000;
  // Largest Frame payload accepted, bytes, in [1 KiB, 1 GiB].
  uint64_t max_frame_bytes = 16u << 20;
  // ZMQ_MAXMSGSIZE: a peer sending a larger message part is disconnected by ZeroMQ before it is read,
  // bytes; 0 = max_frame_bytes + 64 KiB (an oversized frame then costs its sender the connection, not
  // the server the copy), else >= that.
  int64_t max_message_bytes = 0;
  int64_t MessageLimit() const { return max_message_bytes > 0 ? max_message_bytes : MinMessageLimit(); }
  int64_t MinMessageLimit() const { return static_cast<int64_t>(max_frame_bytes) + 65536; }
  // ZMTP heartbeats: interval, and the timeout after which a silent peer's connection is dropped, ms.
  int heartbeat_ivl_ms = 1000;
  int heartbeat_timeout_ms = 5000;
  // Outgoing messages queued per peer before sends fail (ZMQ_SNDHWM), >= 1. Failed sends of map chunks
  // are retried; poses and credits are dropped and counted.
  int send_hwm = 1000;
  // Frames per second one session may send on average, bursts up to twice the frame queue (0 = no limit),
  // in [0, 1000]; faster frames are refused with RESOURCE_EXHAUSTED (retryable) and counted.
  double max_frame_rate_hz = 60;
  // A session whose map and held chunks exceed this (MiB, estimated) is finished with an Error
  // (RESOURCE_EXHAUSTED) and its map so far, in [16, 65536].
  int max_session_memory_mb = 1024;
  // Map chunks waiting for credit kept in memory per session; later ones wait on disk only, in [1, 4096].
  int max_pending_chunks_in_memory = 16;
  // Map chunks a session may send before the client grants more, when OpenSession gives none.
  int default_chunk_credits = 8;
  // On SIGTERM: sessions finish what is queued for at most this long, then stop; ms >= 0.
  int shutdown_deadline_ms = 10000;
  // CURVE: a key file ("public = Z85" and "secret = Z85" lines, `prism-server keygen`); empty = plain
  // TCP (a warning is logged when that listens on a non-loopback address).
  std::string curve_keys;
  // CURVE: the client public keys admitted (one Z85 key per line, '#' comments); required with
  // curve_keys. Other keys are refused in the handshake (the client sees an authentication error).
  std::string allowed_clients;
  // The per-session pipeline (SLAM, dense stage, queues, chunk coding). Its skip_depth_update_backlog
  // is that of upload sessions (input policy upload; default 0: never).
  SessionPipelineOptions pipeline;
  // Live sessions' skip_depth_update_backlog, queued frames, in [0, 1024] (0 = never): faster poses, less depth.
  int skip_depth_update_backlog_live = 2;
  // Live sessions' SlamOptions::keyframe_adjustment_max_wait_ms, ms (< 0: the SLAM's): 0 = shorter frame times.
  double slam_adjustment_max_wait_ms_live = 0;

  Status Check() const;
};

// One key of ServerOptions: the flag --KEY VALUE and the config-file line "KEY = VALUE" ('_' may stand
// for '-'), the name of its value and a line of help for --help, how a value is set, and how the value
// of an options object reads (the defaults in --help).
struct ServerOptionKey {
  std::string key;
  std::string value_name;
  std::string help;
  // INVALID_ARGUMENT naming the key and the value when the value does not parse.
  std::function<Status(const std::string& value, ServerOptions* options)> set;
  std::function<std::string(const ServerOptions& options)> get;
};
// Every key, in --help order. The SLAM options come on top as slam.KEY (core/slam/slam_config.h).
const std::vector<ServerOptionKey>& ServerOptionKeys();

// Applies one "key = value" setting (config file or --key value): a key of ServerOptionKeys or
// slam.KEY. INVALID_ARGUMENT on an unknown key or a bad value, naming both.
Status ApplyServerOption(const std::string& key, const std::string& value, ServerOptions* options);
// Reads a config file of "key = value" lines.
Status LoadServerConfig(const std::string& path, ServerOptions* options);

}  // namespace prism::server
