// A real prism-server process for the integration suites: started on tcp://127.0.0.1:* (a free port),
// its endpoints read back from the JSON line it prints, stopped with SIGTERM; and an HTTP GET for
// its metrics endpoint.
#pragma once

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <string>
#include <thread>
#include <vector>

#include "tests/test_process.h"

namespace prism::test {

class ServerProcess {
 public:
  // args: extra flags ("--max-sessions 1"); stderr goes to log_path.
  ServerProcess(const std::string& data_dir, const std::vector<std::string>& args, const std::string& log_path) {
    int out[2];
    if (pipe(out) != 0) return;
    pid_ = fork();
    if (pid_ == 0) {
      dup2(out[1], 1);
      const int log = open(log_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
      if (log >= 0) dup2(log, 2);
      close(out[0]);
      std::vector<std::string> all = {Bin("prism-server"), "--bind",     "tcp://127.0.0.1:*", "--data-dir", data_dir,
                                      "--metrics",         "127.0.0.1:0"};
      all.insert(all.end(), args.begin(), args.end());
      std::vector<char*> argv;
      for (auto& a : all) argv.push_back(a.data());
      argv.push_back(nullptr);
      execv(argv[0], argv.data());
      _exit(127);
    }
    close(out[1]);
    // The first line: {"endpoint": "tcp://127.0.0.1:PORT", "metrics": "http://127.0.0.1:PORT"}
    std::string line;
    char c;
    while (read(out[0], &c, 1) == 1 && c != '\n') line += c;
    close(out[0]);
    endpoint_ = Field(line, "endpoint");
    metrics_ = Field(line, "metrics");
  }
  ~ServerProcess() { Stop(); }

  bool ok() const { return pid_ > 0 && !endpoint_.empty(); }
  const std::string& endpoint() const { return endpoint_; }
  const std::string& metrics() const { return metrics_; }
  pid_t pid() const { return pid_; }

  // SIGKILL (a crash): nothing is flushed or drained. Returns once the process is gone.
  void Kill() {
    if (pid_ <= 0) return;
    kill(pid_, SIGKILL);
    int status = 0;
    waitpid(pid_, &status, 0);
    pid_ = -1;
  }
  // Resident set size in KiB from /proc (0 when not running).
  long RssKib() const {
    if (pid_ <= 0) return 0;
    FILE* f = fopen(("/proc/" + std::to_string(pid_) + "/status").c_str(), "r");
    if (!f) return 0;
    char line[256];
    long kib = 0;
    while (fgets(line, sizeof(line), f))
      if (sscanf(line, "VmRSS: %ld kB", &kib) == 1) break;
    fclose(f);
    return kib;
  }

  // SIGTERM, then waits up to timeout; returns the exit code (-1 when it had to be killed).
  int Stop(int timeout_ms = 20000) {
    if (pid_ <= 0) return exit_code_;
    kill(pid_, SIGTERM);
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
    int status = 0;
    while (waitpid(pid_, &status, WNOHANG) == 0) {
      if (std::chrono::steady_clock::now() > deadline) {
        kill(pid_, SIGKILL);
        waitpid(pid_, &status, 0);
        pid_ = -1;
        return exit_code_ = -1;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    pid_ = -1;
    return exit_code_ = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  }

 private:
  static std::string Field(const std::string& json, const std::string& key) {
    const size_t k = json.find("\"" + key + "\": \"");
    if (k == std::string::npos) return "";
    const size_t b = k + key.size() + 5, e = json.find('"', b);
    return json.substr(b, e - b);
  }
  pid_t pid_ = -1;
  int exit_code_ = -1;
  std::string endpoint_, metrics_;
};

// The whole HTTP/1.0 response (status line, headers, body) to a GET of http://HOST:PORT/PATH; ""
// when the connection fails.
inline std::string HttpGet(const std::string& url) {
  const size_t host_begin = url.find("//") + 2, colon = url.rfind(':'), path = url.find('/', colon);
  const std::string host = url.substr(host_begin, colon - host_begin);
  const int port = std::stoi(url.substr(colon + 1, path == std::string::npos ? std::string::npos : path - colon - 1));
  const std::string target = path == std::string::npos ? "/" : url.substr(path);
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(static_cast<uint16_t>(port));
  inet_pton(AF_INET, host.c_str(), &addr.sin_addr);
  if (connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) != 0) {
    close(fd);
    return "";
  }
  const std::string req = "GET " + target + " HTTP/1.0\r\n\r\n";
  (void)!write(fd, req.data(), req.size());
  std::string resp;
  char buf[4096];
  ssize_t n;
  while ((n = read(fd, buf, sizeof(buf))) > 0) resp.append(buf, static_cast<size_t>(n));
  close(fd);
  return resp;
}

// GET /metrics until it holds every needle (the server publishes its metrics at least every 100 ms),
// at most timeout_ms; the last body either way.
inline std::string MetricsHolding(const std::string& metrics_url, const std::vector<std::string>& needles,
                                  int timeout_ms = 3000) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
  for (;;) {
    const std::string body = HttpGet(metrics_url + "/metrics");
    bool all = true;
    for (const std::string& n : needles) all = all && body.find(n) != std::string::npos;
    if (all || std::chrono::steady_clock::now() > deadline) return body;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
}

}  // namespace prism::test
