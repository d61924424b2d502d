#include "server/http_endpoint.h"

#include <arpa/inet.h>
#include <microhttpd.h>
#include <netinet/in.h>

#include <cstdarg>
#include <cstring>
#include <nlohmann/json.hpp>

#include "core/util/logging.h"
#include "server/metrics.h"

namespace prism::server {
namespace {

using Clock = std::chrono::steady_clock;

// Per TCP connection (libmicrohttpd's socket context).
struct Connection {
  std::string peer;
  bool served = false;  // at least one request reached the handler
};

std::string PeerAddress(MHD_Connection* connection) {
  const MHD_ConnectionInfo* info = MHD_get_connection_info(connection, MHD_CONNECTION_INFO_CLIENT_ADDRESS);
  if (!info || !info->client_addr || info->client_addr->sa_family != AF_INET) return "?";
  char buf[INET_ADDRSTRLEN] = "?";
  const auto* in = reinterpret_cast<const sockaddr_in*>(info->client_addr);
  inet_ntop(AF_INET, &in->sin_addr, buf, sizeof(buf));
  return buf;
}

}  // namespace

struct HttpEndpoint::Impl {
  HttpOptions options;
  MHD_Daemon* daemon = nullptr;
  std::mutex snapshot_mutex;
  std::shared_ptr<const HttpSnapshot> snapshot;  // Guarded by snapshot_mutex.
  std::atomic<int64_t> published_ns{0};          // steady clock, of the last Publish
  mutable std::mutex metrics_mutex;
  Metrics metrics;  // Guarded by metrics_mutex.
  OncePerPeer once;

  Impl() {
    metrics.Declare("prism_http_requests_total", Metrics::Type::kCounter,
                    "HTTP requests answered, by path and status code.");
    metrics.Declare("prism_http_connections_total", Metrics::Type::kCounter, "HTTP connections accepted.");
    metrics.Declare("prism_http_connections_open", Metrics::Type::kGauge, "HTTP connections open now.");
    metrics.Declare("prism_http_connections_without_request_total", Metrics::Type::kCounter,
                    "HTTP connections closed before a complete request (idle, too slow, garbage or too large).");
    metrics.Declare("prism_allocate_requests_total", Metrics::Type::kCounter,
                    "GET /allocate requests (readiness probes use /readyz and are not counted).");
  }

  std::shared_ptr<const HttpSnapshot> Snapshot() {
    std::lock_guard<std::mutex> lock(snapshot_mutex);
    return snapshot;
  }

  // ms since the transport thread last published; large when it is stuck.
  int64_t StaleMs() const {
    const int64_t now = std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now().time_since_epoch()).count();
    return (now - published_ns.load()) / 1000000;
  }

  void Count(const std::string& name) {
    std::lock_guard<std::mutex> lock(metrics_mutex);
    metrics.Add(name);
  }

  static MHD_Result Reply(MHD_Connection* connection, unsigned int code, const std::string& type,
                          const std::string& body) {
    MHD_Response* response =
        MHD_create_response_from_buffer(body.size(), const_cast<char*>(body.data()), MHD_RESPMEM_MUST_COPY);
    if (!response) return MHD_NO;
    MHD_add_response_header(response, "Content-Type", type.c_str());
    MHD_add_response_header(response, "Cache-Control", "no-store");
    const MHD_Result r = MHD_queue_response(connection, code, response);
    MHD_destroy_response(response);
    return r;
  }

  MHD_Result Handle(MHD_Connection* connection, const std::string& url, const std::string& method) {
    if (const MHD_ConnectionInfo* info = MHD_get_connection_info(connection, MHD_CONNECTION_INFO_SOCKET_CONTEXT);
        info && info->socket_context)
      static_cast<Connection*>(info->socket_context)->served = true;
    unsigned int code = MHD_HTTP_OK;
    std::string type = "text/plain; charset=utf-8", body, path = url;
    const std::shared_ptr<const HttpSnapshot> snap = Snapshot();
    const int64_t stale_ms = StaleMs();
    const bool stale = !snap || stale_ms > options.stale_after_ms;
    const bool draining = snap && snap->draining;
    const int free_slots =
        snap && !draining && !stale ? std::max(0, snap->sessions_capacity - snap->sessions_active) : 0;
    if (method != "GET" && method != "HEAD") {
      code = MHD_HTTP_METHOD_NOT_ALLOWED;
      body = "only GET\n";
      path = "other";
    } else if (url == "/metrics") {
      type = "text/plain; version=0.0.4; charset=utf-8";
      body = (snap ? snap->metrics_text : std::string()) + RenderOwn();
    } else if (url == "/healthz") {
      // Alive: the transport thread publishes (it does on every turn of its loop).
      if (stale) {
        code = MHD_HTTP_SERVICE_UNAVAILABLE;
        body = "stalled: the transport thread has not published for " + std::to_string(stale_ms) + " ms\n";
      } else {
        body = draining ? "draining\n" : "ok\n";
        if (draining) code = MHD_HTTP_SERVICE_UNAVAILABLE;
      }
    } else if (url == "/readyz" || url == "/allocate") {
      // Ready = a free session slot and not draining. /allocate also says where to connect (the Agones
      // pattern behind a Kubernetes Service); 503 tells the caller to ask another replica. Advisory:
      // OpenSession's admission control stays the guard against races.
      if (free_slots == 0) code = MHD_HTTP_SERVICE_UNAVAILABLE;
      if (url == "/allocate") {
        Count("prism_allocate_requests_total");
        nlohmann::json j;
        j["endpoint"] = snap ? snap->endpoint : "";
        j["sessions_active"] = snap ? snap->sessions_active : 0;
        j["sessions_capacity"] = snap ? snap->sessions_capacity : 0;
        j["free"] = free_slots;
        j["draining"] = draining;
        type = "application/json";
        body = j.dump() + "\n";
      } else {
        body = free_slots > 0 ? "ready\n" : (draining ? "draining\n" : "full\n");
      }
    } else {
      code = MHD_HTTP_NOT_FOUND;
      body = "GET /metrics, /healthz, /readyz or /allocate\n";
      path = "other";
    }
    Count("prism_http_requests_total{path=\"" + MetricLabel(path) + "\",code=\"" + std::to_string(code) + "\"}");
    return Reply(connection, code, type, body);
  }

  std::string RenderOwn() const {
    std::lock_guard<std::mutex> lock(metrics_mutex);
    return metrics.Render();
  }

  void OnConnection(MHD_Connection* connection, void** socket_context, MHD_ConnectionNotificationCode code) {
    std::lock_guard<std::mutex> lock(metrics_mutex);
    if (code == MHD_CONNECTION_NOTIFY_STARTED) {
      *socket_context = new Connection{PeerAddress(connection), false};
      metrics.Add("prism_http_connections_total");
      metrics.Set("prism_http_connections_open", metrics.Value("prism_http_connections_open") + 1);
      return;
    }
    auto* c = static_cast<Connection*>(*socket_context);
    metrics.Set("prism_http_connections_open", metrics.Value("prism_http_connections_open") - 1);
    if (c && !c->served) {
      metrics.Add("prism_http_connections_without_request_total");
      if (once.First(c->peer, "http_no_request")) {
        PRISM_LOG(WARNING)
            << "event=http_connection_without_request peer=" << c->peer
            << " message=\"closed before a complete request (idle, slow, garbage or over " << options.max_request_bytes
            << " bytes); logged once per peer, counted in prism_http_connections_without_request_total\"";
      }
    }
    delete c;
    *socket_context = nullptr;
  }
};

namespace {

MHD_Result OnRequest(void* cls, MHD_Connection* connection, const char* url, const char* method, const char*,
                     const char*, size_t* upload_data_size, void** request_context) {
  auto* impl = static_cast<HttpEndpoint::Impl*>(cls);
  if (*request_context == nullptr) {  // headers complete; answer now (a body, if any, is not read)
    *request_context = impl;
    (void)upload_data_size;
  }
  return impl->Handle(connection, url ? url : "", method ? method : "");
}

void OnConnection(void* cls, MHD_Connection* connection, void** socket_context, MHD_ConnectionNotificationCode code) {
  static_cast<HttpEndpoint::Impl*>(cls)->OnConnection(connection, socket_context, code);
}

void OnMhdLog(void*, const char* format, va_list ap) {
  char buf[512];
  std::vsnprintf(buf, sizeof(buf), format, ap);
  std::string s = buf;
  while (!s.empty() && (s.back() == '\n' || s.back() == '\r')) s.pop_back();
  PRISM_LOG(DEBUG) << "event=http_library message=\"" << s << "\"";
}

}  // namespace

StatusOr<std::unique_ptr<HttpEndpoint>> HttpEndpoint::Start(const HttpOptions& options) {
  const size_t colon = options.bind.rfind(':');
  if (colon == std::string::npos)
    return InvalidArgumentError("metrics must be HOST:PORT or off, got '" + options.bind + "'");
  const std::string host = options.bind.substr(0, colon);
  const std::string port_text = options.bind.substr(colon + 1);
  char* end = nullptr;
  const long port = std::strtol(port_text.c_str(), &end, 10);
  if (port_text.empty() || *end != '\0' || port < 0 || port > 65535)
    return InvalidArgumentError("metrics port must be in [0, 65535], got '" + port_text + "'");
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(static_cast<uint16_t>(port));
  if (inet_pton(AF_INET, host.c_str(), &addr.sin_addr) != 1)
    return InvalidArgumentError("metrics host must be an IPv4 address, got '" + host + "'");
  if (options.max_connections < 16 || options.max_connections > 65536)
    return InvalidArgumentError("http max connections must be in [16, 65536]");
  if (options.idle_timeout_s < 1 || options.idle_timeout_s > 3600)
    return InvalidArgumentError("http idle timeout must be in [1, 3600] s");
  if (options.max_request_bytes < 1024 || options.max_request_bytes > (1 << 20))
    return InvalidArgumentError("http max request bytes must be in [1024, 1048576]");

  std::unique_ptr<HttpEndpoint> endpoint(new HttpEndpoint());
  endpoint->impl_ = std::make_unique<Impl>();
  Impl* impl = endpoint->impl_.get();
  impl->options = options;
  impl->published_ns = std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now().time_since_epoch()).count();
  impl->daemon =
      MHD_start_daemon(MHD_USE_EPOLL_INTERNAL_THREAD | MHD_USE_ERROR_LOG, 0, nullptr, nullptr, &OnRequest, impl,
                       MHD_OPTION_SOCK_ADDR, reinterpret_cast<const sockaddr*>(&addr), MHD_OPTION_CONNECTION_LIMIT,
                       static_cast<unsigned int>(options.max_connections), MHD_OPTION_CONNECTION_TIMEOUT,
                       static_cast<unsigned int>(options.idle_timeout_s), MHD_OPTION_CONNECTION_MEMORY_LIMIT,
                       static_cast<size_t>(options.max_request_bytes), MHD_OPTION_NOTIFY_CONNECTION, &OnConnection,
                       impl, MHD_OPTION_LISTEN_BACKLOG_SIZE, 512u, MHD_OPTION_LISTENING_ADDRESS_REUSE, 1u,
                       MHD_OPTION_EXTERNAL_LOGGER, &OnMhdLog, nullptr, MHD_OPTION_END);
  if (!impl->daemon) return UnavailableError("cannot listen for HTTP on " + options.bind + ": " + std::strerror(errno));
  const MHD_DaemonInfo* info = MHD_get_daemon_info(impl->daemon, MHD_DAEMON_INFO_BIND_PORT);
  endpoint->url_ = "http://" + host + ":" + std::to_string(info ? info->port : port);
  return endpoint;
}

HttpEndpoint::~HttpEndpoint() {
  if (impl_ && impl_->daemon) MHD_stop_daemon(impl_->daemon);
}

void HttpEndpoint::Publish(std::shared_ptr<const HttpSnapshot> snapshot) {
  {
    std::lock_guard<std::mutex> lock(impl_->snapshot_mutex);
    impl_->snapshot = std::move(snapshot);
  }
  impl_->published_ns = std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now().time_since_epoch()).count();
}

std::string HttpEndpoint::RenderOwnMetrics() const { return impl_->RenderOwn(); }

}  // namespace prism::server
