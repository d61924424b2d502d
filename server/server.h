// prism-server's transport: the sole owner of the ROUTER socket (and of the metrics listener), one
// thread. Sessions' pipelines run on their own SLAM threads and the shared dense workers; their
// events come back through a mutex-guarded outbox and an eventfd that wakes this thread's zmq::poll
// (an fd poll item; the same role as an inproc socket, without a socket per producer thread).
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "core/util/status.h"
#include "server/server_options.h"

namespace prism::server {

class Server {
 public:
  // Binds the ROUTER socket and the metrics listener. INVALID_ARGUMENT on bad options, UNAVAILABLE
  // when an endpoint cannot be bound.
  static StatusOr<std::unique_ptr<Server>> Create(const ServerOptions& options);
  ~Server();

  // The bound endpoints, e.g. "tcp://127.0.0.1:40123" and "http://127.0.0.1:40124" ("" when off).
  const std::string& endpoint() const;
  const std::string& metrics_endpoint() const;

  // Serves until RequestStop, then drains: no new sessions, sessions finish their queued work within
  // the shutdown deadline, persist their maps and get a SessionSummary. Returns OK after a clean drain.
  Status Run();
  // Async-signal-safe: may be called from a signal handler or any thread.
  void RequestStop();

  // For the fuzz targets: handles one multipart message [routing id][Envelope][payload?] exactly as Run
  // does (validation, handlers, then the pipelines' pending events), on the calling thread; Run must
  // not be running. Replies go to the ROUTER, which drops those for unknown routing ids. Exceptions
  // (broken invariants, which Run would log and survive) propagate, so the fuzzer reports them.
  void HandleMessageForFuzzing(const std::vector<std::string>& parts);

 private:
  struct Impl;
  explicit Server(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace prism::server
