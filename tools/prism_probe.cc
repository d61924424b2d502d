// prism-probe [--timeout-ms MS] http://HOST:PORT/PATH
// One HTTP/1.0 GET against prism-server's metrics listener (/healthz,
// /allocate, /metrics) without curl: the container's HEALTHCHECK and scripted
// clients use it. Prints the body on stdout; exits 0 on a 2xx status, 1 on
// another status, 2 on a bad argument or when the server cannot be reached in
// time.
#include <iostream>
#include <string>

#include "tools/cli.h"
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
  CLI::App app{"", "prism-probe"};
  prism::cli::Setup(&app, "one HTTP GET, e.g. against prism-server's /healthz, /allocate or /metrics",
                    {"prism-probe [--timeout-ms MS] http://HOST:PORT/PATH"},
                    "Prints the body; exit 0 on a 2xx status, 1 on another status, 2 when unreachable within the\n"
                    "timeout or on a bad argument. E.g. prism-probe http://127.0.0.1:9100/healthz");
  app.add_option("URL", url, "http://HOST:PORT/PATH")->type_name("")->required();
  app.add_option("--timeout-ms", timeout_ms, "give up after this long, ms")
      ->type_name("MS")
      ->check(CLI::PositiveNumber);
  if (const int exit = prism::cli::Parse(&app, argc, argv); exit != prism::cli::kContinue) return exit;
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
