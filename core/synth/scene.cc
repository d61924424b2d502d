#include "core/synth/scene.h"

#include <cmath>
#include <limits>

namespace prism::synth {

int Scene::AddObject(SceneObject object) {
  Bound b;
  b.centre = object.world_from_object.translation;
  switch (object.shape) {
    case ShapeKind::kPlane:
      b.radius = object.half_extents_m.head<2>().norm();
      break;
    case ShapeKind::kSphere:
      b.radius = object.radius_m;
      break;
    case ShapeKind::kBox:
      b.radius = object.half_extents_m.norm();
      break;
    case ShapeKind::kMesh: {
      const Eigen::Vector3d lo = object.mesh->bounds_min(), hi = object.mesh->bounds_max();
      b.centre = object.world_from_object * (0.5 * (lo + hi));
      b.radius = 0.5 * (hi - lo).norm();
      break;
    }
  }
  objects_.push_back(std::move(object));
  bounds_.push_back(b);
  return static_cast<int>(objects_.size()) - 1;
}

bool Scene::IntersectObject(int i, const Eigen::Vector3d& origin, const Eigen::Vector3d& dir, double t_min,
                            double t_max, SurfaceHit* hit, bool any_hit) const {
  // Bounding-sphere reject.
  const Bound& b = bounds_[i];
  const Eigen::Vector3d oc = origin - b.centre;
  const double half_b = oc.dot(dir);
  const double disc = half_b * half_b - (oc.squaredNorm() - b.radius * b.radius);
  if (disc < 0) return false;
  const double sq = std::sqrt(disc);
  if (-half_b + sq <= t_min || -half_b - sq >= t_max) return false;

  const SceneObject& obj = objects_[i];
  const Eigen::Quaterniond object_from_world_rot = obj.world_from_object.rotation.conjugate();
  const Eigen::Vector3d o = object_from_world_rot * (origin - obj.world_from_object.translation);
  const Eigen::Vector3d d = object_from_world_rot * dir;
  double t = std::numeric_limits<double>::infinity();
  Eigen::Vector3d n_obj = Eigen::Vector3d::UnitZ(), g_obj = Eigen::Vector3d::UnitZ();
  switch (obj.shape) {
    case ShapeKind::kPlane: {
      if (std::abs(d.z()) < 1e-12) return false;
      const double tp = -o.z() / d.z();
      if (tp <= t_min || tp >= t_max) return false;
      const Eigen::Vector3d p = o + tp * d;
      if (std::abs(p.x()) > obj.half_extents_m.x() || std::abs(p.y()) > obj.half_extents_m.y()) return false;
      t = tp;
      n_obj = g_obj = Eigen::Vector3d::UnitZ();
      break;
    }
    case ShapeKind::kSphere: {
      const double hb = o.dot(d);
      const double c = o.squaredNorm() - obj.radius_m * obj.radius_m;
      const double ds = hb * hb - c;
      if (ds < 0) return false;
      const double s = std::sqrt(ds);
      double tp = -hb - s;
      if (tp <= t_min) tp = -hb + s;
      if (tp <= t_min || tp >= t_max) return false;
      t = tp;
      n_obj = g_obj = (o + tp * d) / obj.radius_m;
      break;
    }
    case ShapeKind::kBox: {
      double t0 = t_min, t1 = t_max;
      int axis0 = -1, axis1 = -1;
      for (int a = 0; a < 3; ++a) {
        if (std::abs(d[a]) < 1e-15) {
          if (std::abs(o[a]) > obj.half_extents_m[a]) return false;
          continue;
        }
        double n = (-obj.half_extents_m[a] - o[a]) / d[a];
        double f = (obj.half_extents_m[a] - o[a]) / d[a];
        if (n > f) std::swap(n, f);
        if (n > t0) {
          t0 = n;
          axis0 = a;
        }
        if (f < t1) {
          t1 = f;
          axis1 = a;
        }
        if (t0 > t1) return false;
      }
      int axis;
      if (axis0 >= 0 && t0 > t_min) {
        t = t0;
        axis = axis0;
      } else if (axis1 >= 0 && t1 < t_max) {
        t = t1;
        axis = axis1;
      } else {
        return false;
      }
      const Eigen::Vector3d p = o + t * d;
      n_obj = Eigen::Vector3d::Zero();
      n_obj[axis] = p[axis] > 0 ? 1.0 : -1.0;
      g_obj = n_obj;
      break;
    }
    case ShapeKind::kMesh: {
      if (any_hit) return obj.mesh->Occluded(o, d, t_min, t_max);
      RayHit rh;
      if (!obj.mesh->Intersect(o, d, t_min, t_max, &rh)) return false;
      t = rh.t;
      n_obj = rh.normal;
      g_obj = rh.geometric_normal;
      break;
    }
  }
  if (any_hit) return true;
  hit->t = t;
  hit->object = i;
  hit->point_in_object = o + t * d;
  hit->point_in_world = origin + t * dir;
  Eigen::Vector3d n = obj.world_from_object.rotation * n_obj;
  Eigen::Vector3d g = obj.world_from_object.rotation * g_obj;
  // Face the viewer: the geometric normal decides the side; the shading normal follows it.
  if (g.dot(dir) > 0) {
    g = -g;
    n = -n;
  }
  hit->normal_in_world = n;
  hit->geometric_normal_in_world = g;
  return true;
}

bool Scene::Intersect(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir, double t_min, double t_max,
                      SurfaceHit* hit) const {
  bool found = false;
  double closest = t_max;
  for (int i = 0; i < static_cast<int>(objects_.size()); ++i) {
    SurfaceHit h;
    if (IntersectObject(i, origin, dir, t_min, closest, &h, false)) {
      closest = h.t;
      *hit = h;
      found = true;
    }
  }
  return found;
}

bool Scene::Occluded(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir, double t_min, double t_max) const {
  for (int i = 0; i < static_cast<int>(objects_.size()); ++i)
    if (IntersectObject(i, origin, dir, t_min, t_max, nullptr, true)) return true;
  return false;
}

void Scene::ObjectBounds(Eigen::Vector3d* centre, double* radius) const {
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e300), hi = Eigen::Vector3d::Constant(-1e300);
  bool any = false;
  for (size_t i = 0; i < objects_.size(); ++i) {
    if (!objects_[i].is_object) continue;
    any = true;
    lo = lo.cwiseMin(bounds_[i].centre - Eigen::Vector3d::Constant(bounds_[i].radius));
    hi = hi.cwiseMax(bounds_[i].centre + Eigen::Vector3d::Constant(bounds_[i].radius));
  }
  if (!any) {
    *centre = Eigen::Vector3d::Zero();
    *radius = 0;
    return;
  }
  *centre = 0.5 * (lo + hi);
  *radius = 0.5 * (hi - lo).maxCoeff();
}

}  // namespace prism::synth
