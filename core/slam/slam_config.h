// One text form of SlamOptions for every entry point, so that a setting means the same thing wherever
// it is given: prism-slam (--slam-config FILE, --set KEY=VALUE), prism-server (its config file and
// command line, as slam.KEY, or slam-config FILE), and the files both write back (prism-slam's
// slam_config.txt). Users of LSD-SLAM and DSO name "parameters that differ between entry points" among
// their main complaints; here every entry point reads the same keys through this file.
//
// Format: one `key = value` per line; '#' starts a comment; blank lines are ignored. The keys are the
// options a user sets (SlamOptionKeys, at most 40; the other SlamOptions fields are the method's own
// settings, set only in code), each the field's path in SlamOptions, e.g.
//   keyframe_distance_fraction = 0.09
//   tracker.min_gradient = 4
//   depth.max_relative_sigma = 0.1
//   final_adjustment_ba.max_iterations = 6
//   tracker.shading_model = local_mean_normalisation
// '-' and '_' in keys are the same ("loop-closure" = "loop_closure"). Values: integers, finite
// decimals, booleans (true/false, 1/0, yes/no, on/off), and for tracker.shading_model one of none,
// local_mean_normalisation, predicted_shading. FormatSlamConfig writes every key (SlamOptionKeys) and
// reads back to the same options.
//
// Errors name the source and line and leave the options unchanged: an unknown key (with the nearest
// known key), a malformed value, a key given twice in one text, or options that fail
// SlamOptions::Check() once every line is applied.
#pragma once

#include <string>
#include <vector>

#include "core/slam/slam_system.h"
#include "core/util/status.h"

namespace prism {

// Every key, in the order FormatSlamConfig writes them.
std::vector<std::string> SlamOptionKeys();

// Sets one option. INVALID_ARGUMENT (options unchanged) for an unknown key or a malformed value. Does
// not run SlamOptions::Check (a later key may fix an earlier one); ApplySlamConfig does.
Status SetSlamOption(const std::string& key, const std::string& value, SlamOptions* options);

// Applies the lines of a config text in order, then checks the result; `source` names the text in
// errors (a path, "--set"). On error the options are unchanged.
Status ApplySlamConfig(const std::string& text, const std::string& source, SlamOptions* options);

// Reads a config file and applies it (NOT_FOUND when it cannot be read).
Status ApplySlamConfigFile(const std::string& path, SlamOptions* options);

// Every key with its value, one `key = value` per line after a comment header; with only_changed, only
// the keys whose value differs from SlamOptions(). Doubles in their shortest exact form.
std::string FormatSlamConfig(const SlamOptions& options, bool only_changed = false);

}  // namespace prism
