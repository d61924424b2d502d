#include <iostream>
#include "core/eval/normal_metrics.h"
#include "core/photometric/photometric_stereo.h"
#include "core/synth/presets.h"
#include "core/synth/renderer.h"
#include "core/synth/semidense.h"
using namespace prism;
int main(int argc, char** argv) {
  for (int a = 1; a < argc; ++a) {
    synth::PresetOptions o; o.frames = std::getenv("FRAMES") ? std::atoi(std::getenv("FRAMES")) : 60; if (std::getenv("SEED")) o.seed = std::atoi(std::getenv("SEED"));
    auto setup = synth::MakePreset(argv[a], o).value();
    if (std::getenv("NOISE0")) { setup.render.noise_sigma = 0; setup.render.shot_noise = 0; }
    auto t = synth::MakeTrajectory(setup.trajectory);
    auto f = synth::RenderFrame(setup.scene, setup.rig, t[std::getenv("FRAME") ? std::atoi(std::getenv("FRAME")) : 40].world_from_camera, setup.render, 11);
    cv::Mat obj = f.mask == 255;
    for (int variant = 0; variant < (std::getenv("V0") ? 1 : 3); ++variant) {
      synth::SemiDenseOptions s; s.scale = 0.37;
      if (variant >= 1) { s.min_gradient = 0; s.dropout = 0; }
      if (variant == 2) s.relative_noise = 0;
      auto prior = synth::SimulateSemiDenseDepth(f.depth, f.rgb, s);
      if (std::getenv("OBJONLY")) { prior.inverse_depth.setTo(0, ~obj); }
      PhotometricOptions po;
      if (argc > 0 && std::getenv("NOSP")) po.superpixel_size_px = 0;
      if (std::getenv("EDGE")) po.min_albedo_edge = std::atof(std::getenv("EDGE"));
      if (std::getenv("CS")) po.min_chromaticity_sigma = std::atof(std::getenv("CS"));
      if (std::getenv("PR")) po.plane_radius_px = std::atoi(std::getenv("PR"));
      if (std::getenv("PRES")) po.max_plane_residual = std::atof(std::getenv("PRES"));
      if (std::getenv("K")) po.max_clusters = std::atoi(std::getenv("K"));
      if (std::getenv("RA")) po.reassignment_rounds = std::atoi(std::getenv("RA"));
      if (std::getenv("SUP")) po.min_prior_support = std::atof(std::getenv("SUP"));
      if (std::getenv("SM")) po.image_smoothing_sigma_px = std::atof(std::getenv("SM"));
      if (std::getenv("STEP")) po.prior.step_px = std::atoi(std::getenv("STEP"));
      if (std::getenv("PSM")) po.prior.smoothing_sigma_px = std::atof(std::getenv("PSM"));
      if (std::getenv("KNOWN")) { po.estimate_depth_scale = false; po.depth_scale = 0.37; }
      auto r = EstimateNormals(f.rgb, prior, setup.rig, po);
      if (!r.ok()) { std::cout << r.status() << "\n"; continue; }
      auto e = ComputeNormalError(r->normals, f.normals, obj).value();
      auto ep = ComputeNormalError(r->prior_normals, f.normals, obj).value();
      cv::Mat conf_obj = obj & (r->confidence > 0.5);
      auto ec = ComputeNormalError(r->normals, f.normals, conf_obj).value();
      std::cout << argv[a] << " variant " << variant << " (0 semidense, 1 dense noisy, 2 dense exact): PS median " << e.median_deg << " mean " << e.mean_deg << " | conf>0.5 median " << ec.median_deg << " (" << ec.count << "/" << e.count << ") | prior median " << ep.median_deg << " scale " << r->depth_scale << " k " << r->num_clusters << "\n";
    }
  }
}
