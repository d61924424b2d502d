#include <atomic>
#include <chrono>
#include <future>
#include <memory>
#include <nlohmann/json.hpp>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "core/util/log_level.h"
#include "core/util/status.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace {

StatusOr<int> ParsePositive(int v) {
  if (v <= 0) return InvalidArgumentError("value must be positive, got " + std::to_string(v));
  return v;
}

Status UsesMacros(int v, int* out) {
  PRISM_ASSIGN_OR_RETURN(*out, ParsePositive(v));
  return Status::Ok();
}

TEST(StatusTest, OkAndErrorsCarryCodeAndMessage) {
  EXPECT_TRUE(Status::Ok().ok());
  const Status s = NotFoundError("no such session 42");
  EXPECT_FALSE(s.ok());
  EXPECT_EQ(s.code(), StatusCode::kNotFound);
  EXPECT_EQ(s.ToString(), "NOT_FOUND: no such session 42");
}

TEST(StatusTest, AssignOrReturnPropagates) {
  int out = 0;
  EXPECT_TRUE(UsesMacros(3, &out).ok());
  EXPECT_EQ(out, 3);
  const Status s = UsesMacros(-1, &out);
  EXPECT_EQ(s.code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(out, 3);
}

TEST(LogJsonTest, KeyValueMessagesBecomeFieldsAndOtherTextAMessage) {
  const std::string line = FormatLogJson("2026-01-01T00:00:00.000Z", "INFO", "server.cc:12",
                                         "event=session_opened session=s1-ab client=\"a \\\"quoted\\\" name\" "
                                         "frames=300 ratio=0.5 ok=true");
  const nlohmann::json j = nlohmann::json::parse(line);
  EXPECT_EQ(j["level"], "INFO");
  EXPECT_EQ(j["source"], "server.cc:12");
  EXPECT_EQ(j["event"], "session_opened");
  EXPECT_EQ(j["session"], "s1-ab");
  EXPECT_EQ(j["client"], "a \"quoted\" name");
  EXPECT_EQ(j["frames"], 300);
  EXPECT_DOUBLE_EQ(j["ratio"].get<double>(), 0.5);
  EXPECT_EQ(j["ok"], true);
  // Free text (newlines, quotes, bytes that are not UTF-8) stays one valid JSON object on one line.
  const std::string free_text = FormatLogJson("t", "WARN", "x.cc:1", "slam: \"odd\" text\nsecond line \xff end");
  EXPECT_EQ(free_text.find('\n'), std::string::npos);
  const nlohmann::json k = nlohmann::json::parse(free_text);
  EXPECT_EQ(k["message"].get<std::string>().substr(0, 18), "slam: \"odd\" text\ns");
  EXPECT_FALSE(k.contains("slam"));
  // Pairs, then free text: both kept.
  const nlohmann::json m = nlohmann::json::parse(FormatLogJson("t", "INFO", "x.cc:1", "event=a n=1 (logged once)"));
  EXPECT_EQ(m["event"], "a");
  EXPECT_EQ(m["message"], "(logged once)");
}

TEST(LogJsonTest, FormatNamesAreChecked) {
  EXPECT_TRUE(SetLogFormat("json"));
  EXPECT_TRUE(SetLogFormat("text"));
  EXPECT_FALSE(SetLogFormat("xml"));
}

TEST(CheckTest, FailedCheckThrowsWithMessage) {
  EXPECT_THROW(PRISM_CHECK(1 == 2) << "context", CheckError);
  try {
    PRISM_CHECK_LT(5, 2) << "five";
  } catch (const CheckError& e) {
    EXPECT_NE(std::string(e.what()).find("five"), std::string::npos);
  }
  PRISM_CHECK(true) << "never evaluated";
}

TEST(ThreadPoolTest, ParallelForVisitsEveryIndexOnce) {
  ThreadPool pool(3);
  std::vector<std::atomic<int>> hits(1000);
  pool.ParallelFor(
      0, 1000, [&](std::ptrdiff_t i) { hits[i]++; }, 7);
  for (auto& h : hits) EXPECT_EQ(h.load(), 1);
}

TEST(ThreadPoolTest, ExceptionIsRethrown) {
  ThreadPool pool(2);
  EXPECT_THROW(pool.ParallelFor(0, 100, [](std::ptrdiff_t i) { PRISM_CHECK(i != 50); }), CheckError);
  // The pool still works afterwards.
  std::atomic<int> n{0};
  pool.ParallelFor(0, 10, [&](std::ptrdiff_t) { n++; });
  EXPECT_EQ(n.load(), 10);
}

// Two ParallelFor calls from different threads share the pool's worker. The first call's work blocks
// until the second call has returned; the second's helper task sits in the queue behind the first's,
// so the second call must not wait for that helper (it runs every index itself and returns).
TEST(ThreadPoolTest, ACallDoesNotWaitForAnotherCallsWork) {
  ThreadPool pool(2);
  std::promise<void> release;
  std::shared_future<void> released = release.get_future().share();
  std::atomic<int> blocked{0};
  std::thread first([&] {
    pool.ParallelFor(0, 2, [&](std::ptrdiff_t) {
      ++blocked;
      released.wait();
    });
  });
  // Both threads of the pool (the worker and `first`) are inside the first call's work.
  while (blocked.load() < 2) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  std::atomic<int> n{0};
  std::future<void> second =
      std::async(std::launch::async, [&] { pool.ParallelFor(0, 100, [&](std::ptrdiff_t) { n++; }); });
  // Generous: the second call's own work is 100 increments. Without the fix it returns only after release.
  const bool returned = second.wait_for(std::chrono::seconds(30)) == std::future_status::ready;
  release.set_value();
  first.join();
  second.wait();
  EXPECT_TRUE(returned) << "the second ParallelFor waited for the first call's work";
  EXPECT_EQ(n.load(), 100);
  // The stale helper of the second call ran as a no-op; the pool still works.
  std::atomic<int> m{0};
  pool.ParallelFor(0, 10, [&](std::ptrdiff_t) { m++; });
  EXPECT_EQ(m.load(), 10);
}

// A call made from inside another call's loop (both threads of the pool in the outer loop): each inner
// call runs its indices itself and returns; its helper task, queued behind the outer loop's, no longer has
// to run first. With the old pool both threads waited for helpers only they could run, for ever.
TEST(ThreadPoolTest, ACallInsideAnotherCallsLoopReturns) {
  // The pool and the calling thread are leaked when the calls never return, so that the test fails
  // instead of hanging (a detached thread; std::async's future would wait in its destructor).
  auto* pool = new ThreadPool(2);
  auto inner_sum = std::make_shared<std::atomic<int>>(0);
  auto done = std::make_shared<std::promise<void>>();
  std::future<void> returned = done->get_future();
  std::thread([pool, inner_sum, done] {
    std::atomic<int> entered{0};
    pool->ParallelFor(0, 2, [&](std::ptrdiff_t) {
      // Both threads inside the outer loop before either calls again.
      ++entered;
      while (entered.load() < 2) std::this_thread::yield();
      pool->ParallelFor(0, 50, [&](std::ptrdiff_t) { ++*inner_sum; });
    });
    done->set_value();
  }).detach();
  ASSERT_EQ(returned.wait_for(std::chrono::seconds(30)), std::future_status::ready)
      << "a ParallelFor inside another one's loop did not return";
  EXPECT_EQ(inner_sum->load(), 100);
  delete pool;
}

}  // namespace
}  // namespace prism
