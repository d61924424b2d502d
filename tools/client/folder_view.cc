#include "tools/client/folder_view.h"

#include <prism/client/client.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <iterator>
#include <nlohmann/json.hpp>
#include <thread>
#include <vector>

#include "core/io/trajectory_io.h"
#include "tools/view/view_server.h"

namespace prism {
namespace {

namespace fs = std::filesystem;

int Fail(const std::string& m) {
  std::cerr << "prism-client: " << m << "\n";
  return 1;
}

struct ChunkFile {
  uint64_t sequence = 0, keyframe_id = 0;
  bool replaces_map = false;
};

// chunks.json when the folder has one (it says which chunk replaced the map), else every .drc in
// sequence order (older folders: each taken as an update).
std::vector<ChunkFile> ListChunks(const std::string& dir) {
  std::vector<ChunkFile> chunks;
  std::ifstream index(dir + "/chunks.json");
  if (index) {
    const nlohmann::json j = nlohmann::json::parse(index, nullptr, /*allow_exceptions=*/false);
    if (j.is_array()) {
      for (const auto& c : j)
        chunks.push_back(
            {c.value("sequence", uint64_t{0}), c.value("keyframe_id", uint64_t{0}), c.value("replaces_map", false)});
      return chunks;
    }
  }
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(dir + "/chunks", ec))
    if (e.path().extension() == ".drc") chunks.push_back({std::stoull("0" + e.path().stem().string()), 0, false});
  std::sort(chunks.begin(), chunks.end(),
            [](const ChunkFile& a, const ChunkFile& b) { return a.sequence < b.sequence; });
  return chunks;
}

}  // namespace

int ServeFolderView(const std::string& dir, const std::string& address, const std::atomic<bool>& stop) {
  std::error_code ec;
  if (!fs::is_directory(dir + "/chunks", ec))
    return Fail("'" + dir + "' has no chunks/ folder (give the --out folder of prism-client stream or fetch)");
  StatusOr<std::string> web = ViewServer::FindWebDir();
  if (!web.ok()) return Fail(web.status().ToString());
  StatusOr<std::unique_ptr<ViewServer>> view = ViewServer::Start(address, *web);
  if (!view.ok()) return Fail(view.status().ToString());
  ViewServer& v = **view;

  client::Rig rig;
  if (fs::exists(dir + "/camera.yaml", ec)) {
    if (client::Status s = client::LoadRig(dir + "/camera.yaml", &rig); s.ok()) v.SetCamera(rig.camera);
    else std::cerr << "prism-client: " << s.ToString() << " (the frustum is drawn without it)\n";
  }
  size_t points = 0, chunks = 0;
  char name[64];
  for (const ChunkFile& c : ListChunks(dir)) {
    std::snprintf(name, sizeof(name), "/chunks/%06llu.drc", static_cast<unsigned long long>(c.sequence));
    std::ifstream in(dir + name, std::ios::binary);
    std::vector<uint8_t> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    std::vector<client::Point> decoded;
    if (client::Status s = client::DecodeChunk(bytes.data(), bytes.size(), &decoded); !s.ok()) {
      std::cerr << "prism-client: " << dir << name << ": " << s.ToString() << "; left out\n";
      continue;
    }
    if (c.replaces_map) points = 0;
    points += decoded.size();
    ++chunks;
    v.AddChunkBytes(c.sequence, c.keyframe_id, decoded.size(), c.replaces_map, std::move(bytes));
  }
  if (chunks == 0) return Fail("'" + dir + "/chunks' holds no map chunk that decodes");
  size_t poses = 0;
  if (StatusOr<Trajectory> t = ReadTumTrajectory(dir + "/trajectory.txt"); t.ok()) {
    for (const TimedPose& p : *t) {
      const Eigen::Quaterniond& q = p.world_from_camera.rotation;
      const Eigen::Vector3d& x = p.world_from_camera.translation;
      v.SetPose(poses++, p.timestamp_s, {x.x(), x.y(), x.z()}, {q.x(), q.y(), q.z(), q.w()}, "tracking", false);
    }
  } else {
    std::cerr << "prism-client: " << t.status().ToString() << " (the view shows the map without the path)\n";
  }
  v.SetMetresPerUnit(1.0);  // trajectory.txt is in metres already
  ViewStatus status;
  status.mode = "folder";
  status.source = dir;
  status.state = "finished";
  status.poses = poses;
  status.map_points = points;
  std::ifstream summary_file(dir + "/summary.json");
  if (summary_file) {
    const nlohmann::json j = nlohmann::json::parse(summary_file, nullptr, false);
    if (j.is_object()) {
      status.session = j.value("session", "");
      status.frames_sent = j.value("frames_sent", uint64_t{0});
      status.map_points = j.value("map_points", points);
      status.seconds = j.value("seconds", 0.0);
    }
  }
  v.SetStatus(status);
  std::cerr << "prism-client: " << chunks << " chunks, " << poses << " poses from " << dir << "; view at " << v.url()
            << " (Ctrl-C ends it)\n";
  while (!stop) std::this_thread::sleep_for(std::chrono::milliseconds(50));
  return 0;
}

}  // namespace prism
