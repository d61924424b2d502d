// prism-server's HTTP listener: GET /metrics, /healthz, /readyz and /allocate, served by libmicrohttpd
// on its own epoll thread. Handlers only read the snapshot the transport thread publishes, so no peer
// of this port (slow, idle, garbage, huge) can delay the transport thread or a session; a slow peer
// costs one connection slot, not a thread.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>

#include "core/util/status.h"

namespace prism::server {

struct HttpOptions {
  // "HOST:PORT" (IPv4; port 0 = any free port).
  std::string bind = "127.0.0.1:0";
  // Connections open at once; beyond, new ones wait in the kernel's backlog, in [16, 65536].
  int max_connections = 1024;
  // A connection that sends or reads nothing for this long is closed, seconds, in [1, 3600].
  int idle_timeout_s = 5;
  // Bytes of one request's line and headers; a larger request gets 431 and is closed, in [1 KiB, 1 MiB].
  int max_request_bytes = 16 * 1024;
  // /healthz answers 503 when the transport thread has not published for this long, ms, >= 1000.
  int stale_after_ms = 10000;
};

// What the transport thread publishes for the HTTP thread.
struct HttpSnapshot {
  std::string metrics_text;  // Prometheus text of the transport's metrics
  std::string endpoint;      // what /allocate hands out
  int sessions_active = 0;
  int sessions_capacity = 0;
  bool draining = false;
};

class HttpEndpoint {
 public:
  // Binds and starts the listener thread. INVALID_ARGUMENT on a bad bind string, UNAVAILABLE when it
  // cannot listen.
  static StatusOr<std::unique_ptr<HttpEndpoint>> Start(const HttpOptions& options);
  ~HttpEndpoint();  // stops the listener thread, closes every connection
  HttpEndpoint(const HttpEndpoint&) = delete;
  HttpEndpoint& operator=(const HttpEndpoint&) = delete;

  // "http://HOST:PORT" as bound.
  const std::string& url() const { return url_; }

  // Any thread (the transport thread): replaces the snapshot the handlers read.
  void Publish(std::shared_ptr<const HttpSnapshot> snapshot);

  // The listener's own counters and histogram, as Prometheus text (appended to /metrics).
  std::string RenderOwnMetrics() const;

  struct Impl;  // libmicrohttpd callbacks reach it

 private:
  HttpEndpoint() = default;
  std::unique_ptr<Impl> impl_;
  std::string url_;
};

}  // namespace prism::server
