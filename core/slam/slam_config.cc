#include "core/slam/slam_config.h"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <limits>
#include <set>
#include <sstream>
#include <variant>

#include "core/util/key_value_text.h"

namespace prism {
namespace {

using FieldPtr = std::variant<int*, double*, bool*, ShadingModel*>;

struct Field {
  std::string key;
  FieldPtr ptr;
};

// The options a user sets (at most 40; the rest of SlamOptions are the method's internal settings), by
// key. Pointers into `o`: valid while it lives.
std::vector<Field> Fields(SlamOptions& o) {
  return {
      {"keyframe_distance_fraction", &o.keyframe_distance_fraction},
      {"keyframe_min_visible_fraction", &o.keyframe_min_visible_fraction},
      {"keyframe_max_rotation_deg", &o.keyframe_max_rotation_deg},
      {"init_min_frames", &o.init_min_frames},
      {"init_max_frames", &o.init_max_frames},
      {"init_threads", &o.init_threads},
      {"depth_update_interval", &o.depth_update_interval},
      {"mapping_budget_ms", &o.mapping_budget_ms},
      {"relocalise_after_lost_frames", &o.relocalise_after_lost_frames},
      {"loop_closure", &o.loop_closure},
      {"loop_min_keyframe_gap", &o.loop_min_keyframe_gap},
      {"loop_max_candidates", &o.loop_max_candidates},
      {"keyframe_adjustment", &o.keyframe_adjustment},
      {"keyframe_window", &o.keyframe_window},
      {"keyframe_adjustment_async", &o.keyframe_adjustment_async},
      {"keyframe_adjustment_max_wait_ms", &o.keyframe_adjustment_max_wait_ms},
      {"repropagate_after_adjustment", &o.repropagate_after_adjustment},
      {"final_adjustment", &o.final_adjustment},
      {"final_adjustment_max_keyframes", &o.final_adjustment_max_keyframes},
      {"final_feature_adjustment", &o.final_feature_adjustment},
      {"final_refinement_neighbours", &o.final_refinement_neighbours},
      {"final_refinement_rounds", &o.final_refinement_rounds},
      {"start_check_keyframes", &o.start_check_keyframes},
      {"start_check_async", &o.start_check_async},
      {"tracker.pyramid_levels", &o.tracker.pyramid_levels},
      {"tracker.min_gradient", &o.tracker.min_gradient},
      {"tracker.max_points_per_level", &o.tracker.max_points_per_level},
      {"tracker.max_iterations", &o.tracker.max_iterations},
      {"tracker.image_noise_sigma", &o.tracker.image_noise_sigma},
      {"tracker.shading_model", &o.tracker.shading_model},
      {"tracker.min_inlier_fraction", &o.tracker.min_inlier_fraction},
      {"depth.min_gradient", &o.depth.min_gradient},
      {"depth.max_search_px", &o.depth.max_search_px},
      {"depth.image_noise_sigma", &o.depth.image_noise_sigma},
      {"depth.max_relative_sigma", &o.depth.max_relative_sigma},
      {"depth.min_observations", &o.depth.min_observations},
      {"keyframe_window_ba.max_iterations", &o.keyframe_window_ba.max_iterations},
      {"final_adjustment_ba.max_iterations", &o.final_adjustment_ba.max_iterations},
  };
}

constexpr const char* kShadingModelNames[] = {"none", "local_mean_normalisation", "predicted_shading"};

std::string NormaliseKey(std::string key) {
  key = TrimWhitespace(key);
  std::replace(key.begin(), key.end(), '-', '_');
  return key;
}

size_t EditDistance(const std::string& a, const std::string& b) {
  std::vector<size_t> row(b.size() + 1);
  for (size_t j = 0; j <= b.size(); ++j) row[j] = j;
  for (size_t i = 1; i <= a.size(); ++i) {
    size_t diagonal = row[0];
    row[0] = i;
    for (size_t j = 1; j <= b.size(); ++j) {
      const size_t up = row[j];
      row[j] = std::min({row[j] + 1, row[j - 1] + 1, diagonal + (a[i - 1] == b[j - 1] ? 0 : 1)});
      diagonal = up;
    }
  }
  return row[b.size()];
}

bool ParseIntValue(const std::string& s, int* out) {
  long long v = 0;
  const char* end = s.data() + s.size();
  const auto [ptr, ec] = std::from_chars(s.data(), end, v);
  if (ec != std::errc() || ptr != end || s.empty()) return false;
  if (v < std::numeric_limits<int>::min() || v > std::numeric_limits<int>::max()) return false;
  *out = static_cast<int>(v);
  return true;
}

bool ParseDoubleValue(const std::string& s, double* out) {
  if (s.empty()) return false;
  char* end = nullptr;
  const double v = std::strtod(s.c_str(), &end);
  if (end != s.c_str() + s.size() || !std::isfinite(v)) return false;
  *out = v;
  return true;
}

bool ParseBoolValue(std::string s, bool* out) {
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  if (s == "true" || s == "1" || s == "yes" || s == "on") return (*out = true, true);
  if (s == "false" || s == "0" || s == "no" || s == "off") return (*out = false, true);
  return false;
}

std::string FormatDouble(double v) {
  char buf[64];
  const auto [ptr, ec] = std::to_chars(buf, buf + sizeof(buf), v);
  return ec == std::errc() ? std::string(buf, ptr) : std::to_string(v);
}

std::string FormatValue(const FieldPtr& p) {
  if (auto* i = std::get_if<int*>(&p)) return std::to_string(**i);
  if (auto* d = std::get_if<double*>(&p)) return FormatDouble(**d);
  if (auto* b = std::get_if<bool*>(&p)) return **b ? "true" : "false";
  return kShadingModelNames[static_cast<int>(*std::get<ShadingModel*>(p))];
}

}  // namespace

std::vector<std::string> SlamOptionKeys() {
  SlamOptions o;
  std::vector<std::string> keys;
  for (const Field& f : Fields(o)) keys.push_back(f.key);
  return keys;
}

Status SetSlamOption(const std::string& key_in, const std::string& value_in, SlamOptions* options) {
  const std::string key = NormaliseKey(key_in), value = TrimWhitespace(value_in);
  std::vector<Field> fields = Fields(*options);
  auto it = std::find_if(fields.begin(), fields.end(), [&](const Field& f) { return f.key == key; });
  if (it == fields.end()) {
    const Field* nearest = &fields.front();
    for (const Field& f : fields)
      if (EditDistance(key, f.key) < EditDistance(key, nearest->key)) nearest = &f;
    return InvalidArgumentError("unknown SLAM option '" + key_in + "' (nearest: '" + nearest->key +
                                "'; every key: prism-slam writes them to slam_config.txt)");
  }
  auto bad = [&](const std::string& expected) {
    return InvalidArgumentError("SLAM option '" + key + "': bad value '" + value + "' (expected " + expected + ")");
  };
  if (auto* i = std::get_if<int*>(&it->ptr)) {
    if (!ParseIntValue(value, *i)) return bad("an integer");
  } else if (auto* d = std::get_if<double*>(&it->ptr)) {
    if (!ParseDoubleValue(value, *d)) return bad("a finite number");
  } else if (auto* b = std::get_if<bool*>(&it->ptr)) {
    if (!ParseBoolValue(value, *b)) return bad("true or false");
  } else {
    ShadingModel* m = std::get<ShadingModel*>(it->ptr);
    int index = -1;
    for (int k = 0; k < 3; ++k)
      if (value == kShadingModelNames[k]) index = k;
    if (index < 0) return bad("none, local_mean_normalisation or predicted_shading");
    *m = static_cast<ShadingModel>(index);
  }
  return Status::Ok();
}

Status ApplySlamConfig(const std::string& text, const std::string& source, SlamOptions* options) {
  SlamOptions result = *options;
  std::set<std::string> seen;
  PRISM_RETURN_IF_ERROR(
      ForEachKeyValueLine(text, source, "=", [&](const std::string& key_in, const std::string& value) {
        const std::string key = NormaliseKey(key_in);
        if (!seen.insert(key).second) return InvalidArgumentError("SLAM option '" + key + "' given twice");
        return SetSlamOption(key, value, &result);
      }));
  if (Status s = result.Check(); !s.ok()) return InvalidArgumentError(source + ": " + s.message());
  *options = result;
  return Status::Ok();
}

Status ApplySlamConfigFile(const std::string& path, SlamOptions* options) {
  std::ifstream in(path);
  if (!in) return NotFoundError("cannot read SLAM config '" + path + "'");
  std::ostringstream text;
  text << in.rdbuf();
  if (in.bad()) return NotFoundError("cannot read SLAM config '" + path + "'");
  return ApplySlamConfig(text.str(), path, options);
}

std::string FormatSlamConfig(const SlamOptions& options, bool only_changed) {
  SlamOptions copy = options, defaults;
  const std::vector<Field> fields = Fields(copy), default_fields = Fields(defaults);
  std::ostringstream out;
  out << "# prism SLAM options; format and keys: core/slam/slam_config.h\n";
  for (size_t i = 0; i < fields.size(); ++i) {
    const std::string v = FormatValue(fields[i].ptr);
    if (only_changed && v == FormatValue(default_fields[i].ptr)) continue;
    out << fields[i].key << " = " << v << "\n";
  }
  return out.str();
}

}  // namespace prism
