#include "tools/http_get.h"

#include <netdb.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <sstream>

namespace prism {

HttpResponse FetchHttp(const std::string& url, int timeout_ms) {
  HttpResponse out;
  if (url.rfind("http://", 0) != 0) {
    out.error = "expected an http://HOST:PORT/PATH URL, got '" + url + "'";
    return out;
  }
  const std::string rest = url.substr(7);
  const size_t slash = rest.find('/');
  const std::string authority = rest.substr(0, slash), path = slash == std::string::npos ? "/" : rest.substr(slash);
  const size_t colon = authority.rfind(':');
  if (colon == std::string::npos || colon == 0 || colon + 1 == authority.size()) {
    out.error = "expected HOST:PORT in '" + url + "'";
    return out;
  }
  const std::string host = authority.substr(0, colon), port = authority.substr(colon + 1);
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  addrinfo* addresses = nullptr;
  if (const int e = getaddrinfo(host.c_str(), port.c_str(), &hints, &addresses); e != 0) {
    out.error = "cannot resolve '" + host + "': " + gai_strerror(e);
    return out;
  }
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
  auto remaining_ms = [&] {
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
    return static_cast<int>(std::max<long long>(0, left.count()));
  };
  int fd = -1;
  std::string last_error = "no address";
  for (addrinfo* a = addresses; a && fd < 0; a = a->ai_next) {
    fd = ::socket(a->ai_family, a->ai_socktype | SOCK_NONBLOCK | SOCK_CLOEXEC, a->ai_protocol);
    if (fd < 0) continue;
    int err = 0;
    if (::connect(fd, a->ai_addr, a->ai_addrlen) != 0) {
      err = errno;
      if (err == EINPROGRESS) {
        pollfd p{fd, POLLOUT, 0};
        socklen_t len = sizeof(err);
        err = ETIMEDOUT;
        if (::poll(&p, 1, remaining_ms()) == 1) ::getsockopt(fd, SOL_SOCKET, SO_ERROR, &err, &len);
      }
    }
    if (err != 0) {
      last_error = std::strerror(err);
      ::close(fd);
      fd = -1;
    }
  }
  freeaddrinfo(addresses);
  if (fd < 0) {
    out.error = "cannot connect to " + authority + ": " + last_error;
    return out;
  }
  const std::string request = "GET " + path + " HTTP/1.0\r\nHost: " + authority + "\r\n\r\n";
  size_t sent = 0;
  std::string response;
  bool closed = false;
  while (!closed) {
    pollfd p{fd, static_cast<short>(sent < request.size() ? POLLOUT : POLLIN), 0};
    const int left = remaining_ms();
    if (left == 0 || ::poll(&p, 1, left) != 1) {
      ::close(fd);
      out.error = "no answer from " + authority + " within " + std::to_string(timeout_ms) + " ms";
      return out;
    }
    if (sent < request.size()) {
      const ssize_t n = ::send(fd, request.data() + sent, request.size() - sent, MSG_NOSIGNAL);
      if (n < 0 && errno != EAGAIN) break;
      if (n > 0) sent += static_cast<size_t>(n);
      continue;
    }
    char buf[4096];
    const ssize_t n = ::recv(fd, buf, sizeof(buf), 0);
    if (n < 0 && errno == EAGAIN) continue;
    if (n <= 0) closed = true;
    else response.append(buf, static_cast<size_t>(n));
  }
  ::close(fd);
  // "HTTP/1.x CODE reason\r\n...\r\n\r\nbody"
  const size_t space = response.find(' '), header_end = response.find("\r\n\r\n");
  if (response.rfind("HTTP/", 0) != 0 || space == std::string::npos || header_end == std::string::npos) {
    out.error = "not an HTTP response from " + authority;
    return out;
  }
  out.status = std::atoi(response.c_str() + space + 1);
  out.body = response.substr(header_end + 4);
  return out;
}

std::map<std::string, double> FetchMetrics(const std::string& base_url, int timeout_ms) {
  std::map<std::string, double> series;
  const HttpResponse r = FetchHttp(base_url + "/metrics", timeout_ms);
  std::istringstream in(r.body);
  std::string line;
  while (std::getline(in, line)) {
    if (line.empty() || line[0] == '#') continue;
    const size_t space = line.rfind(' ');
    if (space != std::string::npos) series[line.substr(0, space)] = std::atof(line.c_str() + space + 1);
  }
  return series;
}

}  // namespace prism
