#include "core/util/thread_pool.h"

#include <pthread.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <exception>
#include <memory>
#include <string>

namespace prism {

void SetCurrentThreadName(const char* name) {
#if defined(__linux__)
  pthread_setname_np(pthread_self(), std::string(name).substr(0, 15).c_str());
#else
  (void)name;
#endif
}

bool SetThreadNice(int tid, int nice) {
#if defined(__linux__)
  return setpriority(PRIO_PROCESS, static_cast<id_t>(tid), nice) == 0;
#else
  (void)tid;
  (void)nice;
  return false;
#endif
}

bool SetCurrentThreadNice(int nice) {
#if defined(__linux__)
  return setpriority(PRIO_PROCESS, static_cast<id_t>(syscall(SYS_gettid)), nice) == 0;
#else
  (void)nice;
  return false;
#endif
}

ThreadPool::ThreadPool(int num_threads, int nice, const char* name) {
  if (num_threads <= 0) num_threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  // The calling thread also works in ParallelFor, so the pool needs one thread fewer.
  for (int i = 0; i + 1 < num_threads; ++i)
    workers_.emplace_back([this, nice, name] {
      SetCurrentThreadName(name);
      if (nice != 0) SetCurrentThreadNice(nice);
      WorkerLoop();
    });
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

namespace {
thread_local bool parallel_for_inline = false;
}  // namespace

void RunParallelForInlineOnThisThread() { parallel_for_inline = true; }

void ThreadPool::ParallelFor(std::ptrdiff_t begin, std::ptrdiff_t end, const std::function<void(std::ptrdiff_t)>& fn,
                             std::ptrdiff_t grain) {
  if (end <= begin) return;
  if (parallel_for_inline) {
    for (std::ptrdiff_t i = begin; i < end; ++i) fn(i);
    return;
  }
  if (grain < 1) grain = 1;
  // The helpers' tasks share this state and may outlive the call: a helper still in the queue when the
  // caller has claimed every chunk finds the call closed and does nothing. The caller waits only for the
  // helpers that started (they read fn, which lives on the caller's stack), never for a helper queued
  // behind other callers' work: two ParallelFor calls on one pool from different threads (prism-server's
  // dense workers) do not wait for each other.
  struct Call {
    std::atomic<std::ptrdiff_t> next{0};
    std::ptrdiff_t end = 0;
    std::ptrdiff_t grain = 1;
    const std::function<void(std::ptrdiff_t)>* fn = nullptr;
    std::mutex mutex;
    std::condition_variable done;
    int running = 0;           // helpers inside Run; guarded by mutex
    bool closed = false;       // the caller has finished its own Run; guarded by mutex
    std::exception_ptr error;  // guarded by mutex

    void Run() {
      for (;;) {
        const std::ptrdiff_t start = next.fetch_add(grain);
        if (start >= end) break;
        const std::ptrdiff_t stop = std::min(end, start + grain);
        try {
          for (std::ptrdiff_t i = start; i < stop; ++i) (*fn)(i);
        } catch (...) {
          std::lock_guard<std::mutex> lock(mutex);
          if (!error) error = std::current_exception();
          next = end;
        }
      }
    }
  };
  auto call = std::make_shared<Call>();
  call->next = begin;
  call->end = end;
  call->grain = grain;
  call->fn = &fn;

  const int helpers = static_cast<int>(std::min<std::ptrdiff_t>(workers_.size(), (end - begin + grain - 1) / grain));
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (int i = 0; i < helpers; ++i) {
      tasks_.push([call] {
        {
          std::lock_guard<std::mutex> l(call->mutex);
          if (call->closed) return;
          ++call->running;
        }
        call->Run();
        std::lock_guard<std::mutex> l(call->mutex);
        if (--call->running == 0) call->done.notify_all();
      });
    }
  }
  cv_.notify_all();
  call->Run();
  std::unique_lock<std::mutex> lock(call->mutex);
  call->closed = true;
  call->done.wait(lock, [&] { return call->running == 0; });
  if (call->error) std::rethrow_exception(call->error);
}

}  // namespace prism
