#include "server/metrics.h"

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <sstream>

#include "core/util/check.h"

namespace prism::server {

void SplitMetricName(const std::string& name, std::string* family, std::string* labels) {
  const size_t brace = name.find('{');
  *family = name.substr(0, brace);
  *labels = brace == std::string::npos ? "" : name.substr(brace + 1, name.size() - brace - 2);
}

std::string MetricLabel(const std::string& value) {
  std::string out;
  for (char c : value) {
    if (c == '\\' || c == '"') out += '\\';
    if (c == '\n') {
      out += "\\n";
      continue;
    }
    out += c;
  }
  return out;
}

void Metrics::Declare(const std::string& family, Type type, const std::string& help, std::vector<double> bounds) {
  PRISM_CHECK(type != Type::kHistogram || !bounds.empty()) << family << ": a histogram needs buckets";
  PRISM_CHECK(std::is_sorted(bounds.begin(), bounds.end())) << family;
  families_[family] = Family{type, help, std::move(bounds)};
}

const Metrics::Family& Metrics::FamilyOf(const std::string& name) const {
  std::string family, labels;
  SplitMetricName(name, &family, &labels);
  auto it = families_.find(family);
  PRISM_CHECK(it != families_.end()) << "metric family " << family << " is not declared";
  return it->second;
}

void Metrics::Add(const std::string& name, double v) {
  PRISM_CHECK(FamilyOf(name).type == Type::kCounter) << name << " is not a counter";
  values_[name] += v;
}

void Metrics::Set(const std::string& name, double v) {
  PRISM_CHECK(FamilyOf(name).type == Type::kGauge) << name << " is not a gauge";
  values_[name] = v;
}

void Metrics::Observe(const std::string& name, double v) {
  const Family& f = FamilyOf(name);
  PRISM_CHECK(f.type == Type::kHistogram) << name << " is not a histogram";
  Histogram& h = histograms_[name];
  if (h.counts.empty()) h.counts.assign(f.bounds.size() + 1, 0);
  const size_t bucket = std::lower_bound(f.bounds.begin(), f.bounds.end(), v) - f.bounds.begin();
  ++h.counts[bucket];
  ++h.count;
  h.sum += v;
}

void Metrics::Remove(const std::string& family, const std::string& label_fragment) {
  auto matches = [&](const std::string& name) {
    std::string f, labels;
    SplitMetricName(name, &f, &labels);
    return f == family && labels.find(label_fragment) != std::string::npos;
  };
  for (auto it = values_.begin(); it != values_.end();) it = matches(it->first) ? values_.erase(it) : std::next(it);
  for (auto it = histograms_.begin(); it != histograms_.end();)
    it = matches(it->first) ? histograms_.erase(it) : std::next(it);
}

double Metrics::Value(const std::string& name) const {
  auto it = values_.find(name);
  return it == values_.end() ? 0.0 : it->second;
}

namespace {

// The shortest decimal that reads back as v.
std::string Number(double v) {
  char buf[32];
  for (int precision = 15; precision <= 17; ++precision) {
    std::snprintf(buf, sizeof(buf), "%.*g", precision, v);
    if (std::strtod(buf, nullptr) == v) break;
  }
  return buf;
}

std::string WithLabel(const std::string& labels, const std::string& extra) {
  if (labels.empty()) return "{" + extra + "}";
  return "{" + labels + "," + extra + "}";
}

// The series of `family` in a map keyed by full name: the bare name, then "family{...}" ones.
template <typename Map>
std::vector<const typename Map::value_type*> SeriesOf(const Map& map, const std::string& family) {
  std::vector<const typename Map::value_type*> out;
  if (auto it = map.find(family); it != map.end()) out.push_back(&*it);
  const std::string prefix = family + "{";
  for (auto it = map.lower_bound(prefix); it != map.end() && it->first.compare(0, prefix.size(), prefix) == 0; ++it)
    out.push_back(&*it);
  return out;
}

}  // namespace

std::string Metrics::Render() const {
  std::ostringstream out;
  for (const auto& [family, f] : families_) {
    const char* type = f.type == Type::kCounter ? "counter" : f.type == Type::kGauge ? "gauge" : "histogram";
    out << "# HELP " << family << " " << f.help << "\n# TYPE " << family << " " << type << "\n";
    if (f.type == Type::kHistogram) {
      for (const auto* entry : SeriesOf(histograms_, family)) {
        std::string name_family, labels;
        SplitMetricName(entry->first, &name_family, &labels);
        const Histogram& h = entry->second;
        uint64_t cumulative = 0;
        for (size_t b = 0; b < f.bounds.size(); ++b) {
          cumulative += h.counts[b];
          out << family << "_bucket" << WithLabel(labels, "le=\"" + Number(f.bounds[b]) + "\"") << " " << cumulative
              << "\n";
        }
        out << family << "_bucket" << WithLabel(labels, "le=\"+Inf\"") << " " << h.count << "\n";
        const std::string suffix = labels.empty() ? "" : "{" + labels + "}";
        out << family << "_sum" << suffix << " " << Number(h.sum) << "\n";
        out << family << "_count" << suffix << " " << h.count << "\n";
      }
    } else {
      for (const auto* entry : SeriesOf(values_, family)) out << entry->first << " " << Number(entry->second) << "\n";
    }
  }
  return out.str();
}

void DeclareServerMetrics(Metrics* m) {
  using T = Metrics::Type;
  const std::vector<double> fast = {0.005, 0.01, 0.02, 0.033, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5, 1, 2, 5};
  const std::vector<double> slow = {0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 1, 2, 3, 5, 10, 20, 60};
  // Sessions.
  m->Declare("prism_sessions_active", T::kGauge, "Sessions open now (running or replaying).");
  m->Declare("prism_sessions_capacity", T::kGauge, "Sessions this server admits at once (max-sessions).");
  m->Declare("prism_sessions_opened_total", T::kCounter, "Sessions opened.");
  m->Declare("prism_sessions_resumed_total", T::kCounter, "Sessions resumed by id and token.");
  m->Declare("prism_sessions_closed_total", T::kCounter, "Sessions ended with a summary sent.");
  m->Declare("prism_sessions_deprioritised_total", T::kCounter,
             "Sessions moved to the lowest CPU priority for sending over max-frame-rate-hz.");
  m->Declare("prism_sessions_failed_total", T::kCounter, "Sessions ended by a fatal pipeline error.");
  m->Declare("prism_sessions_reaped_total", T::kCounter, "Sessions closed after idle-timeout-ms without a message.");
  m->Declare("prism_sessions_limited_total", T::kCounter, "Sessions finished early by a limit, by limit.");
  m->Declare("prism_sessions_rejected_total", T::kCounter, "OpenSession refused, by reason.");
  m->Declare("prism_resumes_rejected_total", T::kCounter, "Resumes refused, by reason.");
  // Per session (series removed when the session ends).
  m->Declare("prism_session_tracking_state", T::kGauge,
             "The SLAM's state at the last pose: 0 initialising, 1 tracking, 2 lost; by session.");
  m->Declare("prism_session_frames_dropped", T::kGauge,
             "Frames of the session dropped (full live queue) or refused (rate, size, closing); by session.");
  m->Declare("prism_session_frame_queue_depth", T::kGauge, "Frames waiting for the session's SLAM; by session.");
  m->Declare("prism_session_keyframe_queue_depth", T::kGauge,
             "Finished keyframes waiting for the dense stage; by session.");
  m->Declare("prism_session_chunks_waiting", T::kGauge, "Map chunks waiting for the client's credit; by session.");
  // Latency.
  m->Declare("prism_frame_to_pose_seconds", T::kHistogram,
             "From a frame's arrival at the transport thread to its pose sent.", fast);
  m->Declare("prism_keyframe_to_chunk_seconds", T::kHistogram,
             "From the SLAM handing a finished keyframe to the dense stage to its chunk ready to send.", slow);
  m->Declare("prism_keyframe_wait_seconds", T::kHistogram,
             "From the SLAM handing a finished keyframe over to the dense stage taking it (the keyframe queue).", slow);
  m->Declare("prism_dense_keyframe_seconds", T::kHistogram,
             "The dense stage's time per keyframe, from taking it to its chunk ready to send.", slow);
  m->Declare("prism_dense_part_seconds", T::kHistogram,
             "The dense stage's time per keyframe by part: photometric (stereo), fusion, map (the cloud, ICP, "
             "the merge), encode (Draco).",
             {0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2});
  // Frames, poses, chunks.
  m->Declare("prism_messages_received_total", T::kCounter, "ZeroMQ messages received.");
  m->Declare("prism_frames_received_total", T::kCounter, "Frames accepted into a session's queue.");
  m->Declare("prism_frame_bytes_total", T::kCounter, "Payload bytes of the frames accepted.");
  m->Declare("prism_frames_refused_total", T::kCounter, "Frames refused with an error (their credit comes back).");
  m->Declare("prism_frames_dropped_total", T::kCounter, "Frames dropped, by reason (rate limit, full live queue).");
  m->Declare("prism_frames_bad_total", T::kCounter, "Frames that failed to decode (corrupt, wrong size).");
  m->Declare("prism_poses_sent_total", T::kCounter, "Poses sent.");
  m->Declare("prism_poses_refined_total", T::kCounter, "Refined poses sent (end of session, loop closures).");
  m->Declare("prism_keyframes_merged_total", T::kCounter, "Keyframes merged into a map (a chunk each).");
  m->Declare("prism_keyframes_dropped_total", T::kCounter,
             "Keyframes the dense stage skipped (queue overflow, a session over max-frame-rate-hz, or covered "
             "by the map while another keyframe waited).");
  m->Declare("prism_chunks_sent_total", T::kCounter, "Map chunks sent.");
  m->Declare("prism_chunk_credit_stalls_total", T::kCounter,
             "Chunks made while their session had no chunk credit left (the client is not keeping up).");
  m->Declare("prism_chunk_bytes_total", T::kCounter, "Bytes of the map chunks sent.");
  // Queues.
  m->Declare("prism_chunks_waiting_for_credit", T::kGauge, "Map chunks waiting for client credits, all sessions.");
  m->Declare("prism_chunk_bytes_waiting_in_memory", T::kGauge, "Bytes of those chunks held in memory.");
  m->Declare("prism_dense_jobs_pending", T::kGauge, "Dense keyframe jobs queued or running, all sessions.");
  m->Declare("prism_transport_events_pending", T::kGauge,
             "Pipeline events waiting for the transport thread (at its last turn).");
  // Bad input and peers.
  m->Declare("prism_malformed_messages_total", T::kCounter,
             "Messages refused: wrong part count, unparsable envelope, wrong protocol version, no body.");
  m->Declare("prism_unknown_session_total", T::kCounter, "Messages naming a session that is not the peer's.");
  m->Declare("prism_stale_credits_total", T::kCounter, "Chunk credits for a session that is not the peer's.");
  m->Declare("prism_errors_sent_total", T::kCounter, "Error messages sent, by code.");
  m->Declare("prism_send_failures_total", T::kCounter, "Sends that failed, by reason (peer gone, queue full).");
  m->Declare("prism_handler_failures_total", T::kCounter, "Messages whose handling hit a bug (logged).");
  m->Declare("prism_persist_failures_total", T::kCounter, "Writes to the data dir that failed.");
  m->Declare("prism_auth_accepted_total", T::kCounter, "CURVE handshakes admitted.");
  m->Declare("prism_auth_refused_total", T::kCounter, "CURVE handshakes refused (key not on the allow-list).");
  m->Declare("prism_zmq_connections_accepted_total", T::kCounter, "TCP connections accepted by the ZeroMQ port.");
  m->Declare("prism_zmq_disconnects_total", T::kCounter, "Connections of the ZeroMQ port that ended.");
  m->Declare("prism_zmq_handshake_failures_total", T::kCounter,
             "ZMTP handshakes that failed, by reason (timeout or no detail, protocol, auth).");
  m->Declare("prism_zmq_connections_open", T::kGauge, "Connections of the ZeroMQ port open now.");
}

bool OncePerPeer::First(const std::string& peer, const std::string& kind) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (seen_.size() >= capacity_) seen_.clear();
  return seen_.insert(kind + "\n" + peer).second;
}

std::string PeerName(const std::string& routing_id) {
  static const char* kHex = "0123456789abcdef";
  std::string s;
  for (size_t i = 0; i < routing_id.size() && i < 16; ++i) {
    const auto b = static_cast<unsigned char>(routing_id[i]);
    s += kHex[b >> 4];
    s += kHex[b & 15];
  }
  return s.empty() ? "-" : s;
}

}  // namespace prism::server
