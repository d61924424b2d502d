#include "core/io/ply_io.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstring>
#include <fstream>
#include <sstream>
#include <unordered_map>

namespace prism {
namespace {

enum class PlyFormat { kAscii, kBinaryLittle, kBinaryBig };
enum class PlyType { kInt8, kUInt8, kInt16, kUInt16, kInt32, kUInt32, kFloat32, kFloat64, kInvalid };

PlyType ParseType(const std::string& s) {
  if (s == "char" || s == "int8") return PlyType::kInt8;
  if (s == "uchar" || s == "uint8") return PlyType::kUInt8;
  if (s == "short" || s == "int16") return PlyType::kInt16;
  if (s == "ushort" || s == "uint16") return PlyType::kUInt16;
  if (s == "int" || s == "int32") return PlyType::kInt32;
  if (s == "uint" || s == "uint32") return PlyType::kUInt32;
  if (s == "float" || s == "float32") return PlyType::kFloat32;
  if (s == "double" || s == "float64") return PlyType::kFloat64;
  return PlyType::kInvalid;
}

int TypeSize(PlyType t) {
  switch (t) {
    case PlyType::kInt8:
    case PlyType::kUInt8:
      return 1;
    case PlyType::kInt16:
    case PlyType::kUInt16:
      return 2;
    case PlyType::kInt32:
    case PlyType::kUInt32:
    case PlyType::kFloat32:
      return 4;
    case PlyType::kFloat64:
      return 8;
    default:
      return 0;
  }
}

struct PlyProperty {
  std::string name;
  PlyType type = PlyType::kInvalid;
  bool is_list = false;
  PlyType count_type = PlyType::kInvalid;
};

struct PlyElement {
  std::string name;
  size_t count = 0;
  std::vector<PlyProperty> properties;
};

// The scalar of type T stored (host byte order) at `buf`.
template <typename T>
double Load(const unsigned char* buf) {
  T x;
  std::memcpy(&x, buf, sizeof(T));
  return static_cast<double>(x);
}

class PlyReader {
 public:
  explicit PlyReader(std::istream& in, PlyFormat format) : in_(in), format_(format) {}

  // Reads one scalar of type t; false on EOF or parse error.
  bool Read(PlyType t, double* v) {
    if (format_ == PlyFormat::kAscii) {
      if (!(in_ >> token_)) return false;
      char* end = nullptr;
      *v = std::strtod(token_.c_str(), &end);
      return end != token_.c_str() && *end == '\0';
    }
    unsigned char buf[8];
    const int n = TypeSize(t);
    if (!in_.read(reinterpret_cast<char*>(buf), n)) return false;
    if (format_ == PlyFormat::kBinaryBig) std::reverse(buf, buf + n);
    switch (t) {
      case PlyType::kInt8:
        *v = Load<int8_t>(buf);
        break;
      case PlyType::kUInt8:
        *v = Load<uint8_t>(buf);
        break;
      case PlyType::kInt16:
        *v = Load<int16_t>(buf);
        break;
      case PlyType::kUInt16:
        *v = Load<uint16_t>(buf);
        break;
      case PlyType::kInt32:
        *v = Load<int32_t>(buf);
        break;
      case PlyType::kUInt32:
        *v = Load<uint32_t>(buf);
        break;
      case PlyType::kFloat32:
        *v = Load<float>(buf);
        break;
      case PlyType::kFloat64:
        *v = Load<double>(buf);
        break;
      default:
        return false;
    }
    return true;
  }

 private:
  std::istream& in_;
  PlyFormat format_;
  std::string token_;
};

struct PlyData {
  std::vector<std::vector<double>> vertex_values;  // per vertex, per scalar property
  std::vector<std::string> vertex_names;
  std::vector<std::vector<int>> faces;
};

StatusOr<PlyData> ParsePly(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return NotFoundError("cannot open PLY '" + path + "'");
  std::string line;
  if (!std::getline(in, line) || line.substr(0, 3) != "ply")
    return InvalidArgumentError("'" + path + "' is not a PLY file");
  PlyFormat format = PlyFormat::kAscii;
  std::vector<PlyElement> elements;
  bool header_done = false;
  while (std::getline(in, line)) {
    if (!line.empty() && line.back() == '\r') line.pop_back();
    std::istringstream ls(line);
    std::string key;
    ls >> key;
    if (key == "format") {
      std::string f;
      ls >> f;
      if (f == "ascii") format = PlyFormat::kAscii;
      else if (f == "binary_little_endian") format = PlyFormat::kBinaryLittle;
      else if (f == "binary_big_endian") format = PlyFormat::kBinaryBig;
      else return InvalidArgumentError(path + ": unknown PLY format '" + f + "'");
    } else if (key == "element") {
      PlyElement e;
      long long count = -1;
      ls >> e.name >> count;
      if (count < 0 || count > (1LL << 31)) return InvalidArgumentError(path + ": bad element count");
      e.count = static_cast<size_t>(count);
      elements.push_back(e);
    } else if (key == "property") {
      if (elements.empty()) return InvalidArgumentError(path + ": property before element");
      PlyProperty p;
      std::string type;
      ls >> type;
      if (type == "list") {
        std::string ct, it;
        ls >> ct >> it >> p.name;
        p.is_list = true;
        p.count_type = ParseType(ct);
        p.type = ParseType(it);
        if (p.count_type == PlyType::kInvalid || p.type == PlyType::kInvalid)
          return InvalidArgumentError(path + ": bad list property types");
      } else {
        p.type = ParseType(type);
        ls >> p.name;
        if (p.type == PlyType::kInvalid) return InvalidArgumentError(path + ": unknown property type '" + type + "'");
      }
      elements.back().properties.push_back(p);
    } else if (key == "end_header") {
      header_done = true;
      break;
    }
  }
  if (!header_done) return InvalidArgumentError(path + ": PLY header has no end_header");

  PlyData data;
  PlyReader reader(in, format);
  for (const PlyElement& e : elements) {
    const bool is_vertex = e.name == "vertex";
    const bool is_face = e.name == "face";
    if (is_vertex)
      for (const PlyProperty& p : e.properties)
        if (!p.is_list) data.vertex_names.push_back(p.name);
    for (size_t i = 0; i < e.count; ++i) {
      std::vector<double> values;
      for (const PlyProperty& p : e.properties) {
        double v = 0;
        if (p.is_list) {
          double n = 0;
          if (!reader.Read(p.count_type, &n) || n < 0 || n > 1000)
            return InvalidArgumentError(path + ": truncated or malformed list in element '" + e.name + "'");
          std::vector<int> idx(static_cast<size_t>(n));
          for (int& k : idx) {
            if (!reader.Read(p.type, &v)) return InvalidArgumentError(path + ": truncated list data");
            k = static_cast<int>(v);
          }
          if (is_face && (p.name == "vertex_indices" || p.name == "vertex_index")) data.faces.push_back(idx);
        } else {
          if (!reader.Read(p.type, &v))
            return InvalidArgumentError(path + ": truncated data in element '" + e.name + "' at item " +
                                        std::to_string(i));
          if (is_vertex) values.push_back(v);
        }
      }
      if (is_vertex) data.vertex_values.push_back(std::move(values));
    }
  }
  return data;
}

int FindName(const std::vector<std::string>& names, std::initializer_list<const char*> candidates) {
  for (const char* c : candidates)
    for (size_t i = 0; i < names.size(); ++i)
      if (names[i] == c) return static_cast<int>(i);
  return -1;
}

std::string LowerExtension(const std::string& path) {
  const size_t dot = path.find_last_of('.');
  std::string ext = dot == std::string::npos ? "" : path.substr(dot + 1);
  for (char& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return ext;
}

Status AddFaces(const std::vector<std::vector<int>>& polys, size_t num_vertices, const std::string& path,
                TriangleMesh* mesh) {
  for (const auto& poly : polys) {
    for (int k : poly)
      if (k < 0 || static_cast<size_t>(k) >= num_vertices)
        return InvalidArgumentError(path + ": face index " + std::to_string(k) + " out of range");
    for (size_t k = 1; k + 1 < poly.size(); ++k) mesh->faces.emplace_back(poly[0], poly[k], poly[k + 1]);
  }
  return Status::Ok();
}

StatusOr<TriangleMesh> ReadOff(const std::string& path) {
  std::ifstream in(path);
  if (!in) return NotFoundError("cannot open OFF '" + path + "'");
  // Tokens, skipping comments.
  std::vector<std::string> tokens;
  std::string line;
  while (std::getline(in, line)) {
    const size_t hash = line.find('#');
    if (hash != std::string::npos) line.resize(hash);
    std::istringstream ls(line);
    std::string t;
    while (ls >> t) tokens.push_back(t);
  }
  size_t pos = 0;
  if (tokens.empty()) return InvalidArgumentError(path + ": empty OFF file");
  if (tokens[0] == "OFF") pos = 1;
  auto next = [&](double* v) {
    if (pos >= tokens.size()) return false;
    char* end = nullptr;
    *v = std::strtod(tokens[pos].c_str(), &end);
    return end != tokens[pos++].c_str() && *end == '\0';
  };
  double nv, nf, ne;
  if (!next(&nv) || !next(&nf) || !next(&ne) || nv < 0 || nf < 0)
    return InvalidArgumentError(path + ": bad OFF counts");
  TriangleMesh mesh;
  for (int i = 0; i < static_cast<int>(nv); ++i) {
    Eigen::Vector3d v;
    if (!next(&v.x()) || !next(&v.y()) || !next(&v.z())) return InvalidArgumentError(path + ": truncated vertices");
    mesh.vertices.push_back(v);
  }
  std::vector<std::vector<int>> polys;
  for (int i = 0; i < static_cast<int>(nf); ++i) {
    double n;
    if (!next(&n) || n < 3 || n > 1000) return InvalidArgumentError(path + ": bad face");
    std::vector<int> poly(static_cast<size_t>(n));
    for (int& k : poly) {
      double v;
      if (!next(&v)) return InvalidArgumentError(path + ": truncated faces");
      k = static_cast<int>(v);
    }
    polys.push_back(poly);
    // Optional colour values after the indices are not supported by position, so skip to line end is
    // impossible after tokenising; OFF files with face colours are rare and rejected by the index check.
  }
  PRISM_RETURN_IF_ERROR(AddFaces(polys, mesh.vertices.size(), path, &mesh));
  return mesh;
}

StatusOr<TriangleMesh> ReadObj(const std::string& path) {
  std::ifstream in(path);
  if (!in) return NotFoundError("cannot open OBJ '" + path + "'");
  TriangleMesh mesh;
  std::vector<std::vector<int>> polys;
  std::string line;
  while (std::getline(in, line)) {
    std::istringstream ls(line);
    std::string key;
    ls >> key;
    if (key == "v") {
      Eigen::Vector3d v;
      if (!(ls >> v.x() >> v.y() >> v.z())) return InvalidArgumentError(path + ": bad vertex line");
      mesh.vertices.push_back(v);
    } else if (key == "f") {
      std::vector<int> poly;
      std::string t;
      while (ls >> t) {
        const int k = std::atoi(t.c_str());  // "i", "i/t", "i/t/n", "i//n"
        poly.push_back(k > 0 ? k - 1 : static_cast<int>(mesh.vertices.size()) + k);
      }
      if (poly.size() < 3) return InvalidArgumentError(path + ": face with fewer than 3 vertices");
      polys.push_back(poly);
    }
  }
  PRISM_RETURN_IF_ERROR(AddFaces(polys, mesh.vertices.size(), path, &mesh));
  return mesh;
}

}  // namespace

StatusOr<PointCloud> ReadPointCloudPly(const std::string& path) {
  PRISM_ASSIGN_OR_RETURN(PlyData data, ParsePly(path));
  const auto& names = data.vertex_names;
  const int x = FindName(names, {"x"}), y = FindName(names, {"y"}), z = FindName(names, {"z"});
  if (x < 0 || y < 0 || z < 0) return InvalidArgumentError(path + ": vertex element lacks x, y, z");
  const int nx = FindName(names, {"nx", "normal_x"}), ny = FindName(names, {"ny", "normal_y"}),
            nz = FindName(names, {"nz", "normal_z"});
  const int r = FindName(names, {"red", "r"}), g = FindName(names, {"green", "g"}), b = FindName(names, {"blue", "b"});
  const int conf = FindName(names, {"confidence", "quality", "scalar_confidence"});
  PointCloud cloud;
  for (const auto& v : data.vertex_values) {
    cloud.positions.emplace_back(static_cast<float>(v[x]), static_cast<float>(v[y]), static_cast<float>(v[z]));
    if (nx >= 0 && ny >= 0 && nz >= 0)
      cloud.normals.emplace_back(static_cast<float>(v[nx]), static_cast<float>(v[ny]), static_cast<float>(v[nz]));
    if (r >= 0 && g >= 0 && b >= 0)
      cloud.colors.emplace_back(static_cast<uint8_t>(std::clamp(v[r], 0.0, 255.0)),
                                static_cast<uint8_t>(std::clamp(v[g], 0.0, 255.0)),
                                static_cast<uint8_t>(std::clamp(v[b], 0.0, 255.0)));
    if (conf >= 0) cloud.confidences.push_back(static_cast<float>(v[conf]));
  }
  return cloud;
}

Status WritePointCloudPly(const std::string& path, const PointCloud& cloud) {
  if (!cloud.IsConsistent()) return InvalidArgumentError("point cloud attribute arrays differ in length");
  std::ofstream out(path, std::ios::binary);
  if (!out) return UnavailableError("cannot write PLY '" + path + "'");
  out << "ply\nformat binary_little_endian 1.0\ncomment written by prism\n";
  out << "element vertex " << cloud.size() << "\n";
  out << "property float x\nproperty float y\nproperty float z\n";
  if (cloud.HasNormals()) out << "property float nx\nproperty float ny\nproperty float nz\n";
  if (cloud.HasColors()) out << "property uchar red\nproperty uchar green\nproperty uchar blue\n";
  if (cloud.HasConfidences()) out << "property float confidence\n";
  out << "end_header\n";
  std::vector<char> buf;
  const size_t stride =
      12 + (cloud.HasNormals() ? 12 : 0) + (cloud.HasColors() ? 3 : 0) + (cloud.HasConfidences() ? 4 : 0);
  buf.resize(stride * cloud.size());
  char* p = buf.data();
  for (size_t i = 0; i < cloud.size(); ++i) {
    std::memcpy(p, cloud.positions[i].data(), 12);
    p += 12;
    if (cloud.HasNormals()) {
      std::memcpy(p, cloud.normals[i].data(), 12);
      p += 12;
    }
    if (cloud.HasColors()) {
      std::memcpy(p, cloud.colors[i].data(), 3);
      p += 3;
    }
    if (cloud.HasConfidences()) {
      std::memcpy(p, &cloud.confidences[i], 4);
      p += 4;
    }
  }
  out.write(buf.data(), static_cast<std::streamsize>(buf.size()));
  if (!out) return UnavailableError("write failed for '" + path + "'");
  return Status::Ok();
}

StatusOr<TriangleMesh> ReadTriangleMesh(const std::string& path) {
  const std::string ext = LowerExtension(path);
  if (ext == "off") return ReadOff(path);
  if (ext == "obj") return ReadObj(path);
  if (ext == "ply") {
    PRISM_ASSIGN_OR_RETURN(PlyData data, ParsePly(path));
    const auto& names = data.vertex_names;
    const int x = FindName(names, {"x"}), y = FindName(names, {"y"}), z = FindName(names, {"z"});
    if (x < 0 || y < 0 || z < 0) return InvalidArgumentError(path + ": vertex element lacks x, y, z");
    TriangleMesh mesh;
    for (const auto& v : data.vertex_values) mesh.vertices.emplace_back(v[x], v[y], v[z]);
    PRISM_RETURN_IF_ERROR(AddFaces(data.faces, mesh.vertices.size(), path, &mesh));
    return mesh;
  }
  return InvalidArgumentError("unsupported mesh format '" + ext + "' (use .off, .ply or .obj): " + path);
}

Status WriteTriangleMeshPly(const std::string& path, const TriangleMesh& mesh) {
  std::ofstream out(path, std::ios::binary);
  if (!out) return UnavailableError("cannot write PLY '" + path + "'");
  out << "ply\nformat binary_little_endian 1.0\nelement vertex " << mesh.vertices.size()
      << "\nproperty float x\nproperty float y\nproperty float z\nelement face " << mesh.faces.size()
      << "\nproperty list uchar int vertex_indices\nend_header\n";
  for (const Eigen::Vector3d& v : mesh.vertices) {
    const Eigen::Vector3f f = v.cast<float>();
    out.write(reinterpret_cast<const char*>(f.data()), 12);
  }
  for (const Eigen::Vector3i& f : mesh.faces) {
    const uint8_t n = 3;
    out.write(reinterpret_cast<const char*>(&n), 1);
    out.write(reinterpret_cast<const char*>(f.data()), 12);
  }
  if (!out) return UnavailableError("write failed for '" + path + "'");
  return Status::Ok();
}

}  // namespace prism
