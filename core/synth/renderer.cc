#include "core/synth/renderer.h"

#include <cmath>
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
  else if (!(supersampling >= 1 && supersampling <= 8))
    e << "RenderOptions.supersampling = " << supersampling << "; violated: in [1, 8]";
  if (e.str().empty()) return Status::Ok();
  return InvalidArgumentError(e.str());
}

namespace {

// Per-frame constants of the shading model, computed once per frame instead of once per pixel.
struct FrameContext {
  Rigid3d world_from_camera;
  Rigid3d camera_from_world;
  Eigen::Vector3d light_in_world[3];
};

FrameContext MakeContext(const RigCalibration& rig, const Rigid3d& world_from_camera) {
  FrameContext c;
  c.world_from_camera = world_from_camera;
  c.camera_from_world = world_from_camera.Inverse();
  for (int l = 0; l < 3; ++l) c.light_in_world[l] = world_from_camera * rig.lights[l].position_in_camera;
  return c;
}

Eigen::Vector3d Shade(const Scene& scene, const RigCalibration& rig, const FrameContext& ctx, const SurfaceHit& hit,
                      const RenderOptions& options) {
  const SceneObject& obj = scene.objects()[hit.object];
  const Eigen::Vector3d rho = obj.albedo.Evaluate(hit.point_in_object);
  const Eigen::Vector3d& n = hit.normal_in_world;
  const double specular = obj.specular * options.specular_scale;
  Eigen::Vector3d view = Eigen::Vector3d::Zero();
  if (specular > 0) view = (ctx.world_from_camera.translation - hit.point_in_world).normalized();

  Eigen::Vector3d per_light = Eigen::Vector3d::Zero();
  for (int l = 0; l < 3; ++l) {
    const Light& light = rig.lights[l];
    Eigen::Vector3d to_light;
    double irradiance, dist;
    if (light.type == LightType::kPoint) {
      to_light = ctx.light_in_world[l] - hit.point_in_world;
      const double d2 = to_light.squaredNorm();
      dist = std::sqrt(d2);
      to_light /= dist;
      irradiance = light.intensity / d2;
    } else {
      to_light = ctx.world_from_camera.rotation * light.direction_in_camera.normalized();
      irradiance = light.intensity;
      dist = options.max_depth_m;
    }
    const double cosine = n.dot(to_light);
    if (cosine <= 0 || irradiance <= 0) continue;  // attached shadow
    // The geometric normal must also face the light, else the interpolated normal lies.
    if (hit.geometric_normal_in_world.dot(to_light) <= 0) continue;
    if (options.cast_shadows) {
      const Eigen::Vector3d origin = hit.point_in_world + options.shadow_bias_m * hit.geometric_normal_in_world;
      if (scene.Occluded(origin, to_light, 1e-9, dist)) continue;
    }
    per_light[l] = rho[l] * irradiance * cosine;
    if (specular > 0) {
      const Eigen::Vector3d h = (to_light + view).normalized();
      per_light[l] += specular * irradiance * std::pow(std::max(0.0, n.dot(h)), obj.shininess);
    }
  }
  return rig.crosstalk * per_light + options.ambient * rho;
}

// SplitMix64-seeded xoshiro256+ with Box-Muller: a fast, deterministic Gaussian source.
class FastGaussian {
 public:
  explicit FastGaussian(uint64_t seed) {
    for (uint64_t& w : s_) {
      seed += 0x9E3779B97F4A7C15ull;
      uint64_t z = seed;
      z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
      z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
      w = z ^ (z >> 31);
    }
  }
  double operator()() {
    if (has_spare_) {
      has_spare_ = false;
      return spare_;
    }
    const double u1 = (static_cast<double>(Next() >> 11) + 0.5) * 0x1.0p-53;
    const double u2 = static_cast<double>(Next() >> 11) * 0x1.0p-53;
    const double r = std::sqrt(-2.0 * std::log(u1));
    spare_ = r * std::sin(2 * M_PI * u2);
    has_spare_ = true;
    return r * std::cos(2 * M_PI * u2);
  }

 private:
  uint64_t Next() {
    const uint64_t result = s_[0] + s_[3];
    const uint64_t t = s_[1] << 17;
    s_[2] ^= s_[0];
    s_[3] ^= s_[1];
    s_[1] ^= s_[2];
    s_[0] ^= s_[3];
    s_[2] ^= t;
    s_[3] = (s_[3] << 45) | (s_[3] >> 19);
    return result;
  }
  uint64_t s_[4];
  double spare_ = 0;
  bool has_spare_ = false;
};

}  // namespace

Eigen::Vector3d ShadePoint(const Scene& scene, const RigCalibration& rig, const Rigid3d& world_from_camera,
                           const SurfaceHit& hit, const RenderOptions& options) {
  return Shade(scene, rig, MakeContext(rig, world_from_camera), hit, options);
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
  const FrameContext ctx = MakeContext(rig, world_from_camera);

  const int n = options.supersampling;
  auto render_row = [&](std::ptrdiff_t y) {
    // Per-row noise stream: deterministic whatever the thread schedule.
    FastGaussian gauss(noise_seed * 0x9E3779B97F4A7C15ull + static_cast<uint64_t>(y) + 1);
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
        if (n == 1) radiance = Shade(scene, rig, ctx, hit, options);
        depth[x] = static_cast<float>(hit.t * dir_cam.z());
        const Eigen::Vector3d n_cam = camera_from_world_rot * hit.normal_in_world;
        nrm[x] = cv::Vec3f(static_cast<float>(n_cam.x()), static_cast<float>(n_cam.y()), static_cast<float>(n_cam.z()));
        mask[x] = scene.objects()[hit.object].is_object ? 255 : 64;
      } else {
        depth[x] = 0.f;
        nrm[x] = cv::Vec3f(0, 0, 0);
        mask[x] = 0;
      }
      if (n > 1) {
        // Sub-pixel rays at offsets (i + 0.5) / n - 0.5 across the pixel.
        for (int sy = 0; sy < n; ++sy) {
          for (int sx = 0; sx < n; ++sx) {
            const Eigen::Vector2d p(x + (sx + 0.5) / n - 0.5, y + (sy + 0.5) / n - 0.5);
            const Eigen::Vector3d d = world_from_camera.rotation * cam.Unproject(p).normalized();
            SurfaceHit sub;
            if (scene.Intersect(world_from_camera.translation, d, 1e-6, options.max_depth_m, &sub))
              radiance += Shade(scene, rig, ctx, sub, options);
          }
        }
        radiance /= static_cast<double>(n * n);
      }
      for (int c = 0; c < 3; ++c) {
        rad[x][c] = static_cast<float>(radiance[c]);
        const double signal = 255.0 * radiance[c];
        const double sigma =
            std::sqrt(options.noise_sigma * options.noise_sigma + options.shot_noise * std::max(0.0, signal));
        const double v = std::round(signal + sigma * gauss());
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

cv::Mat QuantiseRadiance(const cv::Mat& radiance, const RenderOptions& options, uint64_t noise_seed) {
  cv::Mat rgb(radiance.rows, radiance.cols, CV_8UC3);
  for (int y = 0; y < radiance.rows; ++y) {
    FastGaussian gauss(noise_seed * 0x9E3779B97F4A7C15ull + static_cast<uint64_t>(y) + 1);
    const cv::Vec3f* rad = radiance.ptr<cv::Vec3f>(y);
    cv::Vec3b* out = rgb.ptr<cv::Vec3b>(y);
    for (int x = 0; x < radiance.cols; ++x)
      for (int c = 0; c < 3; ++c) {
        const double signal = 255.0 * rad[x][c];
        const double sigma =
            std::sqrt(options.noise_sigma * options.noise_sigma + options.shot_noise * std::max(0.0, signal));
        out[x][c] = static_cast<uint8_t>(std::min(255.0, std::max(0.0, std::round(signal + sigma * gauss()))));
      }
  }
  return rgb;
}

}  // namespace prism::synth
