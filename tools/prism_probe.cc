// prism-probe [--timeout-ms MS] http://HOST:PORT/PATH
// One HTTP/1.0 GET against prism-server's metrics listener (/healthz,
// /allocate, /metrics) without curl: the container's HEALTHCHECK and scripted
// clients use it. Prints the body on stdout; exits 0 on a 2xx status, 1 on
// another status, 2 on a bad argument or when the server cannot be reached in
// time.
#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <iostream>
#include <string>

#include "tools/http_get.h"

namespace {

int Fail(const std::string &message) {
  std::cerr << "prism-probe: " << message << "\n";
  return 2;
}

}  // namespace

int main(int argc, char **argv) {
  int timeout_ms = 3000;
  std::string url;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--help" || a == "-h") {
      std::cout << "usage: prism-probe [--timeout-ms MS] http://HOST:PORT/PATH\n\n"
                   "GETs the URL (HTTP/1.0), prints the body; exit 0 on 2xx, 1 on "
                   "another status, 2 when\n"
                   "unreachable within the timeout (default 3000 ms). E.g. "
                   "prism-probe http://127.0.0.1:9100/healthz\n";
      return 0;
    }
    if (a == "--timeout-ms" && i + 1 < argc) {
      timeout_ms = std::atoi(argv[++i]);
      if (timeout_ms <= 0) return Fail("--timeout-ms must be > 0");
    } else if (url.empty() && a.rfind("--", 0) != 0) {
      url = a;
    } else {
      return Fail("unknown argument '" + a + "' (see --help)");
    }
  }
  if (url.rfind("http://", 0) != 0) return Fail("expected an http://HOST:PORT/PATH URL, got '" + url + "'");
  const prism::HttpResponse r = prism::FetchHttp(url, timeout_ms);
  if (r.status < 0) return Fail(r.error);
  std::cout << r.body;
  if (r.status < 200 || r.status > 299) {
    std::cerr << "prism-probe: " << url << " answered " << r.status << "\n";
    return 1;
  }
  return 0;
}
