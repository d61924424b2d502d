// Prometheus metrics of prism-server: counters, gauges and histograms with optional labels, rendered as
// the text exposition format. One owner thread (the transport thread); the HTTP thread reads rendered
// text only. Every family is declared with its help text (docs/operations.md lists them).
#pragma once

#include <cstdint>
#include <map>
#include <mutex>
#include <string>
#include <unordered_set>
#include <vector>

namespace prism::server {

class Metrics {
 public:
  enum class Type { kCounter, kGauge, kHistogram };

  // Declares a family; Add/Set/Observe on an undeclared family is a bug (PRISM_CHECK).
  void Declare(const std::string& family, Type type, const std::string& help, std::vector<double> bucket_bounds = {});
  // name is the family with optional labels: `prism_frames_dropped_total{reason="rate"}`.
  void Add(const std::string& name, double v = 1.0);
  void Set(const std::string& name, double v);
  void Observe(const std::string& name, double v);
  // Removes every series of `family` whose labels contain `label_fragment` (a session's, when it ends).
  void Remove(const std::string& family, const std::string& label_fragment);
  double Value(const std::string& name) const;  // 0 when absent

  std::string Render() const;

 private:
  struct Family {
    Type type = Type::kCounter;
    std::string help;
    std::vector<double> bounds;  // histograms: upper bounds, ascending (+Inf implied)
  };
  struct Histogram {
    std::vector<uint64_t> counts;  // per bucket, not cumulative
    uint64_t count = 0;
    double sum = 0;
  };
  const Family& FamilyOf(const std::string& name) const;

  std::map<std::string, Family> families_;
  std::map<std::string, double> values_;         // counters and gauges by full name
  std::map<std::string, Histogram> histograms_;  // by full name
};

// Declares every family prism-server's transport thread exports (docs/operations.md lists them).
void DeclareServerMetrics(Metrics* metrics);

// Splits `family{labels}` into its parts ("" labels when there are none).
void SplitMetricName(const std::string& name, std::string* family, std::string* labels);

// Escapes a label value (backslash, quote, newline) for the text format.
std::string MetricLabel(const std::string& value);

// Logs a peer's first misbehaviour of each kind, once: a flood of bad messages from one peer is one log
// line (and a metric per message). Thread-safe; remembers at most `capacity` (peer, kind) pairs, then
// starts over.
class OncePerPeer {
 public:
  explicit OncePerPeer(size_t capacity = 4096) : capacity_(capacity) {}
  // true the first time (peer, kind) is seen.
  bool First(const std::string& peer, const std::string& kind);

 private:
  std::mutex mutex_;
  size_t capacity_;
  std::unordered_set<std::string> seen_;  // Guarded by mutex_.
};

// A printable form of a ZeroMQ routing id (bytes) for logs: hex, at most 16 bytes.
std::string PeerName(const std::string& routing_id);

}  // namespace prism::server
