// prism-convert: the exchange formats users expect, in and out of Prism (subcommands cloud, camera,
// colmap, trajectory). Prints one JSON line on stdout; exits 2 on bad arguments, 1 on unreadable input or a failed
// write.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <iostream>
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
#include "tools/cli.h"
#include "tools/json_output.h"

namespace {

using namespace prism;

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

// Every command's arguments (each command reads its own).
struct Args {
  std::string in, out, lights, trajectory, camera, sequence, map;
  bool ascii = false;
  int draco_bits = DracoFileOptions().position_bits, every = 1, max_points = 200000;
};

StatusOr<PointCloud> ReadCloud(const std::string& path) {
  const std::string e = Extension(path);
  if (e == "ply") return ReadPointCloudPly(path);
  if (e == "pcd") return ReadPointCloudPcd(path);
  if (e == "drc") return ReadPointCloudDraco(path);
  return InvalidArgumentError("unknown point cloud extension '." + e + "' of " + path + " (ply, pcd, drc)");
}

int Cloud(const Args& args) {
  const std::string &in = args.in, &out = args.out;
  const std::string e = Extension(out);
  if (e != "ply" && e != "pcd" && e != "drc") return Usage("unknown output extension '." + e + "' (ply, pcd, drc)");
  DracoFileOptions draco;
  draco.position_bits = args.draco_bits;
  if (draco.position_bits == 0) draco.normal_bits = 0;
  StatusOr<PointCloud> cloud = ReadCloud(in);
  if (!cloud.ok()) return Fail(cloud.status());
  Status st;
  if (e == "ply") st = WritePointCloudPly(out, *cloud);
  if (e == "pcd") st = WritePointCloudPcd(out, *cloud, args.ascii ? PcdEncoding::kAscii : PcdEncoding::kBinary);
  if (e == "drc") st = WritePointCloudDraco(out, *cloud, draco);
  if (!st.ok()) return Fail(st);
  std::cout << JsonText(
      Json{{"points", cloud->size()}, {"normals", cloud->HasNormals()}, {"colors", cloud->HasColors()}, {"out", out}});
  return 0;
}

int Camera(const Args& args) {
  StatusOr<PinholeCamera> camera = ReadCameraIntrinsics(args.in);
  if (!camera.ok()) return Fail(camera.status());
  RigCalibration rig;
  if (!args.lights.empty()) {
    StatusOr<RigCalibration> base = ReadCalibrationYaml(args.lights);
    if (!base.ok()) return Fail(base.status());
    rig = *base;
  } else {
    rig = synth::MakeDefaultRig(camera->width, camera->height);
  }
  rig.camera = *camera;
  if (Status st = WriteCalibrationYaml(args.out, rig); !st.ok()) return Fail(st);
  std::cout << JsonText(Json{{"width", camera->width},
                             {"height", camera->height},
                             {"fx", camera->fx},
                             {"fy", camera->fy},
                             {"cx", camera->cx},
                             {"cy", camera->cy},
                             {"out", args.out}});
  return 0;
}

int Colmap(const Args& args) {
  const int every = args.every, max_points = args.max_points;
  StatusOr<Trajectory> trajectory = ReadTrajectoryAutoDetect(args.trajectory);
  if (!trajectory.ok()) return Fail(trajectory.status());
  StatusOr<PinholeCamera> camera = ReadCameraIntrinsics(args.camera);
  if (!camera.ok()) return Fail(camera.status());
  StatusOr<Sequence> sequence = InvalidArgumentError("");
  if (!args.sequence.empty()) {
    sequence = LoadSequence(args.sequence);
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
  if (!args.map.empty()) {
    StatusOr<PointCloud> map = ReadCloud(args.map);
    if (!map.ok()) return Fail(map.status());
    const size_t step =
        max_points > 0 ? std::max<size_t>(1, (map->size() + max_points - 1) / max_points) : map->size() + 1;
    for (size_t i = 0; i < map->size(); i += step) {
      model.points.positions.push_back(map->positions[i]);
      model.points.colors.push_back(map->HasColors() ? map->colors[i] : Eigen::Matrix<uint8_t, 3, 1>(128, 128, 128));
    }
  }
  if (Status st = WriteColmapText(args.out, model); !st.ok()) return Fail(st);
  std::cout << JsonText(Json{{"images", model.images.size()},
                             {"points", model.points.size()},
                             {"images_without_sequence_frame", unnamed},
                             {"out", args.out}});
  return 0;
}

int TrajectoryCommand(const Args& args) {
  StatusOr<Trajectory> t = ReadTrajectoryAutoDetect(args.in);
  if (!t.ok()) return Fail(t.status());
  if (Status st = WriteTumTrajectory(args.out, *t); !st.ok()) return Fail(st);
  std::cout << JsonText(Json{{"poses", t->size()}, {"out", args.out}});
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  Args args;
  CLI::App app{"", "prism-convert"};
  cli::Setup(&app, "converts clouds, cameras and trajectories between Prism's formats and others",
             {"prism-convert cloud|camera|colmap|trajectory ...   ('prism-convert COMMAND --help': its options)"},
             "Prints one JSON line on stdout; exits 2 on bad arguments, 1 on unreadable input or a failed write.");
  app.require_subcommand(1);

  CLI::App* cloud = app.add_subcommand("cloud", "a point cloud between PLY, PCD and Draco .drc, by extension");
  cli::Setup(
      cloud, cloud->get_description(), {"prism-convert cloud IN OUT [--ascii] [--draco-bits N]"},
      "PLY is written binary; PCD binary or ASCII; Draco with quantised positions. Positions, normals, colours.");
  cloud->add_option("IN", args.in, "the cloud to read (.ply, .pcd, .drc)")->type_name("")->required();
  cloud->add_option("OUT", args.out, "the cloud to write (.ply, .pcd, .drc)")->type_name("")->required();
  cloud->add_flag("--ascii", args.ascii, "PCD as ASCII");
  cloud->add_option("--draco-bits", args.draco_bits, "Draco position bits (0 = lossless)")
      ->type_name("N")
      ->check(CLI::Range(0, 30));

  CLI::App* camera = app.add_subcommand("camera", "camera intrinsics from another format into Prism's camera.yaml");
  cli::Setup(camera, camera->get_description(), {"prism-convert camera IN --out FILE [--lights FILE]"},
             "IN: an OpenCV calibration YAML, a ROS camera_info YAML, a DSO / LSD-SLAM camera.txt (RadTan or\n"
             "Pinhole; relative values are scaled as DSO does) or a Prism camera.yaml. Lights and crosstalk come\n"
             "from --lights (a camera.yaml) or else the default rig (red left, green right, blue above, 0.2 m\n"
             "from the lens).");
  camera->add_option("IN", args.in, "the camera file")->type_name("")->required();
  camera->add_option("--out", args.out, "the camera.yaml to write")->type_name("FILE")->required();
  camera->add_option("--lights", args.lights, "take the lights and crosstalk from this camera.yaml")->type_name("FILE");

  CLI::App* colmap = app.add_subcommand("colmap", "a COLMAP text model of a trajectory's cameras (and a cloud)");
  cli::Setup(colmap, colmap->get_description(),
             {"prism-convert colmap --trajectory T --camera C --out DIR [--sequence S] [--map M] [options]"},
             "Writes cameras.txt, images.txt and points3D.txt.");
  colmap->add_option("--trajectory", args.trajectory, "the cameras: TUM, world_from_camera (e.g. trajectory.txt)")
      ->type_name("T")
      ->required();
  colmap->add_option("--camera", args.camera, "their intrinsics (any camera file prism-convert camera reads)")
      ->type_name("C")
      ->required();
  colmap->add_option("--out", args.out, "the model's folder")->type_name("DIR")->required();
  colmap
      ->add_option("--sequence", args.sequence,
                   "name each image after the sequence's rgb file at that time (else <t>.png)")
      ->type_name("S");
  colmap->add_option("--map", args.map, "add the points of this cloud (.ply, .pcd, .drc)")->type_name("M");
  colmap->add_option("--every", args.every, "keep every K-th pose (keyframe spacing)")
      ->type_name("K")
      ->check(CLI::Range(1, 1 << 30));
  colmap->add_option("--max-points", args.max_points, "every n-th point of --map to stay under N")
      ->type_name("N")
      ->check(CLI::Range(0, 1 << 30));

  CLI::App* trajectory = app.add_subcommand("trajectory", "a TUM or KITTI trajectory (auto-detected) as TUM");
  cli::Setup(trajectory, trajectory->get_description(), {"prism-convert trajectory IN OUT"});
  trajectory->add_option("IN", args.in, "TUM or KITTI trajectory")->type_name("")->required();
  trajectory->add_option("OUT", args.out, "TUM trajectory to write")->type_name("")->required();

  if (const int exit = cli::Parse(&app, argc, argv); exit != cli::kContinue) return exit;
  if (cloud->parsed()) return Cloud(args);
  if (camera->parsed()) return Camera(args);
  if (colmap->parsed()) return Colmap(args);
  return TrajectoryCommand(args);
}
