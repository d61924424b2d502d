// The printed ChArUco calibration board (OpenCV's aruco module): its layout, drawing, detection in
// an image, and the points of its white paper that the light fit samples.
// Board frame: origin at the top-left corner of the chessboard, x along the columns, y down the
// rows, z into the board (the printed side faces -z), metres.
#pragma once

#include <string>
#include <vector>

#include <Eigen/Core>
#include <opencv2/aruco/charuco.hpp>
#include <opencv2/core.hpp>

#include "core/util/status.h"

namespace prism::calibration {

struct CharucoBoardOptions {
  // Chessboard squares along x (columns) and y (rows), each in [3, 100]. The default fills an A3 sheet.
  int squares_x = 8;
  int squares_y = 6;
  // Side of a chessboard square and of an ArUco marker as printed, metres (marker < square).
  double square_m = 0.045;
  double marker_m = 0.034;
  // ArUco dictionary: DICT_4X4_50, DICT_4X4_100, DICT_5X5_100, DICT_6X6_250 (enough markers needed).
  std::string dictionary = "DICT_4X4_50";

  Status Check() const;
  // "7x5 squares of 40 mm, markers 30 mm, DICT_5X5_100", for messages.
  std::string Describe() const;
};

// OpenCV's board for `options` (which must pass Check()).
cv::Ptr<cv::aruco::CharucoBoard> MakeBoard(const CharucoBoardOptions& options);

// The board as printed: CV_8U, 255 white paper, 0 ink, `texel_m` metres per pixel, with a white
// paper margin of `margin_m` around the chessboard. Texel (0, 0) of the chessboard proper starts at
// board point (0, 0).
cv::Mat DrawBoard(const CharucoBoardOptions& options, double texel_m, double margin_m);

// Chessboard corners found in an image: ids index board->chessboardCorners.
struct BoardDetection {
  std::vector<cv::Point2f> corners;
  std::vector<int> ids;
  int markers = 0;  // ArUco markers found
};

// Detects the board in an 8-bit image (any channels; colour is summed and stretched to the full
// range, so an image lit by one coloured light works).
BoardDetection DetectBoard(const cv::Mat& image, const cv::Ptr<cv::aruco::CharucoBoard>& board);

// A point of the board frame (z = 0) on white paper and its distance to the nearest ink or the board's
// outer edge, metres.
struct WhitePoint {
  Eigen::Vector2d point;
  double ink_distance_m = 0;
};

// The white-paper points at least `inset_m` from any ink or the board's outer edge, on a grid of `spacing_m`.
std::vector<WhitePoint> WhitePaperPoints(const CharucoBoardOptions& options, double spacing_m, double inset_m);

}  // namespace prism::calibration
