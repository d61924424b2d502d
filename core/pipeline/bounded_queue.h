// A bounded multi-producer queue with a stated overflow policy (STYLE.md §5): a producer on the
// network thread never blocks. Push says what happened so the caller can count it.
#pragma once

#include <condition_variable>
#include <cstddef>
#include <deque>
#include <mutex>
#include <optional>
#include <utility>

namespace prism {

enum class OverflowPolicy {
  kDropOldest,  // a full queue drops its oldest item to make room (live input)
  kReject,      // a full queue refuses the new item (upload: the client retries later)
};

enum class PushResult { kPushed, kDroppedOldest, kRejected, kClosed };

template <typename T>
class BoundedQueue {
 public:
  BoundedQueue(size_t capacity, OverflowPolicy policy) : capacity_(capacity < 1 ? 1 : capacity), policy_(policy) {}

  // Never blocks. kDroppedOldest: the item was queued and the oldest one discarded.
  PushResult Push(T item) {
    PushResult result = PushResult::kPushed;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (closed_) return PushResult::kClosed;
      if (items_.size() >= capacity_) {
        if (policy_ == OverflowPolicy::kReject) return PushResult::kRejected;
        items_.pop_front();
        result = PushResult::kDroppedOldest;
      }
      items_.push_back(std::move(item));
    }
    cv_.notify_one();
    return result;
  }

  // Blocks until an item is available or the queue is closed and empty (nullopt).
  std::optional<T> Pop() {
    std::unique_lock<std::mutex> lock(mutex_);
    cv_.wait(lock, [this] { return closed_ || !items_.empty(); });
    if (items_.empty()) return std::nullopt;
    T item = std::move(items_.front());
    items_.pop_front();
    return item;
  }

  // No more pushes; Pop drains what is queued, then returns nullopt.
  void Close() {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      closed_ = true;
    }
    cv_.notify_all();
  }
  // Discards the queued items; returns how many.
  size_t Clear() {
    std::lock_guard<std::mutex> lock(mutex_);
    const size_t n = items_.size();
    items_.clear();
    return n;
  }
  size_t size() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return items_.size();
  }
  size_t capacity() const { return capacity_; }

 private:
  const size_t capacity_;
  const OverflowPolicy policy_;
  mutable std::mutex mutex_;
  std::condition_variable cv_;
  std::deque<T> items_;  // Guarded by mutex_.
  bool closed_ = false;  // Guarded by mutex_.
};

}  // namespace prism
