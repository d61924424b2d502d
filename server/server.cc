#include "server/server.h"

#include <sys/eventfd.h>
#include <unistd.h>

#include <deque>
#include <filesystem>
#include <memory>
#include <mutex>
#include <string>
#include <system_error>
#include <utility>
#include <vector>

#include <zmq.hpp>

#include "core/util/logging.h"
#include "server/curve.h"
#include "server/server_impl.h"

namespace prism::server {

Server::Impl::Impl() { DeclareServerMetrics(&metrics); }

Server::Impl::~Impl() {
  http.reset();      // no handler runs past here
  sessions.clear();  // pipelines stop before the workers and pool go
  workers.reset();
  if (wake_fd >= 0) ::close(wake_fd);
}

Server::Server(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Server::~Server() = default;

StatusOr<std::unique_ptr<Server>> Server::Create(const ServerOptions& options) {
  PRISM_RETURN_IF_ERROR(options.Check());
  auto impl = std::make_unique<Impl>();
  impl->options = options;
  impl->store = SessionStore(options.data_dir);
  std::error_code ec;
  std::filesystem::create_directories(options.data_dir + "/sessions", ec);
  if (ec) return UnavailableError("cannot create data dir '" + options.data_dir + "': " + ec.message());
  impl->wake_fd = ::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (impl->wake_fd < 0) return InternalError("eventfd failed");
  try {
    zmq::socket_t& r = impl->router;
    if (!options.curve_keys.empty()) {
      if (!zmq_has("curve")) return UnavailableError("curve_keys is set but this libzmq was built without CURVE");
      PRISM_ASSIGN_OR_RETURN(CurveKeyPair keys, ReadCurveKeyFile(options.curve_keys));
      PRISM_ASSIGN_OR_RETURN(impl->allowed_clients, ReadAllowList(options.allowed_clients));
      impl->zap = std::make_unique<zmq::socket_t>(impl->context, zmq::socket_type::rep);
      impl->zap->set(zmq::sockopt::linger, 0);
      impl->zap->bind("inproc://zeromq.zap.01");
      r.set(zmq::sockopt::curve_server, 1);
      r.set(zmq::sockopt::curve_secretkey, keys.secret_key);
      r.set(zmq::sockopt::zap_domain, std::string("prism"));
      PRISM_LOG(INFO) << "event=curve_enabled server_key=" << keys.public_key
                      << " allowed_clients=" << impl->allowed_clients.size();
    }
    r.set(zmq::sockopt::router_mandatory, 1);
    r.set(zmq::sockopt::linger, 0);
    r.set(zmq::sockopt::maxmsgsize, options.MessageLimit());
    r.set(zmq::sockopt::handshake_ivl, options.handshake_timeout_ms);
    r.set(zmq::sockopt::heartbeat_ivl, options.heartbeat_ivl_ms);
    r.set(zmq::sockopt::heartbeat_timeout, options.heartbeat_timeout_ms);
    r.set(zmq::sockopt::heartbeat_ttl, options.heartbeat_timeout_ms);
    r.set(zmq::sockopt::sndhwm, options.send_hwm);
    r.set(zmq::sockopt::rcvhwm, options.send_hwm);
    r.bind(options.bind);
    impl->endpoint = r.get(zmq::sockopt::last_endpoint);
    if (options.curve_keys.empty() && !IsLoopbackEndpoint(impl->endpoint)) {
      PRISM_LOG(WARNING) << "event=unencrypted_listener endpoint=" << impl->endpoint
                         << " message=\"plain TCP on a non-loopback address: anyone who can reach it may open "
                            "sessions and read the traffic; use --curve-keys and --allowed-clients\"";
    }
  } catch (const zmq::error_t& e) {
    return UnavailableError("cannot bind " + options.bind + ": " + e.what());
  }
  impl->pool = std::make_unique<ThreadPool>(options.threads, options.dense_nice);
  impl->workers = std::make_unique<DenseWorkers>(options.dense_workers, impl->pool.get(), options.dense_nice);
  impl->StartMonitor();
  PRISM_RETURN_IF_ERROR(impl->StartHttp());
  return std::unique_ptr<Server>(new Server(std::move(impl)));
}

const std::string& Server::endpoint() const { return impl_->endpoint; }
const std::string& Server::metrics_endpoint() const { return impl_->metrics_endpoint; }
Status Server::Run() { return impl_->Run(); }
void Server::HandleMessageForFuzzing(const std::vector<std::string>& parts) {
  std::vector<zmq::message_t> messages;
  for (const std::string& p : parts) messages.emplace_back(p.data(), p.size());
  if (messages.empty()) return;
  impl_->HandleMessage(messages);  // Run catches what escapes; a fuzzer must see it
  std::deque<Impl::Outgoing> events;
  {
    std::lock_guard<std::mutex> lock(impl_->outbox_mutex);
    events.swap(impl_->outbox);
  }
  for (Impl::Outgoing& o : events) impl_->HandleEvent(o);
}

void Server::RequestStop() {
  impl_->stop_requested = true;
  impl_->Wake();
}

}  // namespace prism::server
