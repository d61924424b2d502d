#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <random>
#include <string>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/codec/frame_codec.h"
#include "core/codec/map_chunk_codec.h"
#include "core/io/ply_io.h"
#include "core/mapping/global_map.h"

namespace prism {
namespace {

// Smooth shading plus seeded noise: like a camera frame, not trivially compressible.
cv::Mat TestImage(int width, int height, uint32_t seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> noise(0.0f, 3.0f);
  cv::Mat rgb(height, width, CV_8UC3);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x) {
      const float r = 128 + 100 * std::sin(x * 0.05f), g = 128 + 90 * std::cos(y * 0.07f), b = 60 + 0.3f * (x + y);
      rgb.at<cv::Vec3b>(y, x) =
          cv::Vec3b(cv::saturate_cast<uint8_t>(r + noise(rng)), cv::saturate_cast<uint8_t>(g + noise(rng)),
                    cv::saturate_cast<uint8_t>(b + noise(rng)));
    }
  return rgb;
}

// Sampling factors (h << 4 | v) of the components in a JPEG's SOF0 segment.
std::vector<int> JpegSamplingFactors(const std::vector<uint8_t>& jpeg) {
  for (size_t i = 2; i + 9 < jpeg.size(); ++i)
    if (jpeg[i] == 0xFF && (jpeg[i + 1] == 0xC0 || jpeg[i + 1] == 0xC2)) {
      const int components = jpeg[i + 9];
      std::vector<int> f;
      for (int c = 0; c < components; ++c) f.push_back(jpeg[i + 11 + 3 * c]);
      return f;
    }
  return {};
}

TEST(FrameCodecTest, PngAndRawAreLossless) {
  const cv::Mat rgb = TestImage(96, 64, 1);
  for (FrameCodec codec : {FrameCodec::kPng, FrameCodec::kRaw}) {
    FrameEncodeOptions options;
    options.codec = codec;
    std::vector<uint8_t> bytes;
    ASSERT_TRUE(EncodeFrame(rgb, options, &bytes).ok());
    cv::Mat back;
    const Status st = DecodeFrame(bytes.data(), bytes.size(), codec, 96, 64, &back);
    ASSERT_TRUE(st.ok()) << FrameCodecName(codec) << ": " << st;
    EXPECT_EQ(cv::norm(rgb, back, cv::NORM_INF), 0.0) << FrameCodecName(codec);
  }
}

TEST(FrameCodecTest, JpegIsFourFourFourAndClose) {
  const cv::Mat rgb = TestImage(96, 64, 2);
  FrameEncodeOptions options;
  options.codec = FrameCodec::kJpeg;
  options.jpeg_quality = 95;
  std::vector<uint8_t> bytes;
  ASSERT_TRUE(EncodeFrame(rgb, options, &bytes).ok());
  EXPECT_EQ(JpegSamplingFactors(bytes), (std::vector<int>{0x11, 0x11, 0x11}));
  cv::Mat back;
  ASSERT_TRUE(DecodeFrame(bytes.data(), bytes.size(), FrameCodec::kJpeg, 96, 64, &back).ok());
  EXPECT_LT(cv::norm(rgb, back, cv::NORM_L2) / std::sqrt(double(rgb.total() * 3)), /*max_rms_grey_levels=*/4.0);
}

TEST(FrameCodecTest, SubsampledJpegIsRejected) {
  cv::Mat bgr;
  cv::cvtColor(TestImage(96, 64, 3), bgr, cv::COLOR_RGB2BGR);
  std::vector<uint8_t> bytes;
  ASSERT_TRUE(cv::imencode(".jpg", bgr, bytes));  // OpenCV 4.6 writes 4:2:0
  ASSERT_EQ(JpegSamplingFactors(bytes), (std::vector<int>{0x22, 0x11, 0x11}));
  cv::Mat back;
  const Status st = DecodeFrame(bytes.data(), bytes.size(), FrameCodec::kJpeg, 96, 64, &back);
  EXPECT_EQ(st.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(st.message().find("4:4:4"), std::string::npos) << st;
}

TEST(FrameCodecTest, WrongSizeIsRejectedWithBothSizes) {
  const cv::Mat rgb = TestImage(96, 64, 4);
  for (FrameCodec codec : {FrameCodec::kPng, FrameCodec::kJpeg, FrameCodec::kRaw}) {
    FrameEncodeOptions options;
    options.codec = codec;
    std::vector<uint8_t> bytes;
    ASSERT_TRUE(EncodeFrame(rgb, options, &bytes).ok());
    cv::Mat back;
    const Status st = DecodeFrame(bytes.data(), bytes.size(), codec, 128, 64, &back);
    EXPECT_EQ(st.code(), StatusCode::kInvalidArgument) << FrameCodecName(codec);
    EXPECT_NE(st.message().find("128x64"), std::string::npos) << st;
  }
}

TEST(FrameCodecTest, CorruptAndTruncatedFramesAreErrorsNotCrashes) {
  const cv::Mat rgb = TestImage(96, 64, 5);
  std::mt19937 rng(5);
  for (FrameCodec codec : {FrameCodec::kPng, FrameCodec::kJpeg}) {
    FrameEncodeOptions options;
    options.codec = codec;
    std::vector<uint8_t> bytes;
    ASSERT_TRUE(EncodeFrame(rgb, options, &bytes).ok());
    cv::Mat back;
    // Truncated to half.
    EXPECT_FALSE(DecodeFrame(bytes.data(), bytes.size() / 2, codec, 96, 64, &back).ok()) << FrameCodecName(codec);
    // Garbage that is not an image at all.
    std::vector<uint8_t> garbage(bytes.size());
    for (auto& b : garbage) b = static_cast<uint8_t>(rng());
    EXPECT_FALSE(DecodeFrame(garbage.data(), garbage.size(), codec, 96, 64, &back).ok()) << FrameCodecName(codec);
    // The header intact, the entropy-coded body overwritten.
    std::vector<uint8_t> body = bytes;
    for (size_t i = body.size() / 3; i < body.size(); ++i) body[i] = static_cast<uint8_t>(rng());
    EXPECT_FALSE(DecodeFrame(body.data(), body.size(), codec, 96, 64, &back).ok()) << FrameCodecName(codec);
  }
  cv::Mat back;
  EXPECT_FALSE(DecodeFrame(nullptr, 0, FrameCodec::kPng, 96, 64, &back).ok());
  EXPECT_FALSE(ParseFrameCodec("webp").ok());
}

// A map built from a sphere of points with normals and colours.
MapChunk SphereChunk(double voxel_m, int n, uint32_t seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> g(0.0f, 1.0f);
  PointCloud cloud;
  for (int i = 0; i < n; ++i) {
    Eigen::Vector3f d(g(rng), g(rng), g(rng));
    d.normalize();
    cloud.positions.push_back(Eigen::Vector3f(0.1f, -0.05f, 0.6f) + 0.08f * d);
    cloud.normals.push_back(d);
    cloud.colors.push_back(Eigen::Matrix<uint8_t, 3, 1>(static_cast<uint8_t>(rng()), 128, static_cast<uint8_t>(i)));
  }
  MapOptions options;
  options.voxel_m = voxel_m;
  GlobalMap map(options);
  EXPECT_TRUE(map.Insert(cloud, 1).ok());
  return map.TakeChanges();
}

TEST(MapChunkCodecTest, RoundTripKeepsVoxelsNormalsColoursAndMortonOrder) {
  MapChunkCodecOptions options;
  const MapChunk chunk = SphereChunk(options.voxel_m, 60000, 7);
  ASSERT_GT(chunk.size(), 5000u);
  StatusOr<EncodedMapChunk> encoded = EncodeMapChunk(chunk.cloud, options);
  ASSERT_TRUE(encoded.ok()) << encoded.status();
  EXPECT_EQ(encoded->num_points, chunk.size());
  EXPECT_EQ(encoded->dropped_points, 0u);
  StatusOr<PointCloud> decoded = DecodeMapChunk(encoded->bytes.data(), encoded->bytes.size());
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  ASSERT_EQ(decoded->size(), chunk.size());
  ASSERT_TRUE(decoded->HasNormals());
  ASSERT_TRUE(decoded->HasColors());
  const double step = options.grid_step_m();
  double max_position_error = 0, max_normal_deg = 0;
  uint64_t last_code = 0;
  for (size_t k = 0; k < decoded->size(); ++k) {
    const uint32_t i = encoded->order[k];
    const Eigen::Vector3f p = decoded->positions[k], q = chunk.cloud.positions[i];
    max_position_error = std::max(max_position_error, double((p - q).cwiseAbs().maxCoeff()));
    // Same voxel as the map's: the client's key.
    EXPECT_EQ(PackVoxelKey(VoxelOfDecodedPoint(p, options.voxel_m)), chunk.keys[i]) << k;
    const double cosine = std::clamp(double(decoded->normals[k].dot(chunk.cloud.normals[i])), -1.0, 1.0);
    max_normal_deg = std::max(max_normal_deg, std::acos(cosine) * 180 / M_PI);
    EXPECT_EQ(decoded->colors[k], chunk.cloud.colors[i]);
    // Morton order of the grid cells.
    const int64_t half = int64_t{1} << (options.position_bits - 1);
    auto cell = [&](float v) { return static_cast<uint32_t>(std::floor(v / step + 1e-3) + half); };
    const uint64_t code = MortonCode(cell(p.x()), cell(p.y()), cell(p.z()));
    EXPECT_GE(code, last_code) << k;
    last_code = code;
  }
  EXPECT_LE(max_position_error, step * (1 + 1e-3));  // one cell at most (clamped inside the voxel)
  EXPECT_LT(max_normal_deg, /*max_normal_quantisation_deg=*/0.25);
  const double bits_per_point = 8.0 * encoded->bytes.size() / encoded->num_points;
  std::cout << "map chunk: " << encoded->num_points << " points, " << bits_per_point << " bits/point (positions on a "
            << step * 1000 << " mm grid, normals " << options.normal_bits << " bits, RGB)\n";
  EXPECT_LT(bits_per_point, /*max_bits_per_point=*/48.0);
}

TEST(MapChunkCodecTest, CorruptTruncatedAndEmptyInputs) {
  MapChunkCodecOptions options;
  const MapChunk chunk = SphereChunk(options.voxel_m, 5000, 8);
  StatusOr<EncodedMapChunk> encoded = EncodeMapChunk(chunk.cloud, options);
  ASSERT_TRUE(encoded.ok());
  const std::vector<uint8_t>& bytes = encoded->bytes;
  EXPECT_EQ(DecodeMapChunk(bytes.data(), bytes.size() / 2).status().code(), StatusCode::kDataLoss);
  std::vector<uint8_t> garbage(bytes.size());
  std::mt19937 rng(9);
  for (auto& b : garbage) b = static_cast<uint8_t>(rng());
  EXPECT_EQ(DecodeMapChunk(garbage.data(), garbage.size()).status().code(), StatusCode::kDataLoss);
  EXPECT_FALSE(DecodeMapChunk(nullptr, 0).ok());
  // Flipped bytes after the header: an error or a cloud, never a crash.
  for (int trial = 0; trial < 50; ++trial) {
    std::vector<uint8_t> flipped = bytes;
    for (int j = 0; j < 8; ++j) flipped[16 + rng() % (flipped.size() - 16)] ^= static_cast<uint8_t>(1 + rng() % 255);
    (void)DecodeMapChunk(flipped.data(), flipped.size());
  }
  // Empty cloud and dropped points.
  EXPECT_EQ(EncodeMapChunk(PointCloud(), options).status().code(), StatusCode::kFailedPrecondition);
  PointCloud wild;
  wild.positions = {Eigen::Vector3f(0, 0, 0), Eigen::Vector3f(1e6f, 0, 0), Eigen::Vector3f(NAN, 0, 0)};
  StatusOr<EncodedMapChunk> w = EncodeMapChunk(wild, options);
  ASSERT_TRUE(w.ok());
  EXPECT_EQ(w->num_points, 1u);
  EXPECT_EQ(w->dropped_points, 2u);
  options.subdivisions = 0;
  EXPECT_EQ(EncodeMapChunk(wild, options).status().code(), StatusCode::kInvalidArgument);
}

// Regression (fuzz/fuzz_draco_chunk, out-of-memory): a chunk whose header claims far more points than
// its bytes could carry made Draco allocate ~800 MB from a few hundred bytes; it is refused before
// Draco sizes anything.
TEST(MapChunkCodecTest, ClaimedPointCountBeyondTheBytesIsRefusedBeforeDecoding) {
  MapChunkCodecOptions options;
  const MapChunk chunk = SphereChunk(options.voxel_m, 200, 8);
  StatusOr<EncodedMapChunk> encoded = EncodeMapChunk(chunk.cloud, options);
  ASSERT_TRUE(encoded.ok());
  ASSERT_TRUE(DecodeMapChunk(encoded->bytes.data(), encoded->bytes.size()).ok());
  for (const int32_t claimed :
       {int32_t{1} << 30, int32_t{50'000'000}, -1, static_cast<int32_t>(8 * encoded->bytes.size() + 65)}) {
    std::vector<uint8_t> bytes = encoded->bytes;
    std::memcpy(bytes.data() + 11, &claimed, sizeof(claimed));  // the int32 point count after the header
    const Status s = DecodeMapChunk(bytes.data(), bytes.size()).status();
    EXPECT_EQ(s.code(), StatusCode::kDataLoss) << claimed;
    EXPECT_NE(s.message().find("claims"), std::string::npos) << s;
  }
  // Not what EncodeMapChunk writes: a mesh, metadata, another major or an older minor version, kd-tree
  // coding (fuzzing found Draco 2.0 kd-tree input asking for ~43 GB).
  for (const auto& [offset, value] :
       {std::pair{7, 1}, std::pair{10, 0x80}, std::pair{5, 1}, std::pair{6, 0}, std::pair{8, 1}}) {
    std::vector<uint8_t> bytes = encoded->bytes;
    bytes[static_cast<size_t>(offset)] = static_cast<uint8_t>(value);
    EXPECT_FALSE(DecodeMapChunk(bytes.data(), bytes.size()).ok()) << offset;
  }
}

TEST(MapChunkCodecTest, DebianDracoDecoderReadsTheChunk) {
  const char* tool = "/usr/bin/draco_decoder";
  if (access(tool, X_OK) != 0) GTEST_SKIP() << "Debian's draco package (draco_decoder) is not installed";
  MapChunkCodecOptions options;
  const MapChunk chunk = SphereChunk(options.voxel_m, 5000, 10);
  StatusOr<EncodedMapChunk> encoded = EncodeMapChunk(chunk.cloud, options);
  ASSERT_TRUE(encoded.ok());
  const std::string dir =
      (std::filesystem::temp_directory_path() / ("prism_codec_" + std::to_string(getpid()))).string();
  std::filesystem::create_directories(dir);
  const std::string drc = dir + "/chunk.drc", ply = dir + "/chunk.ply";
  FILE* f = std::fopen(drc.c_str(), "wb");
  ASSERT_NE(f, nullptr);
  std::fwrite(encoded->bytes.data(), 1, encoded->bytes.size(), f);
  std::fclose(f);
  const std::string cmd = std::string(tool) + " -i " + drc + " -o " + ply + " > /dev/null 2>&1";
  ASSERT_EQ(std::system(cmd.c_str()), 0) << cmd;
  StatusOr<PointCloud> read = ReadPointCloudPly(ply);
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_EQ(read->size(), encoded->num_points);
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace prism
