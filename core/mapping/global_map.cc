#include "core/mapping/global_map.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <string>

#include "core/util/check.h"

namespace prism {
namespace {

constexpr int kKeyBits = 21;
constexpr uint64_t kKeyMask = (uint64_t{1} << kKeyBits) - 1;

bool IsFinite(const Eigen::Vector3f& v) { return std::isfinite(v.x()) && std::isfinite(v.y()) && std::isfinite(v.z()); }

// Normals shorter than 0.5 (zero = "none" by convention) or non-finite do not vote.
bool HasValidNormal(const Eigen::Vector3f& n) { return IsFinite(n) && n.squaredNorm() > 0.25f; }

size_t SlotOf(VoxelKey key, size_t mask) {
  // Fibonacci hashing: the high bits of the product are well mixed.
  return static_cast<size_t>((key * 0x9E3779B97F4A7C15ull) >> 32) & mask;
}

VoxelKey PackUnchecked(const Eigen::Vector3i& voxel) {
  return (static_cast<uint64_t>(static_cast<uint32_t>(voxel.x())) & kKeyMask) |
         ((static_cast<uint64_t>(static_cast<uint32_t>(voxel.y())) & kKeyMask) << kKeyBits) |
         ((static_cast<uint64_t>(static_cast<uint32_t>(voxel.z())) & kKeyMask) << (2 * kKeyBits));
}

struct Identity {
  Eigen::Vector3f Point(const Eigen::Vector3f& p) const { return p; }
  Eigen::Vector3f Normal(const Eigen::Vector3f& n) const { return n; }
};

struct RigidTransform {
  Eigen::Matrix3f r;
  Eigen::Vector3f t;
  Eigen::Vector3f Point(const Eigen::Vector3f& p) const { return r * p + t; }
  Eigen::Vector3f Normal(const Eigen::Vector3f& n) const { return r * n; }
};

}  // namespace

Status MapOptions::Check() const {
  if (!(voxel_m >= 1e-5 && voxel_m <= 10.0)) {
    std::ostringstream s;
    s << "MapOptions.voxel_m = " << voxel_m << "; violated: in [1e-5, 10]";
    return InvalidArgumentError(s.str());
  }
  if (min_keyframes < 1 || min_keyframes > 1000)
    return InvalidArgumentError("MapOptions.min_keyframes = " + std::to_string(min_keyframes) +
                                "; violated: in [1, 1000]");
  return Status::Ok();
}

VoxelKey PackVoxelKey(const Eigen::Vector3i& voxel) {
  for (int a = 0; a < 3; ++a) {
    PRISM_CHECK(voxel[a] >= kMinVoxelCoordinate && voxel[a] <= kMaxVoxelCoordinate)
        << "voxel coordinate " << voxel[a] << " out of the key range";
  }
  return PackUnchecked(voxel);
}

Eigen::Vector3i UnpackVoxelKey(VoxelKey key) {
  Eigen::Vector3i v;
  for (int a = 0; a < 3; ++a) {
    const uint32_t bits = static_cast<uint32_t>((key >> (a * kKeyBits)) & kKeyMask);
    // Sign-extend the 21-bit two's complement value.
    v[a] = static_cast<int32_t>(bits << (32 - kKeyBits)) >> (32 - kKeyBits);
  }
  return v;
}

MapInsertStats& MapInsertStats::operator+=(const MapInsertStats& o) {
  merged_points += o.merged_points;
  new_voxels += o.new_voxels;
  skipped_non_finite += o.skipped_non_finite;
  skipped_bad_confidence += o.skipped_bad_confidence;
  skipped_out_of_range += o.skipped_out_of_range;
  return *this;
}

GlobalMap::GlobalMap(const MapOptions& options) : options_(options) {
  const Status status = options.Check();
  PRISM_CHECK(status.ok()) << status.ToString();
  inv_voxel_m_ = 1.0 / options_.voxel_m;
  slots_.resize(1024);
  recent_.resize(size_t{1} << (3 * kRecentBits));
}

bool GlobalMap::VoxelOf(const Eigen::Vector3f& point, Eigen::Vector3i* voxel) const {
  for (int a = 0; a < 3; ++a) {
    const double c = std::floor(static_cast<double>(point[a]) * inv_voxel_m_);
    // Also false for NaN and infinities.
    if (!(c >= static_cast<double>(kMinVoxelCoordinate) && c <= static_cast<double>(kMaxVoxelCoordinate))) {
      return false;
    }
    (*voxel)[a] = static_cast<int>(c);
  }
  return true;
}

uint32_t GlobalMap::Find(VoxelKey key) const {
  const size_t mask = slots_.size() - 1;
  for (size_t s = SlotOf(key, mask);; s = (s + 1) & mask) {
    const Slot& slot = slots_[s];
    if (slot.index == kEmptySlot) return kEmptySlot;
    if (slot.key == key) return slot.index;
  }
}

uint32_t GlobalMap::FindOrCreate(VoxelKey key, bool* created) {
  size_t mask = slots_.size() - 1;
  size_t s = SlotOf(key, mask);
  for (;; s = (s + 1) & mask) {
    const Slot& slot = slots_[s];
    if (slot.index == kEmptySlot) break;
    if (slot.key == key) {
      *created = false;
      return slot.index;
    }
  }
  PRISM_CHECK_LT(voxels_.size(), size_t{kEmptySlot}) << "too many voxels";
  const uint32_t index = static_cast<uint32_t>(voxels_.size());
  voxels_.emplace_back();
  voxels_.back().key = key;
  *created = true;
  if (2 * voxels_.size() > slots_.size()) {
    Rehash(2 * slots_.size());  // re-inserts every voxel, the new one included
  } else {
    slots_[s] = Slot{key, index};
  }
  return index;
}

void GlobalMap::Rehash(size_t capacity) {
  slots_.assign(capacity, Slot{});
  const size_t mask = capacity - 1;
  for (uint32_t i = 0; i < voxels_.size(); ++i) {
    size_t s = SlotOf(voxels_[i].key, mask);
    while (slots_[s].index != kEmptySlot) s = (s + 1) & mask;
    slots_[s] = Slot{voxels_[i].key, i};
  }
}

template <typename Transform>
StatusOr<MapInsertStats> GlobalMap::InsertImpl(const PointCloud& cloud, const Transform& to_world,
                                               uint64_t keyframe_id) {
  if (!cloud.IsConsistent()) {
    return InvalidArgumentError("GlobalMap::Insert: attribute arrays do not match the number of positions");
  }
  MapInsertStats stats;
  const bool has_normals = cloud.HasNormals();
  const bool has_colors = cloud.HasColors();
  const bool has_confidences = cloud.HasConfidences();
  // Neighbouring pixels often share a voxel: remember the last one to skip the hash lookup.
  VoxelKey last_key = 0;
  uint32_t last_index = kEmptySlot;
  for (size_t i = 0; i < cloud.size(); ++i) {
    const Eigen::Vector3f p = to_world.Point(cloud.positions[i]);
    if (!IsFinite(p)) {
      ++stats.skipped_non_finite;
      continue;
    }
    const float w = has_confidences ? cloud.confidences[i] : 1.0f;
    if (!(w > 0.0f) || !std::isfinite(w)) {
      ++stats.skipped_bad_confidence;
      continue;
    }
    Eigen::Vector3i v;
    if (!VoxelOf(p, &v)) {
      ++stats.skipped_out_of_range;
      continue;
    }
    const VoxelKey key = PackUnchecked(v);  // VoxelOf checked the range
    uint32_t index = last_index;
    if (index == kEmptySlot || key != last_key) {
      Slot& recent = recent_[RecentSlot(v)];
      if (recent.index != kEmptySlot && recent.key == key) {
        index = recent.index;
      } else {
        bool created = false;
        index = FindOrCreate(key, &created);
        if (created) ++stats.new_voxels;
        recent = Slot{key, index};
      }
      last_key = key;
      last_index = index;
    }
    Voxel& voxel = voxels_[index];
    voxel.weight += w;
    voxel.position += (w / voxel.weight) * (p - voxel.position);
    if (has_normals) {
      const Eigen::Vector3f& n = cloud.normals[i];
      if (HasValidNormal(n)) voxel.normal_sum += w * to_world.Normal(n.normalized());
    }
    if (has_colors) {
      voxel.color_sum += w * cloud.colors[i].cast<float>();
      voxel.color_weight += w;
    }
    if (voxel.observations == 0 || voxel.last_keyframe_id != keyframe_id) {
      if (++voxel.keyframes == static_cast<uint32_t>(options_.min_keyframes)) ++output_voxels_;
    }
    ++voxel.observations;
    voxel.last_keyframe_id = keyframe_id;
    if (!voxel.changed) {
      voxel.changed = true;
      changed_.push_back(index);
    }
    ++stats.merged_points;
  }
  has_normals_ = has_normals_ || (has_normals && stats.merged_points > 0);
  has_colors_ = has_colors_ || (has_colors && stats.merged_points > 0);
  totals_ += stats;
  return stats;
}

StatusOr<MapInsertStats> GlobalMap::Insert(const PointCloud& cloud_in_world, uint64_t keyframe_id) {
  return InsertImpl(cloud_in_world, Identity(), keyframe_id);
}

StatusOr<MapInsertStats> GlobalMap::Insert(const PointCloud& cloud, const Rigid3d& world_from_cloud,
                                           uint64_t keyframe_id) {
  if (!world_from_cloud.rotation.coeffs().allFinite() || !world_from_cloud.translation.allFinite()) {
    return InvalidArgumentError("GlobalMap::Insert: world_from_cloud is not finite");
  }
  RigidTransform t{world_from_cloud.RotationMatrix().cast<float>(), world_from_cloud.translation.cast<float>()};
  return InsertImpl(cloud, t, keyframe_id);
}

void GlobalMap::PrepareOutput(size_t n, PointCloud* cloud) const {
  cloud->positions.resize(n);
  cloud->normals.resize(has_normals_ ? n : 0);
  cloud->colors.resize(has_colors_ ? n : 0);
  cloud->confidences.resize(n);
}

void GlobalMap::WriteVoxel(const Voxel& v, size_t i, PointCloud* cloud) const {
  cloud->positions[i] = v.position;
  if (has_normals_) {
    const float norm_sq = v.normal_sum.squaredNorm();
    cloud->normals[i] = norm_sq > 0.0f ? Eigen::Vector3f(v.normal_sum / std::sqrt(norm_sq)) : Eigen::Vector3f::Zero();
  }
  if (has_colors_) {
    Eigen::Matrix<uint8_t, 3, 1> c = Eigen::Matrix<uint8_t, 3, 1>::Zero();
    if (v.color_weight > 0.0f) {
      // Means of values in [0, 255]: round half up, clamped against float round-off.
      const Eigen::Vector3f mean = v.color_sum * (1.0f / v.color_weight) + Eigen::Vector3f::Constant(0.5f);
      for (int a = 0; a < 3; ++a) c[a] = static_cast<uint8_t>(std::min(std::max(mean[a], 0.0f), 255.0f));
    }
    cloud->colors[i] = c;
  }
  cloud->confidences[i] = v.weight;
}

MapChunk GlobalMap::TakeChanges() {
  MapChunk chunk;
  chunk.sequence = ++chunk_sequence_;
  chunk.replaces_map = cleared_;
  cleared_ = false;
  const uint32_t min_keyframes = static_cast<uint32_t>(options_.min_keyframes);
  size_t n = 0;
  for (uint32_t index : changed_) n += voxels_[index].keyframes >= min_keyframes ? 1 : 0;
  PrepareOutput(n, &chunk.cloud);
  chunk.keys.resize(n);
  chunk.observations.resize(n);
  size_t i = 0;
  for (uint32_t index : changed_) {
    Voxel& v = voxels_[index];
    v.changed = false;
    if (v.keyframes < min_keyframes) continue;  // not in the output yet: sent once a later keyframe adds to it
    WriteVoxel(v, i, &chunk.cloud);
    chunk.keys[i] = v.key;
    chunk.observations[i] = v.observations;
    ++i;
  }
  changed_.clear();
  return chunk;
}

void GlobalMap::Clear() {
  voxels_.clear();
  slots_.assign(1024, Slot{});
  recent_.assign(recent_.size(), Slot{});
  changed_.clear();
  has_normals_ = false;
  has_colors_ = false;
  totals_ = MapInsertStats();
  output_voxels_ = 0;
  cleared_ = true;
}

PointCloud GlobalMap::ToPointCloud(double min_confidence, int min_observations) const {
  PointCloud cloud;
  const auto keep = [&](const Voxel& v) {
    return v.keyframes >= static_cast<uint32_t>(options_.min_keyframes) && v.weight >= min_confidence &&
           static_cast<int64_t>(v.observations) >= min_observations;
  };
  size_t n = 0;
  for (const Voxel& v : voxels_) n += keep(v) ? 1 : 0;
  PrepareOutput(n, &cloud);
  size_t i = 0;
  for (const Voxel& v : voxels_) {
    if (keep(v)) WriteVoxel(v, i++, &cloud);
  }
  return cloud;
}

uint32_t GlobalMap::Observations(VoxelKey key) const {
  const uint32_t index = Find(key);
  return index == kEmptySlot ? 0 : voxels_[index].observations;
}

uint32_t GlobalMap::Keyframes(VoxelKey key) const {
  const uint32_t index = Find(key);
  return index == kEmptySlot ? 0 : voxels_[index].keyframes;
}

bool GlobalMap::LastKeyframe(VoxelKey key, uint64_t* keyframe_id) const {
  const uint32_t index = Find(key);
  if (index == kEmptySlot) return false;
  *keyframe_id = voxels_[index].last_keyframe_id;
  return true;
}

}  // namespace prism
