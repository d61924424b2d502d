// The sweep behind FusionOptions' defaults: for each keyframe and setting it prints the depth RMSE of
// the semi-dense input and of the fused depth on the object (known SLAM scale, mm), the coverage of
// the object, the median angular error of the input, corrected and fused normals (deg), the solver
// iterations and the wall time of the call.
//
// Keyframes: prism-synth presets at 512x512, frame 40 of 60, SLAM depth simulated at scale 0.37;
// normals either ground truth + seeded noise (4 deg RMS per pixel + 4 deg smooth bias; "gt+noise")
// or EstimateNormals output ("ps", --ps); and the real DiLiGenT ball ("diligent-ball": real 3-light
// normals, fitted-sphere depth; see MakeDiligentBallFrame) when the data is present.
//
//   build/bin/fusion_sweep [--presets a,b,...] [--weights w1,w2,...] [--ps] [--settings all|default]
//                          [--sigma PX] [--threads N]
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <sstream>
#include <string>
#include <vector>

#include "core/fusion/fusion.h"
#include "core/fusion/fusion_testing.h"
#include "core/photometric/photometric_stereo.h"
#include "core/util/thread_pool.h"

#ifndef PRISM_SHARED_DATA_DIR
#define PRISM_SHARED_DATA_DIR "../shared/data"
#endif

namespace {

std::vector<std::string> Split(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  std::string item;
  while (std::getline(ss, item, ',')) out.push_back(item);
  return out;
}

struct Setting {
  int passes;
  bool correction;
};

}  // namespace

int main(int argc, char** argv) {
  std::vector<std::string> presets = {"sphere-uniform-sideways", "sphere-multicolor-sideways", "torus-textured-forward",
                                      "bunny-multicolor-forward", "diligent-ball"};
  std::vector<double> weights = {1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2};
  bool use_ps = false;
  bool all_settings = true;
  prism::FusionOptions base;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "%s needs a value\n", a.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--presets") {
      presets = Split(next());
    } else if (a == "--weights") {
      weights.clear();
      for (const std::string& w : Split(next())) weights.push_back(std::atof(w.c_str()));
    } else if (a == "--ps") {
      use_ps = true;
    } else if (a == "--settings") {
      all_settings = next() == "all";
    } else if (a == "--sigma") {
      base.correction_sigma_px = std::atof(next().c_str());
    } else if (a == "--threads") {
      base.num_threads = std::atoi(next().c_str());
    } else {
      std::fprintf(stderr,
                   "usage: fusion_sweep [--presets a,b] [--weights w1,w2] [--ps] [--settings all|default] "
                   "[--sigma PX] [--threads N]\n");
      return 2;
    }
  }
  std::vector<Setting> settings = {{base.passes, base.normal_correction}};
  if (all_settings) settings = {{1, false}, {2, false}, {2, true}, {3, true}};
  prism::ThreadPool pool(2);
  std::printf("%-27s %-8s %7s %4s %4s | %6s %8s %6s | %6s %6s %7s | %5s %6s\n", "keyframe", "normals", "weight", "pass",
              "corr", "in_mm", "fused_mm", "cover", "n_in", "n_corr", "n_fused", "iters", "ms");
  for (const std::string& preset : presets) {
    prism::FusionTestFrame frame;
    cv::Mat normals, confidence;
    const char* kind = use_ps ? "ps" : "gt+noise";
    if (preset == "diligent-ball") {
      auto ball = prism::MakeDiligentBallFrame(std::string(PRISM_SHARED_DATA_DIR) + "/diligent-ball");
      if (!ball.ok()) {
        std::printf("%-27s skipped: %s\n", preset.c_str(), ball.status().ToString().c_str());
        continue;
      }
      frame = ball->frame;
      normals = ball->ps_normals;
      kind = "real-ps";
      std::printf("# diligent-ball: fitted sphere vs ground-truth normals, median %.2f deg\n",
                  ball->sphere_vs_gt_median_deg);
    } else {
      auto made = prism::MakeFusionTestFrame(preset, prism::FusionTestFrameOptions());
      if (!made.ok()) {
        std::printf("%-27s skipped: %s\n", preset.c_str(), made.status().ToString().c_str());
        continue;
      }
      frame = *made;
      if (use_ps) {
        const auto ps =
            prism::EstimateNormals(frame.frame.rgb, frame.semi_dense, frame.rig, prism::PhotometricOptions());
        if (!ps.ok()) {
          std::printf("%-27s PS failed: %s\n", preset.c_str(), ps.status().ToString().c_str());
          continue;
        }
        normals = ps->normals;
        confidence = ps->confidence;
      } else {
        normals = prism::PerturbNormals(frame.frame.normals, prism::NormalNoiseOptions());
      }
    }
    for (const Setting& setting : settings)
      for (double w : weights) {
        prism::FusionOptions o = base;
        o.position_weight = w;
        o.passes = setting.passes;
        o.normal_correction = setting.correction;
        prism::FusionInput in = prism::MakeFusionInput(frame, normals);
        in.confidence = confidence;
        const auto t0 = std::chrono::steady_clock::now();
        const auto r = prism::FuseDepthAndNormals(in, o, &pool);
        const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
        if (!r.ok()) {
          std::printf("%-27s fusion failed: %s\n", preset.c_str(), r.status().ToString().c_str());
          continue;
        }
        const prism::FusionScore s = prism::ScoreFusion(frame, normals, *r);
        std::printf("%-27s %-8s %7.4f %4d %4s | %6.3f %8.3f %6.4f | %6.2f %6.2f %7.2f | %5d %6.1f\n", preset.c_str(),
                    kind, w, setting.passes, setting.correction ? "on" : "off", 1e3 * s.input_depth_rmse_m,
                    1e3 * s.fused_depth_rmse_m, s.coverage, s.input_normal_median_deg, s.corrected_normal_median_deg,
                    s.fused_normal_median_deg, r->iterations, ms);
        std::fflush(stdout);
      }
  }
  return 0;
}
