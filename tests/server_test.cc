// prism-server as a real process on 127.0.0.1, driven by scripted DEALER clients speaking the wire
// protocol directly (so malformed input can be sent) and by libprism_client: every bad input gets a
// readable Error, and the server and the other sessions go on.
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>
#include <zmq.hpp>

#include "core/codec/frame_codec.h"
#include "core/synth/presets.h"
#include "prism/v1/session.pb.h"
#include "server/rig_wire.h"
#include "tests/server_process.h"

namespace prism {
namespace {
namespace fs = std::filesystem;
using test::HttpGet;
using test::ServerProcess;

constexpr int kWidth = 160, kHeight = 120;

// One scripted client: a DEALER speaking [Envelope][payload].
class RawClient {
 public:
  explicit RawClient(const std::string& endpoint) : socket_(context_, zmq::socket_type::dealer) {
    socket_.set(zmq::sockopt::linger, 0);
    socket_.connect(endpoint);
  }
  void SendParts(const std::vector<std::string>& parts) {
    for (size_t i = 0; i < parts.size(); ++i)
      socket_.send(zmq::buffer(parts[i]), i + 1 < parts.size() ? zmq::send_flags::sndmore : zmq::send_flags::none);
  }
  void Send(const v1::Envelope& env, const std::string* payload = nullptr) {
    std::vector<std::string> parts = {env.SerializeAsString()};
    if (payload) parts.push_back(*payload);
    SendParts(parts);
  }
  // The next envelope whose body is `body` (others skipped), within timeout.
  std::optional<v1::Envelope> Await(v1::Envelope::BodyCase body, int timeout_ms = 10000) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
    while (std::chrono::steady_clock::now() < deadline) {
      zmq::pollitem_t item{socket_.handle(), 0, ZMQ_POLLIN, 0};
      zmq::poll(&item, 1, std::chrono::milliseconds(50));
      zmq::message_t part;
      while (socket_.recv(part, zmq::recv_flags::dontwait)) {
        v1::Envelope env;
        const bool parsed = env.ParseFromArray(part.data(), static_cast<int>(part.size()));
        while (part.more()) (void)socket_.recv(part, zmq::recv_flags::none);
        if (parsed && env.body_case() == body) return env;
      }
    }
    return std::nullopt;
  }
  std::optional<std::string> Open(v1::Envelope* reply = nullptr) {
    Send(OpenEnvelope());
    for (;;) {
      std::optional<v1::Envelope> r = AwaitAny({v1::Envelope::kSessionOpened, v1::Envelope::kError});
      if (!r) return std::nullopt;
      if (reply) *reply = *r;
      if (r->has_session_opened()) return r->session_opened().session_id();
      return std::nullopt;
    }
  }
  std::optional<v1::Envelope> AwaitAny(const std::vector<v1::Envelope::BodyCase>& bodies, int timeout_ms = 10000) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
    while (std::chrono::steady_clock::now() < deadline) {
      zmq::pollitem_t item{socket_.handle(), 0, ZMQ_POLLIN, 0};
      zmq::poll(&item, 1, std::chrono::milliseconds(50));
      zmq::message_t part;
      while (socket_.recv(part, zmq::recv_flags::dontwait)) {
        v1::Envelope env;
        const bool parsed = env.ParseFromArray(part.data(), static_cast<int>(part.size()));
        while (part.more()) (void)socket_.recv(part, zmq::recv_flags::none);
        if (!parsed) continue;
        for (auto b : bodies)
          if (env.body_case() == b) return env;
      }
    }
    return std::nullopt;
  }
  static v1::Envelope OpenEnvelope() {
    const RigCalibration rig = synth::MakeDefaultRig(kWidth, kHeight);
    v1::Envelope env;
    env.set_protocol_version(v1::PROTOCOL_VERSION_1);
    v1::OpenSession* o = env.mutable_open_session();
    o->set_protocol_version(v1::PROTOCOL_VERSION_1);
    o->set_codec(v1::FRAME_CODEC_PNG);
    o->set_client_name("server_test");
    RigToWire(rig, o->mutable_calibration());
    return env;
  }
  static v1::Envelope FrameEnvelope(const std::string& session, uint64_t seq, v1::FrameCodec codec) {
    v1::Envelope env;
    env.set_protocol_version(v1::PROTOCOL_VERSION_1);
    v1::Frame* f = env.mutable_frame();
    f->set_session_id(session);
    f->set_sequence_number(seq);
    f->set_timestamp_ns(static_cast<int64_t>(seq) * 33'333'333);
    f->set_codec(codec);
    return env;
  }

 private:
  zmq::context_t context_{1};
  zmq::socket_t socket_;
};

std::string Png(int width, int height) {
  cv::Mat rgb(height, width, CV_8UC3);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x) rgb.at<cv::Vec3b>(y, x) = cv::Vec3b(x % 256, y % 256, (x * y) % 256);
  std::vector<uint8_t> bytes;
  FrameEncodeOptions o;
  EXPECT_TRUE(EncodeFrame(rgb, o, &bytes).ok());
  return std::string(bytes.begin(), bytes.end());
}

class ServerTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("prism_server_test_" + std::to_string(getpid()) + "_" +
                                        ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override {
    if (!HasFailure()) fs::remove_all(dir_);
  }
  std::unique_ptr<ServerProcess> Start(const std::vector<std::string>& args = {}) {
    auto s = std::make_unique<ServerProcess>((dir_ / "data").string(), args, (dir_ / "server.log").string());
    EXPECT_TRUE(s->ok()) << "prism-server did not start; log in " << dir_;
    return s;
  }
  fs::path dir_;
};

// SLAM options given as slam.KEY (core/slam/slam_config.h, the keys prism-slam reads) reach the
// server, which logs every one that differs from the defaults once it listens.
TEST_F(ServerTest, SlamOptionsOnTheCommandLineAreTakenAndLogged) {
  {
    std::ofstream cfg(dir_ / "slam.cfg");
    cfg << "tracker.min_gradient = 5\n";
  }
  auto server = Start({"--slam.keyframe_distance_fraction", "0.18", "--slam.loop-closure", "false", "--slam-config",
                       (dir_ / "slam.cfg").string()});
  ASSERT_TRUE(server->ok());
  std::ifstream log(dir_ / "server.log");
  std::ostringstream text;
  text << log.rdbuf();
  for (const char* line :
       {"\nkeyframe_distance_fraction = 0.18", "\nloop_closure = false", "\ntracker.min_gradient = 5"})
    EXPECT_NE(text.str().find(line), std::string::npos) << line << " in\n" << text.str();
  EXPECT_EQ(text.str().find("\nkeyframe_window = "), std::string::npos) << "only the options that differ are logged";
}

TEST_F(ServerTest, BadVersionAndMalformedMessagesGetErrorsAndTheServerGoesOn) {
  auto server = Start();
  ASSERT_TRUE(server->ok());
  RawClient c(server->endpoint());
  v1::Envelope env = RawClient::OpenEnvelope();
  env.set_protocol_version(static_cast<v1::ProtocolVersion>(7));
  c.Send(env);
  std::optional<v1::Envelope> e = c.Await(v1::Envelope::kError);
  ASSERT_TRUE(e.has_value());
  EXPECT_EQ(e->error().code(), v1::ERROR_CODE_VERSION_MISMATCH);
  EXPECT_NE(e->error().message().find("version 7"), std::string::npos) << e->error().message();

  c.SendParts({std::string("\x08\xff\xff\xff\xff\xff\xff\xff\xff\xff\xff\xff", 12)});
  e = c.Await(v1::Envelope::kError);
  ASSERT_TRUE(e.has_value());
  EXPECT_EQ(e->error().code(), v1::ERROR_CODE_INVALID_ARGUMENT);
  EXPECT_NE(e->error().message().find("malformed envelope"), std::string::npos) << e->error().message();

  c.SendParts({RawClient::OpenEnvelope().SerializeAsString(), "x", "y", "z"});
  e = c.Await(v1::Envelope::kError);
  ASSERT_TRUE(e.has_value());
  EXPECT_NE(e->error().message().find("4 parts"), std::string::npos) << e->error().message();

  v1::Envelope empty;
  empty.set_protocol_version(v1::PROTOCOL_VERSION_1);
  c.Send(empty);
  e = c.Await(v1::Envelope::kError);
  ASSERT_TRUE(e.has_value());
  EXPECT_NE(e->error().message().find("no body"), std::string::npos) << e->error().message();

  // The server is still there for this client and a new one.
  EXPECT_TRUE(c.Open().has_value());
  RawClient other(server->endpoint());
  EXPECT_TRUE(other.Open().has_value());
  EXPECT_EQ(server->Stop(), 0);
}

TEST_F(ServerTest, WrongSizeCorruptImagesAndUnknownSessionsAreErrorsAndTheSessionGoesOn) {
  auto server = Start();
  ASSERT_TRUE(server->ok());
  RawClient c(server->endpoint());
  std::optional<std::string> id = c.Open();
  ASSERT_TRUE(id.has_value());

  // Wrong size: a 100x100 PNG for a 160x120 camera.
  const std::string small = Png(100, 100);
  c.Send(RawClient::FrameEnvelope(*id, 0, v1::FRAME_CODEC_PNG), &small);
  std::optional<v1::Envelope> e = c.Await(v1::Envelope::kError);
  ASSERT_TRUE(e.has_value());
  EXPECT_EQ(e->error().code(), v1::ERROR_CODE_INVALID_ARGUMENT);
  EXPECT_TRUE(e->error().has_frame());
  EXPECT_EQ(e->error().frame_sequence_number(), 0u);
  EXPECT_NE(e->error().message().find("100x100"), std::string::npos) << e->error().message();
  EXPECT_FALSE(e->error().session_closed());

  // Corrupt PNG: a valid header, garbage after it.
  std::string corrupt = Png(kWidth, kHeight);
  for (size_t i = 40; i < corrupt.size(); ++i) corrupt[i] = static_cast<char>(i * 131);
  c.Send(RawClient::FrameEnvelope(*id, 1, v1::FRAME_CODEC_PNG), &corrupt);
  e = c.Await(v1::Envelope::kError);
  ASSERT_TRUE(e.has_value());
  EXPECT_NE(e->error().message().find("corrupt"), std::string::npos) << e->error().message();

  // Corrupt JPEG, and a raw frame of the wrong length.
  const std::string not_jpeg(5000, '\x42');
  c.Send(RawClient::FrameEnvelope(*id, 2, v1::FRAME_CODEC_JPEG), &not_jpeg);
  e = c.Await(v1::Envelope::kError);
  ASSERT_TRUE(e.has_value());
  EXPECT_NE(e->error().message().find("JPEG"), std::string::npos) << e->error().message();
  const std::string short_raw(kWidth * kHeight * 3 - 1, '\0');
  c.Send(RawClient::FrameEnvelope(*id, 3, v1::FRAME_CODEC_RAW), &short_raw);
  e = c.Await(v1::Envelope::kError);
  ASSERT_TRUE(e.has_value());
  EXPECT_NE(e->error().message().find("raw frame has"), std::string::npos) << e->error().message();

  // A frame without payload, and one for a session that does not exist.
  c.Send(RawClient::FrameEnvelope(*id, 4, v1::FRAME_CODEC_PNG));
  e = c.Await(v1::Envelope::kError);
  ASSERT_TRUE(e.has_value());
  EXPECT_NE(e->error().message().find("payload"), std::string::npos) << e->error().message();
  const std::string good = Png(kWidth, kHeight);
  c.Send(RawClient::FrameEnvelope("no-such-session", 5, v1::FRAME_CODEC_PNG), &good);
  e = c.Await(v1::Envelope::kError);
  ASSERT_TRUE(e.has_value());
  EXPECT_EQ(e->error().code(), v1::ERROR_CODE_NOT_FOUND);
  EXPECT_NE(e->error().message().find("unknown session 'no-such-session'"), std::string::npos);

  // The session goes on: a good frame is tracked and its pose comes back.
  c.Send(RawClient::FrameEnvelope(*id, 6, v1::FRAME_CODEC_PNG), &good);
  std::optional<v1::Envelope> pose = c.Await(v1::Envelope::kPoseUpdate, 30000);
  ASSERT_TRUE(pose.has_value());
  EXPECT_EQ(pose->pose_update().frame_sequence_number(), 6u);

  // Close: summary; frames after close are refused.
  v1::Envelope close;
  close.set_protocol_version(v1::PROTOCOL_VERSION_1);
  close.mutable_close()->set_session_id(*id);
  c.Send(close);
  std::optional<v1::Envelope> summary = c.Await(v1::Envelope::kSessionSummary, 30000);
  ASSERT_TRUE(summary.has_value());
  EXPECT_EQ(summary->session_summary().reason(), "closed by client");
  EXPECT_GE(summary->session_summary().frames_rejected(), 5u);
  c.Send(RawClient::FrameEnvelope(*id, 7, v1::FRAME_CODEC_PNG), &good);
  e = c.Await(v1::Envelope::kError);
  ASSERT_TRUE(e.has_value());
  EXPECT_EQ(e->error().code(), v1::ERROR_CODE_NOT_FOUND);
  EXPECT_TRUE(fs::exists(dir_ / "data" / "sessions" / *id / "summary.txt"));
  EXPECT_EQ(server->Stop(), 0);
}

// What the contract (session.proto, Frame) calls invalid is refused with INVALID_ARGUMENT naming the
// field, and costs only that frame: a stated size other than the camera's, a duplicate or backwards
// sequence number, a backwards timestamp. A jump forward in sequence numbers is accepted (a live client
// drops frames). ChunkCredits for an unknown session gets NOT_FOUND, as Frame and Close do.
TEST_F(ServerTest, FramesTheContractCallsInvalidAreRefusedNamingTheField) {
  auto server = Start();
  ASSERT_TRUE(server->ok());
  RawClient c(server->endpoint());
  std::optional<std::string> id = c.Open();
  ASSERT_TRUE(id.has_value());
  const std::string good = Png(kWidth, kHeight);
  auto frame = [&](uint64_t seq, int64_t timestamp_ns, uint32_t width, uint32_t height) {
    v1::Envelope env = RawClient::FrameEnvelope(*id, seq, v1::FRAME_CODEC_PNG);
    env.mutable_frame()->set_timestamp_ns(timestamp_ns);
    env.mutable_frame()->set_width(width);
    env.mutable_frame()->set_height(height);
    return env;
  };
  c.Send(frame(10, 1'000'000, kWidth, kHeight), &good);
  std::optional<v1::Envelope> pose = c.Await(v1::Envelope::kPoseUpdate, 30000);
  ASSERT_TRUE(pose.has_value());
  EXPECT_EQ(pose->pose_update().frame_sequence_number(), 10u);
  const struct {
    v1::Envelope envelope;
    const char* field;
  } invalid[] = {
      {frame(11, 2'000'000, 100, kHeight), "Frame.width"},   {frame(12, 2'000'000, kWidth, 100), "Frame.height"},
      {frame(10, 2'000'000, 0, 0), "Frame.sequence_number"},  // a duplicate
      {frame(9, 2'000'000, 0, 0), "Frame.sequence_number"},   // backwards
      {frame(13, 999'999, 0, 0), "Frame.timestamp_ns"},       // backwards
  };
  for (const auto& [envelope, field] : invalid) {
    SCOPED_TRACE(field);
    c.Send(envelope, &good);
    std::optional<v1::Envelope> e = c.Await(v1::Envelope::kError);
    ASSERT_TRUE(e.has_value());
    EXPECT_EQ(e->error().code(), v1::ERROR_CODE_INVALID_ARGUMENT);
    EXPECT_NE(e->error().message().find(field), std::string::npos) << e->error().message();
    EXPECT_TRUE(e->error().has_frame());
    EXPECT_EQ(e->error().frame_sequence_number(), envelope.frame().sequence_number());
    EXPECT_FALSE(e->error().session_closed());
    EXPECT_FALSE(e->error().retryable());
  }
  // A refused frame's number is free: 11 goes again, then a jump forward and an equal timestamp.
  for (const uint64_t seq : {11u, 20u}) {
    c.Send(frame(seq, 2'000'000, 0, 0), &good);
    pose = c.Await(v1::Envelope::kPoseUpdate, 30000);
    ASSERT_TRUE(pose.has_value());
    EXPECT_EQ(pose->pose_update().frame_sequence_number(), seq);
  }
  v1::Envelope credits;
  credits.set_protocol_version(v1::PROTOCOL_VERSION_1);
  credits.mutable_chunk_credits()->set_session_id("s999-000000000000");
  credits.mutable_chunk_credits()->set_chunks(4);
  c.Send(credits);
  std::optional<v1::Envelope> e = c.Await(v1::Envelope::kError);
  ASSERT_TRUE(e.has_value());
  EXPECT_EQ(e->error().code(), v1::ERROR_CODE_NOT_FOUND);
  EXPECT_EQ(e->error().session_id(), "s999-000000000000");
  EXPECT_TRUE(e->error().session_closed());
  v1::Envelope close;
  close.set_protocol_version(v1::PROTOCOL_VERSION_1);
  close.mutable_close()->set_session_id(*id);
  c.Send(close);
  std::optional<v1::Envelope> summary = c.Await(v1::Envelope::kSessionSummary, 30000);
  ASSERT_TRUE(summary.has_value());
  EXPECT_EQ(summary->session_summary().frames_received(), 3u);
  EXPECT_EQ(summary->session_summary().frames_rejected(), 5u);
  EXPECT_EQ(server->Stop(), 0);
}

TEST_F(ServerTest, AdmissionLimitRefusesWithResourceExhaustedUntilASessionCloses) {
  auto server = Start({"--max-sessions", "1"});
  ASSERT_TRUE(server->ok());
  RawClient a(server->endpoint()), b(server->endpoint());
  std::optional<std::string> id = a.Open();
  ASSERT_TRUE(id.has_value());
  v1::Envelope reply;
  EXPECT_FALSE(b.Open(&reply).has_value());
  ASSERT_TRUE(reply.has_error());
  EXPECT_EQ(reply.error().code(), v1::ERROR_CODE_RESOURCE_EXHAUSTED);
  EXPECT_TRUE(reply.error().retryable());
  EXPECT_NE(reply.error().message().find("1 of 1 sessions"), std::string::npos) << reply.error().message();
  v1::Envelope close;
  close.set_protocol_version(v1::PROTOCOL_VERSION_1);
  close.mutable_close()->set_session_id(*id);
  a.Send(close);
  ASSERT_TRUE(a.Await(v1::Envelope::kSessionSummary, 30000).has_value());
  EXPECT_TRUE(b.Open().has_value());
  const std::string metrics = test::MetricsHolding(
      server->metrics(), {"prism_sessions_rejected_total{reason=\"capacity\"} 1", "prism_sessions_opened_total 2"});
  EXPECT_NE(metrics.find("prism_sessions_rejected_total{reason=\"capacity\"} 1"), std::string::npos) << metrics;
  EXPECT_NE(metrics.find("prism_sessions_opened_total 2"), std::string::npos) << metrics;
  EXPECT_NE(HttpGet(server->metrics() + "/healthz").find("200 OK"), std::string::npos);
  EXPECT_EQ(server->Stop(), 0);
}

TEST_F(ServerTest, OversizedFramesAndMessagesAreRefusedAndTheServerGoesOn) {
  auto server = Start({"--max-frame-bytes", "4096", "--max-message-bytes", "70000"});
  ASSERT_TRUE(server->ok());
  RawClient c(server->endpoint());
  std::optional<std::string> id = c.Open();
  ASSERT_TRUE(id.has_value());
  const std::string big(10000, 'x');
  c.Send(RawClient::FrameEnvelope(*id, 0, v1::FRAME_CODEC_RAW), &big);
  std::optional<v1::Envelope> e = c.Await(v1::Envelope::kError);
  ASSERT_TRUE(e.has_value());
  EXPECT_NE(e->error().message().find("exceeds 4096"), std::string::npos) << e->error().message();
  // Beyond ZMQ_MAXMSGSIZE ZeroMQ drops the connection; the server itself goes on.
  RawClient rogue(server->endpoint());
  ASSERT_TRUE(rogue.Open().has_value());
  const std::string huge(200000, 'y');
  rogue.Send(RawClient::FrameEnvelope("x", 0, v1::FRAME_CODEC_RAW), &huge);
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  RawClient after(server->endpoint());
  EXPECT_TRUE(after.Open().has_value());
  EXPECT_EQ(server->Stop(), 0);
}

TEST_F(ServerTest, IdleSessionsAreReapedAndSigtermPersistsOpenSessions) {
  auto server = Start({"--idle-timeout-ms", "400"});
  ASSERT_TRUE(server->ok());
  RawClient idle(server->endpoint());
  std::optional<std::string> idle_id = idle.Open();
  ASSERT_TRUE(idle_id.has_value());
  std::optional<v1::Envelope> e = idle.Await(v1::Envelope::kError, 5000);
  ASSERT_TRUE(e.has_value());
  EXPECT_TRUE(e->error().session_closed());
  EXPECT_NE(e->error().message().find("without a message"), std::string::npos) << e->error().message();
  std::optional<v1::Envelope> summary = idle.Await(v1::Envelope::kSessionSummary, 5000);
  ASSERT_TRUE(summary.has_value());
  EXPECT_EQ(summary->session_summary().reason(), "idle timeout");
  EXPECT_NE(
      test::MetricsHolding(server->metrics(), {"prism_sessions_reaped_total 1"}).find("prism_sessions_reaped_total 1"),
      std::string::npos);

  RawClient open(server->endpoint());
  std::optional<std::string> id = open.Open();
  ASSERT_TRUE(id.has_value());
  EXPECT_EQ(server->Stop(), 0);  // SIGTERM while the session is open
  std::optional<v1::Envelope> last = open.Await(v1::Envelope::kSessionSummary, 2000);
  ASSERT_TRUE(last.has_value());
  EXPECT_EQ(last->session_summary().reason(), "server shutdown");
  EXPECT_TRUE(fs::exists(dir_ / "data" / "sessions" / *id / "summary.txt"));
}

// Resume: a second connection re-attaches with the id and token (a wrong token, an unknown or malformed
// id are refused with readable errors); after the session ended, and after the server was SIGKILLed
// and restarted on the same data dir, a resume replays the persisted session read-only with its
// summary ("interrupted" for the one that was running at the kill).
TEST_F(ServerTest, ResumeReattachesAndReplaysPersistedSessionsAfterAKill) {
  auto server = Start();
  ASSERT_TRUE(server->ok());
  RawClient first(server->endpoint());
  v1::Envelope opened;
  std::optional<std::string> id = first.Open(&opened);
  ASSERT_TRUE(id.has_value());
  const std::string token = opened.session_opened().resume_token();
  ASSERT_GE(token.size(), 16u);
  EXPECT_TRUE(fs::exists(dir_ / "data" / "sessions" / *id / "session.txt"));
  auto resume = [](const std::string& session, const std::string& tok) {
    v1::Envelope env = RawClient::OpenEnvelope();
    env.mutable_open_session()->clear_calibration();
    env.mutable_open_session()->set_resume_session_id(session);
    env.mutable_open_session()->set_resume_token(tok);
    return env;
  };
  {
    RawClient thief(server->endpoint());
    thief.Send(resume(*id, token + "x"));
    std::optional<v1::Envelope> e = thief.Await(v1::Envelope::kError, 5000);
    ASSERT_TRUE(e.has_value());
    EXPECT_EQ(e->error().code(), v1::ERROR_CODE_UNAUTHENTICATED) << e->error().message();
    thief.Send(resume("s999-000000000000", token));
    e = thief.Await(v1::Envelope::kError, 5000);
    ASSERT_TRUE(e.has_value());
    EXPECT_EQ(e->error().code(), v1::ERROR_CODE_NOT_FOUND) << e->error().message();
    thief.Send(resume("../../etc", token));
    e = thief.Await(v1::Envelope::kError, 5000);
    ASSERT_TRUE(e.has_value());
    EXPECT_EQ(e->error().code(), v1::ERROR_CODE_INVALID_ARGUMENT) << e->error().message();
  }
  RawClient second(server->endpoint());
  second.Send(resume(*id, token));
  std::optional<v1::Envelope> r = second.AwaitAny({v1::Envelope::kSessionOpened, v1::Envelope::kError});
  ASSERT_TRUE(r.has_value());
  ASSERT_TRUE(r->has_session_opened()) << r->DebugString();
  EXPECT_TRUE(r->session_opened().resumed());
  EXPECT_FALSE(r->session_opened().read_only());
  EXPECT_EQ(r->session_opened().session_id(), *id);
  // The policy and the rate limit in force, as the first SessionOpened said.
  EXPECT_EQ(r->session_opened().input_policy(), opened.session_opened().input_policy());
  EXPECT_EQ(r->session_opened().max_frame_rate_hz(), opened.session_opened().max_frame_rate_hz());
  EXPECT_GT(r->session_opened().max_frame_rate_hz(), 0);
  // The old connection no longer owns the session.
  const std::string png = Png(kWidth, kHeight);
  first.Send(RawClient::FrameEnvelope(*id, 0, v1::FRAME_CODEC_PNG), &png);
  std::optional<v1::Envelope> e = first.Await(v1::Envelope::kError, 5000);
  ASSERT_TRUE(e.has_value());
  EXPECT_EQ(e->error().code(), v1::ERROR_CODE_NOT_FOUND);
  // Frames on the new connection are tracked (a pose comes back).
  second.Send(RawClient::FrameEnvelope(*id, 0, v1::FRAME_CODEC_PNG), &png);
  ASSERT_TRUE(second.Await(v1::Envelope::kPoseUpdate, 10000).has_value());
  v1::Envelope close;
  close.set_protocol_version(v1::PROTOCOL_VERSION_1);
  close.mutable_close()->set_session_id(*id);
  second.Send(close);
  std::optional<v1::Envelope> summary = second.Await(v1::Envelope::kSessionSummary, 10000);
  ASSERT_TRUE(summary.has_value());
  EXPECT_EQ(summary->session_summary().reason(), "closed by client");

  // A second session is left running when the server is killed.
  RawClient running(server->endpoint());
  v1::Envelope running_opened;
  std::optional<std::string> running_id = running.Open(&running_opened);
  ASSERT_TRUE(running_id.has_value());
  running.Send(RawClient::FrameEnvelope(*running_id, 0, v1::FRAME_CODEC_PNG), &png);
  ASSERT_TRUE(running.Await(v1::Envelope::kPoseUpdate, 10000).has_value());
  const std::string endpoint = server->endpoint();
  server->Kill();
  server = Start({"--bind", endpoint});
  ASSERT_TRUE(server->ok());
  for (const auto& [session, tok, reason] :
       {std::make_tuple(*id, token, std::string("closed by client")),
        std::make_tuple(*running_id, running_opened.session_opened().resume_token(), std::string("interrupted"))}) {
    RawClient later(server->endpoint());
    later.Send(resume(session, tok));
    r = later.AwaitAny({v1::Envelope::kSessionOpened, v1::Envelope::kError});
    ASSERT_TRUE(r.has_value());
    ASSERT_TRUE(r->has_session_opened()) << r->DebugString();
    EXPECT_TRUE(r->session_opened().read_only());
    std::optional<v1::Envelope> pose = later.Await(v1::Envelope::kPoseUpdate, 5000);  // the persisted pose
    ASSERT_TRUE(pose.has_value());
    EXPECT_EQ(pose->pose_update().frame_sequence_number(), 0u);
    summary = later.Await(v1::Envelope::kSessionSummary, 5000);
    ASSERT_TRUE(summary.has_value());
    EXPECT_EQ(summary->session_summary().reason().rfind(reason, 0), 0u) << summary->session_summary().reason();
    // A read-only session takes no frames.
    later.Send(RawClient::FrameEnvelope(session, 1, v1::FRAME_CODEC_PNG), &png);
    e = later.Await(v1::Envelope::kError, 5000);
    ASSERT_TRUE(e.has_value());
  }
  EXPECT_TRUE(fs::exists(dir_ / "data" / "sessions" / *running_id / "summary.pb"));
  EXPECT_EQ(server->Stop(), 0);
}

}  // namespace
}  // namespace prism
