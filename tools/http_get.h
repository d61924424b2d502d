// A minimal HTTP/1.0 GET with a deadline, for prism-probe and the benchmarks (no curl in the image).
#pragma once

#include <map>
#include <string>

namespace prism {

struct HttpResponse {
  int status = -1;    // the HTTP status code; -1 when there was no answer
  std::string body;   // after the headers
  std::string error;  // why there was no answer
};

// GETs http://HOST:PORT/PATH, all of it (resolve, connect, send, read to the end) within timeout_ms.
HttpResponse FetchHttp(const std::string& url, int timeout_ms);

// GETs http://HOST:PORT/metrics (Prometheus text) and returns every series' value by its name with
// labels, e.g. "prism_dense_part_seconds_sum{part=\"fusion\"}"; empty when there was no answer.
std::map<std::string, double> FetchMetrics(const std::string& base_url, int timeout_ms);

}  // namespace prism
