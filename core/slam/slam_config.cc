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

void AddTracker(const std::string& p, TrackerOptions& t, std::vector<Field>* f) {
  f->push_back({p + "pyramid_levels", &t.pyramid_levels});
  f->push_back({p + "min_gradient", &t.min_gradient});
  f->push_back({p + "max_points_per_level", &t.max_points_per_level});
  f->push_back({p + "max_iterations", &t.max_iterations});
  f->push_back({p + "convergence_threshold", &t.convergence_threshold});
  f->push_back({p + "image_noise_sigma", &t.image_noise_sigma});
  f->push_back({p + "huber_threshold", &t.huber_threshold});
  f->push_back({p + "inlier_threshold", &t.inlier_threshold});
  f->push_back({p + "shading_model", &t.shading_model});
  f->push_back({p + "normal_window_radius_px", &t.normal_window_radius_px});
  f->push_back({p + "normal_max_depth_jump", &t.normal_max_depth_jump});
  f->push_back({p + "normal_min_view_cosine", &t.normal_min_view_cosine});
  f->push_back({p + "max_shading_ratio", &t.max_shading_ratio});
  f->push_back({p + "local_mean_radius_px", &t.local_mean_radius_px});
  f->push_back({p + "local_mean_floor", &t.local_mean_floor});
  f->push_back({p + "min_local_mean", &t.min_local_mean});
  f->push_back({p + "estimate_affine_brightness", &t.estimate_affine_brightness});
  f->push_back({p + "affine_prior_a", &t.affine_prior_a});
  f->push_back({p + "affine_prior_b", &t.affine_prior_b});
  f->push_back({p + "min_visible_fraction", &t.min_visible_fraction});
  f->push_back({p + "min_inlier_fraction", &t.min_inlier_fraction});
  f->push_back({p + "max_affine_gain", &t.max_affine_gain});
  f->push_back({p + "max_residual_rms", &t.max_residual_rms});
  f->push_back({p + "camera_attached_min_votes", &t.camera_attached_min_votes});
  f->push_back({p + "camera_attached_min_flow_px", &t.camera_attached_min_flow_px});
  f->push_back({p + "camera_attached_residual_ratio", &t.camera_attached_residual_ratio});
}

void AddDepthFilter(const std::string& p, DepthFilterOptions& d, std::vector<Field>* f) {
  f->push_back({p + "min_gradient", &d.min_gradient});
  f->push_back({p + "min_gradient_line_cosine", &d.min_gradient_line_cosine});
  f->push_back({p + "max_match_error", &d.max_match_error});
  f->push_back({p + "min_match_ratio", &d.min_match_ratio});
  f->push_back({p + "max_search_px", &d.max_search_px});
  f->push_back({p + "image_noise_sigma", &d.image_noise_sigma});
  f->push_back({p + "epipolar_sigma_px", &d.epipolar_sigma_px});
  f->push_back({p + "seed_max_relative_sigma", &d.seed_max_relative_sigma});
  f->push_back({p + "search_sigmas", &d.search_sigmas});
  f->push_back({p + "outlier_sigmas", &d.outlier_sigmas});
  f->push_back({p + "propagation_relative_sigma", &d.propagation_relative_sigma});
  f->push_back({p + "local_mean_radius_px", &d.local_mean_radius_px});
  f->push_back({p + "max_local_mean_log_gradient", &d.max_local_mean_log_gradient});
  f->push_back({p + "local_mean_edge_dim_side_only", &d.local_mean_edge_dim_side_only});
  f->push_back({p + "local_mean_floor", &d.local_mean_floor});
  f->push_back({p + "min_local_mean", &d.min_local_mean});
  f->push_back({p + "regularise_sigmas", &d.regularise_sigmas});
  f->push_back({p + "min_neighbours", &d.min_neighbours});
  f->push_back({p + "min_observations", &d.min_observations});
  f->push_back({p + "max_relative_sigma", &d.max_relative_sigma});
  f->push_back({p + "light_edge_radius_px", &d.light_edge_radius_px});
  f->push_back({p + "light_edge_low_share", &d.light_edge_low_share});
  f->push_back({p + "light_edge_high_share", &d.light_edge_high_share});
  f->push_back({p + "camera_attached_min_votes", &d.camera_attached_min_votes});
  f->push_back({p + "camera_attached_min_flow_px", &d.camera_attached_min_flow_px});
  f->push_back({p + "camera_attached_error_ratio", &d.camera_attached_error_ratio});
  f->push_back({p + "skip_information_ratio", &d.skip_information_ratio});
}

void AddDirectBa(const std::string& p, DirectBaOptions& b, std::vector<Field>* f) {
  f->push_back({p + "pyramid_levels", &b.pyramid_levels});
  f->push_back({p + "max_iterations", &b.max_iterations});
  f->push_back({p + "huber", &b.huber});
  f->push_back({p + "outlier", &b.outlier});
  f->push_back({p + "border_px", &b.border_px});
  f->push_back({p + "function_tolerance", &b.function_tolerance});
  f->push_back({p + "gradient_weight_c", &b.gradient_weight_c});
  f->push_back({p + "gain_ratio_damping", &b.gain_ratio_damping});
  f->push_back({p + "linearise_from_evaluation", &b.linearise_from_evaluation});
}

void AddFeatureAdjustment(const std::string& p, FeatureAdjustmentOptions& a, std::vector<Field>* f) {
  f->push_back({p + "max_features", &a.max_features});
  f->push_back({p + "contrast_threshold", &a.contrast_threshold});
  f->push_back({p + "min_local_mean", &a.min_local_mean});
  f->push_back({p + "ratio", &a.ratio});
  f->push_back({p + "ransac_threshold_px", &a.ransac_threshold_px});
  f->push_back({p + "min_pair_matches", &a.min_pair_matches});
  f->push_back({p + "max_pair_angle_deg", &a.max_pair_angle_deg});
  f->push_back({p + "huber_px", &a.huber_px});
  f->push_back({p + "outlier_px", &a.outlier_px});
  f->push_back({p + "max_iterations", &a.max_iterations});
  f->push_back({p + "function_tolerance", &a.function_tolerance});
  f->push_back({p + "min_triangulation_angle_deg", &a.min_triangulation_angle_deg});
}

// The fields of `o`, by key. Pointers into `o`: valid while it lives.
std::vector<Field> Fields(SlamOptions& o) {
  std::vector<Field> f;
  f.push_back({"keyframe_distance_fraction", &o.keyframe_distance_fraction});
  f.push_back({"keyframe_min_visible_fraction", &o.keyframe_min_visible_fraction});
  f.push_back({"keyframe_max_rotation_deg", &o.keyframe_max_rotation_deg});
  f.push_back({"init_min_frames", &o.init_min_frames});
  f.push_back({"init_min_converged_fraction", &o.init_min_converged_fraction});
  f.push_back({"init_min_parallax_fraction", &o.init_min_parallax_fraction});
  f.push_back({"init_max_frames", &o.init_max_frames});
  f.push_back({"init_track_normalised", &o.init_track_normalised});
  f.push_back({"init_min_feature_local_mean", &o.init_min_feature_local_mean});
  f.push_back({"init_residual_factor", &o.init_residual_factor});
  f.push_back({"init_rounds", &o.init_rounds});
  f.push_back({"init_threads", &o.init_threads});
  f.push_back({"init_depth_edge_test", &o.init_depth_edge_test});
  f.push_back({"new_pixel_relative_sigma", &o.new_pixel_relative_sigma});
  f.push_back({"tracker_refresh_frames", &o.tracker_refresh_frames});
  f.push_back({"depth_update_interval", &o.depth_update_interval});
  f.push_back({"mapping_budget_ms", &o.mapping_budget_ms});
  f.push_back({"tracking_min_observations", &o.tracking_min_observations});
  f.push_back({"tracking_max_relative_sigma", &o.tracking_max_relative_sigma});
  f.push_back({"max_step_rotation_deg", &o.max_step_rotation_deg});
  f.push_back({"max_step_translation_fraction", &o.max_step_translation_fraction});
  f.push_back({"keep_velocity_across_keyframes", &o.keep_velocity_across_keyframes});
  f.push_back({"relocalise_max_keyframes", &o.relocalise_max_keyframes});
  f.push_back({"relocalise_after_lost_frames", &o.relocalise_after_lost_frames});
  f.push_back({"loop_closure", &o.loop_closure});
  f.push_back({"loop_min_keyframe_gap", &o.loop_min_keyframe_gap});
  f.push_back({"loop_max_distance_fraction", &o.loop_max_distance_fraction});
  f.push_back({"loop_max_angle_deg", &o.loop_max_angle_deg});
  f.push_back({"loop_max_candidates", &o.loop_max_candidates});
  f.push_back({"loop_max_rotation_inconsistency_deg", &o.loop_max_rotation_inconsistency_deg});
  f.push_back({"loop_min_depth_matches", &o.loop_min_depth_matches});
  f.push_back({"odometry_rotation_sigma", &o.odometry_rotation_sigma});
  f.push_back({"odometry_translation_sigma", &o.odometry_translation_sigma});
  f.push_back({"odometry_log_scale_sigma", &o.odometry_log_scale_sigma});
  f.push_back({"loop_rotation_sigma", &o.loop_rotation_sigma});
  f.push_back({"loop_translation_sigma", &o.loop_translation_sigma});
  f.push_back({"loop_log_scale_sigma", &o.loop_log_scale_sigma});
  f.push_back({"keyframe_adjustment", &o.keyframe_adjustment});
  f.push_back({"keyframe_window", &o.keyframe_window});
  f.push_back({"keyframe_window_cell_px", &o.keyframe_window_cell_px});
  f.push_back({"keyframe_window_min_points", &o.keyframe_window_min_points});
  f.push_back({"keyframe_adjustment_interval", &o.keyframe_adjustment_interval});
  f.push_back({"keyframe_window_min_overlap", &o.keyframe_window_min_overlap});
  f.push_back({"repropagate_after_adjustment", &o.repropagate_after_adjustment});
  f.push_back({"keyframe_adjustment_async", &o.keyframe_adjustment_async});
  f.push_back({"keyframe_adjustment_max_wait_ms", &o.keyframe_adjustment_max_wait_ms});
  f.push_back({"refit_oldest_keyframe_scale", &o.refit_oldest_keyframe_scale});
  f.push_back({"distribute_keyframe_corrections", &o.distribute_keyframe_corrections});
  f.push_back({"final_adjustment", &o.final_adjustment});
  f.push_back({"final_adjustment_max_keyframes", &o.final_adjustment_max_keyframes});
  f.push_back({"final_feature_adjustment", &o.final_feature_adjustment});
  f.push_back({"feature_adjustment_min_overlap", &o.feature_adjustment_min_overlap});
  f.push_back({"feature_adjustment_max_keyframes", &o.feature_adjustment_max_keyframes});
  AddFeatureAdjustment("feature_adjustment.", o.feature_adjustment, &f);
  f.push_back({"final_refinement_neighbours", &o.final_refinement_neighbours});
  f.push_back({"final_refinement_first_from_second", &o.final_refinement_first_from_second});
  f.push_back({"final_refinement_relative_sigma", &o.final_refinement_relative_sigma});
  f.push_back({"final_refinement_rounds", &o.final_refinement_rounds});
  AddTracker("tracker.", o.tracker, &f);
  AddTracker("wide_baseline_tracker.", o.wide_baseline_tracker, &f);
  AddDepthFilter("depth.", o.depth, &f);
  AddDirectBa("keyframe_window_ba.", o.keyframe_window_ba, &f);
  AddDirectBa("final_adjustment_ba.", o.final_adjustment_ba, &f);
  f.push_back({"final_adjustment_relit", &o.final_adjustment_relit});
  f.push_back({"final_adjustment_mixed", &o.final_adjustment_mixed});
  f.push_back({"final_adjustment_mixed_relit_scale", &o.final_adjustment_mixed_relit_scale});
  f.push_back({"metric_scale_min_band_fraction", &o.metric_scale_min_band_fraction});
  f.push_back({"metric_scale_max_pair_spread", &o.metric_scale_max_pair_spread});
  f.push_back({"scale_drift_correction", &o.scale_drift_correction});
  f.push_back({"scale_drift_window", &o.scale_drift_window});
  f.push_back({"start_check_keyframes", &o.start_check_keyframes});
  f.push_back({"start_check_max_pair_spread", &o.start_check_max_pair_spread});
  f.push_back({"start_check_retry_parallax_fraction", &o.start_check_retry_parallax_fraction});
  f.push_back({"start_check_max_frames", &o.start_check_max_frames});
  f.push_back({"start_check_window_cell_px", &o.start_check_window_cell_px});
  f.push_back({"start_check_async", &o.start_check_async});
  AddDirectBa("final_adjustment_relit_ba.", o.final_adjustment_relit_ba, &f);
  return f;
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
