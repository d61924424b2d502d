#include "core/synth/renderer.h"

#include <cmath>
#include <random>
#include <sstream>

#include "core/util/thread_pool.h"

namespace prism::synth {

Status RenderOptions::Check() const {
  std::ostringstream e;
  if (!(ambient >= 0 && ambient <= 1)) e << "RenderOptions.ambient = " << ambient << "; violated: in [0, 1]";
  else if (!(specular_scale >= 0 && specular_scale <= 10))
    e << "RenderOptions.specular_scale = " << specular_scale << "; violated: in [0, 10]";
  else if (!(noise_sigma >= 0 && noise_sigma <= 50))
    e << "RenderOptions.noise_sigma = " << noise_sigma << "; violated: in [0, 50]";
  else if (!(shot_noise >= 0 && shot_noise <= 10))
    e << "RenderOptions.shot_noise = " << shot_noise << "; violated: in [0, 10]";
  else if (!(max_depth_m > 0)) e << "RenderOptions.max_depth_m = " << max_depth_m << "; violated: > 0";
  else if (!(shadow_bias_m >= 0 && shadow_bias_m < 0.01))
    e << "RenderOptions.shadow_bias_m = " << shadow_bias_m << "; violated: in [0, 0.01)";
  if (e.str().empty()) return Status::Ok();
  return InvalidArgumentError(e.str());
}

Eigen::Vector3d ShadePoint(const Scene& scene, const RigCalibration& rig, const Rigid3d& world_from_camera,
                           const SurfaceHit& hit, const RenderOptions& options) {
  const SceneObject& obj = scene.objects()[hit.object];
  const Eigen::Vector3d rho = obj.albedo.Evaluate(hit.point_in_object);
  const Eigen::Vector3d& n = hit.normal_in_world;
  const Eigen::Vector3d view = (world_from_camera.translation - hit.point_in_world).normalized();
  const Rigid3d camera_from_world = world_from_camera.Inverse();
  const Eigen::Vector3d point_in_camera = camera_from_world * hit.point_in_world;
  const double specular = obj.specular * options.specular_scale;

  Eigen::Vector3d diffuse_per_light = Eigen::Vector3d::Zero();
  Eigen::Vector3d specular_per_light = Eigen::Vector3d::Zero();
  for (int l = 0; l < 3; ++l) {
    Eigen::Vector3d to_light_cam;
    double irradiance;
    rig.lights[l].Illuminate(point_in_camera, &to_light_cam, &irradiance);
    const Eigen::Vector3d to_light = world_from_camera.rotation * to_light_cam;
    const double cosine = n.dot(to_light);
    if (cosine <= 0 || irradiance <= 0) continue;
    // The geometric normal must also face the light, else the interpolated normal lies.
    if (hit.geometric_normal_in_world.dot(to_light) <= 0) continue;
    if (options.cast_shadows) {
      const double dist = rig.lights[l].type == LightType::kPoint
                              ? (rig.lights[l].position_in_camera - point_in_camera).norm()
                              : options.max_depth_m;
      const Eigen::Vector3d origin = hit.point_in_world + options.shadow_bias_m * hit.geometric_normal_in_world;
      if (scene.Occluded(origin, to_light, 1e-9, dist)) continue;
    }
    diffuse_per_light[l] = rho[l] * irradiance * cosine;
    if (specular > 0) {
      const Eigen::Vector3d h = (to_light + view).normalized();
      specular_per_light[l] = specular * irradiance * std::pow(std::max(0.0, n.dot(h)), obj.shininess);
    }
  }
  Eigen::Vector3d radiance = rig.crosstalk * (diffuse_per_light + specular_per_light);
  radiance += options.ambient * rho;
  return radiance;
}

RenderedFrame RenderFrame(const Scene& scene, const RigCalibration& rig, const Rigid3d& world_from_camera,
                          const RenderOptions& options, uint64_t noise_seed, ThreadPool* pool) {
  const PinholeCamera& cam = rig.camera;
  RenderedFrame f;
  f.rgb.create(cam.height, cam.width, CV_8UC3);
  f.radiance.create(cam.height, cam.width, CV_32FC3);
  f.depth.create(cam.height, cam.width, CV_32F);
  f.normals.create(cam.height, cam.width, CV_32FC3);
  f.mask.create(cam.height, cam.width, CV_8U);
  const Eigen::Quaterniond camera_from_world_rot = world_from_camera.rotation.conjugate();

  auto render_row = [&](std::ptrdiff_t y) {
    // Per-row noise stream: deterministic whatever the thread schedule.
    std::mt19937_64 rng(noise_seed * 0x9E3779B97F4A7C15ull + static_cast<uint64_t>(y) + 1);
    std::normal_distribution<double> gauss(0.0, 1.0);
    cv::Vec3b* rgb = f.rgb.ptr<cv::Vec3b>(static_cast<int>(y));
    cv::Vec3f* rad = f.radiance.ptr<cv::Vec3f>(static_cast<int>(y));
    float* depth = f.depth.ptr<float>(static_cast<int>(y));
    cv::Vec3f* nrm = f.normals.ptr<cv::Vec3f>(static_cast<int>(y));
    uint8_t* mask = f.mask.ptr<uint8_t>(static_cast<int>(y));
    for (int x = 0; x < cam.width; ++x) {
      const Eigen::Vector3d ray_cam = cam.Unproject(Eigen::Vector2d(x, static_cast<double>(y)));
      const Eigen::Vector3d dir_cam = ray_cam.normalized();
      const Eigen::Vector3d dir = world_from_camera.rotation * dir_cam;
      SurfaceHit hit;
      Eigen::Vector3d radiance = Eigen::Vector3d::Zero();
      if (scene.Intersect(world_from_camera.translation, dir, 1e-6, options.max_depth_m, &hit)) {
        radiance = ShadePoint(scene, rig, world_from_camera, hit, options);
        depth[x] = static_cast<float>(hit.t * dir_cam.z());
        const Eigen::Vector3d n_cam = camera_from_world_rot * hit.normal_in_world;
        nrm[x] = cv::Vec3f(static_cast<float>(n_cam.x()), static_cast<float>(n_cam.y()), static_cast<float>(n_cam.z()));
        mask[x] = scene.objects()[hit.object].is_object ? 255 : 64;
      } else {
        depth[x] = 0.f;
        nrm[x] = cv::Vec3f(0, 0, 0);
        mask[x] = 0;
      }
      for (int c = 0; c < 3; ++c) {
        rad[x][c] = static_cast<float>(radiance[c]);
        const double signal = 255.0 * radiance[c];
        const double sigma = std::sqrt(options.noise_sigma * options.noise_sigma + options.shot_noise * std::max(0.0, signal));
        const double v = std::round(signal + sigma * gauss(rng));
        rgb[x][c] = static_cast<uint8_t>(std::min(255.0, std::max(0.0, v)));
      }
    }
  };
  if (pool) {
    pool->ParallelFor(0, cam.height, render_row, 4);
  } else {
    for (int y = 0; y < cam.height; ++y) render_row(y);
  }
  return f;
}

}  // namespace prism::synth
