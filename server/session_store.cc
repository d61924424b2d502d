#include "server/session_store.h"

#include <algorithm>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <map>
#include <sstream>
#include <utility>
#include <vector>

#include "core/codec/map_chunk_codec.h"
#include "core/io/ply_io.h"

namespace prism::server {
namespace {

namespace fs = std::filesystem;

std::string ChunkStem(const std::string& dir, uint64_t sequence) {
  char name[32];
  std::snprintf(name, sizeof(name), "/chunks/%06llu", static_cast<unsigned long long>(sequence));
  return dir + name;
}

bool ReadFile(const std::string& path, std::string* out) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return false;
  std::ostringstream ss;
  ss << in.rdbuf();
  *out = ss.str();
  return true;
}

// Writes path atomically: a reader (or a restarted server) sees the old file or the whole new one.
Status WriteFileAtomic(const std::string& path, const void* data, size_t size) {
  const std::string tmp = path + ".tmp";
  {
    std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
    out.write(static_cast<const char*>(data), static_cast<std::streamsize>(size));
    if (!out) return UnavailableError("cannot write '" + tmp + "'");
  }
  std::error_code ec;
  fs::rename(tmp, path, ec);
  if (ec) return UnavailableError("cannot rename '" + tmp + "': " + ec.message());
  return Status::Ok();
}

}  // namespace

bool IsValidSessionId(const std::string& id) {
  if (id.empty() || id.size() > 64 || id[0] != 's') return false;
  return std::all_of(id.begin(), id.end(),
                     [](char c) { return (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '-'; });
}

Status SessionStore::Create(const StoredSession& s) const {
  const std::string dir = Dir(s.id);
  std::error_code ec;
  fs::create_directories(dir + "/chunks", ec);
  if (ec) return UnavailableError("cannot create '" + dir + "': " + ec.message());
  std::ostringstream out;
  out << "id " << s.id << "\ntoken " << s.resume_token << "\nvoxel_m " << s.voxel_m << "\nclient " << s.client_name
      << "\n";
  const std::string text = out.str();
  return WriteFileAtomic(dir + "/session.txt", text.data(), text.size());
}

StatusOr<StoredSession> SessionStore::Load(const std::string& id) const {
  if (!IsValidSessionId(id)) return InvalidArgumentError("malformed session id '" + id + "'");
  const std::string dir = Dir(id);
  std::string text;
  if (!ReadFile(dir + "/session.txt", &text)) return NotFoundError("no session '" + id + "' on this server");
  StoredSession s;
  std::istringstream in(text);
  std::string key;
  while (in >> key) {
    if (key == "id") in >> s.id;
    else if (key == "token") in >> s.resume_token;
    else if (key == "voxel_m") in >> s.voxel_m;
    else if (key == "client") std::getline(in >> std::ws, s.client_name);
    else std::getline(in, key);
  }
  if (s.id != id || s.resume_token.empty()) return DataLossError("session '" + id + "': damaged session.txt");
  std::string summary;
  if (ReadFile(dir + "/summary.pb", &summary)) s.has_summary = s.summary.ParseFromString(summary);
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(dir + "/chunks", ec)) {
    if (e.path().extension() != ".pb") continue;
    const std::string stem = e.path().stem().string();
    char* end = nullptr;
    const unsigned long long seq = std::strtoull(stem.c_str(), &end, 10);
    if (!stem.empty() && *end == '\0') s.chunk_sequences.push_back(seq);
  }
  std::sort(s.chunk_sequences.begin(), s.chunk_sequences.end());
  return s;
}

Status SessionStore::WriteChunk(const std::string& id, const v1::MapChunk& chunk,
                                const std::vector<uint8_t>& draco) const {
  const std::string stem = ChunkStem(Dir(id), chunk.chunk_sequence_number());
  PRISM_RETURN_IF_ERROR(WriteFileAtomic(stem + ".drc", draco.data(), draco.size()));
  const std::string header = chunk.SerializeAsString();
  return WriteFileAtomic(stem + ".pb", header.data(), header.size());
}

Status SessionStore::ReadChunk(const std::string& id, uint64_t sequence, v1::MapChunk* chunk,
                               std::vector<uint8_t>* draco) const {
  const std::string stem = ChunkStem(Dir(id), sequence);
  std::string header, bytes;
  if (!ReadFile(stem + ".pb", &header) || !ReadFile(stem + ".drc", &bytes))
    return NotFoundError("session '" + id + "': chunk " + std::to_string(sequence) + " is not persisted");
  if (!chunk->ParseFromString(header) || chunk->payload_bytes() != bytes.size())
    return DataLossError("session '" + id + "': chunk " + std::to_string(sequence) + " is damaged");
  draco->assign(bytes.begin(), bytes.end());
  return Status::Ok();
}

std::vector<v1::PoseUpdate> SessionStore::ReadPoses(const std::string& id, uint64_t from) const {
  std::vector<v1::PoseUpdate> poses;
  std::string data;
  if (!ReadFile(Dir(id) + "/poses.bin", &data)) return poses;
  size_t at = 0;
  while (at + 4 <= data.size()) {
    uint32_t n = 0;
    for (int b = 0; b < 4; ++b) n |= static_cast<uint32_t>(static_cast<uint8_t>(data[at + b])) << (8 * b);
    if (at + 4 + n > data.size()) break;  // torn last record
    v1::PoseUpdate p;
    if (!p.ParseFromArray(data.data() + at + 4, static_cast<int>(n))) break;
    // Refined poses carry earlier sequence numbers than the client's cursor: always replayed (the
    // latest pose of a frame wins, so a repeat is harmless).
    if (p.frame_sequence_number() >= from || p.refined()) poses.push_back(std::move(p));
    at += 4 + n;
  }
  return poses;
}

Status SessionStore::WriteSummary(const std::string& id, const v1::SessionSummary& summary) const {
  const std::string dir = Dir(id);
  const std::string text = summary.DebugString();
  PRISM_RETURN_IF_ERROR(WriteFileAtomic(dir + "/summary.txt", text.data(), text.size()));
  const std::string bytes = summary.SerializeAsString();
  return WriteFileAtomic(dir + "/summary.pb", bytes.data(), bytes.size());
}

StatusOr<size_t> SessionStore::RebuildMap(const std::string& id, double voxel_m) const {
  PRISM_ASSIGN_OR_RETURN(StoredSession s, Load(id));
  if (voxel_m <= 0) return InvalidArgumentError("voxel_m must be > 0");
  struct Key {
    bool operator()(const Eigen::Vector3i& a, const Eigen::Vector3i& b) const {
      return std::lexicographical_compare(a.data(), a.data() + 3, b.data(), b.data() + 3);
    }
  };
  std::map<Eigen::Vector3i, std::tuple<Eigen::Vector3f, Eigen::Vector3f, Eigen::Matrix<uint8_t, 3, 1>>, Key> voxels;
  for (uint64_t seq : s.chunk_sequences) {
    v1::MapChunk header;
    std::vector<uint8_t> draco;
    if (!ReadChunk(id, seq, &header, &draco).ok()) continue;
    if (header.replaces_map()) voxels.clear();  // the map rebuilt at the final poses
    StatusOr<PointCloud> cloud = DecodeMapChunk(draco.data(), draco.size());
    if (!cloud.ok()) continue;
    for (size_t i = 0; i < cloud->size(); ++i)
      voxels[VoxelOfDecodedPoint(cloud->positions[i], voxel_m)] = {
          cloud->positions[i], cloud->HasNormals() ? cloud->normals[i] : Eigen::Vector3f::Zero(),
          cloud->HasColors() ? cloud->colors[i] : Eigen::Matrix<uint8_t, 3, 1>::Zero()};
  }
  PointCloud map;
  for (const auto& [key, v] : voxels) {
    map.positions.push_back(std::get<0>(v));
    map.normals.push_back(std::get<1>(v));
    map.colors.push_back(std::get<2>(v));
  }
  if (!map.empty()) PRISM_RETURN_IF_ERROR(WritePointCloudPly(Dir(id) + "/map.ply", map));
  return map.size();
}

Status PoseLog::Open(const std::string& dir) {
  dir_ = dir;
  poses_.open(dir + "/poses.bin", std::ios::binary | std::ios::app);
  trajectory_.open(dir + "/trajectory.txt", std::ios::app);
  if (!poses_ || !trajectory_) return UnavailableError("cannot open the pose files in '" + dir + "'");
  return Status::Ok();
}

void PoseLog::Append(const v1::PoseUpdate& pose) {
  const std::string bytes = pose.SerializeAsString();
  const auto n = static_cast<uint32_t>(bytes.size());
  const char len[4] = {static_cast<char>(n & 0xFF), static_cast<char>((n >> 8) & 0xFF),
                       static_cast<char>((n >> 16) & 0xFF), static_cast<char>((n >> 24) & 0xFF)};
  poses_.write(len, 4).write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  poses_.flush();
  if (pose.state() == v1::PoseUpdate::TRACKING_STATE_TRACKING) {
    const v1::Pose& p = pose.world_from_camera();
    char line[256];
    std::snprintf(line, sizeof(line), "%.6f %.9g %.9g %.9g %.9g %.9g %.9g %.9g\n", pose.timestamp_ns() * 1e-9,
                  p.translation().x(), p.translation().y(), p.translation().z(), p.rotation().x(), p.rotation().y(),
                  p.rotation().z(), p.rotation().w());
    if (pose.refined()) {
      refined_[std::string(line, std::strchr(line, ' ') - line)] = line;
    } else {
      trajectory_ << line;
      trajectory_.flush();
    }
  }
}

Status PoseLog::WriteFinalTrajectory() {
  if (refined_.empty()) return Status::Ok();
  // trajectory.txt in order, each line replaced by its frame's refined pose; refined poses of frames
  // that were not tracked when first sent (initialisation) go first, by timestamp.
  std::map<std::string, std::string> lines;  // timestamp (as written) -> line
  std::ifstream streamed(dir_ + "/trajectory.txt");
  std::vector<std::string> order;
  for (std::string l; std::getline(streamed, l);) {
    if (l.empty() || l[0] == '#') continue;
    const std::string key = l.substr(0, l.find(' '));
    order.push_back(key);
    lines[key] = l + "\n";
  }
  const std::string path = dir_ + "/trajectory_final.txt";
  std::ofstream f(path);
  f << "# timestamp tx ty tz qx qy qz qw (world_from_camera, SLAM units; the latest pose of every tracked frame)\n";
  std::vector<std::pair<double, const std::string*>> first;
  for (const auto& [key, line] : refined_)
    if (!lines.count(key)) first.emplace_back(std::stod(key), &line);
  std::sort(first.begin(), first.end());
  for (const auto& [t, line] : first) f << *line;
  for (const std::string& key : order) {
    auto r = refined_.find(key);
    f << (r != refined_.end() ? r->second : lines[key]);
  }
  f.flush();
  if (!f) return UnavailableError("cannot write '" + path + "'");
  return Status::Ok();
}

}  // namespace prism::server
