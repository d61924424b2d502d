#include "server/memory_trimmer.h"

#include <unistd.h>

#include <chrono>
#include <cstring>
#include <fstream>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

namespace prism {
namespace {

double ResidentMb() {
  std::ifstream statm("/proc/self/statm");
  double pages_total = 0, pages_resident = 0;
  statm >> pages_total >> pages_resident;
  return pages_resident * static_cast<double>(sysconf(_SC_PAGESIZE)) / (1 << 20);
}

bool WaitForTrims(const MemoryTrimmer& trimmer, uint64_t n) {
  for (int i = 0; i < 500 && trimmer.trims() < n; ++i) std::this_thread::sleep_for(std::chrono::milliseconds(10));
  return trimmer.trims() >= n;
}

// The pages between live blocks that glibc keeps after a free go back to the system on a trim.
TEST(MemoryTrimmerTest, ATrimReturnsTheFreedPagesBetweenLiveBlocks) {
  MemoryTrimmer trimmer;
  constexpr size_t kBlocks = 100000, kBlockBytes = 2000, kKeepEvery = 64;
  std::vector<char*> blocks(kBlocks);
  for (char*& b : blocks) {
    b = new char[kBlockBytes];
    std::memset(b, 1, kBlockBytes);
  }
  for (size_t i = 0; i < kBlocks; ++i)
    if (i % kKeepEvery != 0) delete[] blocks[i];
  const double before = ResidentMb();
  trimmer.Request();
  ASSERT_TRUE(WaitForTrims(trimmer, 1));
  const double after = ResidentMb();
  // About 190 MB freed among live blocks 128 KB apart; most of it goes back.
  constexpr double kMinReturnedMb = 100;
  EXPECT_GT(before - after, kMinReturnedMb) << "RSS before " << before << " MB, after " << after << " MB";
  for (size_t i = 0; i < kBlocks; i += kKeepEvery) delete[] blocks[i];
}

TEST(MemoryTrimmerTest, RequestsNeverBlockAndFoldIntoFewerTrims) {
  MemoryTrimmer trimmer;
  for (int i = 0; i < 1000; ++i) trimmer.Request();
  ASSERT_TRUE(WaitForTrims(trimmer, 1));
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_GE(trimmer.trims(), 1u);
  EXPECT_LT(trimmer.trims(), 1000u);
}

}  // namespace
}  // namespace prism
