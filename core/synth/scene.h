// A renderable scene: a textured ground plane and objects (analytic spheres and boxes, triangle
// meshes), each with a Lambertian albedo (texture.h) and optional mild specularity.
// World frame: z up, the ground is the plane z = 0.
#pragma once

#include <memory>
#include <vector>

#include <Eigen/Core>

#include "core/geometry/rigid3.h"
#include "core/synth/mesh_bvh.h"
#include "core/synth/texture.h"

namespace prism::synth {

enum class ShapeKind { kPlane, kSphere, kBox, kMesh };

struct SceneObject {
  ShapeKind shape = ShapeKind::kSphere;
  Rigid3d world_from_object;
  double radius_m = 0.1;                                             // kSphere
  Eigen::Vector3d half_extents_m = Eigen::Vector3d::Constant(0.05);  // kBox; kPlane uses x, y (z ignored)
  std::shared_ptr<const MeshBvh> mesh;                               // kMesh, vertices in metres, object frame
  AlbedoOptions albedo;
  double specular = 0.0;    // Blinn-Phong weight (0 = Lambertian)
  double shininess = 40.0;  // Blinn-Phong exponent
  bool is_object = true;    // false for the ground: mask label 64 instead of 255
};

struct SurfaceHit {
  double t = 0;  // ray parameter (distance when the direction is unit)
  int object = -1;
  Eigen::Vector3d point_in_world;
  Eigen::Vector3d normal_in_world;            // shading normal, facing the ray origin
  Eigen::Vector3d geometric_normal_in_world;  // facing the ray origin
  Eigen::Vector3d point_in_object;            // for the albedo texture
};

class Scene {
 public:
  int AddObject(SceneObject object);
  const std::vector<SceneObject>& objects() const { return objects_; }

  // Closest surface along origin + t * dir (dir unit), t in (t_min, t_max).
  bool Intersect(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir, double t_min, double t_max,
                 SurfaceHit* hit) const;
  // True when any surface lies on the segment (t_min, t_max): shadow rays.
  bool Occluded(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir, double t_min, double t_max) const;

  // Centre and radius of a sphere bounding all non-ground objects (the "object" of the scene).
  void ObjectBounds(Eigen::Vector3d* centre, double* radius) const;

 private:
  struct Bound {
    Eigen::Vector3d centre;  // world
    double radius;           // infinite for planes
  };
  bool IntersectObject(int i, const Eigen::Vector3d& origin, const Eigen::Vector3d& dir, double t_min, double t_max,
                       SurfaceHit* hit, bool any_hit) const;

  std::vector<SceneObject> objects_;
  std::vector<Bound> bounds_;
};

}  // namespace prism::synth
