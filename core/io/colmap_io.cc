#include "core/io/colmap_io.h"

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>

namespace prism {
namespace {

// COLMAP pixel centres are at +0.5 from OpenCV's.
constexpr double kColmapPixelOffset = 0.5;

bool HasWhitespace(const std::string& s) { return s.find_first_of(" \t\r\n") != std::string::npos; }

// Data lines of a COLMAP text file ('#' comments skipped; empty lines kept only when keep_empty).
StatusOr<std::vector<std::string>> DataLines(const std::string& path, bool keep_empty) {
  std::ifstream in(path);
  if (!in) return NotFoundError("cannot open '" + path + "'");
  std::vector<std::string> lines;
  std::string line;
  while (std::getline(in, line)) {
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (!line.empty() && line[0] == '#') continue;
    if (line.find_first_not_of(" \t") == std::string::npos && !keep_empty) continue;
    lines.push_back(line);
  }
  return lines;
}

}  // namespace

Status WriteColmapText(const std::string& dir, const ColmapModel& model) {
  std::set<uint32_t> image_ids;
  for (const ColmapImage& im : model.images) {
    if (im.image_id == 0 || !image_ids.insert(im.image_id).second)
      return InvalidArgumentError("COLMAP image ids must be unique and > 0 (image '" + im.name + "')");
    if (!model.cameras.count(im.camera_id))
      return InvalidArgumentError("image '" + im.name + "' uses camera " + std::to_string(im.camera_id) +
                                  ", not in the model");
    if (im.name.empty() || HasWhitespace(im.name))
      return InvalidArgumentError("COLMAP image names must be non-empty without whitespace, got '" + im.name + "'");
  }
  if (!model.points.IsConsistent()) return InvalidArgumentError("point cloud attributes do not match its size");
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return UnavailableError("cannot create '" + dir + "': " + ec.message());

  char buf[512];
  std::ofstream cameras(dir + "/cameras.txt");
  if (!cameras) return UnavailableError("cannot write '" + dir + "/cameras.txt'");
  cameras << "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
          << "# Number of cameras: " << model.cameras.size() << "\n";
  for (const auto& [id, c] : model.cameras) {
    PRISM_RETURN_IF_ERROR(c.Check());
    const double cx = c.cx + kColmapPixelOffset, cy = c.cy + kColmapPixelOffset;
    const auto& d = c.distortion;
    if (!c.HasDistortion())
      std::snprintf(buf, sizeof(buf), "%u PINHOLE %d %d %.17g %.17g %.17g %.17g\n", id, c.width, c.height, c.fx, c.fy,
                    cx, cy);
    else if (d[4] == 0)
      std::snprintf(buf, sizeof(buf), "%u OPENCV %d %d %.17g %.17g %.17g %.17g %.17g %.17g %.17g %.17g\n", id, c.width,
                    c.height, c.fx, c.fy, cx, cy, d[0], d[1], d[2], d[3]);
    else
      std::snprintf(buf, sizeof(buf),
                    "%u FULL_OPENCV %d %d %.17g %.17g %.17g %.17g %.17g %.17g %.17g %.17g %.17g 0 0 0\n", id, c.width,
                    c.height, c.fx, c.fy, cx, cy, d[0], d[1], d[2], d[3], d[4]);
    cameras << buf;
  }

  std::ofstream images(dir + "/images.txt");
  if (!images) return UnavailableError("cannot write '" + dir + "/images.txt'");
  images << "# Image list with two lines of data per image:\n"
         << "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
         << "# Number of images: " << model.images.size() << ", mean observations per image: 0\n";
  for (const ColmapImage& im : model.images) {
    // q and -q are the same rotation; COLMAP writes w >= 0.
    const Eigen::Quaterniond q = im.cam_from_world.rotation.w() < 0
                                     ? Eigen::Quaterniond(-im.cam_from_world.rotation.coeffs())
                                     : im.cam_from_world.rotation;
    const Eigen::Vector3d& t = im.cam_from_world.translation;
    std::snprintf(buf, sizeof(buf), "%u %.17g %.17g %.17g %.17g %.17g %.17g %.17g %u ", im.image_id, q.w(), q.x(),
                  q.y(), q.z(), t.x(), t.y(), t.z(), im.camera_id);
    images << buf << im.name << "\n\n";
  }

  std::ofstream points(dir + "/points3D.txt");
  if (!points) return UnavailableError("cannot write '" + dir + "/points3D.txt'");
  points << "# 3D point list with one line of data per point:\n"
         << "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
         << "# Number of points: " << model.points.size() << ", mean track length: 0\n";
  for (size_t i = 0; i < model.points.size(); ++i) {
    const Eigen::Vector3f& p = model.points.positions[i];
    const int r = model.points.HasColors() ? model.points.colors[i][0] : 128;
    const int g = model.points.HasColors() ? model.points.colors[i][1] : 128;
    const int b = model.points.HasColors() ? model.points.colors[i][2] : 128;
    std::snprintf(buf, sizeof(buf), "%zu %.9g %.9g %.9g %d %d %d 0\n", i + 1, p.x(), p.y(), p.z(), r, g, b);
    points << buf;
  }
  if (!cameras || !images || !points) return UnavailableError("write failed under '" + dir + "'");
  return Status::Ok();
}

StatusOr<ColmapModel> ReadColmapText(const std::string& dir) {
  ColmapModel model;
  StatusOr<std::vector<std::string>> camera_lines = DataLines(dir + "/cameras.txt", false);
  if (!camera_lines.ok()) return camera_lines.status();
  for (const std::string& line : *camera_lines) {
    std::istringstream s(line);
    uint32_t id = 0;
    std::string type;
    PinholeCamera c;
    std::vector<double> p;
    if (!(s >> id >> type >> c.width >> c.height))
      return InvalidArgumentError(dir + "/cameras.txt: bad line '" + line + "'");
    for (double v; s >> v;) p.push_back(v);
    size_t expected = 0;
    if (type == "PINHOLE") expected = 4;
    else if (type == "OPENCV") expected = 8;
    else if (type == "FULL_OPENCV") expected = 12;
    else if (type == "SIMPLE_PINHOLE") expected = 3;
    else return InvalidArgumentError(dir + "/cameras.txt: camera model " + type + " is not supported");
    if (p.size() != expected)
      return InvalidArgumentError(dir + "/cameras.txt: " + type + " needs " + std::to_string(expected) + " parameters");
    if (type == "SIMPLE_PINHOLE") p.insert(p.begin() + 1, p[0]);
    c.fx = p[0];
    c.fy = p[1];
    c.cx = p[2] - kColmapPixelOffset;
    c.cy = p[3] - kColmapPixelOffset;
    for (size_t k = 4; k < p.size() && k < 9; ++k) c.distortion[k - 4] = p[k];
    for (size_t k = 9; k < p.size(); ++k)
      if (p[k] != 0) return InvalidArgumentError(dir + "/cameras.txt: FULL_OPENCV k4..k6 must be 0 for Prism's model");
    const Status st = c.Check();
    if (!st.ok()) return InvalidArgumentError(dir + "/cameras.txt: camera " + std::to_string(id) + ": " + st.message());
    model.cameras[id] = c;
  }
  StatusOr<std::vector<std::string>> image_lines = DataLines(dir + "/images.txt", true);
  if (!image_lines.ok()) return image_lines.status();
  // Two lines per image; the second (2D points) may be empty.
  for (size_t i = 0; i < image_lines->size(); ++i) {
    const std::string& line = (*image_lines)[i];
    if (line.find_first_not_of(" \t") == std::string::npos) continue;
    std::istringstream s(line);
    ColmapImage im;
    double qw, qx, qy, qz, tx, ty, tz;
    if (!(s >> im.image_id >> qw >> qx >> qy >> qz >> tx >> ty >> tz >> im.camera_id >> im.name))
      return InvalidArgumentError(dir + "/images.txt: bad line '" + line + "'");
    if (!model.cameras.count(im.camera_id))
      return InvalidArgumentError(dir + "/images.txt: image " + im.name + " uses unknown camera " +
                                  std::to_string(im.camera_id));
    im.cam_from_world = Rigid3d(Eigen::Quaterniond(qw, qx, qy, qz), Eigen::Vector3d(tx, ty, tz));
    model.images.push_back(im);
    ++i;  // skip the 2D points line
  }
  StatusOr<std::vector<std::string>> point_lines = DataLines(dir + "/points3D.txt", false);
  if (point_lines.ok()) {
    for (const std::string& line : *point_lines) {
      std::istringstream s(line);
      uint64_t id;
      float x, y, z;
      int r, g, b;
      if (!(s >> id >> x >> y >> z >> r >> g >> b))
        return InvalidArgumentError(dir + "/points3D.txt: bad line '" + line + "'");
      model.points.positions.emplace_back(x, y, z);
      model.points.colors.emplace_back(static_cast<uint8_t>(r), static_cast<uint8_t>(g), static_cast<uint8_t>(b));
    }
  }
  return model;
}

}  // namespace prism
