// A fixed-size worker pool and ParallelFor over an index range (COLMAP's ThreadPool, reduced).
// One process-wide pool is meant to be shared; ParallelFor without a pool runs inline.
#pragma once

#include <condition_variable>
#include <cstddef>
#include <functional>
#include <mutex>
#include <queue>
#include <thread>
#include <vector>

namespace prism {

// Names the calling thread (at most 15 characters; shown by top -H, perf and /proc/PID/task/*/comm).
void SetCurrentThreadName(const char* name);

// Sets the calling thread's niceness (Linux; raising it needs no privilege). false when refused.
bool SetCurrentThreadNice(int nice);

// Sets thread `tid`'s niceness (the kernel's thread id; Linux; raising it needs no privilege, lowering
// it back does). false when refused.
bool SetThreadNice(int tid, int nice);

// From now on, ParallelFor called on this thread runs its whole range here, without the pool's
// workers: for background work that must take no CPU from the pool's other users.
void RunParallelForInlineOnThisThread();

class ThreadPool {
 public:
  // num_threads <= 0 means std::thread::hardware_concurrency(). The workers run at `nice` (Linux
  // niceness, 0-19; higher yields the CPU to other threads, e.g. background work beside latency-bound).
  explicit ThreadPool(int num_threads = 0, int nice = 0, const char* name = "prism-pool");
  ~ThreadPool();
  ThreadPool(const ThreadPool&) = delete;
  ThreadPool& operator=(const ThreadPool&) = delete;

  // Threads that run ParallelFor work: the workers plus the calling thread.
  int num_threads() const { return static_cast<int>(workers_.size()) + 1; }

  // Runs fn(i) for i in [begin, end) on the pool and the calling thread; returns when all are done.
  // Indices are handed out in chunks of `grain`. An exception in fn is rethrown here (the first one).
  // Calls from several threads share the workers: a call waits only for the workers that took part in
  // it, never for its helper tasks still queued behind another call's work (the calling thread then
  // runs the rest itself), so one caller's long loop does not hold up another's short one.
  void ParallelFor(std::ptrdiff_t begin, std::ptrdiff_t end, const std::function<void(std::ptrdiff_t)>& fn,
                   std::ptrdiff_t grain = 1);

 private:
  void WorkerLoop();

  std::vector<std::thread> workers_;
  std::mutex mutex_;
  std::condition_variable cv_;
  std::queue<std::function<void()>> tasks_;  // Guarded by mutex_.
  bool stop_ = false;                        // Guarded by mutex_.
};

}  // namespace prism
