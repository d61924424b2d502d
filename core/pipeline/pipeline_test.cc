#include <atomic>
#include <chrono>
#include <condition_variable>
#include <mutex>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "core/codec/frame_codec.h"
#include "core/pipeline/bounded_queue.h"
#include "core/pipeline/dense_workers.h"
#include "core/pipeline/session_pipeline.h"
#include "core/synth/presets.h"

namespace prism {
namespace {

TEST(BoundedQueueTest, DropOldestKeepsTheNewestAndRejectRefuses) {
  BoundedQueue<int> live(2, OverflowPolicy::kDropOldest);
  EXPECT_EQ(live.Push(1), PushResult::kPushed);
  EXPECT_EQ(live.Push(2), PushResult::kPushed);
  EXPECT_EQ(live.Push(3), PushResult::kDroppedOldest);
  EXPECT_EQ(*live.Pop(), 2);
  EXPECT_EQ(*live.Pop(), 3);
  BoundedQueue<int> upload(1, OverflowPolicy::kReject);
  EXPECT_EQ(upload.Push(1), PushResult::kPushed);
  EXPECT_EQ(upload.Push(2), PushResult::kRejected);
  upload.Close();
  EXPECT_EQ(upload.Push(3), PushResult::kClosed);
  EXPECT_EQ(*upload.Pop(), 1);
  EXPECT_FALSE(upload.Pop().has_value());
}

TEST(DenseWorkersTest, StrandsRunInOrderOneAtATimeAndInParallelWithEachOther) {
  DenseWorkers workers(2, nullptr);
  auto a = workers.NewStrand(), b = workers.NewStrand();
  std::mutex m;
  std::vector<int> order_a;
  std::atomic<int> running_a{0}, max_running_a{0}, running_total{0}, max_total{0};
  for (int i = 0; i < 20; ++i) {
    a->Post([&, i] {
      const int r = ++running_a, t = ++running_total;
      max_running_a = std::max(max_running_a.load(), r);
      max_total = std::max(max_total.load(), t);
      std::this_thread::sleep_for(std::chrono::milliseconds(2));
      {
        std::lock_guard<std::mutex> lock(m);
        order_a.push_back(i);
      }
      --running_a;
      --running_total;
    });
    b->Post([&] {
      const int t = ++running_total;
      max_total = std::max(max_total.load(), t);
      std::this_thread::sleep_for(std::chrono::milliseconds(2));
      --running_total;
    });
  }
  while (workers.pending_jobs() > 0) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  ASSERT_EQ(order_a.size(), 20u);
  for (int i = 0; i < 20; ++i) EXPECT_EQ(order_a[i], i);
  EXPECT_EQ(max_running_a.load(), 1);
  EXPECT_EQ(max_total.load(), 2);  // the two strands overlapped
}

// Collects a pipeline's events until kFinished.
struct EventLog {
  std::mutex mutex;
  std::condition_variable cv;
  std::vector<PipelineEvent> events;
  bool finished = false;
  PipelineEventSink Sink() {
    return [this](PipelineEvent&& e) {
      std::lock_guard<std::mutex> lock(mutex);
      if (e.kind == PipelineEvent::Kind::kFinished) finished = true;
      events.push_back(std::move(e));
      cv.notify_all();
    };
  }
  bool WaitFinished(int timeout_ms) {
    std::unique_lock<std::mutex> lock(mutex);
    return cv.wait_for(lock, std::chrono::milliseconds(timeout_ms), [this] { return finished; });
  }
};

TEST(SessionPipelineTest, BadFramesAreErrorsAndTheSessionGoesOnToFinish) {
  const RigCalibration rig = synth::MakeDefaultRig(160, 120);
  ThreadPool pool(2);
  DenseWorkers workers(1, &pool);
  EventLog log;
  SessionPipelineOptions options;
  StatusOr<std::unique_ptr<SessionPipeline>> p = SessionPipeline::Create(rig, options, &workers, log.Sink());
  ASSERT_TRUE(p.ok()) << p.status();
  EncodedFrame corrupt;
  corrupt.sequence_number = 1;
  corrupt.codec = FrameCodec::kPng;
  corrupt.bytes = {1, 2, 3, 4};
  ASSERT_TRUE((*p)->Push(corrupt).ok());  // accepted at the queue, refused at decode
  EncodedFrame wrong_size;
  wrong_size.sequence_number = 2;
  wrong_size.codec = FrameCodec::kRaw;
  wrong_size.bytes.assign(10 * 10 * 3, 0);
  ASSERT_TRUE((*p)->Push(wrong_size).ok());
  (*p)->Finish();
  ASSERT_TRUE(log.WaitFinished(10000));
  EXPECT_EQ((*p)->Push(corrupt).code(), StatusCode::kFailedPrecondition);
  int frame_errors = 0;
  for (const PipelineEvent& e : log.events)
    if (e.kind == PipelineEvent::Kind::kError) {
      EXPECT_TRUE(e.has_frame);
      EXPECT_FALSE(e.fatal);
      EXPECT_EQ(e.status.code(), StatusCode::kInvalidArgument) << e.status;
      ++frame_errors;
    }
  EXPECT_EQ(frame_errors, 2);
  EXPECT_EQ(log.events.back().kind, PipelineEvent::Kind::kFinished);
  EXPECT_EQ(log.events.back().stats.frames_bad, 2u);
  EXPECT_EQ(log.events.back().stats.frames_received, 2u);
}

TEST(SessionPipelineTest, RejectPolicyRefusesWhenFullAndCountsIt) {
  const RigCalibration rig = synth::MakeDefaultRig(160, 120);
  DenseWorkers workers(1, nullptr);
  EventLog log;
  SessionPipelineOptions options;
  options.frame_queue_capacity = 1;
  options.input_policy = OverflowPolicy::kReject;
  StatusOr<std::unique_ptr<SessionPipeline>> p = SessionPipeline::Create(rig, options, &workers, log.Sink());
  ASSERT_TRUE(p.ok()) << p.status();
  EncodedFrame f;
  f.codec = FrameCodec::kRaw;
  f.bytes.assign(3, 0);
  int rejected = 0;
  for (int i = 0; i < 200; ++i) {
    f.sequence_number = static_cast<uint64_t>(i);
    const Status s = (*p)->Push(f);
    if (!s.ok()) {
      EXPECT_EQ(s.code(), StatusCode::kResourceExhausted);
      ++rejected;
    }
  }
  (*p)->Finish();
  ASSERT_TRUE(log.WaitFinished(10000));
  EXPECT_EQ(log.events.back().stats.frames_rejected, static_cast<uint64_t>(rejected));
  EXPECT_EQ(log.events.back().stats.frames_received + rejected, 200u);
}

TEST(SessionPipelineTest, InvalidOptionsAreRefused) {
  SessionPipelineOptions options;
  options.frame_queue_capacity = 0;
  DenseWorkers workers(1, nullptr);
  EventLog log;
  EXPECT_EQ(SessionPipeline::Create(synth::MakeDefaultRig(160, 120), options, &workers, log.Sink()).status().code(),
            StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace prism
