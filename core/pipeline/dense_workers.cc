#include "core/pipeline/dense_workers.h"

#include <algorithm>

#include "core/util/logging.h"

namespace prism {

DenseWorkers::DenseWorkers(int num_workers, ThreadPool* pool, int nice) : pool_(pool) {
  if (num_workers < 1) num_workers = 1;
  for (int i = 0; i < num_workers; ++i)
    threads_.emplace_back([this, nice] {
      SetCurrentThreadName("prism-dense");
      if (nice != 0) SetCurrentThreadNice(nice);
      WorkerLoop(/*background=*/false);
    });
  threads_.emplace_back([this] {
    SetCurrentThreadName("prism-dense-bg");
    SetCurrentThreadNice(19);
    RunParallelForInlineOnThisThread();
    WorkerLoop(/*background=*/true);
  });
}

DenseWorkers::~DenseWorkers() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = true;
  }
  cv_.notify_all();
  background_cv_.notify_all();
  for (auto& t : threads_) t.join();
}

std::shared_ptr<DenseWorkers::Strand> DenseWorkers::NewStrand() { return std::shared_ptr<Strand>(new Strand(this)); }

size_t DenseWorkers::pending_jobs() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return pending_;
}

void DenseWorkers::Strand::Post(std::function<void()> job) {
  DenseWorkers* w = owner_;
  {
    std::lock_guard<std::mutex> lock(w->mutex_);
    jobs_.push_back(std::move(job));
    ++w->pending_;
    if (scheduled_) return;
    scheduled_ = true;
    // The strand is kept alive while queued or running.
    w->Schedule(shared_from_this());
  }
}

void DenseWorkers::Strand::MoveToBackground() {
  DenseWorkers* w = owner_;
  std::lock_guard<std::mutex> lock(w->mutex_);
  if (background_) return;
  background_ = true;
  auto it = std::find(w->ready_.begin(), w->ready_.end(), shared_from_this());
  if (it == w->ready_.end()) return;  // idle or running: queued by its kind next time
  w->ready_.erase(it);
  w->Schedule(shared_from_this());
}

void DenseWorkers::Schedule(std::shared_ptr<Strand> strand) {
  if (strand->background_) {
    background_ready_.push_back(std::move(strand));
    background_cv_.notify_one();
  } else {
    ready_.push_back(std::move(strand));
    cv_.notify_one();
  }
}

size_t DenseWorkers::Strand::pending() const {
  std::lock_guard<std::mutex> lock(owner_->mutex_);
  return jobs_.size() + running_;
}

void DenseWorkers::WorkerLoop(bool background) {
  std::deque<std::shared_ptr<Strand>>& ready = background ? background_ready_ : ready_;
  std::condition_variable& cv = background ? background_cv_ : cv_;
  std::unique_lock<std::mutex> lock(mutex_);
  for (;;) {
    cv.wait(lock, [&] { return !ready.empty() || (stop_ && pending_ == 0); });
    if (ready.empty()) return;  // stop_ and nothing pending
    std::shared_ptr<Strand> strand = std::move(ready.front());
    ready.pop_front();
    std::function<void()> job = std::move(strand->jobs_.front());
    strand->jobs_.pop_front();
    ++strand->running_;
    lock.unlock();
    try {
      job();
    } catch (const std::exception& e) {
      PRISM_LOG(ERROR) << "dense job threw: " << e.what();
    } catch (...) {
      PRISM_LOG(ERROR) << "dense job threw";
    }
    job = nullptr;
    lock.lock();
    --strand->running_;
    --pending_;
    if (!strand->jobs_.empty()) Schedule(std::move(strand));  // round robin: to the back
    else strand->scheduled_ = false;
    if (stop_ && pending_ == 0) {
      cv_.notify_all();
      background_cv_.notify_all();
    }
  }
}

}  // namespace prism
