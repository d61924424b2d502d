// libFuzzer target: the SLAM config text (core/slam/slam_config.h), which prism-slam and prism-server
// read from operators' files and flags. Invariants: an accepted text gives options that pass Check and
// read back from their own FormatSlamConfig unchanged; a refused one leaves the options as they were.
#include <cstdint>
#include <string>

#include "core/slam/slam_config.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  prism::SlamOptions options;
  options.keyframe_window = 7;  // not the default, so that a reset would show
  const std::string before = prism::FormatSlamConfig(options);
  const prism::Status s = prism::ApplySlamConfig(text, "fuzz", &options);
  const std::string after = prism::FormatSlamConfig(options);
  if (!s.ok()) {
    if (after != before || s.message().empty()) __builtin_trap();
    return 0;
  }
  if (!options.Check().ok()) __builtin_trap();
  prism::SlamOptions again;
  if (!prism::ApplySlamConfig(after, "formatted", &again).ok() || prism::FormatSlamConfig(again) != after)
    __builtin_trap();
  return 0;
}
