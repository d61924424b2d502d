#include "core/photometric/superpixels.h"

#include <algorithm>
#include <cfloat>
#include <vector>

#include "core/util/check.h"

namespace prism {
namespace {

// One row of a centre's window: the SLICO distance of each pixel to the centre (colour over the
// centre's normaliser plus squared image distance over the grid step squared), and the pixel joins
// the centre when closer than to any centre so far. Branch-free on plain arrays: vectorised.
void AssignRow(int x0, int x1, float cl, float ca, float cb, float cx, float dy, float norm, float spatial_weight,
               int k, const float* __restrict p0, const float* __restrict p1, const float* __restrict p2,
               float* __restrict dist, float* __restrict dcol, int* __restrict label) {
  const float dy2 = dy * dy;
  for (int x = x0; x < x1; ++x) {
    const float d0 = p0[x] - cl, d1 = p1[x] - ca, d2 = p2[x] - cb;
    const float dc = d0 * d0 + d1 * d1 + d2 * d2;
    const float dx = static_cast<float>(x) - cx;
    const float d = dc / norm + (dx * dx + dy2) / spatial_weight;
    dcol[x] = dc;
    const float old = dist[x];
    const bool closer = d < old;
    dist[x] = closer ? d : old;
    // An integer mask rather than a select on the float comparison, which GCC does not vectorise.
    const int mask = -static_cast<int>(closer);
    label[x] = (k & mask) | (label[x] & ~mask);
  }
}

}  // namespace

int SlicSuperpixels(const cv::Mat& lab, int step_px, int iterations, cv::Mat* labels) {
  PRISM_CHECK(lab.type() == CV_8UC3 && lab.cols >= 2 && lab.rows >= 2) << "SlicSuperpixels: CV_8UC3 of >= 2x2";
  PRISM_CHECK(step_px >= 2) << "SlicSuperpixels: step_px = " << step_px << "; violated: >= 2";
  const int w = lab.cols, h = lab.rows, s = step_px;
  const size_t num_pixels = static_cast<size_t>(w) * h;
  // Colour planes as float, row-major.
  std::vector<float> plane[3];
  for (auto& p : plane) p.resize(num_pixels);
  for (int y = 0; y < h; ++y) {
    const cv::Vec3b* row = lab.ptr<cv::Vec3b>(y);
    for (int x = 0; x < w; ++x)
      for (int c = 0; c < 3; ++c) plane[c][static_cast<size_t>(y) * w + x] = row[x][c];
  }
  // Edge magnitude: squared central differences summed over the channels (reflected at the border).
  auto reflect = [](int i, int n) { return i < 0 ? std::min(1, n - 1) : (i >= n ? std::max(0, n - 2) : i); };
  auto edge = [&](int x, int y) {
    const size_t l = static_cast<size_t>(y) * w + reflect(x - 1, w), r = static_cast<size_t>(y) * w + reflect(x + 1, w);
    const size_t u = static_cast<size_t>(reflect(y - 1, h)) * w + x, d = static_cast<size_t>(reflect(y + 1, h)) * w + x;
    float gx = 0, gy = 0;
    for (int c = 0; c < 3; ++c) {
      const float dx = plane[c][r] - plane[c][l], dy = plane[c][d] - plane[c][u];
      gx += dx * dx;
      gy += dy * dy;
    }
    return gx + gy;
  };
  // Seeds on a hexagonal grid (odd rows shifted by half a step); a seed moves to the neighbour with
  // the lowest edge magnitude when that neighbour is diagonal (as OpenCV does).
  struct Centre {
    float c[3];
    float x, y;
  };
  std::vector<Centre> centres;
  for (int j = 0, row = 0; j * s + s / 2 <= h - 1; ++j, ++row)
    for (int i = 0; i * s + ((s / 2) << (row & 1)) <= w - 1; ++i) {
      const int ox = i * s + ((s / 2) << (row & 1)), oy = j * s + s / 2;
      int bx = ox, by = oy;
      static constexpr int kDx[8] = {-1, -1, 0, 1, 1, 1, 0, -1};
      static constexpr int kDy[8] = {0, -1, -1, -1, 0, 1, 1, 1};
      for (int k = 0; k < 8; ++k) {
        const int nx = ox + kDx[k], ny = oy + kDy[k];
        if (nx >= 0 && nx < w && ny >= 0 && ny < h && edge(nx, ny) < edge(bx, by)) {
          bx = nx;
          by = ny;
        }
      }
      if (bx == ox || by == oy) {
        bx = ox;
        by = oy;
      }
      const size_t p = static_cast<size_t>(by) * w + bx;
      centres.push_back({{plane[0][p], plane[1][p], plane[2][p]}, static_cast<float>(bx), static_cast<float>(by)});
    }
  const int n = static_cast<int>(centres.size());
  std::vector<int> label(num_pixels, 0);
  std::vector<float> distance(num_pixels);
  // Colour distance to the last centre whose window covered the pixel: the running maximum over a
  // superpixel's pixels (across iterations) is that superpixel's colour normaliser.
  std::vector<float> colour_distance(num_pixels, FLT_MAX);
  std::vector<float> max_colour(n, FLT_MIN);  // the first iteration is (almost) colour only
  const float spatial_weight = static_cast<float>(s) * s;
  std::vector<float> sum(static_cast<size_t>(n) * 5);
  std::vector<int> count(n);
  for (int iter = 0; iter < iterations; ++iter) {
    std::fill(distance.begin(), distance.end(), FLT_MAX);
    for (int k = 0; k < n; ++k) {
      const Centre& c = centres[k];
      const float norm = max_colour[k];
      const int y0 = std::max(0, static_cast<int>(c.y) - s), y1 = std::min(h, static_cast<int>(c.y) + s);
      const int x0 = std::max(0, static_cast<int>(c.x) - s), x1 = std::min(w, static_cast<int>(c.x) + s);
      for (int y = y0; y < y1; ++y) {
        const size_t base = static_cast<size_t>(y) * w;
        const float* p0 = &plane[0][base];
        const float* p1 = &plane[1][base];
        const float* p2 = &plane[2][base];
        float* dist = &distance[base];
        float* dcol = &colour_distance[base];
        int* lab_row = &label[base];
        AssignRow(x0, x1, c.c[0], c.c[1], c.c[2], c.x, y - c.y, norm, spatial_weight, k, p0, p1, p2, dist, dcol,
                  lab_row);
      }
    }
    std::fill(sum.begin(), sum.end(), 0.f);
    std::fill(count.begin(), count.end(), 0);
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x) {
        const size_t i = static_cast<size_t>(y) * w + x;
        const int k = label[i];
        max_colour[k] = std::max(max_colour[k], colour_distance[i]);
        // Integer-valued, so the float sums are exact (below 2^24) in any order.
        float* acc = &sum[static_cast<size_t>(k) * 5];
        acc[0] += plane[0][i];
        acc[1] += plane[1][i];
        acc[2] += plane[2][i];
        acc[3] += x;
        acc[4] += y;
        count[k]++;
      }
    for (int k = 0; k < n; ++k) {
      const float c = static_cast<float>(std::max(1, count[k]));
      const float* acc = &sum[static_cast<size_t>(k) * 5];
      centres[k] = {{acc[0] / c, acc[1] / c, acc[2] / c}, acc[3] / c, acc[4] / c};
    }
  }
  *labels = cv::Mat(h, w, CV_32S);
  for (int y = 0; y < h; ++y) std::copy_n(&label[static_cast<size_t>(y) * w], w, labels->ptr<int>(y));
  return n;
}

}  // namespace prism
