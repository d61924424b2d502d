#include "core/calibration/charuco_board.h"

#include <cmath>
#include <sstream>

#include <opencv2/aruco.hpp>
#include <opencv2/imgproc.hpp>

namespace prism::calibration {
namespace {

struct DictionaryName {
  const char* name;
  cv::aruco::PREDEFINED_DICTIONARY_NAME id;
  int size;
};
constexpr DictionaryName kDictionaries[] = {{"DICT_4X4_50", cv::aruco::DICT_4X4_50, 50},
                                            {"DICT_4X4_100", cv::aruco::DICT_4X4_100, 100},
                                            {"DICT_5X5_100", cv::aruco::DICT_5X5_100, 100},
                                            {"DICT_6X6_250", cv::aruco::DICT_6X6_250, 250}};

const DictionaryName* FindDictionary(const std::string& name) {
  for (const DictionaryName& d : kDictionaries)
    if (name == d.name) return &d;
  return nullptr;
}

}  // namespace

Status CharucoBoardOptions::Check() const {
  std::ostringstream e;
  const DictionaryName* dict = FindDictionary(dictionary);
  if (!(squares_x >= 3 && squares_x <= 100))
    e << "CharucoBoardOptions.squares_x = " << squares_x << "; violated: in [3, 100]";
  else if (!(squares_y >= 3 && squares_y <= 100))
    e << "CharucoBoardOptions.squares_y = " << squares_y << "; violated: in [3, 100]";
  else if (!(square_m > 0 && square_m < 1))
    e << "CharucoBoardOptions.square_m = " << square_m << "; violated: in (0, 1)";
  else if (!(marker_m > 0 && marker_m < square_m))
    e << "CharucoBoardOptions.marker_m = " << marker_m << "; violated: in (0, square_m)";
  else if (!dict)
    e << "CharucoBoardOptions.dictionary = " << dictionary
      << "; violated: one of DICT_4X4_50, DICT_4X4_100, DICT_5X5_100, DICT_6X6_250";
  else if (squares_x * squares_y / 2 > dict->size)
    e << "CharucoBoardOptions.dictionary = " << dictionary << "; violated: has " << dict->size
      << " markers, the board needs " << squares_x * squares_y / 2;
  if (e.str().empty()) return Status::Ok();
  return InvalidArgumentError(e.str());
}

std::string CharucoBoardOptions::Describe() const {
  std::ostringstream s;
  s << squares_x << "x" << squares_y << " squares of " << square_m * 1000 << " mm, markers " << marker_m * 1000
    << " mm, " << dictionary;
  return s.str();
}

cv::Ptr<cv::aruco::CharucoBoard> MakeBoard(const CharucoBoardOptions& options) {
  const DictionaryName* dict = FindDictionary(options.dictionary);
  return cv::aruco::CharucoBoard::create(options.squares_x, options.squares_y, static_cast<float>(options.square_m),
                                         static_cast<float>(options.marker_m),
                                         cv::aruco::getPredefinedDictionary(dict ? dict->id : cv::aruco::DICT_5X5_100));
}

cv::Mat DrawBoard(const CharucoBoardOptions& options, double texel_m, double margin_m) {
  const int w = static_cast<int>(std::lround(options.squares_x * options.square_m / texel_m));
  const int h = static_cast<int>(std::lround(options.squares_y * options.square_m / texel_m));
  const int margin = static_cast<int>(std::lround(margin_m / texel_m));
  cv::Mat board;
  MakeBoard(options)->draw(cv::Size(w, h), board, 0, 1);
  cv::Mat out(h + 2 * margin, w + 2 * margin, CV_8U, cv::Scalar(255));
  board.copyTo(out(cv::Rect(margin, margin, w, h)));
  return out;
}

BoardDetection DetectBoard(const cv::Mat& image, const cv::Ptr<cv::aruco::CharucoBoard>& board) {
  cv::Mat grey;
  if (image.channels() == 1) {
    image.convertTo(grey, CV_32F);
  } else {
    cv::Mat f;
    image.convertTo(f, CV_32F);
    cv::transform(f, grey, cv::Matx13f(1, 1, 1));
  }
  cv::normalize(grey, grey, 0, 255, cv::NORM_MINMAX);
  grey.convertTo(grey, CV_8U);
  BoardDetection d;
  std::vector<std::vector<cv::Point2f>> marker_corners;
  std::vector<int> marker_ids;
  cv::Ptr<cv::aruco::DetectorParameters> params = cv::aruco::DetectorParameters::create();
  params->cornerRefinementMethod = cv::aruco::CORNER_REFINE_NONE;  // the ChArUco corners are refined instead
  cv::aruco::detectMarkers(grey, board->dictionary, marker_corners, marker_ids, params);
  d.markers = static_cast<int>(marker_ids.size());
  if (marker_ids.empty()) return d;
  cv::aruco::interpolateCornersCharuco(marker_corners, marker_ids, grey, board, d.corners, d.ids);
  return d;
}

std::vector<WhitePoint> WhitePaperPoints(const CharucoBoardOptions& options, double spacing_m, double inset_m) {
  const double texel_m = std::min(0.0005, options.square_m / 40);
  const cv::Mat printed = DrawBoard(options, texel_m, 0.0);
  cv::Mat white = printed > 127;
  // Paper beyond the board's edge is not known to be there: treat it as ink.
  cv::Mat padded, distance;
  cv::copyMakeBorder(white, padded, 1, 1, 1, 1, cv::BORDER_CONSTANT, cv::Scalar(0));
  cv::distanceTransform(padded, distance, cv::DIST_L2, cv::DIST_MASK_PRECISE);
  std::vector<WhitePoint> points;
  const double width_m = options.squares_x * options.square_m, height_m = options.squares_y * options.square_m;
  for (double y = 0.5 * spacing_m; y < height_m; y += spacing_m) {
    for (double x = 0.5 * spacing_m; x < width_m; x += spacing_m) {
      const int u = static_cast<int>(x / texel_m) + 1, v = static_cast<int>(y / texel_m) + 1;
      if (v >= distance.rows || u >= distance.cols) continue;
      const double ink_distance_m = distance.at<float>(v, u) * texel_m;
      if (ink_distance_m >= inset_m) points.push_back({Eigen::Vector2d(x, y), ink_distance_m});
    }
  }
  return points;
}

}  // namespace prism::calibration
