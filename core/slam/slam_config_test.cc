#include "core/slam/slam_config.h"

#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <set>
#include <string>

#include <gtest/gtest.h>

namespace prism {
namespace {

// Every option the text form knows reads back to the value written, for defaults and for changed
// values of every type (int, double, bool, enum, nested structs).
TEST(SlamConfigTest, FormatReadsBackToTheSameOptions) {
  SlamOptions changed;
  changed.keyframe_distance_fraction = 0.1234567890123;
  changed.init_max_frames = 77;
  changed.loop_closure = false;
  changed.tracker.shading_model = ShadingModel::kPredictedShading;
  changed.tracker.min_gradient = 5.5;
  changed.depth.max_relative_sigma = 0.07;
  changed.keyframe_window_ba.max_iterations = 7;
  changed.final_adjustment_ba.max_iterations = 9;
  for (const SlamOptions& original : {SlamOptions(), changed}) {
    const std::string text = FormatSlamConfig(original);
    SlamOptions read;
    // Start from different values so that a key left out of the text would show.
    read.keyframe_distance_fraction = 0.5;
    read.tracker.min_gradient = 1;
    read.loop_closure = !original.loop_closure;
    ASSERT_TRUE(ApplySlamConfig(text, "formatted", &read).ok()) << ApplySlamConfig(text, "formatted", &read);
    EXPECT_EQ(FormatSlamConfig(read), text);
  }
  SlamOptions read;
  ASSERT_TRUE(ApplySlamConfig(FormatSlamConfig(changed), "formatted", &read).ok());
  EXPECT_EQ(read.keyframe_distance_fraction, changed.keyframe_distance_fraction);  // exact, not rounded
  EXPECT_EQ(read.init_max_frames, 77);
  EXPECT_FALSE(read.loop_closure);
  EXPECT_EQ(read.tracker.shading_model, ShadingModel::kPredictedShading);
  EXPECT_EQ(read.tracker.min_gradient, 5.5);
  EXPECT_EQ(read.depth.max_relative_sigma, 0.07);
  EXPECT_EQ(read.keyframe_window_ba.max_iterations, 7);
  EXPECT_EQ(read.final_adjustment_ba.max_iterations, 9);
}

TEST(SlamConfigTest, EveryKeyIsWrittenOnceAndOnlyChangedKeysOnRequest) {
  const std::vector<std::string> keys = SlamOptionKeys();
  constexpr size_t kMaxUserOptions = 40;  // what a user sets; the rest are the method's own settings
  EXPECT_LE(keys.size(), kMaxUserOptions);
  EXPECT_EQ(std::set<std::string>(keys.begin(), keys.end()).size(), keys.size());
  const std::string text = FormatSlamConfig(SlamOptions());
  for (const std::string& k : keys) EXPECT_NE(text.find("\n" + k + " = "), std::string::npos) << k;

  EXPECT_EQ(FormatSlamConfig(SlamOptions(), /*only_changed=*/true).find('='), std::string::npos);
  SlamOptions o;
  o.loop_closure = false;
  o.depth.min_gradient = 2.5;
  const std::string diff = FormatSlamConfig(o, /*only_changed=*/true);
  EXPECT_NE(diff.find("loop_closure = false\n"), std::string::npos);
  EXPECT_NE(diff.find("depth.min_gradient = 2.5\n"), std::string::npos);
  EXPECT_EQ(std::count(diff.begin(), diff.end(), '='), 2);
}

TEST(SlamConfigTest, CommentsBlankLinesDashesAndBooleanSpellings) {
  SlamOptions o;
  const std::string text =
      "# a comment\n"
      "\n"
      "  loop-closure = off   # trailing comment\n"
      "keyframe-adjustment-async=no\n"
      "final_adjustment = 0\n"
      "keyframe_window = 9\n"
      "depth.max_search_px = 48\r\n";
  ASSERT_TRUE(ApplySlamConfig(text, "t", &o).ok()) << ApplySlamConfig(text, "t", &o);
  EXPECT_FALSE(o.loop_closure);
  EXPECT_FALSE(o.keyframe_adjustment_async);
  EXPECT_FALSE(o.final_adjustment);
  EXPECT_EQ(o.keyframe_window, 9);
  EXPECT_EQ(o.depth.max_search_px, 48);
}

// Each kind of bad input gets an error naming the source, the line and the key, and changes nothing.
TEST(SlamConfigTest, BadInputIsRefusedWithItsLineAndLeavesTheOptionsUnchanged) {
  struct Case {
    std::string text, expect;
  };
  const Case cases[] = {
      {"loop_closure = false\ntracker.min_gradiant = 4\n",
       "cfg:2: unknown SLAM option 'tracker.min_gradiant' (nearest: 'tracker.min_gradient'"},
      {"keyframe_window = 6.5\n", "cfg:1: SLAM option 'keyframe_window': bad value '6.5' (expected an integer)"},
      {"keyframe_window = 99999999999\n", "bad value '99999999999'"},
      {"keyframe_distance_fraction = nan\n", "bad value 'nan' (expected a finite number)"},
      {"keyframe_distance_fraction = 0.1x\n", "bad value '0.1x'"},
      {"loop_closure = maybe\n", "bad value 'maybe' (expected true or false)"},
      {"tracker.shading_model = fancy\n", "expected none, local_mean_normalisation or predicted_shading"},
      {"loop_closure\n", "cfg:1: expected 'key = value', got 'loop_closure'"},
      {"keyframe_window = \n", "bad value ''"},
      {"loop_closure = false\nloop-closure = true\n", "cfg:2: SLAM option 'loop_closure' given twice"},
      // Every value parses, but the options fail their own check.
      {"keyframe_window = 2\n", "cfg: SlamOptions: keyframe_window must be >= 3"},
      {"keyframe_min_visible_fraction = 1.5\n", "keyframe_min_visible_fraction must be in [0, 1]"},
      {"init_min_frames = 20\ninit_max_frames = 10\n", "init_max_frames must be >= init_min_frames"},
      {"loop_min_keyframe_gap = 1\n", "loop_min_keyframe_gap must be >= 2"},
      {"init_threads = 0\n", "init_threads must be in [1, 64]"},
      {"final_refinement_neighbours = 6\n", "final_refinement_neighbours must be in [0, 5]"},
      {"final_refinement_rounds = 11\n", "final_refinement_rounds must be in [1, 10]"},
      {"start_check_keyframes = 3\n", "start_check_keyframes must be 0 (off) or >= 4"},
      {"depth_update_interval = 0\n", "depth_update_interval must be >= 1"},
      {"final_adjustment_max_keyframes = 2\n", "final_adjustment_max_keyframes must be >= 3"},
      // Internal settings are not options.
      {"init_rounds = 2\n", "unknown SLAM option 'init_rounds'"},
      {"wide_baseline_tracker.min_gradient = 4\n", "unknown SLAM option"},
  };
  for (const Case& c : cases) {
    SlamOptions o;
    o.keyframe_window = 7;  // not the default: an error must not reset it either
    const std::string before = FormatSlamConfig(o);
    const Status s = ApplySlamConfig(c.text, "cfg", &o);
    EXPECT_FALSE(s.ok()) << c.text;
    EXPECT_EQ(s.code(), StatusCode::kInvalidArgument) << c.text;
    EXPECT_NE(s.message().find(c.expect), std::string::npos) << "got: " << s.message();
    EXPECT_EQ(FormatSlamConfig(o), before) << c.text;
  }
  SlamOptions o;
  EXPECT_FALSE(SetSlamOption("no_such_key", "1", &o).ok());
  EXPECT_FALSE(SetSlamOption("keyframe_window", "three", &o).ok());
  EXPECT_EQ(o.keyframe_window, SlamOptions().keyframe_window);
}

TEST(SlamConfigTest, FilesAreReadAndAMissingFileIsNotFound) {
  const std::string path =
      (std::filesystem::temp_directory_path() / ("slam_config_test_" + std::to_string(::getpid()) + ".txt")).string();
  {
    std::ofstream f(path);
    f << "keyframe_distance_fraction = 0.12\nfinal_adjustment_ba.max_iterations = 3\n";
  }
  SlamOptions o;
  ASSERT_TRUE(ApplySlamConfigFile(path, &o).ok());
  EXPECT_EQ(o.keyframe_distance_fraction, 0.12);
  EXPECT_EQ(o.final_adjustment_ba.max_iterations, 3);
  std::remove(path.c_str());
  const Status missing = ApplySlamConfigFile(path, &o);
  EXPECT_EQ(missing.code(), StatusCode::kNotFound);
  EXPECT_NE(missing.message().find(path), std::string::npos);
}

}  // namespace
}  // namespace prism
