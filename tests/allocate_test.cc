// The allocation endpoint a Kubernetes deployment routes new sessions with
// (deploy/k8s/README.md): a real prism-server, queried with prism-probe (the
// tool the container's HEALTHCHECK uses), filled to capacity with a real client
// session.
#include <unistd.h>

#include <filesystem>
#include <memory>
#include <regex>
#include <string>

#include <gtest/gtest.h>

#include "prism/client/client.h"
#include "tests/client_rig.h"
#include "tests/server_process.h"
#include "tests/test_process.h"

namespace prism {
namespace {
namespace fs = std::filesystem;
using test::Bin;
using test::Execute;
using test::JsonNumber;
using test::ProcessResult;
using test::ServerProcess;
using test::SmallRig;

class AllocateTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("prism_allocate_test_" + std::to_string(getpid()));
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override {
    if (!HasFailure()) fs::remove_all(dir_);
  }
  fs::path dir_;
};

TEST_F(AllocateTest, AdvertisesTheEndpointAndFreeCapacityThenRefusesWhenFull) {
  ServerProcess server((dir_ / "data").string(),
                       {"--max-sessions", "1", "--advertise", "tcp://prism-0.prism-pods.default.svc:5555"},
                       (dir_ / "server.log").string());
  ASSERT_TRUE(server.ok());
  const std::string probe = Bin("prism-probe") + " " + server.metrics();

  ProcessResult r = Execute(probe + "/healthz");
  EXPECT_EQ(r.exit_code, 0) << r.out;
  EXPECT_EQ(r.out, "ok\n");

  r = Execute(probe + "/allocate");
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_EQ(test::JsonString(r.out, "endpoint"), "tcp://prism-0.prism-pods.default.svc:5555") << r.out;
  EXPECT_EQ(JsonNumber(r.out, "free"), 1) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "sessions_capacity"), 1) << r.out;
  r = Execute(probe + "/readyz");  // the readiness probe: the same test, not an allocation request
  EXPECT_EQ(r.exit_code, 0) << r.out;
  EXPECT_EQ(r.out, "ready\n");

  // One open session fills the server: /allocate says 503 with free 0, so a
  // caller asks another replica.
  std::unique_ptr<client::Session> session;
  const client::Status open = client::Session::Open(server.endpoint(), SmallRig(), {}, &session);
  ASSERT_TRUE(open.ok()) << open.ToString();
  r = Execute(probe + "/allocate");
  EXPECT_EQ(r.exit_code, 1) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "free"), 0) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "sessions_active"), 1) << r.out;
  r = Execute(probe + "/readyz");
  EXPECT_EQ(r.exit_code, 1) << r.out;
  EXPECT_EQ(r.out.rfind("full\n", 0), 0u) << r.out;  // prism-probe adds the status on stderr

  client::Summary summary;
  EXPECT_TRUE(session->Close(20000, &summary).ok());
  session.reset();
  r = Execute(probe + "/allocate");
  EXPECT_EQ(r.exit_code, 0) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "free"), 1) << r.out;

  r = Execute(probe + "/nothing-here");
  EXPECT_EQ(r.exit_code, 1) << r.out;
  // Three /allocate requests; the two /readyz probes are not among them.
  r = Execute(probe + "/metrics");
  std::smatch count;
  ASSERT_TRUE(std::regex_search(r.out, count, std::regex("\nprism_allocate_requests_total ([0-9]+)\n"))) << r.out;
  EXPECT_EQ(count[1], "3") << r.out;
  EXPECT_EQ(server.Stop(), 0);
  // Nobody listens any more: prism-probe says so with exit code 2.
  r = Execute(Bin("prism-probe") + " --timeout-ms 500 " + server.metrics() + "/healthz");
  EXPECT_EQ(r.exit_code, 2) << r.out;
}

TEST_F(AllocateTest, ProbeRejectsBadArguments) {
  EXPECT_EQ(Execute(Bin("prism-probe") + " ftp://x/").exit_code, 2);
  EXPECT_EQ(Execute(Bin("prism-probe") + " http://127.0.0.1/healthz").exit_code, 2);
  EXPECT_EQ(Execute(Bin("prism-probe") + " --timeout-ms 0 http://127.0.0.1:1/").exit_code, 2);
}

TEST(ServerOptionsTest, AdvertiseMustBeATcpEndpoint) {
  const ProcessResult r = Execute(Bin("prism-server") + " --data-dir /tmp --advertise prism-0:5555");
  EXPECT_EQ(r.exit_code, 2) << r.out;
  EXPECT_NE(r.out.find("advertise"), std::string::npos) << r.out;
}

// The live sessions' backlog (skip-depth-update-backlog-live) is checked like the upload sessions'.
TEST(ServerOptionsTest, TheLiveBacklogMustBeInRange) {
  for (const char* bad : {"-1", "1025", "two"}) {
    const ProcessResult r = Execute(Bin("prism-server") + " --data-dir /tmp --skip-depth-update-backlog-live " + bad);
    EXPECT_EQ(r.exit_code, 2) << bad << ": " << r.out;
    EXPECT_NE(r.out.find("skip"), std::string::npos) << bad << ": " << r.out;
  }
}

// The live sessions' wait for the SLAM's adjustment (slam-adjustment-max-wait-live) must be a finite
// number of milliseconds.
TEST(ServerOptionsTest, TheLiveAdjustmentWaitMustBeANumber) {
  for (const char* bad : {"soon", "inf", "nan"}) {
    const ProcessResult r = Execute(Bin("prism-server") + " --data-dir /tmp --slam-adjustment-max-wait-live " + bad);
    EXPECT_EQ(r.exit_code, 2) << bad << ": " << r.out;
    EXPECT_NE(r.out.find("adjustment"), std::string::npos) << bad << ": " << r.out;
  }
}

}  // namespace
}  // namespace prism
