// Writes the fuzz targets' seed corpora from the real encoders and the wire contract (no binaries from
// elsewhere): make_seed_corpus OUT_DIR -> OUT_DIR/{envelope,frame_decoder,draco_chunk,slam_config}/seed_NNN.
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "core/codec/frame_codec.h"
#include "core/codec/map_chunk_codec.h"
#include "core/slam/slam_config.h"
#include "core/synth/presets.h"
#include "fuzz/fuzz_input.h"
#include "prism/v1/session.pb.h"
#include "server/rig_wire.h"

namespace {

namespace fs = std::filesystem;
using namespace prism;

void Write(const fs::path& dir, int* n, const std::string& bytes) {
  char name[32];
  std::snprintf(name, sizeof(name), "seed_%03d", (*n)++);
  std::ofstream(dir / name, std::ios::binary) << bytes;
}

v1::Envelope Envelope() {
  v1::Envelope env;
  env.set_protocol_version(v1::PROTOCOL_VERSION_1);
  return env;
}

v1::Envelope Open(int width, int height) {
  const RigCalibration rig = synth::MakeDefaultRig(width, height);
  v1::Envelope env = Envelope();
  v1::OpenSession* o = env.mutable_open_session();
  o->set_protocol_version(v1::PROTOCOL_VERSION_1);
  o->set_codec(v1::FRAME_CODEC_RAW);
  o->set_input_policy(v1::INPUT_POLICY_UPLOAD);
  RigToWire(rig, o->mutable_calibration());
  return env;
}

cv::Mat Image(int width, int height) {
  cv::Mat rgb(height, width, CV_8UC3);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x) rgb.at<cv::Vec3b>(y, x) = cv::Vec3b(x * 7 % 256, y * 5 % 256, (x * y) % 256);
  return rgb;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: make_seed_corpus OUT_DIR\n");
    return 2;
  }
  const fs::path out = argv[1];
  for (const char* d : {"envelope", "frame_decoder", "draco_chunk", "slam_config"}) fs::create_directories(out / d);

  // Envelopes: every client message type, valid, with a routing id part first.
  int n = 0;
  const std::string peer = std::string("\0\x01\x02\x03\x04", 5);
  auto message = [&](const v1::Envelope& env, const std::string* payload = nullptr) {
    std::vector<std::string> parts = {peer, env.SerializeAsString()};
    if (payload) parts.push_back(*payload);
    Write(out / "envelope", &n, fuzz::JoinParts(parts));
  };
  message(Open(16, 12));
  v1::Envelope resume = Open(16, 12);
  resume.mutable_open_session()->clear_calibration();
  resume.mutable_open_session()->set_resume_session_id("s1-0123456789ab");
  resume.mutable_open_session()->set_resume_token("00112233445566778899aabbccddeeff");
  resume.mutable_open_session()->set_resume_next_chunk(3);
  message(resume);
  v1::Envelope frame = Envelope();
  frame.mutable_frame()->set_session_id("s1-0123456789ab");
  frame.mutable_frame()->set_sequence_number(7);
  frame.mutable_frame()->set_codec(v1::FRAME_CODEC_RAW);
  const std::string raw(16 * 12 * 3, '\x40');
  message(frame, &raw);
  v1::Envelope credits = Envelope();
  credits.mutable_chunk_credits()->set_session_id("s1-0123456789ab");
  credits.mutable_chunk_credits()->set_chunks(4);
  message(credits);
  v1::Envelope close = Envelope();
  close.mutable_close()->set_session_id("s1-0123456789ab");
  close.mutable_close()->set_abort(true);
  message(close);
  v1::Envelope wrong = Envelope();
  wrong.mutable_pose_update()->set_session_id("x");
  message(wrong);

  // Frames: PNG, JPEG (4:4:4) and raw at small sizes, prefixed with [codec][width-1][height-1].
  n = 0;
  for (const auto& [w, h] : {std::pair{16, 12}, std::pair{33, 7}, std::pair{64, 64}}) {
    const cv::Mat rgb = Image(w, h);
    for (const auto& [codec, tag] :
         {std::pair{FrameCodec::kPng, 0}, std::pair{FrameCodec::kJpeg, 1}, std::pair{FrameCodec::kRaw, 2}}) {
      FrameEncodeOptions o;
      o.codec = codec;
      std::vector<uint8_t> bytes;
      if (!EncodeFrame(rgb, o, &bytes).ok()) return 1;
      std::string seed = {static_cast<char>(tag), static_cast<char>(w - 1), static_cast<char>(h - 1)};
      seed.append(bytes.begin(), bytes.end());
      Write(out / "frame_decoder", &n, seed);
    }
  }

  // Draco chunks from small clouds (with normals and colours, and positions only).
  n = 0;
  for (int points : {1, 10, 200}) {
    for (bool attributes : {true, false}) {
      PointCloud cloud;
      for (int i = 0; i < points; ++i) {
        cloud.positions.emplace_back(0.001f * i, 0.002f * (i % 7), 0.5f + 0.0005f * (i % 13));
        if (attributes) {
          cloud.normals.emplace_back(0.f, 0.f, 1.f);
          cloud.colors.emplace_back(static_cast<uint8_t>(i), 100, 200);
        }
      }
      StatusOr<EncodedMapChunk> chunk = EncodeMapChunk(cloud, MapChunkCodecOptions());
      if (!chunk.ok()) return 1;
      Write(out / "draco_chunk", &n, std::string(chunk->bytes.begin(), chunk->bytes.end()));
    }
  }
  // SLAM config texts: every key at its default, only changed keys, and a few lines with comments.
  n = 0;
  SlamOptions changed;
  changed.loop_closure = false;
  changed.tracker.shading_model = ShadingModel::kPredictedShading;
  changed.depth.max_relative_sigma = 0.07;
  Write(out / "slam_config", &n, FormatSlamConfig(SlamOptions()));
  Write(out / "slam_config", &n, FormatSlamConfig(changed, /*only_changed=*/true));
  Write(out / "slam_config", &n, "# comment\nkeyframe-window = 8  # trailing\n\nfinal_adjustment = off\n");
  std::printf("{\"envelope\": 6, \"frame_decoder\": 9, \"draco_chunk\": 6, \"slam_config\": 3, \"out\": \"%s\"}\n",
              out.c_str());
  return 0;
}
