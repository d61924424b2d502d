// The live 3D view in a real browser: prism-client streams a rendered sequence to a real prism-server
// with --view, and Debian's headless chromium (driven by playwright-core: tests/live_view_browser.mjs)
// loads the page while the session runs. From the page itself: every chunk decoded to the points
// prism-client says it holds, the points shown are prism-client's map, and the picture is not blank.
// The screenshot is left in build/test_outputs/live_view/. Skips only without chromium, node or
// playwright-core (scripts/setup.sh installs all three).
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <regex>
#include <string>
#include <thread>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "tests/server_process.h"
#include "tests/test_process.h"

namespace prism {
namespace {

namespace fs = std::filesystem;
using test::Bin;
using test::Execute;
using test::JsonNumber;
using test::ProcessResult;
using test::ReadFileText;
using test::ServerProcess;

// Pixels of `png` that differ from its bottom-right corner (the background) by more than a few levels.
double DrawnFraction(const std::string& png) {
  const cv::Mat image = cv::imread(png, cv::IMREAD_COLOR);
  if (image.empty()) return 0;
  const cv::Vec3b background = image.at<cv::Vec3b>(image.rows - 1, image.cols - 1);
  size_t drawn = 0;
  for (int y = 0; y < image.rows; ++y)
    for (int x = 0; x < image.cols; ++x) {
      const cv::Vec3b p = image.at<cv::Vec3b>(y, x);
      if (std::abs(p[0] - background[0]) + std::abs(p[1] - background[1]) + std::abs(p[2] - background[2]) > 24)
        ++drawn;
    }
  return static_cast<double>(drawn) / static_cast<double>(image.total());
}

TEST(LiveViewTest, ChromiumShowsTheMapAsItStreams) {
  const std::string web = std::string(PRISM_SOURCE_DIR) + "/web";
  if (access("/usr/bin/chromium", X_OK) != 0)
    GTEST_SKIP() << "Debian's chromium is not installed (bash scripts/setup.sh installs it)";
  if (Execute("node --version").exit_code != 0) GTEST_SKIP() << "node is not installed (bash scripts/setup.sh)";
  if (!fs::exists(web + "/node_modules/playwright-core"))
    GTEST_SKIP() << "playwright-core is not in web/node_modules (bash scripts/setup.sh runs npm ci there)";

  const fs::path dir = fs::temp_directory_path() / ("prism_live_view_test_" + std::to_string(getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  auto P = [&](const std::string& name) { return (dir / name).string(); };
  constexpr int kFrames = 90;
  ProcessResult r = Execute(Bin("prism-synth") + " --preset bunny-multicolor-forward --frames " +
                            std::to_string(kFrames) + " --size 256x256 --out " + P("seq"));
  ASSERT_EQ(r.exit_code, 0) << r.out;
  ServerProcess server(P("data"), {"--keyframe-queue", "64"}, P("server.log"));
  ASSERT_TRUE(server.ok());

  // prism-client in the background: it streams once the page has connected (--view-wait), so that the
  // page sees the map grow, and keeps the view up after the session until the test's SIGTERM.
  const std::string command = "exec " + Bin("prism-client") + " stream --server " + server.endpoint() + " --sequence " +
                              P("seq") + " --out " + P("out") +
                              " --view 127.0.0.1:0 --view-wait 120 --view-linger 600 > " + P("client.json") + " 2> " +
                              P("client.log");
  const pid_t client = fork();
  if (client == 0) {
    execl("/bin/sh", "sh", "-c", command.c_str(), static_cast<char*>(nullptr));
    _exit(127);
  }
  ASSERT_GT(client, 0);
  std::string url;
  const std::regex url_line("live view at (http://127\\.0\\.0\\.1:[0-9]+/)");
  for (int i = 0; i < 300 && url.empty(); ++i) {
    std::smatch m;
    const std::string log = ReadFileText(P("client.log"));
    if (std::regex_search(log, m, url_line)) url = m[1];
    else std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  ASSERT_FALSE(url.empty()) << ReadFileText(P("client.log"));

  const fs::path outputs = fs::path(PRISM_BINARY_DIR) / "test_outputs" / "live_view";
  fs::create_directories(outputs);
  const std::string screenshot = (outputs / "live_view.png").string();
  fs::remove(screenshot);
  constexpr int kPageTimeoutMs = 240000;  // the stream, the session's end and the last chunk's decode
  r = Execute("node " + std::string(PRISM_SOURCE_DIR) + "/tests/live_view_browser.mjs " + url + " " + screenshot + " " +
              web + " " + std::to_string(kPageTimeoutMs));
  kill(client, SIGTERM);  // ends the view's linger; the client exits as after any stream
  int status = 0;
  waitpid(client, &status, 0);
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << ReadFileText(P("client.log"));
  EXPECT_EQ(server.Stop(), 0);
  ASSERT_EQ(r.exit_code, 0) << r.out;
  std::printf("live view: screenshot %s\npage: %s", screenshot.c_str(), r.out.c_str());

  const std::string summary = ReadFileText(P("client.json"));
  // The page was open while the session ran (it saw it before its end).
  EXPECT_TRUE(r.out.find("\"streaming\"") != std::string::npos || r.out.find("\"closing\"") != std::string::npos)
      << r.out;
  // Every chunk the page fetched decoded to the points prism-client said it holds ...
  EXPECT_NE(r.out.find("\"mismatches\":[]"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("\"errors\":[]"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("\"console_errors\":[]"), std::string::npos) << r.out;
  // The map grew chunk by chunk in the page (the last keyframe's chunk may be replaced by the rebuilt
  // map before the page's next poll, so not every chunk need have been decoded).
  EXPECT_GE(JsonNumber(r.out, "chunks_decoded"), 2) << r.out;
  EXPECT_LE(JsonNumber(r.out, "points_decoded"), JsonNumber(summary, "chunk_points")) << summary;
  // ... and the points shown are those of the chunks that make the map now, which at the end is
  // prism-client's map (one chunk that replaced the map, voxel for voxel).
  EXPECT_EQ(JsonNumber(r.out, "points_shown"), JsonNumber(r.out, "api_chunk_points")) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "chunks_shown"), JsonNumber(r.out, "api_chunks")) << r.out;
  if (JsonNumber(r.out, "api_chunks") == 1 && summary.find("\"map_replaced\":true") != std::string::npos) {
    EXPECT_EQ(JsonNumber(r.out, "points_shown"), JsonNumber(summary, "map_points")) << summary;
  }
  EXPECT_GT(JsonNumber(r.out, "points_shown"), 1000) << r.out;
  // The path: every tracked pose of trajectory.txt.
  std::ifstream trajectory(P("out/trajectory.txt"));
  double tracked = 0;
  for (std::string line; std::getline(trajectory, line);) tracked += !line.empty() && line[0] != '#';
  EXPECT_EQ(JsonNumber(r.out, "poses_shown"), tracked) << r.out;
  // Not blank: the map and the path cover a good part of the picture, read back from the page's own
  // canvas and from the screenshot file. Measured: 0.12 of the canvas; a blank canvas is 0.
  constexpr double kMinDrawnFraction = 0.05;
  const double canvas_drawn = JsonNumber(r.out, "drawn"), canvas_total = JsonNumber(r.out, "total");
  ASSERT_GT(canvas_total, 0) << r.out;
  EXPECT_GT(canvas_drawn / canvas_total, kMinDrawnFraction) << r.out;
  EXPECT_GT(DrawnFraction(screenshot), kMinDrawnFraction) << screenshot;
  if (!HasFailure()) fs::remove_all(dir);
}

}  // namespace
}  // namespace prism
