// The process-wide dense workers shared by all sessions: a fixed number of threads run keyframe jobs
// (photometric stereo, fusion, ICP, map, chunk encoding) whose inner loops use one shared ThreadPool.
// Each session posts to its own Strand: a strand's jobs run one at a time in posting order (its map
// has one writer), different strands run in parallel, and ready strands take turns (round robin), so
// N sessions never start N x cores threads and one busy session cannot starve the others. A strand
// moved to the background (a session that floods the server) runs on one more worker of its own at the
// lowest priority (nice 19), its loops inline: it gets little CPU while other sessions want it.
#pragma once

#include <condition_variable>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

#include "core/util/thread_pool.h"

namespace prism {

class DenseWorkers {
 public:
  class Strand;

  // num_workers >= 1 job threads at niceness `nice` (ThreadPool), plus the background worker; pool
  // (not owned, may be null) runs the jobs' ParallelFor loops.
  DenseWorkers(int num_workers, ThreadPool* pool, int nice = 0);
  // Runs the jobs already posted, then joins the workers.
  ~DenseWorkers();
  DenseWorkers(const DenseWorkers&) = delete;
  DenseWorkers& operator=(const DenseWorkers&) = delete;

  std::shared_ptr<Strand> NewStrand();
  ThreadPool* pool() const { return pool_; }
  int num_workers() const { return static_cast<int>(threads_.size()) - 1; }  // besides the background one
  // Jobs posted and not yet finished, over all strands.
  size_t pending_jobs() const;

  class Strand : public std::enable_shared_from_this<Strand> {
   public:
    // Queues a job; it runs on a worker thread after this strand's earlier jobs. Exceptions escaping
    // the job are swallowed (jobs catch their own).
    void Post(std::function<void()> job);
    // Jobs queued or running on this strand.
    size_t pending() const;
    // Its jobs from now on run on the background worker (one running now finishes where it is).
    void MoveToBackground();

   private:
    friend class DenseWorkers;
    explicit Strand(DenseWorkers* owner) : owner_(owner) {}
    DenseWorkers* owner_;
    std::deque<std::function<void()>> jobs_;  // Guarded by owner_->mutex_.
    bool scheduled_ = false;                  // queued (either kind) or running; guarded by owner_->mutex_.
    bool background_ = false;                 // Guarded by owner_->mutex_.
    size_t running_ = 0;                      // Guarded by owner_->mutex_.
  };

 private:
  void WorkerLoop(bool background);
  // Queues a strand that has jobs and wakes a worker of its kind (mutex_ held).
  void Schedule(std::shared_ptr<Strand> strand);

  ThreadPool* pool_;
  mutable std::mutex mutex_;
  std::condition_variable cv_, background_cv_;
  std::deque<std::shared_ptr<Strand>> ready_;             // Guarded by mutex_.
  std::deque<std::shared_ptr<Strand>> background_ready_;  // Guarded by mutex_.
  size_t pending_ = 0;                                    // Guarded by mutex_.
  bool stop_ = false;                                     // Guarded by mutex_.
  std::vector<std::thread> threads_;
};

}  // namespace prism
