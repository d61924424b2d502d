#include "core/util/thread_pool.h"

#include <atomic>
#include <exception>

namespace prism {

ThreadPool::ThreadPool(int num_threads) {
  if (num_threads <= 0) num_threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  // The calling thread also works in ParallelFor, so the pool needs one thread fewer.
  for (int i = 0; i + 1 < num_threads; ++i) workers_.emplace_back([this] { WorkerLoop(); });
}

ThreadPool::~ThreadPool() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = true;
  }
  cv_.notify_all();
  for (auto& w : workers_) w.join();
}

void ThreadPool::WorkerLoop() {
  for (;;) {
    std::function<void()> task;
    {
      std::unique_lock<std::mutex> lock(mutex_);
      cv_.wait(lock, [this] { return stop_ || !tasks_.empty(); });
      if (stop_ && tasks_.empty()) return;
      task = std::move(tasks_.front());
      tasks_.pop();
    }
    task();
  }
}

void ThreadPool::ParallelFor(std::ptrdiff_t begin, std::ptrdiff_t end, const std::function<void(std::ptrdiff_t)>& fn,
                             std::ptrdiff_t grain) {
  if (end <= begin) return;
  if (grain < 1) grain = 1;
  std::atomic<std::ptrdiff_t> next{begin};
  std::atomic<int> active{0};
  std::mutex done_mutex;
  std::condition_variable done_cv;
  std::exception_ptr error;
  std::mutex error_mutex;

  auto run = [&] {
    for (;;) {
      const std::ptrdiff_t start = next.fetch_add(grain);
      if (start >= end) break;
      const std::ptrdiff_t stop = std::min(end, start + grain);
      try {
        for (std::ptrdiff_t i = start; i < stop; ++i) fn(i);
      } catch (...) {
        std::lock_guard<std::mutex> lock(error_mutex);
        if (!error) error = std::current_exception();
        next = end;
      }
    }
  };

  const int helpers = static_cast<int>(std::min<std::ptrdiff_t>(workers_.size(), (end - begin + grain - 1) / grain));
  active = helpers;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (int i = 0; i < helpers; ++i) {
      tasks_.push([&] {
        run();
        std::lock_guard<std::mutex> l(done_mutex);
        if (--active == 0) done_cv.notify_all();
      });
    }
  }
  cv_.notify_all();
  run();
  std::unique_lock<std::mutex> lock(done_mutex);
  done_cv.wait(lock, [&] { return active.load() == 0; });
  if (error) std::rethrow_exception(error);
}

}  // namespace prism
