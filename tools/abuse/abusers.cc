#include "tools/abuse/abusers.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <signal.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstring>
#include <deque>
#include <iostream>
#include <memory>
#include <random>
#include <thread>

#include <zmq.hpp>

#include "core/codec/frame_codec.h"
#include "core/synth/presets.h"
#include "core/synth/renderer.h"
#include "core/synth/trajectory.h"
#include "core/util/thread_pool.h"
#include "prism/v1/session.pb.h"
#include "server/rig_wire.h"

namespace prism::abuse {
namespace {

using Clock = std::chrono::steady_clock;
std::atomic<bool> g_stop{false};

void OnTerm(int) { g_stop = true; }

struct Deadline {
  Clock::time_point end;
  explicit Deadline(double seconds)
      : end(Clock::now() + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(seconds))) {}
  bool passed() const { return g_stop || Clock::now() >= end; }
};

// Tells the benchmark the abuser is set up and starts now.
void Ready() { std::cout << "ready" << std::endl; }

void SleepMs(double ms) { std::this_thread::sleep_for(std::chrono::duration<double, std::milli>(ms)); }

// host:port -> a TCP socket connecting (non-blocking), -1 on failure.
int ConnectTcp(const std::string& host_port, bool blocking = false) {
  const size_t colon = host_port.rfind(':');
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(static_cast<uint16_t>(std::atoi(host_port.c_str() + colon + 1)));
  inet_pton(AF_INET, host_port.substr(0, colon).c_str(), &addr.sin_addr);
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC | (blocking ? 0 : SOCK_NONBLOCK), 0);
  if (fd < 0) return -1;
  if (::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) != 0 && errno != EINPROGRESS) {
    ::close(fd);
    return -1;
  }
  return fd;
}

std::string HostPort(const std::string& tcp_endpoint) { return tcp_endpoint.substr(tcp_endpoint.find("//") + 2); }

// True when the peer closed (or reset) the connection.
bool PeerClosed(int fd) {
  pollfd p{fd, POLLIN, 0};
  if (::poll(&p, 1, 0) <= 0) return false;
  if (p.revents & (POLLHUP | POLLERR)) return true;
  char buf[4096];
  const ssize_t n = ::recv(fd, buf, sizeof(buf), MSG_DONTWAIT);
  return n == 0 || (n < 0 && errno != EAGAIN && errno != EWOULDBLOCK);
}

// ---- HTTP port ----

// 200 connections each sending its request one byte every 150 ms (never finishing the headers).
int HttpSlowloris(const Target& t) {
  struct Conn {
    int fd = -1;
    size_t pos = 0;  // bytes of the request sent
    Clock::time_point next;
  };
  std::vector<Conn> conns(200);
  const std::string head = "GET /metrics HTTP/1.1\r\nHost: prism\r\nX-Slow: ";
  Ready();
  Deadline deadline(t.seconds);
  size_t opened = 0;
  while (!deadline.passed()) {
    const auto now = Clock::now();
    int new_this_tick = 0;
    for (Conn& c : conns) {
      if (c.fd >= 0 && PeerClosed(c.fd)) {
        ::close(c.fd);
        c.fd = -1;
      }
      if (c.fd < 0) {
        if (new_this_tick++ >= 20) continue;  // ramp up
        c.fd = ConnectTcp(t.http_host_port);
        if (c.fd < 0) continue;
        ++opened;
        c.pos = 0;
        c.next = now + std::chrono::milliseconds(20);
        continue;
      }
      if (now < c.next) continue;
      const char byte = c.pos < head.size() ? head[c.pos] : 'a';
      if (::send(c.fd, &byte, 1, MSG_NOSIGNAL | MSG_DONTWAIT) == 1) ++c.pos;
      c.next = now + std::chrono::milliseconds(150);
    }
    SleepMs(10);
  }
  for (Conn& c : conns)
    if (c.fd >= 0) ::close(c.fd);
  std::cerr << "http-slowloris: " << opened << " connections opened\n";
  return 0;
}

// 500 connections that send nothing; reopened when the server closes them.
int HttpIdle(const Target& t) {
  std::vector<int> fds(500, -1);
  Ready();
  Deadline deadline(t.seconds);
  size_t opened = 0;
  while (!deadline.passed()) {
    int new_this_tick = 0;
    for (int& fd : fds) {
      if (fd >= 0 && PeerClosed(fd)) {
        ::close(fd);
        fd = -1;
      }
      if (fd < 0 && new_this_tick++ < 50) {
        fd = ConnectTcp(t.http_host_port);
        if (fd >= 0) ++opened;
      }
    }
    SleepMs(20);
  }
  for (int fd : fds)
    if (fd >= 0) ::close(fd);
  std::cerr << "http-idle: " << opened << " connections opened\n";
  return 0;
}

// Requests of random bytes, as fast as answers come (about 200 a second).
int HttpGarbage(const Target& t) {
  std::mt19937 rng(7);
  Ready();
  Deadline deadline(t.seconds);
  size_t sent = 0;
  while (!deadline.passed()) {
    const int fd = ConnectTcp(t.http_host_port, /*blocking=*/true);
    if (fd < 0) {
      SleepMs(5);
      continue;
    }
    timeval tv{1, 0};
    setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof(tv));
    std::string junk(64 + rng() % 512, '\0');
    for (char& c : junk) c = static_cast<char>(rng() % 256);
    junk += "\r\n\r\n";
    (void)::send(fd, junk.data(), junk.size(), MSG_NOSIGNAL);
    char buf[1024];
    while (::recv(fd, buf, sizeof(buf), 0) > 0) {
    }
    ::close(fd);
    ++sent;
    SleepMs(5);
  }
  std::cerr << "http-garbage: " << sent << " requests\n";
  return 0;
}

// Requests with a 10 MB header, one after another.
int HttpHugeHeader(const Target& t) {
  const std::string request = "GET /healthz HTTP/1.1\r\nHost: prism\r\nX-Huge: " + std::string(10 << 20, 'a');
  Ready();
  Deadline deadline(t.seconds);
  size_t sent = 0;
  while (!deadline.passed()) {
    const int fd = ConnectTcp(t.http_host_port, /*blocking=*/true);
    if (fd < 0) {
      SleepMs(10);
      continue;
    }
    timeval tv{2, 0};
    setsockopt(fd, SOL_SOCKET, SO_SNDTIMEO, &tv, sizeof(tv));
    size_t off = 0;
    while (off < request.size()) {
      const ssize_t n = ::send(fd, request.data() + off, request.size() - off, MSG_NOSIGNAL);
      if (n <= 0) break;
      off += static_cast<size_t>(n);
    }
    ::close(fd);
    ++sent;
    SleepMs(50);
  }
  std::cerr << "http-huge-header: " << sent << " requests\n";
  return 0;
}

// ---- ZeroMQ port ----

// 200 TCP connections that never start the ZMTP handshake; reopened when dropped.
int ZmqSilent(const Target& t) {
  std::vector<int> fds(200, -1);
  const std::string hp = HostPort(t.zmq_endpoint);
  Ready();
  Deadline deadline(t.seconds);
  size_t opened = 0;
  while (!deadline.passed()) {
    for (int& fd : fds) {
      if (fd >= 0 && PeerClosed(fd)) {
        ::close(fd);
        fd = -1;
      }
      if (fd < 0) {
        fd = ConnectTcp(hp);
        if (fd >= 0) ++opened;
      }
    }
    SleepMs(50);
  }
  for (int fd : fds)
    if (fd >= 0) ::close(fd);
  std::cerr << "zmq-silent: " << opened << " connections opened\n";
  return 0;
}

// 1000 TCP connects and disconnects a second, for at most 10 s.
int ZmqChurn(const Target& t) {
  const std::string hp = HostPort(t.zmq_endpoint);
  Ready();
  Deadline deadline(std::min(10.0, t.seconds));
  size_t n = 0;
  const auto start = Clock::now();
  while (!deadline.passed()) {
    const int fd = ConnectTcp(hp, /*blocking=*/true);
    if (fd >= 0) {
      ::close(fd);
      ++n;
    }
    // Pace at 1000 a second.
    std::this_thread::sleep_until(start + std::chrono::microseconds(1000 * n));
  }
  std::cerr << "zmq-churn: " << n << " connects\n";
  return 0;
}

v1::Envelope OpenEnvelope(const RigCalibration& rig, uint32_t chunk_credits) {
  v1::Envelope env;
  env.set_protocol_version(v1::PROTOCOL_VERSION_1);
  v1::OpenSession* o = env.mutable_open_session();
  o->set_protocol_version(v1::PROTOCOL_VERSION_1);
  o->set_codec(v1::FRAME_CODEC_PNG);
  o->set_client_name("prism-bench-abuse");
  o->set_input_policy(v1::INPUT_POLICY_LIVE);
  o->set_initial_chunk_credits(chunk_credits);
  RigToWire(rig, o->mutable_calibration());
  return env;
}

v1::Envelope FrameEnvelope(const std::string& session, uint64_t seq) {
  v1::Envelope env;
  env.set_protocol_version(v1::PROTOCOL_VERSION_1);
  v1::Frame* f = env.mutable_frame();
  f->set_session_id(session);
  f->set_sequence_number(seq);
  f->set_timestamp_ns(static_cast<int64_t>(seq) * 33'333'333);
  f->set_codec(v1::FRAME_CODEC_PNG);
  return env;
}

// A DEALER speaking the wire protocol, draining what comes back.
class Dealer {
 public:
  Dealer(zmq::context_t& context, const std::string& endpoint) : socket_(context, zmq::socket_type::dealer) {
    socket_.set(zmq::sockopt::linger, 0);
    socket_.set(zmq::sockopt::sndhwm, 100000);
    socket_.connect(endpoint);
  }
  zmq::socket_t& socket() { return socket_; }
  bool Send(const v1::Envelope& env, const std::string* payload = nullptr) {
    const std::string header = env.SerializeAsString();
    if (!socket_.send(zmq::buffer(header),
                      payload ? zmq::send_flags::sndmore | zmq::send_flags::dontwait : zmq::send_flags::dontwait))
      return false;
    if (payload) (void)socket_.send(zmq::buffer(*payload), zmq::send_flags::dontwait);
    return true;
  }
  // Reads whatever arrived; returns the session id of a SessionOpened among it ("" if none).
  std::string Drain(int timeout_ms = 0) {
    std::string opened;
    zmq::pollitem_t item{socket_.handle(), 0, ZMQ_POLLIN, 0};
    if (timeout_ms > 0) zmq::poll(&item, 1, std::chrono::milliseconds(timeout_ms));
    zmq::message_t part;
    while (socket_.recv(part, zmq::recv_flags::dontwait)) {
      v1::Envelope env;
      if (env.ParseFromArray(part.data(), static_cast<int>(part.size())) && env.has_session_opened())
        opened = env.session_opened().session_id();
      while (part.more()) (void)socket_.recv(part, zmq::recv_flags::none);
    }
    return opened;
  }
  std::string Open(const RigCalibration& rig, uint32_t chunk_credits) {
    Send(OpenEnvelope(rig, chunk_credits));
    for (int i = 0; i < 100 && !g_stop; ++i)
      if (std::string id = Drain(100); !id.empty()) return id;
    return "";
  }

 private:
  zmq::socket_t socket_;
};

// A small rendered sequence (PNG bytes), for the abusers that run real sessions.
struct SmallSequence {
  RigCalibration rig;
  std::vector<std::string> png;
};

// The first `frames` of a path spread over `path_frames` (at least `frames`) frames.
SmallSequence RenderSmall(int frames, int path_frames = 0) {
  synth::PresetOptions po;
  po.width = 160;
  po.height = 120;
  po.frames = std::max(frames, path_frames);
  SmallSequence s;
  StatusOr<synth::SynthSetup> setup = synth::MakePreset("torus", po);
  if (!setup.ok()) setup = synth::MakePreset(synth::ListPresets().front().name, po);
  s.rig = setup->rig;
  const Trajectory traj = synth::MakeTrajectory(setup->trajectory);
  s.png.resize(frames);
  ThreadPool pool(1);  // beside the server under test: one core at most
  pool.ParallelFor(0, frames, [&](std::ptrdiff_t i) {
    const cv::Mat rgb =
        synth::RenderFrame(setup->scene, setup->rig, traj[i].world_from_camera, setup->render, 77 + i).rgb;
    std::vector<uint8_t> bytes;
    FrameEncodeOptions fo;
    (void)EncodeFrame(rgb, fo, &bytes);
    s.png[i].assign(bytes.begin(), bytes.end());
  });
  return s;
}

// Streams valid frames at `fps` into one session, ignoring frame credits; never grants chunk credits
// when `grant_chunks` is false.
// The motion per frame is that of a 30 frames/s camera slowed down fps / 30 times (a faster camera on
// the same path), forth and back.
int StreamSession(const Target& t, double fps, bool grant_chunks, const char* name) {
  const int path_frames = static_cast<int>(300 * fps / 30);
  const int frames = std::min(path_frames, static_cast<int>(std::min(1200.0, fps * (t.seconds + 2))));
  const SmallSequence seq = RenderSmall(frames, path_frames);
  zmq::context_t context(1);
  Dealer d(context, t.zmq_endpoint);
  const std::string id = d.Open(seq.rig, 1);
  if (id.empty()) {
    std::cerr << name << ": no session opened\n";
    return 1;
  }
  Ready();
  Deadline deadline(t.seconds);
  const auto start = Clock::now();
  uint64_t n = 0;
  while (!deadline.passed()) {
    // Forth and back through the sequence, so the motion stays smooth.
    const size_t period = 2 * seq.png.size() - 2, k = n % period;
    const std::string& png = seq.png[k < seq.png.size() ? k : period - k];
    d.Send(FrameEnvelope(id, n), &png);
    ++n;
    if (grant_chunks && n % 30 == 0) {
      v1::Envelope env;
      env.set_protocol_version(v1::PROTOCOL_VERSION_1);
      env.mutable_chunk_credits()->set_session_id(id);
      env.mutable_chunk_credits()->set_chunks(8);
      d.Send(env);
    }
    d.Drain();
    std::this_thread::sleep_until(start + std::chrono::duration_cast<Clock::duration>(
                                              std::chrono::duration<double>(static_cast<double>(n) / fps)));
  }
  std::cerr << name << ": " << n << " frames\n";
  return 0;
}

// Frames just over max-frame-bytes (16 MiB + 32 KiB: refused) twice a second, frames of 17 MB (over
// the message limit: ZeroMQ drops the connection) five times a second, and a 70 MB message every 2 s
// from a second socket.
int ZmqOversized(const Target& t) {
  const SmallSequence seq = RenderSmall(2);
  zmq::context_t context(1);
  auto d = std::make_unique<Dealer>(context, t.zmq_endpoint);
  std::string id = d->Open(seq.rig, 8);
  if (id.empty()) return 1;
  const std::string over((16 << 20) + (32 << 10), 'x');
  const std::string big(17 << 20, 'x');
  const std::string huge(70 << 20, 'y');
  Ready();
  Deadline deadline(t.seconds);
  uint64_t n = 0, huge_sent = 0;
  auto last_huge = Clock::now();
  while (!deadline.passed()) {
    d->Send(FrameEnvelope(id, n), n % 5 < 2 ? &over : &big);
    ++n;
    if (Clock::now() - last_huge > std::chrono::seconds(2)) {
      Dealer h(context, t.zmq_endpoint);
      (void)h.socket().send(zmq::buffer(huge), zmq::send_flags::dontwait);
      SleepMs(100);
      last_huge = Clock::now();
      ++huge_sent;
    }
    d->Drain(200);
  }
  std::cerr << "zmq-oversized: " << n << " big frames, " << huge_sent << " huge messages\n";
  return 0;
}

// Frames of random bytes, 100 a second, in a real session.
int ZmqCorrupt(const Target& t) {
  const SmallSequence seq = RenderSmall(2);
  zmq::context_t context(1);
  Dealer d(context, t.zmq_endpoint);
  const std::string id = d.Open(seq.rig, 8);
  if (id.empty()) return 1;
  std::mt19937 rng(3);
  std::string noise(1 << 16, '\0');
  for (char& c : noise) c = static_cast<char>(rng());
  Ready();
  const auto start = Clock::now();
  Deadline deadline(t.seconds);
  uint64_t n = 0;
  while (!deadline.passed()) {
    std::string junk = noise.substr(rng() % 32768, 2000 + rng() % 20000);
    if (n % 2 == 0) junk.replace(0, 8, "\x89PNG\r\n\x1a\n");  // half of them look like PNG
    d.Send(FrameEnvelope(id, n++), &junk);
    d.Drain();
    std::this_thread::sleep_until(start + std::chrono::milliseconds(10 * n));
  }
  std::cerr << "zmq-corrupt: " << n << " frames\n";
  return 0;
}

// Half of a two-part message (the first part, "more" set) from 50 peers, never the rest.
int ZmqHalfMultipart(const Target& t) {
  const SmallSequence seq = RenderSmall(2);
  zmq::context_t context(1);
  std::vector<std::unique_ptr<Dealer>> peers;
  for (int i = 0; i < 50; ++i) {
    peers.push_back(std::make_unique<Dealer>(context, t.zmq_endpoint));
    const std::string header = FrameEnvelope("s1-000000000000", 0).SerializeAsString();
    (void)peers.back()->socket().send(zmq::buffer(header), zmq::send_flags::sndmore);
  }
  Ready();
  Deadline deadline(t.seconds);
  while (!deadline.passed()) SleepMs(100);
  std::cerr << "zmq-half-multipart: 50 peers\n";
  return 0;
}

// Messages with protocol versions the server does not speak, 500 a second.
int ZmqWrongVersion(const Target& t) {
  const SmallSequence seq = RenderSmall(2);
  zmq::context_t context(1);
  Dealer d(context, t.zmq_endpoint);
  Ready();
  Deadline deadline(t.seconds);
  uint64_t n = 0;
  while (!deadline.passed()) {
    v1::Envelope env = OpenEnvelope(seq.rig, 8);
    if (n % 2 == 0) env.set_protocol_version(static_cast<v1::ProtocolVersion>(7));               // the envelope's
    else env.mutable_open_session()->set_protocol_version(static_cast<v1::ProtocolVersion>(9));  // the open's
    d.Send(env);
    ++n;
    d.Drain();
    SleepMs(2);
  }
  std::cerr << "zmq-wrong-version: " << n << " messages\n";
  return 0;
}

// Frames, closes and credits naming sessions that do not exist, 500 a second.
int ZmqUnknownSession(const Target& t) {
  zmq::context_t context(1);
  Dealer d(context, t.zmq_endpoint);
  const std::string payload(1000, 'p');
  Ready();
  Deadline deadline(t.seconds);
  uint64_t n = 0;
  while (!deadline.passed()) {
    const std::string id = "s" + std::to_string(900000 + n % 7) + "-deadbeef0000";
    if (n % 3 == 0) {
      d.Send(FrameEnvelope(id, n), &payload);
    } else if (n % 3 == 1) {
      v1::Envelope env;
      env.set_protocol_version(v1::PROTOCOL_VERSION_1);
      env.mutable_close()->set_session_id(id);
      d.Send(env);
    } else {
      v1::Envelope env;
      env.set_protocol_version(v1::PROTOCOL_VERSION_1);
      env.mutable_chunk_credits()->set_session_id(id);
      env.mutable_chunk_credits()->set_chunks(100);
      d.Send(env);
    }
    ++n;
    d.Drain();
    SleepMs(2);
  }
  std::cerr << "zmq-unknown-session: " << n << " messages\n";
  return 0;
}

// CURVE handshakes with client keys the server does not admit, 100 a second (five keys).
int CurveUnknownKeys(const Target& t) {
  std::vector<std::pair<std::string, std::string>> keys;
  for (int i = 0; i < 5; ++i) {
    char pub[41], sec[41];
    if (zmq_curve_keypair(pub, sec) != 0) return 1;
    keys.emplace_back(pub, sec);
  }
  zmq::context_t context(1);
  std::deque<std::pair<Clock::time_point, std::unique_ptr<zmq::socket_t>>> live;
  Ready();
  Deadline deadline(t.seconds);
  const auto start = Clock::now();
  uint64_t n = 0;
  while (!deadline.passed()) {
    auto s = std::make_unique<zmq::socket_t>(context, zmq::socket_type::dealer);
    s->set(zmq::sockopt::linger, 0);
    s->set(zmq::sockopt::curve_serverkey, t.server_public_key);
    s->set(zmq::sockopt::curve_publickey, keys[n % keys.size()].first);
    s->set(zmq::sockopt::curve_secretkey, keys[n % keys.size()].second);
    s->connect(t.zmq_endpoint);
    live.emplace_back(Clock::now(), std::move(s));
    ++n;
    while (!live.empty() && Clock::now() - live.front().first > std::chrono::milliseconds(300)) live.pop_front();
    std::this_thread::sleep_until(start + std::chrono::milliseconds(10 * n));
  }
  std::cerr << "curve-unknown-keys: " << n << " handshakes\n";
  return 0;
}

}  // namespace

const std::vector<AbuserInfo>& Abusers() {
  static const std::vector<AbuserInfo> kAbusers = {
      {"second-session", "reference, not abuse: a second well-behaved session (160x120, 30 frames/s)",
       "prism_frames_received_total", false, true},
      {"http-slowloris", "200 HTTP connections sending a byte every 150 ms",
       "prism_http_connections_without_request_total"},
      {"http-idle", "500 idle HTTP connections", "prism_http_connections_without_request_total"},
      {"http-garbage", "HTTP requests of random bytes", "prism_http_connections_without_request_total"},
      {"http-huge-header", "HTTP requests with a 10 MB header", "prism_http_connections_without_request_total"},
      {"zmq-silent", "200 TCP peers of the ZeroMQ port that send nothing",
       "prism_zmq_handshake_failures_total{reason=\"no_detail\"}"},
      {"zmq-half-multipart", "50 peers sending half of a multipart message", "prism_zmq_connections_accepted_total"},
      {"zmq-churn", "1000 connects and disconnects a second for 10 s", "prism_zmq_connections_accepted_total"},
      {"zmq-no-credits", "a session that never grants chunk credits", "prism_chunk_credit_stalls_total"},
      {"zmq-frame-flood", "a session sending frames at 300 a second (10x)",
       "prism_frames_dropped_total{reason=\"rate\"}"},
      {"zmq-oversized", "frames over max-frame-bytes and messages over max-message-bytes",
       "prism_frames_refused_total"},
      {"zmq-corrupt", "frames of random bytes", "prism_frames_bad_total"},
      {"zmq-wrong-version", "messages of protocol versions 7 and 9", "prism_malformed_messages_total"},
      {"zmq-unknown-session", "frames, closes and credits for sessions that do not exist",
       "prism_unknown_session_total"},
      {"curve-unknown-keys", "100 CURVE handshakes a second with keys not on the allow-list",
       "prism_auth_refused_total", true},
  };
  return kAbusers;
}

int RunAbuser(const std::string& name, const Target& t) {
  signal(SIGTERM, OnTerm);
  signal(SIGPIPE, SIG_IGN);
  if (name == "http-slowloris") return HttpSlowloris(t);
  if (name == "http-idle") return HttpIdle(t);
  if (name == "http-garbage") return HttpGarbage(t);
  if (name == "http-huge-header") return HttpHugeHeader(t);
  if (name == "zmq-silent") return ZmqSilent(t);
  if (name == "zmq-half-multipart") return ZmqHalfMultipart(t);
  if (name == "zmq-churn") return ZmqChurn(t);
  if (name == "second-session") return StreamSession(t, 30, /*grant_chunks=*/true, "second-session");
  if (name == "zmq-no-credits") return StreamSession(t, 30, /*grant_chunks=*/false, "zmq-no-credits");
  if (name == "zmq-frame-flood") return StreamSession(t, 300, /*grant_chunks=*/true, "zmq-frame-flood");
  if (name == "zmq-oversized") return ZmqOversized(t);
  if (name == "zmq-corrupt") return ZmqCorrupt(t);
  if (name == "zmq-wrong-version") return ZmqWrongVersion(t);
  if (name == "zmq-unknown-session") return ZmqUnknownSession(t);
  if (name == "curve-unknown-keys") return CurveUnknownKeys(t);
  std::cerr << "unknown abuser '" << name << "'\n";
  return 2;
}

}  // namespace prism::abuse
