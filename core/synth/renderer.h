// Renders one frame of the multispectral rig by ray casting: three coloured lights fixed to the
// camera, Lambertian shading per light band, spectral crosstalk, attached and cast shadows, sensor
// noise and 8-bit quantisation.
//
// Image formation (linear, before noise), camera channel c, light l, unit normal n, point x:
//   I_c = sum_l X(c,l) * rho_l(x) * E_l(x) * max(0, n . L_l(x)) * V_l(x)
//       + ambient * rho_c(x)
//       + specular * sum_l X(c,l) * E_l(x) * V_l(x) * max(0, n . H_l)^shininess   (if n . L_l > 0)
// with X the crosstalk matrix, rho_l the albedo in light l's band, E_l = intensity / d^2 (point) or
// intensity (directional), L_l the unit direction to the light, V_l the cast-shadow visibility and
// H_l the half vector between L_l and the view direction. Pixel value = round(255 * I + noise), with
// I the mean over RenderOptions::supersampling^2 rays across the pixel (1: the centre ray only).
#pragma once

#include <cstdint>

#include <opencv2/core.hpp>

#include "core/geometry/rigid3.h"
#include "core/io/calibration_io.h"
#include "core/synth/scene.h"
#include "core/util/status.h"

namespace prism {
class ThreadPool;
}

namespace prism::synth {

struct RenderOptions {
  // Cast shadows from each light (attached shadows, n . L <= 0, are always rendered).
  bool cast_shadows = true;
  // Uniform white ambient light, in [0, 1] pixel units per unit albedo (0 = dark room, as in the paper).
  double ambient = 0.0;
  // Scales every object's specular weight (0 disables specularity), in [0, 10].
  double specular_scale = 1.0;
  // Gaussian read noise, standard deviation in 8-bit levels, in [0, 50].
  double noise_sigma = 1.0;
  // Shot noise: variance grows by shot_noise * signal (8-bit levels), in [0, 10].
  double shot_noise = 0.05;
  // Maximum ray distance in metres.
  double max_depth_m = 20.0;
  // Offset of shadow-ray origins along the geometric normal, metres.
  double shadow_bias_m = 1e-5;
  // Pixel-area integration: each pixel's radiance is the mean over n x n rays on a regular grid
  // across the pixel (a box filter, as a sensor with full fill factor), in [1, 8]. 1 = one ray
  // through the pixel centre (point sampling: sharp albedo edges and silhouettes alias, so sub-pixel
  // motion changes pixel values in steps). Depth, normals and mask stay those of the centre ray.
  int supersampling = 1;

  Status Check() const;
};

struct RenderedFrame {
  cv::Mat rgb;       // CV_8UC3, RGB, noisy and quantised
  cv::Mat radiance;  // CV_32FC3, linear I_c before noise and quantisation (may exceed 1)
  cv::Mat depth;     // CV_32F, z in the camera frame, metres; 0 = no surface
  cv::Mat normals;   // CV_32FC3, camera frame, facing the camera; 0 = no surface
  cv::Mat mask;      // CV_8U, 255 object, 64 ground, 0 none
};

// Renders the scene seen by a camera at world_from_camera. `noise_seed` makes the noise
// deterministic; rows are spread over `pool` when given.
RenderedFrame RenderFrame(const Scene& scene, const RigCalibration& rig, const Rigid3d& world_from_camera,
                          const RenderOptions& options, uint64_t noise_seed, ThreadPool* pool = nullptr);

// 8-bit RGB from linear radiance (CV_32FC3) with the sensor noise of `options`, as RenderFrame does:
// for frames averaged over several renders (motion blur).
cv::Mat QuantiseRadiance(const cv::Mat& radiance, const RenderOptions& options, uint64_t noise_seed);

// The noise-free shading model above at one surface point, for tests and the photometric branch.
Eigen::Vector3d ShadePoint(const Scene& scene, const RigCalibration& rig, const Rigid3d& world_from_camera,
                           const SurfaceHit& hit, const RenderOptions& options);

}  // namespace prism::synth
