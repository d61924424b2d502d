#include "core/eval/statistics.h"

#include <algorithm>
#include <cmath>

namespace prism {

double Median(std::vector<double> values) {
  if (values.empty()) return 0.0;
  const size_t mid = values.size() / 2;
  std::nth_element(values.begin(), values.begin() + mid, values.end());
  const double upper = values[mid];
  if (values.size() % 2 == 1) return upper;
  const double lower = *std::max_element(values.begin(), values.begin() + mid);
  return 0.5 * (lower + upper);
}

ErrorStatistics ComputeErrorStatistics(const std::vector<double>& errors) {
  ErrorStatistics s;
  s.count = errors.size();
  if (errors.empty()) return s;
  const double n = static_cast<double>(errors.size());
  double sum = 0.0;
  double sum_sq = 0.0;
  s.min = errors[0];
  s.max = errors[0];
  for (double e : errors) {
    sum += e;
    sum_sq += e * e;
    s.min = std::min(s.min, e);
    s.max = std::max(s.max, e);
  }
  s.mean = sum / n;
  s.rmse = std::sqrt(sum_sq / n);
  double variance = 0.0;
  for (double e : errors) variance += (e - s.mean) * (e - s.mean);
  s.std_dev = std::sqrt(variance / n);
  s.median = Median(errors);
  return s;
}

}  // namespace prism
