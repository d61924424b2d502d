// Gives the pages malloc holds free back to the system (glibc keeps them otherwise) on a thread of its
// own: malloc_trim walks every arena and takes 2-20 ms on a server that has run sessions, which the
// transport thread must not spend. Request() never blocks; requests made while a trim runs fold into
// one more trim.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <mutex>
#include <thread>

namespace prism {

class MemoryTrimmer {
 public:
  MemoryTrimmer();
  ~MemoryTrimmer();  // waits for a trim under way
  MemoryTrimmer(const MemoryTrimmer&) = delete;
  MemoryTrimmer& operator=(const MemoryTrimmer&) = delete;

  // Asks for a trim soon. Any thread.
  void Request();
  // Trims done so far. Any thread.
  uint64_t trims() const;

 private:
  void Run();

  mutable std::mutex mutex_;
  std::condition_variable wake_;
  bool requested_ = false;  // Guarded by mutex_.
  bool stop_ = false;       // Guarded by mutex_.
  uint64_t trims_ = 0;      // Guarded by mutex_.
  std::thread thread_;
};

}  // namespace prism
