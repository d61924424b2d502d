#include "core/calibration/synthetic_captures.h"

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <random>
#include <sstream>

#include <Eigen/Geometry>

#include "core/calibration/calibrate.h"
#include "core/io/image_io.h"
#include "core/synth/scene.h"

namespace prism::calibration {

Status SyntheticCaptureOptions::Check() const {
  PRISM_RETURN_IF_ERROR(board.Check());
  PRISM_RETURN_IF_ERROR(render.Check());
  std::ostringstream e;
  if (!(margin_m >= 0 && margin_m <= 0.2))
    e << "SyntheticCaptureOptions.margin_m = " << margin_m << "; violated: in [0, 0.2]";
  else if (!(white_albedo > ink_albedo && white_albedo <= 1 && ink_albedo >= 0))
    e << "SyntheticCaptureOptions.white_albedo = " << white_albedo << ", ink_albedo = " << ink_albedo
      << "; violated: 0 <= ink < white <= 1";
  else if (!(intrinsics_views >= 1 && intrinsics_views <= 200 && light_views >= 1 && light_views <= 200))
    e << "SyntheticCaptureOptions.intrinsics_views, light_views = " << intrinsics_views << ", " << light_views
      << "; violated: in [1, 200]";
  else if (!(min_distance_m > 0.05 && min_distance_m <= max_distance_m && min_light_distance_m >= min_distance_m &&
             min_light_distance_m <= max_distance_m && max_distance_m <= 10))
    e << "SyntheticCaptureOptions distances " << min_distance_m << ", " << min_light_distance_m << ", "
      << max_distance_m << "; violated: 0.05 < min <= min_light <= max <= 10";
  else if (!(max_tilt_deg >= 0 && max_tilt_deg <= 70))
    e << "SyntheticCaptureOptions.max_tilt_deg = " << max_tilt_deg << "; violated: in [0, 70]";
  else if (!(texel_m > 0 && texel_m <= 0.005))
    e << "SyntheticCaptureOptions.texel_m = " << texel_m << "; violated: in (0, 0.005]";
  if (e.str().empty()) return Status::Ok();
  return InvalidArgumentError(e.str());
}

namespace {

namespace fs = std::filesystem;

// A board pose with its centre `distance` along a ray inside the middle of the view, tilted.
Rigid3d RandomBoardPose(const PinholeCamera& cam, const SyntheticCaptureOptions& o, double min_distance,
                        std::mt19937* rng) {
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  const double distance = min_distance + (o.max_distance_m - min_distance) * unit(*rng);
  const Eigen::Vector2d pixel(cam.cx + (unit(*rng) - 0.5) * 0.4 * cam.width,
                              cam.cy + (unit(*rng) - 0.5) * 0.4 * cam.height);
  const Eigen::Vector3d centre = distance * cam.Unproject(pixel).normalized();
  const double tilt = (0.25 + 0.75 * unit(*rng)) * o.max_tilt_deg * M_PI / 180;
  const double axis_angle = 2 * M_PI * unit(*rng);
  const double spin = (unit(*rng) - 0.5) * 40 * M_PI / 180;
  const Eigen::Quaterniond rotation =
      Eigen::Quaterniond(Eigen::AngleAxisd(tilt, Eigen::Vector3d(std::cos(axis_angle), std::sin(axis_angle), 0))) *
      Eigen::Quaterniond(Eigen::AngleAxisd(spin, Eigen::Vector3d::UnitZ()));
  const Eigen::Vector3d board_centre(0.5 * o.board.squares_x * o.board.square_m,
                                     0.5 * o.board.squares_y * o.board.square_m, 0);
  return Rigid3d(rotation, centre - rotation * board_centre);  // cam_from_board
}

synth::Scene BoardScene(const Rigid3d& cam_from_board, const std::shared_ptr<const synth::ImageTexture>& texture,
                        const SyntheticCaptureOptions& o) {
  synth::SceneObject plane;
  plane.shape = synth::ShapeKind::kPlane;
  const Eigen::Vector3d board_centre(0.5 * o.board.squares_x * o.board.square_m,
                                     0.5 * o.board.squares_y * o.board.square_m, 0);
  plane.world_from_object = cam_from_board * Rigid3d(Eigen::Quaterniond::Identity(), board_centre);
  plane.half_extents_m = Eigen::Vector3d(board_centre.x() + o.margin_m, board_centre.y() + o.margin_m, 0);
  plane.albedo.kind = synth::AlbedoKind::kImage;
  plane.albedo.base = Eigen::Vector3d::Constant(o.white_albedo);
  plane.albedo.image = texture;
  plane.is_object = true;
  synth::Scene scene;
  scene.AddObject(plane);
  return scene;
}

Status Render(const synth::Scene& scene, RigCalibration rig, int lit, const SyntheticCaptureOptions& o, uint64_t seed,
              const fs::path& file) {
  for (int l = 0; l < 3; ++l)
    if (!((lit >> l) & 1) || ((o.dark_lights >> l) & 1)) rig.lights[l].intensity = 0;
  const synth::RenderedFrame frame = synth::RenderFrame(scene, rig, Rigid3d(), o.render, seed);
  return WriteRgbImage(file.string(), frame.rgb);
}

std::string Numbered(int i) {
  char name[16];
  std::snprintf(name, sizeof(name), "%03d.png", i);
  return name;
}

}  // namespace

Status WriteSyntheticCaptures(const RigCalibration& rig, const SyntheticCaptureOptions& options,
                              const std::string& dir) {
  PRISM_RETURN_IF_ERROR(options.Check());
  PRISM_RETURN_IF_ERROR(rig.Check());
  const fs::path root(dir);
  std::error_code ec;
  fs::create_directories(root / "intrinsics", ec);
  for (const char* f : kLightFolders) fs::create_directories(root / "lights" / f, ec);
  if (ec) return UnavailableError("cannot create " + dir + ": " + ec.message());

  auto texture = std::make_shared<synth::ImageTexture>();
  const cv::Mat printed = DrawBoard(options.board, options.texel_m, options.margin_m);
  texture->width = printed.cols;
  texture->height = printed.rows;
  texture->texel_m = options.texel_m;
  texture->values.resize(printed.total());
  const float ink = static_cast<float>(options.ink_albedo / options.white_albedo);
  for (int y = 0; y < printed.rows; ++y)
    for (int x = 0; x < printed.cols; ++x)
      texture->values[static_cast<size_t>(y) * printed.cols + x] = printed.at<uint8_t>(y, x) > 127 ? 1.0f : ink;

  std::mt19937 rng(options.seed);
  uint64_t noise_seed = static_cast<uint64_t>(options.seed) * 1000;
  for (int i = 0; i < options.intrinsics_views; ++i) {
    const synth::Scene scene =
        BoardScene(RandomBoardPose(rig.camera, options, options.min_distance_m, &rng), texture, options);
    PRISM_RETURN_IF_ERROR(Render(scene, rig, 7, options, ++noise_seed, root / "intrinsics" / Numbered(i)));
  }
  for (int i = 0; i < options.light_views; ++i) {
    const synth::Scene scene =
        BoardScene(RandomBoardPose(rig.camera, options, options.min_light_distance_m, &rng), texture, options);
    for (int f = 0; f < 4; ++f)
      PRISM_RETURN_IF_ERROR(Render(scene, rig, kLightFolderLit[f], options, ++noise_seed,
                                   root / "lights" / kLightFolders[f] / Numbered(i)));
  }
  return WriteCalibrationYaml((root / "truth.yaml").string(), rig);
}

}  // namespace prism::calibration
