// Procedural triangle meshes (object frame, metres) and mesh normalisation.
#pragma once

#include "core/geometry/rigid3.h"
#include "core/geometry/triangle_mesh.h"

namespace prism::synth {

// Torus around the object z axis: major radius R, minor radius r; analytic vertex normals.
TriangleMesh MakeTorus(double major_radius_m, double minor_radius_m, int major_segments, int minor_segments);

// Height field z = h(x, y) >= 0 over [-half, half]^2 with `bumps` smooth Gaussian bumps of up to
// `height_m` (seeded), closed by a skirt down to z = 0; analytic vertex normals on the top.
TriangleMesh MakeRelief(double half_size_m, double height_m, int bumps, int resolution, uint32_t seed);

// Rotates the mesh so its `up_axis` (0 = x, 1 = y, 2 = z; negative values flip: -1 = -x ... use
// up_sign) points along +z, scales it so the largest extent is `size_m`, and moves it so that it is
// centred over the origin in x, y with its lowest point at z = 0.
void NormaliseMesh(int up_axis, double up_sign, double size_m, TriangleMesh* mesh);

}  // namespace prism::synth
