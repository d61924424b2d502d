// Summary statistics of error lists, with numpy's conventions so numbers match the public Python tools.
#pragma once

#include <cstddef>
#include <vector>

namespace prism {

// Median of the values (mean of the two middle ones for an even count, as numpy.median); 0 when empty.
double Median(std::vector<double> values);

// Statistics of a list of errors (std_dev is the population standard deviation, numpy.std). All zero
// when empty.
struct ErrorStatistics {
  size_t count = 0;
  double rmse = 0.0;
  double mean = 0.0;
  double median = 0.0;
  double std_dev = 0.0;
  double min = 0.0;
  double max = 0.0;
};
ErrorStatistics ComputeErrorStatistics(const std::vector<double>& errors);

}  // namespace prism
