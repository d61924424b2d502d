// The Docker image end to end (label slow): ../shared/tools/container.sh builds
// the unmodified Dockerfile with buildah, prism-server runs inside the image
// (through its entrypoint, configured by environment, as the non-root user,
// host network), prism-client streams a synthetic sequence to it from the host
// over 127.0.0.1, and the map that comes back is scored against the ground
// truth. The image's own HEALTHCHECK command is run against the server. Skips,
// saying why, without root, buildah or container.sh.
//
// PRISM_CONTAINER_IMAGE=TAG uses an image already built from this tree instead
// of building prism:test.
#include <fcntl.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "core/io/ply_io.h"
#include "core/io/sequence.h"
#include "core/io/trajectory_io.h"
#include "tests/sim3_from_trajectory.h"
#include "tests/test_process.h"

namespace prism {
namespace {
namespace fs = std::filesystem;
using test::Bin;
using test::Execute;
using test::JsonNumber;
using test::ProcessResult;

std::string ContainerScript() {
  if (const char *env = std::getenv("PRISM_CONTAINER_SH")) return env;
  return std::string(PRISM_SOURCE_DIR) + "/../shared/tools/container.sh";
}

// A port free on 127.0.0.1 right now (the server in the image binds it by
// number: the HEALTHCHECK reads the port from PRISM_METRICS, so "any free port"
// cannot be used there).
int FreePort() {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t len = sizeof(addr);
  if (bind(fd, reinterpret_cast<sockaddr *>(&addr), sizeof(addr)) != 0 ||
      getsockname(fd, reinterpret_cast<sockaddr *>(&addr), &len) != 0) {
    close(fd);
    return -1;
  }
  close(fd);
  return ntohs(addr.sin_port);
}

// `container.sh run TAG -- CMD...` in its own process group, stdout read for
// the server's first line.
class ContainerProcess {
 public:
  ContainerProcess(const std::vector<std::string> &argv_in, const std::string &log_path) {
    int out[2];
    if (pipe(out) != 0) return;
    pid_ = fork();
    if (pid_ == 0) {
      setpgid(0, 0);
      dup2(out[1], 1);
      const int log = open(log_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
      if (log >= 0) dup2(log, 2);
      close(out[0]);
      std::vector<std::string> all = argv_in;
      std::vector<char *> argv;
      for (auto &a : all) argv.push_back(a.data());
      argv.push_back(nullptr);
      execv(argv[0], argv.data());
      _exit(127);
    }
    setpgid(pid_, pid_);
    close(out[1]);
    char c;
    while (read(out[0], &c, 1) == 1 && c != '\n') first_line_ += c;
    close(out[0]);
  }
  ~ContainerProcess() { Stop(); }
  const std::string &first_line() const { return first_line_; }

  // SIGTERM to prism-server itself (buildah run does not pass signals on: it SIGKILLs its child), found
  // among this process's descendants; then waits for container.sh, whose exit code is the server's. -1
  // when the server was not found or everything had to be killed.
  int Stop(int timeout_ms = 30000) {
    if (pid_ <= 0) return exit_code_;
    const std::vector<pid_t> servers = Descendants(pid_, "prism-server");
    for (pid_t server : servers) kill(server, SIGTERM);
    if (servers.empty()) kill(-pid_, SIGTERM);
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
    int status = 0;
    while (waitpid(pid_, &status, WNOHANG) == 0) {
      if (std::chrono::steady_clock::now() > deadline) {
        kill(-pid_, SIGKILL);
        waitpid(pid_, &status, 0);
        pid_ = -1;
        return exit_code_ = -1;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    pid_ = -1;
    if (servers.empty()) return exit_code_ = -1;
    return exit_code_ = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  }

 private:
  // Processes below `root` (by parent pid, from /proc) whose command name is `comm`.
  static std::vector<pid_t> Descendants(pid_t root, const std::string &comm) {
    std::vector<std::pair<pid_t, pid_t>> parent_of;  // (pid, ppid)
    std::vector<std::string> names;
    for (const auto &entry : fs::directory_iterator("/proc")) {
      const std::string name = entry.path().filename().string();
      if (name.find_first_not_of("0123456789") != std::string::npos) continue;
      std::ifstream stat(entry.path() / "stat");
      std::string line;
      if (!std::getline(stat, line)) continue;
      // pid (comm) state ppid ...: comm may hold spaces, so parse after the last ')'.
      const size_t open = line.find('('), close = line.rfind(')');
      if (open == std::string::npos || close == std::string::npos) continue;
      std::istringstream rest(line.substr(close + 2));
      char state;
      pid_t ppid = 0;
      rest >> state >> ppid;
      parent_of.emplace_back(std::stoi(name), ppid);
      names.push_back(line.substr(open + 1, close - open - 1));
    }
    std::vector<pid_t> found, frontier = {root};
    std::vector<bool> seen(parent_of.size(), false);
    while (!frontier.empty()) {
      const pid_t parent = frontier.back();
      frontier.pop_back();
      for (size_t i = 0; i < parent_of.size(); ++i)
        if (!seen[i] && parent_of[i].second == parent) {
          seen[i] = true;
          frontier.push_back(parent_of[i].first);
          if (names[i] == comm) found.push_back(parent_of[i].first);
        }
    }
    return found;
  }

  pid_t pid_ = -1;
  int exit_code_ = -1;
  std::string first_line_;
};

TEST(ContainerTest, ServerInTheImageReconstructsASequenceStreamedFromTheHost) {
  const std::string script = ContainerScript();
  if (geteuid() != 0) GTEST_SKIP() << "container.sh needs root (buildah); skipped";
  if (access(script.c_str(), X_OK) != 0) GTEST_SKIP() << "no " << script << "; skipped";
  if (Execute("command -v buildah").exit_code != 0) GTEST_SKIP() << "buildah is not installed; skipped";
  const fs::path dir = fs::temp_directory_path() / ("prism_container_test_" + std::to_string(getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  auto p = [&](const std::string &name) { return (dir / name).string(); };

  std::string image = "prism:test";
  if (const char *env = std::getenv("PRISM_CONTAINER_IMAGE")) {
    image = env;
  } else {
    // HEALTHCHECK is a Docker-format field: OCI images (buildah's default) drop
    // it.
    const ProcessResult build = Execute("cd " + std::string(PRISM_SOURCE_DIR) + " && BUILDAH_FORMAT=docker " + script +
                                        " build " + image + " > " + p("build.log"));
    ASSERT_EQ(build.exit_code, 0) << build.out << " (see " << p("build.log") << ")";
  }

  // The image's configuration: non-root user, exposed ports, the data volume, a
  // HEALTHCHECK.
  // (buildah's --format templates have no json function: the fields one by
  // one.)
  ProcessResult inspect = Execute(
      "buildah inspect --type image --format '{{.Docker.Config.User}}|{{range "
      "$k, $v := .Docker.Config.ExposedPorts}}"
      "{{$k}} {{end}}|{{range $k, $v := .Docker.Config.Volumes}}{{$k}} "
      "{{end}}' " +
      image);
  ASSERT_EQ(inspect.exit_code, 0) << inspect.out;
  EXPECT_EQ(inspect.out.rfind("prism|", 0), 0u) << "USER: " << inspect.out;
  EXPECT_NE(inspect.out.find("5555/tcp"), std::string::npos) << inspect.out;
  EXPECT_NE(inspect.out.find("9100/tcp"), std::string::npos) << inspect.out;
  EXPECT_NE(inspect.out.find("|/var/lib/prism "), std::string::npos) << inspect.out;
  const ProcessResult healthcheck = Execute(
      "buildah inspect --type image --format '{{index "
      ".Docker.Config.Healthcheck.Test 1}}' " +
      image);
  ASSERT_EQ(healthcheck.exit_code, 0) << healthcheck.out;
  const std::string health_command = healthcheck.out.substr(0, healthcheck.out.find_last_not_of("\n") + 1);
  ASSERT_NE(health_command.find("/healthz"), std::string::npos) << health_command;

  constexpr int kFrames = 60;  // as roundtrip_test
  ProcessResult r = Execute(Bin("prism-synth") + " --preset bunny-multicolor-forward --frames " +
                            std::to_string(kFrames) + " --out " + p("seq"));
  if (r.exit_code != 0 && r.out.find("not found") != std::string::npos) GTEST_SKIP() << r.out;
  ASSERT_EQ(r.exit_code, 0) << r.out;

  const int zmq_port = FreePort(), http_port = FreePort();
  ASSERT_GT(zmq_port, 0);
  ASSERT_GT(http_port, 0);
  const std::string metrics = "127.0.0.1:" + std::to_string(http_port);
  // The entrypoint as the image runs it, configured by environment only.
  ContainerProcess server({script, "run", image, "--", "env", "PRISM_BIND=tcp://127.0.0.1:" + std::to_string(zmq_port),
                           "PRISM_METRICS=" + metrics, "PRISM_MAX_SESSIONS=2", "prism-entrypoint"},
                          p("server.log"));
  ASSERT_NE(server.first_line().find("\"endpoint\": \"tcp://127.0.0.1:" + std::to_string(zmq_port) + "\""),
            std::string::npos)
      << server.first_line() << " (see " << p("server.log") << ")";

  // The HEALTHCHECK exactly as the image declares it, in a second container of
  // the image.
  r = Execute(script + " run " + image + " -- env PRISM_METRICS=" + metrics + " sh -c '" + health_command + "'");
  EXPECT_EQ(r.exit_code, 0) << health_command << ": " << r.out;
  r = Execute(script + " run " + image + " -- id -un");
  EXPECT_NE(r.out.find("prism"), std::string::npos) << r.out;
  // A scripted Python client inside the image (the prism_client bindings, installed there) asks the
  // server where to open a session.
  r = Execute(script + " run " + image + " -- python3 -c 'import prism_client; print(prism_client.allocate(\"http://" +
              metrics + "\"))'");
  EXPECT_EQ(r.exit_code, 0) << r.out;
  EXPECT_NE(r.out.find("'endpoint': 'tcp://127.0.0.1:" + std::to_string(zmq_port) + "'"), std::string::npos) << r.out;
  r = Execute(Bin("prism-probe") + " http://" + metrics + "/allocate");
  EXPECT_EQ(r.exit_code, 0) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "free"), 2) << r.out;

  r = Execute(Bin("prism-client") + " stream --server tcp://127.0.0.1:" + std::to_string(zmq_port) + " --sequence " +
              p("seq") + " --out " + p("out"));
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "poses"), kFrames) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "errors"), 0) << r.out;
  EXPECT_GE(JsonNumber(r.out, "chunks"), 1) << r.out;
  EXPECT_EQ(server.Stop(), 0) << "prism-server in the image should drain and exit 0 on SIGTERM (see " << p("server.log")
                              << ")";

  StatusOr<Trajectory> trajectory = ReadTumTrajectory(p("out/trajectory.txt"));
  ASSERT_TRUE(trajectory.ok()) << trajectory.status();
  EXPECT_GE(trajectory->size(), static_cast<size_t>(kFrames) / 2);
  StatusOr<PointCloud> map = ReadPointCloudPly(p("out/map.ply"));
  ASSERT_TRUE(map.ok()) << map.status();
  ASSERT_GT(map->size(), 1000u);
  // The map in the ground-truth frame (Sim(3) through the streamed trajectory, as roundtrip_test aligns
  // it), scored on the object.
  StatusOr<Sequence> seq = LoadSequence(p("seq"));
  ASSERT_TRUE(seq.ok()) << seq.status();
  const test::TrajectoryAlignment alignment = test::AlignTrajectory(*trajectory, seq->groundtruth);
  ASSERT_TRUE(alignment.ok);
  EXPECT_EQ(alignment.pairs, trajectory->size());
  for (Eigen::Vector3f &point : map->positions) point = (alignment.gt_from_est * point.cast<double>()).cast<float>();
  map->normals.clear();
  ASSERT_TRUE(WritePointCloudPly(p("aligned.ply"), *map).ok());
  r = Execute(Bin("prism-eval") + " cloud --object-only --sequence " + p("seq") + " --cloud " + p("aligned.ply"));
  ASSERT_EQ(r.exit_code, 0) << r.out;
  const double accuracy = JsonNumber(r.out, "accuracy_median_m"), fscore = JsonNumber(r.out, "fscore");
  std::cout << "container round trip: " << kFrames << " frames, ATE " << alignment.ate_rmse_m << " m over a "
            << alignment.path_m << " m path, " << map->size() << " map points; on the object: accuracy median "
            << accuracy << " m, F-score " << fscore << "\n";
  // The same bars as roundtrip_test (a frame or scale mistake puts the map tens of centimetres away).
  EXPECT_LT(alignment.ate_rmse_m / alignment.path_m, /*max_ate_fraction_of_path=*/0.35);
  EXPECT_LT(accuracy, /*max_map_accuracy_median_m=*/0.06);
  EXPECT_GE(fscore, /*min_map_fscore_at_1pct_of_object=*/0.05);
  if (!::testing::Test::HasFailure()) fs::remove_all(dir);
}

}  // namespace
}  // namespace prism
