// Calibration captures rendered with known truth (core/synth's renderer): the ChArUco board as a
// textured plane at random poses, in CalibrateRig's folder layout (calibrate.h), for tests and
// `prism-synth --charuco-board`.
#pragma once

#include <cstdint>
#include <string>

#include "core/calibration/charuco_board.h"
#include "core/io/calibration_io.h"
#include "core/synth/renderer.h"
#include "core/util/status.h"

namespace prism::calibration {

struct SyntheticCaptureOptions {
  // The printed board.
  CharucoBoardOptions board;
  // White paper margin around the chessboard, metres, in [0, 0.2].
  double margin_m = 0.015;
  // Albedo of the paper and of the ink, in [0, 1], ink < paper.
  double white_albedo = 0.85;
  double ink_albedo = 0.04;
  // Views under all lights for the intrinsics, and board poses per light folder, each in [1, 200].
  int intrinsics_views = 10;
  int light_views = 8;
  // Board-centre distances, metres: intrinsics views and light views (nearer light views saturate).
  double min_distance_m = 0.3;
  double max_distance_m = 1.0;
  double min_light_distance_m = 0.45;
  // Largest tilt of the board away from facing the camera, degrees, in [0, 70].
  double max_tilt_deg = 40;
  // Sensor noise and pixel-area integration as in the renderer; shadows and specularity off.
  synth::RenderOptions render;
  // Texture resolution of the printed board, metres per texel, in (0, 0.005].
  double texel_m = 0.00025;
  // Board poses and noise.
  uint32_t seed = 1;
  // Lights whose folder is rendered dark (bit l: light l off throughout), for bad-input tests.
  int dark_lights = 0;

  Status Check() const;
};

// Writes DIR/intrinsics/NNN.png, DIR/lights/{red,green,blue,all}/NNN.png (the same board poses in each
// light folder, as when one holds the board still and switches lights) and DIR/truth.yaml (the rig).
Status WriteSyntheticCaptures(const RigCalibration& rig, const SyntheticCaptureOptions& options,
                              const std::string& dir);

}  // namespace prism::calibration
