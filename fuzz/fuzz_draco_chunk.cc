// libFuzzer target: the Draco map-chunk decoder (what a client runs on server bytes, and the server on
// its persisted chunks when it rebuilds a map).
#include <cmath>
#include <cstdint>

#include "core/codec/map_chunk_codec.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  prism::StatusOr<prism::PointCloud> cloud = prism::DecodeMapChunk(data, size);
  if (cloud.ok() && !cloud->IsConsistent()) __builtin_trap();
  return 0;
}
