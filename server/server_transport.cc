// The transport thread: the poll loop over the ROUTER, the wake eventfd, the connection monitor and the
// ZAP socket; incoming messages dispatched to the session handlers; replies and errors sent; the
// snapshot the HTTP thread serves.
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstring>
#include <deque>
#include <memory>
#include <mutex>
#include <string>
#include <utility>
#include <vector>

#include <zmq.hpp>

#include "core/util/logging.h"
#include "server/curve.h"
#include "server/server_impl.h"

namespace prism::server {
namespace {

v1::ErrorCode ToWireCode(StatusCode code) {
  switch (code) {
    case StatusCode::kInvalidArgument:
    case StatusCode::kOutOfRange:
      return v1::ERROR_CODE_INVALID_ARGUMENT;
    case StatusCode::kNotFound:
      return v1::ERROR_CODE_NOT_FOUND;
    case StatusCode::kResourceExhausted:
      return v1::ERROR_CODE_RESOURCE_EXHAUSTED;
    case StatusCode::kFailedPrecondition:
      return v1::ERROR_CODE_FAILED_PRECONDITION;
    case StatusCode::kUnauthenticated:
      return v1::ERROR_CODE_UNAUTHENTICATED;
    case StatusCode::kDataLoss:
      return v1::ERROR_CODE_DATA_LOSS;
    case StatusCode::kUnavailable:
      return v1::ERROR_CODE_UNAVAILABLE;
    default:
      return v1::ERROR_CODE_INTERNAL;
  }
}

}  // namespace

void Server::Impl::Wake() {
  const uint64_t one = 1;
  (void)!::write(wake_fd, &one, sizeof(one));
}

Status Server::Impl::StartHttp() {
  if (options.metrics_bind == "off") return Status::Ok();
  HttpOptions ho;
  ho.bind = options.metrics_bind;
  ho.max_connections = options.http_max_connections;
  ho.idle_timeout_s = options.http_idle_timeout_s;
  ho.max_request_bytes = options.http_max_request_bytes;
  PRISM_ASSIGN_OR_RETURN(http, HttpEndpoint::Start(ho));
  metrics_endpoint = http->url();
  PublishSnapshot();
  return Status::Ok();
}

// Hands the HTTP thread what /metrics, /healthz, /readyz and /allocate read: at most every 100 ms,
// and at once when the session count or draining changed.
void Server::Impl::PublishSnapshot(bool force) {
  if (!http) return;
  const auto now = Clock::now();
  const bool changed = sessions.size() != published_sessions || draining != published_draining;
  if (!force && !changed && now - last_publish < std::chrono::milliseconds(100)) return;
  last_publish = now;
  published_sessions = sessions.size();
  published_draining = draining;
  UpdateGauges();
  auto snap = std::make_shared<HttpSnapshot>();
  snap->metrics_text = metrics.Render();
  snap->endpoint = options.advertise.empty() ? endpoint : options.advertise;
  snap->sessions_active = static_cast<int>(sessions.size());
  snap->sessions_capacity = options.max_sessions;
  snap->draining = draining;
  http->Publish(std::move(snap));
}

// Starts reading the ROUTER's connection events (accepts, disconnects, failed handshakes).
void Server::Impl::StartMonitor() {
  const char* address = "inproc://prism-router-monitor";
  const int events = ZMQ_EVENT_ACCEPTED | ZMQ_EVENT_DISCONNECTED | ZMQ_EVENT_HANDSHAKE_FAILED_NO_DETAIL |
                     ZMQ_EVENT_HANDSHAKE_FAILED_PROTOCOL | ZMQ_EVENT_HANDSHAKE_FAILED_AUTH;
  if (zmq_socket_monitor(router.handle(), address, events) != 0) {
    PRISM_LOG(WARNING) << "event=monitor_unavailable error=\"" << zmq_strerror(zmq_errno()) << "\"";
    return;
  }
  monitor.set(zmq::sockopt::linger, 0);
  monitor.connect(address);
  monitoring = true;
  window.start = Clock::now();
}

void Server::Impl::ReadMonitor() {
  for (int n = 0; n < 4096; ++n) {
    zmq::message_t event, address;
    if (!monitor.recv(event, zmq::recv_flags::dontwait)) break;
    if (event.more()) (void)monitor.recv(address, zmq::recv_flags::none);
    if (event.size() < 6) continue;
    uint16_t id = 0;
    std::memcpy(&id, event.data(), sizeof(id));
    switch (id) {
      case ZMQ_EVENT_ACCEPTED:
        metrics.Add("prism_zmq_connections_accepted_total");
        metrics.Set("prism_zmq_connections_open", metrics.Value("prism_zmq_connections_open") + 1);
        ++window.accepted;
        break;
      case ZMQ_EVENT_DISCONNECTED:
        metrics.Add("prism_zmq_disconnects_total");
        metrics.Set("prism_zmq_connections_open", std::max(0.0, metrics.Value("prism_zmq_connections_open") - 1));
        break;
      case ZMQ_EVENT_HANDSHAKE_FAILED_PROTOCOL:
        metrics.Add("prism_zmq_handshake_failures_total{reason=\"protocol\"}");
        ++window.handshake_failures;
        break;
      case ZMQ_EVENT_HANDSHAKE_FAILED_AUTH:
        metrics.Add("prism_zmq_handshake_failures_total{reason=\"auth\"}");
        ++window.handshake_failures;
        break;
      default:
        metrics.Add("prism_zmq_handshake_failures_total{reason=\"no_detail\"}");
        ++window.handshake_failures;
        break;
    }
  }
  // Connection events carry no peer identity worth logging one by one: one line per 10 s window when
  // handshakes failed or connections churned (over 10 a second).
  const auto now = Clock::now();
  if (now - window.start < std::chrono::seconds(10)) return;
  if (window.handshake_failures > 0 || window.accepted > 100) {
    PRISM_LOG(WARNING) << "event=zmq_connection_churn accepted=" << window.accepted
                       << " handshake_failures=" << window.handshake_failures
                       << " window_s=" << std::chrono::duration<double>(now - window.start).count();
  }
  window = ConnectionWindow{0, 0, now};
}

void Server::Impl::UpdateGauges() {
  metrics.Set("prism_sessions_active", static_cast<double>(sessions.size()));
  metrics.Set("prism_sessions_capacity", options.max_sessions);
  metrics.Set("prism_dense_jobs_pending", static_cast<double>(workers->pending_jobs()));
  size_t pending_chunks = 0, in_memory = 0;
  for (const auto& [id, s] : sessions) {
    pending_chunks += s->pending_chunks.size();
    in_memory += s->pending_bytes_in_memory;
    const std::string label = "{session=\"" + MetricLabel(id) + "\"}";
    metrics.Set("prism_session_chunks_waiting" + label, static_cast<double>(s->pending_chunks.size()));
    metrics.Set("prism_session_frames_dropped" + label, static_cast<double>(s->frames_dropped));
    if (s->pipeline) {
      metrics.Set("prism_session_frame_queue_depth" + label, static_cast<double>(s->pipeline->queued_frames()));
      metrics.Set("prism_session_keyframe_queue_depth" + label, static_cast<double>(s->pipeline->queued_keyframes()));
    }
  }
  metrics.Set("prism_chunks_waiting_for_credit", static_cast<double>(pending_chunks));
  metrics.Set("prism_chunk_bytes_waiting_in_memory", static_cast<double>(in_memory));
}

// Sends [peer][envelope][payload?] without blocking. false when the peer is gone (ROUTER_MANDATORY:
// EHOSTUNREACH) or its queue is full (EAGAIN); counted either way.
bool Server::Impl::Send(const std::string& peer, const v1::Envelope& env, const std::vector<uint8_t>* payload) {
  const std::string header = env.SerializeAsString();
  try {
    if (!router.send(zmq::buffer(peer), zmq::send_flags::dontwait | zmq::send_flags::sndmore)) {
      metrics.Add("prism_send_failures_total{reason=\"hwm\"}");
      return false;
    }
    if (payload) {
      router.send(zmq::buffer(header), zmq::send_flags::dontwait | zmq::send_flags::sndmore);
      router.send(zmq::buffer(*payload), zmq::send_flags::dontwait);
    } else {
      router.send(zmq::buffer(header), zmq::send_flags::dontwait);
    }
    return true;
  } catch (const zmq::error_t& e) {
    metrics.Add(std::string("prism_send_failures_total{reason=\"") +
                (e.num() == EHOSTUNREACH ? "unreachable" : "other") + "\"}");
    return false;
  }
}

void Server::Impl::SendError(const std::string& peer, const Status& status, const std::string& session_id,
                             bool retryable, bool session_closed, const uint64_t* frame) {
  v1::Envelope env;
  env.set_protocol_version(v1::PROTOCOL_VERSION_1);
  v1::Error* e = env.mutable_error();
  e->set_code(ToWireCode(status.code()));
  e->set_message(status.message());
  e->set_retryable(retryable);
  e->set_session_id(session_id);
  e->set_session_closed(session_closed);
  if (frame) {
    e->set_has_frame(true);
    e->set_frame_sequence_number(*frame);
  }
  metrics.Add(std::string("prism_errors_sent_total{code=\"") + v1::ErrorCode_Name(e->code()) + "\"}");
  // A flood of bad messages from one peer is one line; prism_errors_sent_total counts them all.
  if (once.First(peer, v1::ErrorCode_Name(e->code()))) {
    PRISM_LOG(INFO) << "event=error_sent peer=" << PeerName(peer)
                    << " session=" << (session_id.empty() ? "-" : session_id)
                    << " code=" << v1::ErrorCode_Name(e->code()) << " message=\"" << status.message()
                    << "\" (logged once per peer and code)";
  }
  Send(peer, env);
}

void Server::Impl::SendVersionMismatch(const std::string& peer, int version) {
  v1::Envelope env;
  env.set_protocol_version(v1::PROTOCOL_VERSION_1);
  v1::Error* e = env.mutable_error();
  e->set_code(v1::ERROR_CODE_VERSION_MISMATCH);
  e->set_message("protocol version " + std::to_string(version) + " is not supported; this server speaks version 1");
  metrics.Add("prism_errors_sent_total{code=\"ERROR_CODE_VERSION_MISMATCH\"}");
  if (once.First(peer, "version")) {
    PRISM_LOG(INFO) << "event=error_sent peer=" << PeerName(peer)
                    << " code=ERROR_CODE_VERSION_MISMATCH version=" << version << " (logged once per peer)";
  }
  Send(peer, env);
}

void Server::Impl::HandleMessage(std::vector<zmq::message_t>& parts) {
  metrics.Add("prism_messages_received_total");
  const std::string peer = parts[0].to_string();
  if (parts.size() < 2 || parts.size() > 3) {
    metrics.Add("prism_malformed_messages_total");
    SendError(peer,
              InvalidArgumentError("malformed message: expected [Envelope] or [Envelope][payload], got " +
                                   std::to_string(parts.size() - 1) + " parts"),
              "", false, false);
    return;
  }
  v1::Envelope env;
  if (!env.ParseFromArray(parts[1].data(), static_cast<int>(parts[1].size()))) {
    metrics.Add("prism_malformed_messages_total");
    SendError(peer,
              InvalidArgumentError("malformed envelope: " + std::to_string(parts[1].size()) +
                                   " bytes that do not parse as a prism.v1.Envelope"),
              "", false, false);
    return;
  }
  if (env.protocol_version() != v1::PROTOCOL_VERSION_1) {
    metrics.Add("prism_malformed_messages_total");
    SendVersionMismatch(peer, env.protocol_version());
    return;
  }
  const zmq::message_t* payload = parts.size() == 3 ? &parts[2] : nullptr;
  const bool wants_payload = env.body_case() == v1::Envelope::kFrame;
  if (payload && !wants_payload) {
    metrics.Add("prism_malformed_messages_total");
    SendError(peer, InvalidArgumentError("this message type carries no payload part"), "", false, false);
    return;
  }
  switch (env.body_case()) {
    case v1::Envelope::kOpenSession:
      return OpenSession(peer, env.open_session());
    case v1::Envelope::kFrame:
      return HandleFrame(peer, env.frame(), payload);
    case v1::Envelope::kChunkCredits: {
      // NOT_FOUND like Frame and Close; credits for a session that has just ended (granted for its
      // last chunks) are common, and clients that have its summary ignore the error.
      auto it = sessions.find(env.chunk_credits().session_id());
      if (it == sessions.end() || it->second->peer != peer) metrics.Add("prism_stale_credits_total");
      Session* s = FindSession(peer, env.chunk_credits().session_id());
      if (!s) return;
      s->last_activity = Clock::now();
      s->chunk_credits = std::min<int64_t>(s->chunk_credits + env.chunk_credits().chunks(), 1 << 20);
      FlushChunks(s);
      return;
    }
    case v1::Envelope::kClose: {
      Session* s = FindSession(peer, env.close().session_id());
      if (!s) return;
      s->last_activity = Clock::now();
      if (!s->closing) {
        s->closing = true;
        s->reason = env.close().abort() ? "aborted by client" : "closed by client";
        if (env.close().abort()) s->pipeline->Abort();
        else s->pipeline->Finish();
        PRISM_LOG(INFO) << "event=session_closing session=" << s->id << " reason=\"" << s->reason << "\"";
      }
      return;
    }
    case v1::Envelope::BODY_NOT_SET:
      metrics.Add("prism_malformed_messages_total");
      SendError(peer, InvalidArgumentError("envelope has no body"), "", false, false);
      return;
    default:
      metrics.Add("prism_malformed_messages_total");
      SendError(peer,
                InvalidArgumentError("a client may not send this message type (body " +
                                     std::to_string(static_cast<int>(env.body_case())) + ")"),
                "", false, false);
      return;
  }
}

Status Server::Impl::Run() {
  PRISM_LOG(INFO) << "event=server_started endpoint=" << endpoint << " metrics=" << metrics_endpoint
                  << " max_sessions=" << options.max_sessions << " dense_workers=" << options.dense_workers
                  << " pool_threads=" << pool->num_threads();
  std::vector<zmq::pollitem_t> items;
  for (;;) {
    if (stop_requested && !draining) {
      draining = true;
      drain_deadline = Clock::now() + std::chrono::milliseconds(options.shutdown_deadline_ms);
      PRISM_LOG(INFO) << "event=draining sessions=" << sessions.size();
      for (auto& [id, s] : sessions)
        if (!s->closing) {
          s->closing = true;
          s->reason = "server shutdown";
          s->pipeline->Finish();
        }
    }
    if (draining && sessions.empty()) break;
    items.clear();
    items.push_back({router.handle(), 0, ZMQ_POLLIN, 0});
    items.push_back({nullptr, wake_fd, ZMQ_POLLIN, 0});
    const size_t monitor_item = items.size();
    if (monitoring) items.push_back({monitor.handle(), 0, ZMQ_POLLIN, 0});
    const size_t zap_item = items.size();
    if (zap) items.push_back({zap->handle(), 0, ZMQ_POLLIN, 0});
    try {
      zmq::poll(items.data(), items.size(), std::chrono::milliseconds(50));
    } catch (const zmq::error_t& e) {
      if (e.num() != EINTR) return InternalError(std::string("zmq::poll failed: ") + e.what());
      continue;  // a signal (SIGTERM sets stop_requested)
    }
    if (items[1].revents & ZMQ_POLLIN) {
      uint64_t v;
      (void)!::read(wake_fd, &v, sizeof(v));
    }
    // Incoming: at most a batch per loop so events and housekeeping keep flowing.
    for (int n = 0; n < 256; ++n) {
      std::vector<zmq::message_t> parts;
      zmq::message_t part;
      try {
        if (!router.recv(part, zmq::recv_flags::dontwait)) break;
        parts.push_back(std::move(part));
        while (parts.back().more() && parts.size() < 8) {
          zmq::message_t next;
          (void)router.recv(next, zmq::recv_flags::none);
          parts.push_back(std::move(next));
        }
        while (parts.back().more()) {  // more than 8 parts: drain the rest
          zmq::message_t rest;
          (void)router.recv(rest, zmq::recv_flags::none);
          parts.push_back(zmq::message_t());
          parts.back().swap(rest);
          if (parts.size() > 64) parts.erase(parts.begin() + 8, parts.end() - 1);
        }
      } catch (const zmq::error_t& e) {
        PRISM_LOG(WARNING) << "event=recv_failed error=\"" << e.what() << "\"";
        break;
      }
      try {
        HandleMessage(parts);
      } catch (const std::exception& e) {  // a bug in handling one message never takes the server down
        PRISM_LOG(ERROR) << "event=handler_failed error=\"" << e.what() << "\"";
        metrics.Add("prism_handler_failures_total");
      }
    }
    std::deque<Outgoing> events;
    {
      std::lock_guard<std::mutex> lock(outbox_mutex);
      events.swap(outbox);
    }
    metrics.Set("prism_transport_events_pending", static_cast<double>(events.size()));
    for (Outgoing& o : events) HandleEvent(o);
    if (monitoring && (items[monitor_item].revents & ZMQ_POLLIN)) ReadMonitor();
    if (zap && (items[zap_item].revents & ZMQ_POLLIN)) {
      std::string key;
      for (int n = 0; n < 64; ++n) {
        try {
          const bool admitted = HandleZapRequest(*zap, allowed_clients, &key);
          if (key.empty() && !admitted) break;  // nothing pending (or a non-CURVE request, refused)
          metrics.Add(admitted ? "prism_auth_accepted_total" : "prism_auth_refused_total");
          if (!admitted && once.First(key, "auth")) {
            PRISM_LOG(WARNING) << "event=auth_refused client_key=" << key << " (logged once per key)";
          }
        } catch (const zmq::error_t& e) {
          PRISM_LOG(WARNING) << "event=zap_failed error=\"" << e.what() << "\"";
          break;
        }
      }
    }
    Housekeeping();
    PublishSnapshot(/*force=*/false);
  }
  PublishSnapshot();
  PRISM_LOG(INFO) << "event=server_stopped";
  return Status::Ok();
}

}  // namespace prism::server
