// Procedural solid textures: albedo as a function of a 3D point in the object frame, so surfaces
// need no UV maps. Deterministic for a seed.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include <Eigen/Core>

namespace prism::synth {

// Smooth value noise in [0, 1] with unit feature size (trilinear on a hashed lattice, smoothstep).
double ValueNoise(const Eigen::Vector3d& p, uint32_t seed);
// Sum of `octaves` octaves of ValueNoise, normalised to [0, 1].
double FractalNoise(const Eigen::Vector3d& p, uint32_t seed, int octaves);
// Index of the Voronoi cell (jittered unit lattice) containing p: piecewise-constant regions with
// sharp boundaries, for multi-coloured objects. Returns a hash of the cell.
uint32_t VoronoiCell(const Eigen::Vector3d& p, uint32_t seed);

enum class AlbedoKind {
  kUniform,     // one albedo everywhere
  kTextured,    // base albedo modulated in brightness by fractal noise (chromaticity constant)
  kMultiColor,  // regions of constant albedo drawn from a palette (Voronoi cells)
  kImage,       // base albedo times a grey image on the object's z = 0 plane (a printed target)
};

// A grey image lying on the object's plane z = 0, centred on the origin, x along columns and y along
// rows; `texel_m` metres per texel. Sampled bilinearly; outside the image it is clamped to the edge.
struct ImageTexture {
  int width = 0;
  int height = 0;
  double texel_m = 0.001;
  std::vector<float> values;  // row-major, in [0, 1]

  double Sample(double x_m, double y_m) const;
};

// Albedo per light band (red, green, blue light), in [0, 1].
struct AlbedoOptions {
  AlbedoKind kind = AlbedoKind::kUniform;
  Eigen::Vector3d base = Eigen::Vector3d(0.8, 0.8, 0.8);
  std::vector<Eigen::Vector3d> palette;  // kMultiColor
  double feature_size_m = 0.05;          // texture wavelength / region size
  double contrast = 0.5;                 // kTextured: brightness varies in [1 - contrast, 1]
  int octaves = 3;                       // kTextured
  uint32_t seed = 1;
  std::shared_ptr<const ImageTexture> image;  // kImage

  Eigen::Vector3d Evaluate(const Eigen::Vector3d& point_in_object) const;
};

}  // namespace prism::synth
