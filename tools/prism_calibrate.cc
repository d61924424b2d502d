// prism-calibrate: the rig's camera.yaml from images only (core/calibration): camera intrinsics and
// distortion from a ChArUco board, then the three lights' positions, intensities and crosstalk.
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <string>

#include "core/calibration/calibrate.h"
#include "core/io/calibration_io.h"
#include "core/io/image_io.h"
#include "tools/cli.h"
#include "tools/json_output.h"

namespace {

using namespace prism;

constexpr char kNotes[] = R"(Input folder (docs/rig.md, "Calibrating with prism-calibrate"):
  intrinsics/*.png       the board under any light, at least --min-views poses, 0.3-1 m, tilted
  lights/red/*.png       the board lit by the red light alone (dark room), at least 2 poses
  lights/green/*.png     ... green alone
  lights/blue/*.png      ... blue alone
  lights/all/*.png       optional: all three together
(.jpg also read). Writes camera.yaml (prism-server, prism-slam) and prints a JSON report: the
reprojection error, the light fit's residual and one-sigma uncertainties. Crosstalk has a unit
diagonal; intensities are for a white of albedo 1 given --white-albedo of the board's paper.
Exit status: 0 written, 1 the images do not calibrate (the message says why), 2 usage.)";

int Fail(const std::string& message, int status = 1) {
  std::cerr << "prism-calibrate: " << message << "\n";
  return status;
}

Json Vec(const Eigen::Vector3d& v, double scale = 1) {
  return Json::array({scale * v.x(), scale * v.y(), scale * v.z()});
}

Json Rows(const Eigen::Matrix3d& m) {
  Json rows = Json::array();
  for (int r = 0; r < 3; ++r) rows.push_back(Json::array({m(r, 0), m(r, 1), m(r, 2)}));
  return rows;
}

Json Report(const calibration::CalibrationReport& r, const std::string& out) {
  const PinholeCamera& cam = r.rig.camera;
  Json lights = Json::array();
  for (int l = 0; l < 3; ++l) {
    const Light& light = r.rig.lights[l];
    lights.push_back({{"name", light.name},
                      {"position_m", Vec(light.position_in_camera)},
                      {"position_std_mm", Vec(r.light_fit.position_std[l], 1000)},
                      {"intensity", light.intensity},
                      {"intensity_std", r.intensity_std[l]}});
  }
  return {{"out", out},
          {"width", cam.width},
          {"height", cam.height},
          {"intrinsics",
           {{"views", r.intrinsics_views},
            {"images", r.intrinsics_images},
            {"reprojection_rms_px", r.reprojection_rms_px},
            {"fx", cam.fx},
            {"fy", cam.fy},
            {"cx", cam.cx},
            {"cy", cam.cy},
            {"distortion", cam.distortion},
            {"std_px", {r.intrinsics_std[0], r.intrinsics_std[1], r.intrinsics_std[2], r.intrinsics_std[3]}},
            {"distortion_std", r.distortion_std},
            {"distortion_significant", r.distortion_significant},
            {"distortion_fitted", r.distortion_fitted}}},
          {"lights", lights},
          {"warnings", r.warnings},
          {"crosstalk", Rows(r.rig.crosstalk)},
          {"crosstalk_std", Rows(r.crosstalk_std)},
          {"light_fit",
           {{"views",
             {{"red", r.light_views[0]},
              {"green", r.light_views[1]},
              {"blue", r.light_views[2]},
              {"all", r.light_views[3]}}},
            {"residuals", r.light_fit.residuals},
            {"rms_levels", 255 * r.light_fit.rms},
            {"ambient_levels", Vec(r.light_fit.ambient, 255)},
            {"ambient_std_levels", Vec(r.light_fit.ambient_std, 255)},
            {"iterations", r.light_fit.iterations},
            {"converged", r.light_fit.converged}}},
          {"skipped", r.skipped}};
}

}  // namespace

int main(int argc, char** argv) {
  calibration::CalibrateOptions options;
  std::string input, out, print_board, squares = "8x6";
  double square_mm = 1000 * options.board.square_m, marker_mm = 1000 * options.board.marker_m;
  double dpi = 300;
  CLI::App app{"", "prism-calibrate"};
  cli::Setup(&app, "calibrates the camera and its three coloured lights from images of a ChArUco board",
             {"prism-calibrate DIR [--out camera.yaml] [board options]",
              "prism-calibrate --print-board board.png [--dpi 300] [board options]"},
             kNotes);
  app.add_option("input", input, "the capture folder (layout below)")->type_name("DIR");
  app.add_option("--out", out, "the calibration to write (default: DIR/camera.yaml)")->type_name("FILE");
  app.add_option("--squares", squares, "chessboard squares across x down")->type_name("XxY");
  app.add_option("--square-mm", square_mm, "printed side of a chessboard square, millimetres (measure it)")
      ->type_name("MM");
  app.add_option("--marker-mm", marker_mm, "printed side of an ArUco marker, millimetres")->type_name("MM");
  app.add_option("--dictionary", options.board.dictionary,
                 "ArUco dictionary: DICT_4X4_50, DICT_4X4_100, DICT_5X5_100, DICT_6X6_250")
      ->type_name("NAME");
  app.add_option("--white-albedo", options.white_albedo, "albedo of the board's paper, (0, 1] (office paper: ~0.85)")
      ->type_name("A");
  app.add_option("--min-views", options.min_intrinsics_views, "board views needed for the intrinsics, 3-1000")
      ->type_name("N");
  app.add_flag("--fit-k3", options.fit_k3, "also fit the radial term k3 (wide-angle lenses; needs many views)");
  app.add_option("--print-board", print_board, "write the board as a PNG to print at --dpi (10 mm white margin), exit")
      ->type_name("FILE");
  app.add_option("--dpi", dpi, "with --print-board: printer dots per inch, 72-1200")
      ->type_name("DPI")
      ->check(CLI::Range(72.0, 1200.0));
  if (const int exit = cli::Parse(&app, argc, argv); exit != cli::kContinue) return exit;
  {
    char extra;
    if (std::sscanf(squares.c_str(), "%dx%d%c", &options.board.squares_x, &options.board.squares_y, &extra) != 2)
      return Fail("--squares must look like 8x6 (see --help)", 2);
  }
  options.board.square_m = square_mm / 1000;
  options.board.marker_m = marker_mm / 1000;
  if (Status s = options.Check(); !s.ok()) return Fail(s.ToString() + " (see --help)", 2);

  if (!print_board.empty()) {
    const double texel_m = 0.0254 / dpi;
    const cv::Mat board = calibration::DrawBoard(options.board, texel_m, 0.01);
    cv::Mat rgb;
    cv::Mat channels[] = {board, board, board};
    cv::merge(channels, 3, rgb);
    if (Status s = WriteRgbImage(print_board, rgb); !s.ok()) return Fail(s.ToString());
    std::cout << JsonText({{"board", options.board.Describe()},
                           {"out", print_board},
                           {"dpi", dpi},
                           {"width_mm", rgb.cols * texel_m * 1000},
                           {"height_mm", rgb.rows * texel_m * 1000}});
    return 0;
  }
  if (input.empty()) return Fail("the capture folder DIR is required (see --help)", 2);
  if (out.empty()) out = (std::filesystem::path(input) / "camera.yaml").string();

  StatusOr<calibration::CalibrationReport> report = calibration::CalibrateRig(input, options);
  if (!report.ok()) return Fail(report.status().message());
  if (Status s = WriteCalibrationYaml(out, report->rig); !s.ok()) return Fail(s.ToString());
  // What prism-server and prism-slam will read: the same reader, so a file they reject is caught here.
  if (StatusOr<RigCalibration> back = ReadCalibrationYaml(out); !back.ok())
    return Fail("the written " + out + " does not read back: " + back.status().ToString());
  for (const std::string& w : report->warnings) std::cerr << "prism-calibrate: warning: " << w << "\n";
  std::cout << JsonText(Report(*report, out), 2);
  return 0;
}
