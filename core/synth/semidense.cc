#include "core/synth/semidense.h"

#include <cmath>
#include <random>
#include <sstream>

#include <opencv2/imgproc.hpp>

namespace prism::synth {

Status SemiDenseOptions::Check() const {
  std::ostringstream e;
  if (!(min_gradient >= 0 && min_gradient <= 255))
    e << "SemiDenseOptions.min_gradient = " << min_gradient << "; violated: in [0, 255]";
  else if (!(relative_noise >= 0 && relative_noise <= 0.5))
    e << "SemiDenseOptions.relative_noise = " << relative_noise << "; violated: in [0, 0.5]";
  else if (!(scale > 0)) e << "SemiDenseOptions.scale = " << scale << "; violated: > 0";
  else if (!(dropout >= 0 && dropout < 1)) e << "SemiDenseOptions.dropout = " << dropout << "; violated: in [0, 1)";
  else if (!(outlier_fraction >= 0 && outlier_fraction <= 0.5))
    e << "SemiDenseOptions.outlier_fraction = " << outlier_fraction << "; violated: in [0, 0.5]";
  if (e.str().empty()) return Status::Ok();
  return InvalidArgumentError(e.str());
}

InverseDepthMap SimulateSemiDenseDepth(const cv::Mat& depth, const cv::Mat& rgb, const SemiDenseOptions& o) {
  cv::Mat grey;
  cv::cvtColor(rgb, grey, cv::COLOR_RGB2GRAY);
  grey.convertTo(grey, CV_32F);
  InverseDepthMap out;
  out.inverse_depth = cv::Mat(depth.size(), CV_32F, cv::Scalar(0));
  out.variance = cv::Mat(depth.size(), CV_32F, cv::Scalar(0));
  std::mt19937 rng(o.seed);
  std::normal_distribution<double> gauss(0, 1);
  std::uniform_real_distribution<double> uni(0, 1);
  for (int y = 1; y < depth.rows - 1; ++y)
    for (int x = 1; x < depth.cols - 1; ++x) {
      const float d = depth.at<float>(y, x);
      if (!(d > 0)) continue;
      const double gx = 0.5 * (grey.at<float>(y, x + 1) - grey.at<float>(y, x - 1));
      const double gy = 0.5 * (grey.at<float>(y + 1, x) - grey.at<float>(y - 1, x));
      if (std::sqrt(gx * gx + gy * gy) < o.min_gradient) continue;
      if (uni(rng) < o.dropout) continue;
      // Depth in SLAM units is depth_m / scale, so inverse depth is scale / depth_m.
      const double id = o.scale / d;
      double noisy = id * (1.0 + o.relative_noise * gauss(rng));
      if (uni(rng) < o.outlier_fraction) noisy = id * (1.0 + 0.3 * (2 * uni(rng) - 1));
      if (!(noisy > 0)) continue;
      out.inverse_depth.at<float>(y, x) = static_cast<float>(noisy);
      const double sd = std::max(1e-6, o.relative_noise * id);
      out.variance.at<float>(y, x) = static_cast<float>(sd * sd);
    }
  return out;
}

}  // namespace prism::synth
