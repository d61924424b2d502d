#include "server/metrics.h"

#include <atomic>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "core/util/check.h"

namespace prism::server {
namespace {

TEST(Metrics, RendersCountersGaugesAndLabelsInTheTextFormat) {
  Metrics m;
  m.Declare("prism_things_total", Metrics::Type::kCounter, "Things.");
  m.Declare("prism_things", Metrics::Type::kGauge, "Things now.");
  m.Add("prism_things_total");
  m.Add("prism_things_total", 2);
  m.Add("prism_things_total{kind=\"a\"}");
  m.Set("prism_things", 7);
  const std::string text = m.Render();
  EXPECT_NE(text.find("# HELP prism_things_total Things.\n# TYPE prism_things_total counter\n"), std::string::npos);
  EXPECT_NE(text.find("prism_things_total 3\n"), std::string::npos) << text;
  EXPECT_NE(text.find("prism_things_total{kind=\"a\"} 1\n"), std::string::npos) << text;
  EXPECT_NE(text.find("# TYPE prism_things gauge\nprism_things 7\n"), std::string::npos) << text;
  // A family whose name is a prefix of another's keeps its own series only.
  EXPECT_EQ(text.find("prism_things 3"), std::string::npos);
}

TEST(Metrics, HistogramBucketsAreCumulativeWithSumAndCount) {
  Metrics m;
  m.Declare("prism_latency_seconds", Metrics::Type::kHistogram, "Latency.", {0.01, 0.1, 1});
  // 0.005 + 0.01 + 0.05 + 0.5 + 5 in doubles is 5.5649999999999995.
  for (double v : {0.005, 0.01, 0.05, 0.5, 5.0}) m.Observe("prism_latency_seconds", v);
  const std::string text = m.Render();
  EXPECT_NE(text.find("prism_latency_seconds_bucket{le=\"0.01\"} 2\n"), std::string::npos) << text;  // le is <=
  EXPECT_NE(text.find("prism_latency_seconds_bucket{le=\"0.1\"} 3\n"), std::string::npos) << text;
  EXPECT_NE(text.find("prism_latency_seconds_bucket{le=\"1\"} 4\n"), std::string::npos) << text;
  EXPECT_NE(text.find("prism_latency_seconds_bucket{le=\"+Inf\"} 5\n"), std::string::npos) << text;
  EXPECT_NE(text.find("prism_latency_seconds_count 5\n"), std::string::npos) << text;
  EXPECT_NE(text.find("prism_latency_seconds_sum 5.5649999999999995\n"), std::string::npos) << text;
}

TEST(Metrics, RemovesASessionsSeriesAndRefusesUndeclaredOrMistypedNames) {
  Metrics m;
  m.Declare("prism_session_depth", Metrics::Type::kGauge, "Depth.");
  m.Set("prism_session_depth{session=\"s1\"}", 1);
  m.Set("prism_session_depth{session=\"s2\"}", 2);
  m.Remove("prism_session_depth", "session=\"s1\"");
  EXPECT_EQ(m.Render().find("s1"), std::string::npos);
  EXPECT_NE(m.Render().find("prism_session_depth{session=\"s2\"} 2"), std::string::npos);
  EXPECT_THROW(m.Add("prism_unknown_total"), CheckError);
  EXPECT_THROW(m.Add("prism_session_depth"), CheckError);  // a gauge, not a counter
}

TEST(Metrics, LabelValuesAreEscaped) { EXPECT_EQ(MetricLabel("a\"b\\c\nd"), "a\\\"b\\\\c\\nd"); }

TEST(Metrics, EveryServerFamilyRendersItsHelp) {
  Metrics m;
  DeclareServerMetrics(&m);
  const std::string text = m.Render();
  for (const char* family :
       {"prism_frame_to_pose_seconds", "prism_keyframe_to_chunk_seconds", "prism_dense_keyframe_seconds",
        "prism_session_tracking_state", "prism_zmq_handshake_failures_total", "prism_chunk_credit_stalls_total"})
    EXPECT_NE(text.find(std::string("# HELP ") + family + " "), std::string::npos) << family;
}

TEST(OncePerPeer, LogsEachPeerAndKindOnceAndStaysBounded) {
  OncePerPeer once(4);
  EXPECT_TRUE(once.First("peer-a", "version"));
  EXPECT_FALSE(once.First("peer-a", "version"));
  EXPECT_TRUE(once.First("peer-a", "not_found"));
  EXPECT_TRUE(once.First("peer-b", "version"));
  // Past the capacity it starts over instead of growing.
  EXPECT_TRUE(once.First("peer-c", "version"));
  EXPECT_TRUE(once.First("peer-d", "version"));
  EXPECT_TRUE(once.First("peer-a", "version"));
  // Thread-safe: many threads, one first.
  OncePerPeer shared;
  std::atomic<int> firsts{0};
  std::vector<std::thread> threads;
  for (int t = 0; t < 8; ++t)
    threads.emplace_back([&] {
      for (int i = 0; i < 1000; ++i)
        if (shared.First("same", "kind")) ++firsts;
    });
  for (auto& t : threads) t.join();
  EXPECT_EQ(firsts.load(), 1);
}

TEST(PeerName, IsHexOfTheRoutingId) {
  EXPECT_EQ(PeerName(std::string("\x00\x01\xab", 3)), "0001ab");
  EXPECT_EQ(PeerName(""), "-");
}

}  // namespace
}  // namespace prism::server
