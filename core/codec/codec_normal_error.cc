// The photometric-stereo normal error of each frame codec (and JPEG quality) on a prism-synth frame,
// as JSON: the colour ratios carry the normals, so lossy coding shows up here first.
//   codec_normal_error [--preset NAME] [--size N] [--frame I]
// Each variant encodes the rendered frame, decodes it, and runs EstimateNormals with the true depth
// scale on the same simulated semi-dense depth; the error is against the ground-truth normals on the
// object. "jpeg420" is OpenCV's default JPEG (4:2:0 chroma), which the server refuses.
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <string>
#include <vector>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/codec/frame_codec.h"
#include "core/eval/normal_metrics.h"
#include "core/io/image_io.h"
#include "core/io/sequence.h"
#include "core/photometric/photometric_stereo.h"
#include "core/synth/presets.h"
#include "core/synth/semidense.h"
#include "core/synth/synthesize.h"
#include "core/util/thread_pool.h"

namespace {
int Fail(const std::string& m) {
  std::fprintf(stderr, "codec_normal_error: %s\n", m.c_str());
  return 2;
}
}  // namespace

int main(int argc, char** argv) {
  using namespace prism;
  std::string preset = "bunny-multicolor-forward";
  int size = 512, frame = 0;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string a = argv[i];
    if (a == "--preset") preset = argv[i + 1];
    else if (a == "--size") size = std::atoi(argv[i + 1]);
    else if (a == "--frame") frame = std::atoi(argv[i + 1]);
    else return Fail("unknown argument '" + a + "' (--preset NAME --size N --frame I)");
  }
  synth::PresetOptions po;
  po.width = po.height = size;
  po.frames = frame + 2;
  StatusOr<synth::SynthSetup> setup = synth::MakePreset(preset, po);
  if (!setup.ok()) return Fail(setup.status().ToString());
  const std::string dir =
      (std::filesystem::temp_directory_path() / ("prism_codec_normals_" + std::to_string(getpid()))).string();
  ThreadPool pool(0);
  StatusOr<synth::SynthesizeSummary> summary = synth::SynthesizeSequence(*setup, po.seed, dir, &pool);
  if (!summary.ok()) return Fail(summary.status().ToString());
  StatusOr<Sequence> seq = LoadSequence(dir);
  if (!seq.ok()) return Fail(seq.status().ToString());
  StatusOr<cv::Mat> rgb = seq->ReadRgb(frame), depth = seq->ReadDepth(frame), truth = seq->ReadNormals(frame),
                    mask = seq->ReadMask(frame);
  std::filesystem::remove_all(dir);
  if (!rgb.ok() || !depth.ok() || !truth.ok() || !mask.ok()) return Fail("cannot read the rendered frame");
  const cv::Mat object = *mask == kMaskObject;

  synth::SemiDenseOptions sd;
  sd.scale = 0.37;
  sd.seed = 1;
  const InverseDepthMap semi_dense = synth::SimulateSemiDenseDepth(*depth, *rgb, sd);
  PhotometricOptions ps_options;
  ps_options.estimate_depth_scale = false;
  ps_options.depth_scale = sd.scale;

  struct Variant {
    std::string name;
    FrameCodec codec;
    int quality;
  };
  std::vector<Variant> variants = {{"png", FrameCodec::kPng, 0}, {"raw", FrameCodec::kRaw, 0}};
  for (int q : {100, 98, 95, 90, 85, 75, 50}) variants.push_back({"jpeg", FrameCodec::kJpeg, q});
  variants.push_back({"jpeg420", FrameCodec::kJpeg, 95});

  std::printf("{\n  \"preset\": \"%s\", \"size\": %d, \"frame\": %d,\n  \"variants\": [\n", preset.c_str(), size,
              frame);
  for (size_t v = 0; v < variants.size(); ++v) {
    const Variant& var = variants[v];
    std::vector<uint8_t> bytes;
    cv::Mat decoded;
    if (var.name == "jpeg420") {
      cv::Mat bgr;
      cv::cvtColor(*rgb, bgr, cv::COLOR_RGB2BGR);
      cv::imencode(".jpg", bgr, bytes, {cv::IMWRITE_JPEG_QUALITY, var.quality});
      cv::cvtColor(cv::imdecode(bytes, cv::IMREAD_COLOR), decoded, cv::COLOR_BGR2RGB);
    } else {
      FrameEncodeOptions eo;
      eo.codec = var.codec;
      if (var.quality) eo.jpeg_quality = var.quality;
      if (Status s = EncodeFrame(*rgb, eo, &bytes); !s.ok()) return Fail(s.ToString());
      if (Status s = DecodeFrame(bytes.data(), bytes.size(), var.codec, size, size, &decoded); !s.ok())
        return Fail(s.ToString());
    }
    const double rms = cv::norm(*rgb, decoded, cv::NORM_L2) / std::sqrt(double(rgb->total() * 3));
    StatusOr<PhotometricResult> ps = EstimateNormals(decoded, semi_dense, seq->calibration, ps_options, &pool);
    if (!ps.ok()) return Fail(ps.status().ToString());
    StatusOr<AngularErrorStats> err = ComputeNormalError(ps->normals, *truth, object);
    if (!err.ok()) return Fail(err.status().ToString());
    std::printf(
        "    {\"codec\": \"%s\", \"quality\": %d, \"bytes\": %zu, \"bits_per_pixel\": %.3f, "
        "\"rms_grey_levels\": %.3f, \"normal_median_deg\": %.4f, \"normal_mean_deg\": %.4f}%s\n",
        var.name.c_str(), var.quality, bytes.size(), 8.0 * bytes.size() / rgb->total(), rms, err->median_deg,
        err->mean_deg, v + 1 < variants.size() ? "," : "");
  }
  std::printf("  ]\n}\n");
  return 0;
}
