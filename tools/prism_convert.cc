// prism-convert: the exchange formats users expect, in and out of Prism.
//   prism-convert cloud IN OUT [--ascii] [--draco-bits N]         .ply .pcd .drc, by extension
//   prism-convert camera IN --out camera.yaml [--lights FILE]     OpenCV / ROS / DSO camera file -> rig calibration
//   prism-convert colmap --trajectory T --camera C --out DIR [--sequence S] [--map M] [--every K] [--max-points N]
//   prism-convert trajectory IN OUT                                TUM or KITTI -> TUM
// Prints one JSON line on stdout; exits 2 on bad arguments, 1 on unreadable input or a failed write.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <map>
#include <string>
#include <vector>

#include "core/io/calibration_io.h"
#include "core/io/camera_info_io.h"
#include "core/io/colmap_io.h"
#include "core/io/draco_io.h"
#include "core/io/pcd_io.h"
#include "core/io/ply_io.h"
#include "core/io/sequence.h"
#include "core/io/trajectory_io.h"
#include "core/synth/presets.h"

namespace {

using namespace prism;

constexpr char kUsage[] = R"(usage: prism-convert COMMAND ...

  cloud IN OUT [--ascii] [--draco-bits N]
      Point cloud between PLY (binary), PCD (binary, or ASCII with --ascii) and Draco .drc (positions
      quantised to N bits, default 14; 0 = lossless), chosen by extension. Positions, normals, colours.
  camera IN --out FILE [--lights FILE]
      Camera intrinsics from an OpenCV calibration YAML, a ROS camera_info YAML, a DSO / LSD-SLAM
      camera.txt (RadTan or Pinhole; relative values are scaled as DSO does) or a Prism camera.yaml,
      written as Prism's camera.yaml (rig calibration). Lights and crosstalk come from --lights (a
      camera.yaml) or else the default rig (red left, green right, blue above, 0.2 m from the lens).
  colmap --trajectory T --camera C --out DIR [--sequence S] [--map M] [--every K] [--max-points N]
      COLMAP text model (cameras.txt, images.txt, points3D.txt) of the cameras in trajectory T (TUM,
      world_from_camera; e.g. prism-client's trajectory.txt) with intrinsics from C (any camera file
      above). --sequence names each image after the sequence's rgb file at that timestamp (else
      <timestamp>.png); --every K keeps every K-th pose (keyframe spacing); --map adds the points of a
      cloud (every n-th point to stay under --max-points, default 200000).
  trajectory IN OUT
      TUM or KITTI (auto-detected) trajectory written as TUM.
)";

int Usage(const std::string& message) {
  std::cerr << "prism-convert: " << message << " (see --help)\n";
  return 2;
}
int Fail(const Status& status) {
  std::cerr << "prism-convert: " << status << "\n";
  return 1;
}

std::string Extension(const std::string& path) {
  const size_t dot = path.rfind('.');
  std::string e = dot == std::string::npos ? "" : path.substr(dot + 1);
  std::transform(e.begin(), e.end(), e.begin(), [](unsigned char c) { return std::tolower(c); });
  return e;
}

// "--key value" pairs and bare flags after the positional arguments.
struct Args {
  std::vector<std::string> positional;
  std::map<std::string, std::string> values;
  std::vector<std::string> flags;
  bool Has(const std::string& k) const {
    return values.count(k) || std::find(flags.begin(), flags.end(), k) != flags.end();
  }
  std::string Get(const std::string& k, const std::string& fallback = "") const {
    auto it = values.find(k);
    return it == values.end() ? fallback : it->second;
  }
};

bool ParseArgs(int argc, char** argv, const std::vector<std::string>& flag_names, Args* args, std::string* error) {
  for (int i = 2; i < argc; ++i) {
    const std::string a = argv[i];
    if (a.rfind("--", 0) != 0) {
      args->positional.push_back(a);
    } else if (std::find(flag_names.begin(), flag_names.end(), a.substr(2)) != flag_names.end()) {
      args->flags.push_back(a.substr(2));
    } else if (i + 1 < argc) {
      args->values[a.substr(2)] = argv[++i];
    } else {
      *error = "missing value for " + a;
      return false;
    }
  }
  return true;
}

bool ParseInt(const std::string& s, int* out) {
  char* end = nullptr;
  const long v = std::strtol(s.c_str(), &end, 10);
  if (s.empty() || *end != '\0' || v < 0 || v > (1 << 30)) return false;
  *out = static_cast<int>(v);
  return true;
}

StatusOr<PointCloud> ReadCloud(const std::string& path) {
  const std::string e = Extension(path);
  if (e == "ply") return ReadPointCloudPly(path);
  if (e == "pcd") return ReadPointCloudPcd(path);
  if (e == "drc") return ReadPointCloudDraco(path);
  return InvalidArgumentError("unknown point cloud extension '." + e + "' of " + path + " (ply, pcd, drc)");
}

int Cloud(const Args& args) {
  if (args.positional.size() != 2) return Usage("cloud needs IN and OUT");
  const std::string &in = args.positional[0], &out = args.positional[1];
  const std::string e = Extension(out);
  if (e != "ply" && e != "pcd" && e != "drc") return Usage("unknown output extension '." + e + "' (ply, pcd, drc)");
  DracoFileOptions draco;
  if (args.Has("draco-bits") && !ParseInt(args.Get("draco-bits"), &draco.position_bits))
    return Usage("bad --draco-bits '" + args.Get("draco-bits") + "'");
  if (draco.position_bits == 0) draco.normal_bits = 0;
  StatusOr<PointCloud> cloud = ReadCloud(in);
  if (!cloud.ok()) return Fail(cloud.status());
  Status st;
  if (e == "ply") st = WritePointCloudPly(out, *cloud);
  if (e == "pcd") st = WritePointCloudPcd(out, *cloud, args.Has("ascii") ? PcdEncoding::kAscii : PcdEncoding::kBinary);
  if (e == "drc") st = WritePointCloudDraco(out, *cloud, draco);
  if (!st.ok()) return Fail(st);
  std::printf("{\"points\": %zu, \"normals\": %s, \"colors\": %s, \"out\": \"%s\"}\n", cloud->size(),
              cloud->HasNormals() ? "true" : "false", cloud->HasColors() ? "true" : "false", out.c_str());
  return 0;
}

int Camera(const Args& args) {
  if (args.positional.size() != 1 || !args.Has("out")) return Usage("camera needs IN and --out FILE");
  StatusOr<PinholeCamera> camera = ReadCameraIntrinsics(args.positional[0]);
  if (!camera.ok()) return Fail(camera.status());
  RigCalibration rig;
  if (args.Has("lights")) {
    StatusOr<RigCalibration> base = ReadCalibrationYaml(args.Get("lights"));
    if (!base.ok()) return Fail(base.status());
    rig = *base;
  } else {
    rig = synth::MakeDefaultRig(camera->width, camera->height);
  }
  rig.camera = *camera;
  if (Status st = WriteCalibrationYaml(args.Get("out"), rig); !st.ok()) return Fail(st);
  std::printf(
      "{\"width\": %d, \"height\": %d, \"fx\": %.9g, \"fy\": %.9g, \"cx\": %.9g, \"cy\": %.9g, \"out\": \"%s\"}\n",
      camera->width, camera->height, camera->fx, camera->fy, camera->cx, camera->cy, args.Get("out").c_str());
  return 0;
}

int Colmap(const Args& args) {
  if (!args.Has("trajectory") || !args.Has("camera") || !args.Has("out"))
    return Usage("colmap needs --trajectory, --camera and --out");
  int every = 1, max_points = 200000;
  if (args.Has("every") && (!ParseInt(args.Get("every"), &every) || every < 1)) return Usage("bad --every");
  if (args.Has("max-points") && !ParseInt(args.Get("max-points"), &max_points)) return Usage("bad --max-points");
  StatusOr<Trajectory> trajectory = ReadTrajectoryAutoDetect(args.Get("trajectory"));
  if (!trajectory.ok()) return Fail(trajectory.status());
  StatusOr<PinholeCamera> camera = ReadCameraIntrinsics(args.Get("camera"));
  if (!camera.ok()) return Fail(camera.status());
  StatusOr<Sequence> sequence = InvalidArgumentError("");
  if (args.Has("sequence")) {
    sequence = LoadSequence(args.Get("sequence"));
    if (!sequence.ok()) return Fail(sequence.status());
  }
  ColmapModel model;
  model.cameras[1] = *camera;
  size_t unnamed = 0;
  for (size_t i = 0; i < trajectory->size(); i += static_cast<size_t>(every)) {
    const TimedPose& pose = (*trajectory)[i];
    ColmapImage image;
    image.image_id = static_cast<uint32_t>(model.images.size() + 1);
    image.cam_from_world = pose.world_from_camera.Inverse();
    char name[64];
    std::snprintf(name, sizeof(name), "%.6f.png", pose.timestamp_s);
    image.name = name;
    if (sequence.ok()) {
      // The sequence's colour frame at this time (nearest within 20 ms), named as in rgb.txt.
      double best = 0.02;
      bool found = false;
      for (const SequenceFrame& f : sequence->frames)
        if (std::abs(f.timestamp_s - pose.timestamp_s) <= best) {
          best = std::abs(f.timestamp_s - pose.timestamp_s);
          image.name = f.rgb_file;
          found = true;
        }
      if (!found) ++unnamed;
    }
    model.images.push_back(image);
  }
  if (args.Has("map")) {
    StatusOr<PointCloud> map = ReadCloud(args.Get("map"));
    if (!map.ok()) return Fail(map.status());
    const size_t step =
        max_points > 0 ? std::max<size_t>(1, (map->size() + max_points - 1) / max_points) : map->size() + 1;
    for (size_t i = 0; i < map->size(); i += step) {
      model.points.positions.push_back(map->positions[i]);
      model.points.colors.push_back(map->HasColors() ? map->colors[i] : Eigen::Matrix<uint8_t, 3, 1>(128, 128, 128));
    }
  }
  if (Status st = WriteColmapText(args.Get("out"), model); !st.ok()) return Fail(st);
  std::printf("{\"images\": %zu, \"points\": %zu, \"images_without_sequence_frame\": %zu, \"out\": \"%s\"}\n",
              model.images.size(), model.points.size(), unnamed, args.Get("out").c_str());
  return 0;
}

int TrajectoryCommand(const Args& args) {
  if (args.positional.size() != 2) return Usage("trajectory needs IN and OUT");
  StatusOr<Trajectory> t = ReadTrajectoryAutoDetect(args.positional[0]);
  if (!t.ok()) return Fail(t.status());
  if (Status st = WriteTumTrajectory(args.positional[1], *t); !st.ok()) return Fail(st);
  std::printf("{\"poses\": %zu, \"out\": \"%s\"}\n", t->size(), args.positional[1].c_str());
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) return Usage("expected a command: cloud, camera, colmap or trajectory");
  const std::string command = argv[1];
  if (command == "--help" || command == "-h") {
    std::cout << kUsage;
    return 0;
  }
  Args args;
  std::string error;
  if (!ParseArgs(argc, argv, {"ascii", "help"}, &args, &error)) return Usage(error);
  if (args.Has("help")) {
    std::cout << kUsage;
    return 0;
  }
  if (command == "cloud") return Cloud(args);
  if (command == "camera") return Camera(args);
  if (command == "colmap") return Colmap(args);
  if (command == "trajectory") return TrajectoryCommand(args);
  return Usage("unknown command '" + command + "'");
}
