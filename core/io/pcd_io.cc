#include "core/io/pcd_io.h"

#include <cstdint>
#include <cstring>
#include <fstream>
#include <limits>
#include <sstream>
#include <vector>

namespace prism {
namespace {

struct PcdField {
  std::string name;
  int size = 4;     // bytes per element
  char type = 'F';  // I, U or F
  int count = 1;
  size_t offset = 0;  // in a binary record
};

uint32_t PackRgb(const Eigen::Matrix<uint8_t, 3, 1>& c) {
  return (uint32_t{c[0]} << 16) | (uint32_t{c[1]} << 8) | uint32_t{c[2]};
}

// One scalar from a binary record (little-endian, as PCL writes on every platform it supports).
double ReadScalar(const char* p, const PcdField& f) {
  switch (f.type) {
    case 'F':
      if (f.size == 4) {
        float v;
        std::memcpy(&v, p, 4);
        return v;
      }
      if (f.size == 8) {
        double v;
        std::memcpy(&v, p, 8);
        return v;
      }
      break;
    case 'I':
      if (f.size == 1) {
        int8_t v;
        std::memcpy(&v, p, 1);
        return v;
      }
      if (f.size == 2) {
        int16_t v;
        std::memcpy(&v, p, 2);
        return v;
      }
      if (f.size == 4) {
        int32_t v;
        std::memcpy(&v, p, 4);
        return v;
      }
      if (f.size == 8) {
        int64_t v;
        std::memcpy(&v, p, 8);
        return static_cast<double>(v);
      }
      break;
    case 'U':
      if (f.size == 1) {
        uint8_t v;
        std::memcpy(&v, p, 1);
        return v;
      }
      if (f.size == 2) {
        uint16_t v;
        std::memcpy(&v, p, 2);
        return v;
      }
      if (f.size == 4) {
        uint32_t v;
        std::memcpy(&v, p, 4);
        return v;
      }
      if (f.size == 8) {
        uint64_t v;
        std::memcpy(&v, p, 8);
        return static_cast<double>(v);
      }
      break;
  }
  return std::numeric_limits<double>::quiet_NaN();
}

// The packed colour field (rgb / rgba) as its 32 bits, whatever its declared type.
uint32_t ReadPackedBits(const char* p) {
  uint32_t bits;
  std::memcpy(&bits, p, 4);
  return bits;
}

}  // namespace

StatusOr<PointCloud> ReadPointCloudPcd(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return NotFoundError("cannot open '" + path + "'");
  std::vector<PcdField> fields;
  size_t points = 0, width = 0, height = 1;
  bool have_points = false;
  std::string data, line;
  int line_number = 0;
  auto bad = [&](const std::string& what) {
    return InvalidArgumentError(path + ":" + std::to_string(line_number) + ": " + what);
  };
  while (data.empty() && std::getline(in, line)) {
    ++line_number;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line.empty() || line[0] == '#') continue;
    std::istringstream ls(line);
    std::string key;
    ls >> key;
    std::vector<std::string> values;
    for (std::string v; ls >> v;) values.push_back(v);
    if (key == "VERSION") continue;
    if (key == "FIELDS") {
      fields.resize(values.size());
      for (size_t i = 0; i < values.size(); ++i) fields[i].name = values[i];
    } else if (key == "SIZE" || key == "TYPE" || key == "COUNT") {
      if (values.size() != fields.size())
        return bad(key + " has " + std::to_string(values.size()) + " entries for " + std::to_string(fields.size()) +
                   " fields");
      for (size_t i = 0; i < values.size(); ++i) {
        if (key == "TYPE") {
          if (values[i].size() != 1 || std::string("IUF").find(values[i][0]) == std::string::npos)
            return bad("bad TYPE '" + values[i] + "'");
          fields[i].type = values[i][0];
        } else {
          const int v = std::atoi(values[i].c_str());
          if (v <= 0 || (key == "SIZE" && v != 1 && v != 2 && v != 4 && v != 8))
            return bad("bad " + key + " '" + values[i] + "'");
          (key == "SIZE" ? fields[i].size : fields[i].count) = v;
        }
      }
    } else if (key == "WIDTH" && values.size() == 1) {
      width = std::strtoull(values[0].c_str(), nullptr, 10);
    } else if (key == "HEIGHT" && values.size() == 1) {
      height = std::strtoull(values[0].c_str(), nullptr, 10);
    } else if (key == "POINTS" && values.size() == 1) {
      points = std::strtoull(values[0].c_str(), nullptr, 10);
      have_points = true;
    } else if (key == "VIEWPOINT") {
      continue;
    } else if (key == "DATA" && values.size() == 1) {
      data = values[0];
    } else {
      return bad("unexpected header line '" + line + "'");
    }
  }
  if (data.empty()) return InvalidArgumentError(path + ": no DATA line (not a PCD file?)");
  if (!have_points) points = width * height;
  if (data == "binary_compressed")
    return InvalidArgumentError(path + ": DATA binary_compressed is not supported (re-save as binary or ascii)");
  if (data != "binary" && data != "ascii") return InvalidArgumentError(path + ": unknown DATA '" + data + "'");
  if (points > (size_t{1} << 31))
    return InvalidArgumentError(path + ": too many points (" + std::to_string(points) + ")");

  size_t record = 0;
  int ix = -1, iy = -1, iz = -1, inx = -1, iny = -1, inz = -1, irgb = -1, ir = -1, ig = -1, ib = -1;
  for (size_t i = 0; i < fields.size(); ++i) {
    fields[i].offset = record;
    record += static_cast<size_t>(fields[i].size) * fields[i].count;
    const std::string& n = fields[i].name;
    const int idx = static_cast<int>(i);
    if (n == "x") ix = idx;
    else if (n == "y") iy = idx;
    else if (n == "z") iz = idx;
    else if (n == "normal_x") inx = idx;
    else if (n == "normal_y") iny = idx;
    else if (n == "normal_z") inz = idx;
    else if ((n == "rgb" || n == "rgba") && fields[i].size == 4) irgb = idx;
    else if (n == "r") ir = idx;
    else if (n == "g") ig = idx;
    else if (n == "b") ib = idx;
  }
  if (ix < 0 || iy < 0 || iz < 0) return InvalidArgumentError(path + ": needs fields x y z");
  const bool has_normals = inx >= 0 && iny >= 0 && inz >= 0;
  const bool has_colors = irgb >= 0 || (ir >= 0 && ig >= 0 && ib >= 0);

  PointCloud cloud;
  cloud.positions.resize(points);
  if (has_normals) cloud.normals.resize(points);
  if (has_colors) cloud.colors.resize(points);
  std::vector<char> buffer(record);
  // ASCII values of one point, flattened over fields and counts; packed rgb kept as its bits.
  std::vector<double> values;
  std::vector<uint32_t> packed(fields.size());
  for (size_t p = 0; p < points; ++p) {
    auto get = [&](int f) -> double {
      if (data == "binary") return ReadScalar(buffer.data() + fields[f].offset, fields[f]);
      size_t k = 0;
      for (int i = 0; i < f; ++i) k += fields[i].count;
      return values[k];
    };
    if (data == "binary") {
      if (!in.read(buffer.data(), static_cast<std::streamsize>(record)))
        return DataLossError(path + ": truncated at point " + std::to_string(p) + " of " + std::to_string(points));
      if (irgb >= 0) packed[irgb] = ReadPackedBits(buffer.data() + fields[irgb].offset);
    } else {
      values.clear();
      for (size_t f = 0; f < fields.size(); ++f)
        for (int c = 0; c < fields[f].count; ++c) {
          std::string token;
          if (!(in >> token))
            return DataLossError(path + ": truncated at point " + std::to_string(p) + " of " + std::to_string(points));
          if (static_cast<int>(f) == irgb) {
            // PCL writes the packed colour in ASCII as an unsigned integer even when TYPE is F (opaque
            // colours would be NaN as floats); older writers used the float whose bits are the colour.
            if (token.find_first_not_of("0123456789") == std::string::npos) {
              packed[f] = static_cast<uint32_t>(std::strtoul(token.c_str(), nullptr, 10));
            } else {
              const float v = std::strtof(token.c_str(), nullptr);
              std::memcpy(&packed[f], &v, 4);
            }
            values.push_back(0);
          } else {
            char* end = nullptr;
            values.push_back(std::strtod(token.c_str(), &end));
            if (end == token.c_str())
              return InvalidArgumentError(path + ": bad number '" + token + "' at point " + std::to_string(p));
          }
        }
    }
    cloud.positions[p] =
        Eigen::Vector3f(static_cast<float>(get(ix)), static_cast<float>(get(iy)), static_cast<float>(get(iz)));
    if (has_normals)
      cloud.normals[p] =
          Eigen::Vector3f(static_cast<float>(get(inx)), static_cast<float>(get(iny)), static_cast<float>(get(inz)));
    if (irgb >= 0) {
      const uint32_t c = packed[irgb];
      cloud.colors[p] = {static_cast<uint8_t>(c >> 16), static_cast<uint8_t>(c >> 8), static_cast<uint8_t>(c)};
    } else if (has_colors) {
      cloud.colors[p] = {static_cast<uint8_t>(get(ir)), static_cast<uint8_t>(get(ig)), static_cast<uint8_t>(get(ib))};
    }
  }
  return cloud;
}

Status WritePointCloudPcd(const std::string& path, const PointCloud& cloud, PcdEncoding encoding) {
  if (!cloud.IsConsistent()) return InvalidArgumentError("point cloud attributes do not match its size");
  std::ofstream out(path, std::ios::binary);
  if (!out) return UnavailableError("cannot write '" + path + "'");
  const bool normals = cloud.HasNormals(), colors = cloud.HasColors();
  std::string fields = "x y z", sizes = "4 4 4", types = "F F F", counts = "1 1 1";
  if (normals) {
    fields += " normal_x normal_y normal_z curvature";
    sizes += " 4 4 4 4";
    types += " F F F F";
    counts += " 1 1 1 1";
  }
  if (colors) {
    fields += " rgb";
    sizes += " 4";
    types += " U";  // as PCL 1.13 writes rgb: the packed colour as an unsigned integer (PCL reads U rgb
                    // into PointXYZRGB's float field bit for bit; an ASCII F rgb would be read as a value)
    counts += " 1";
  }
  out << "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS " << fields << "\nSIZE " << sizes << "\nTYPE "
      << types << "\nCOUNT " << counts << "\nWIDTH " << cloud.size() << "\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS "
      << cloud.size() << "\nDATA " << (encoding == PcdEncoding::kBinary ? "binary" : "ascii") << "\n";
  std::vector<float> row;
  for (size_t i = 0; i < cloud.size(); ++i) {
    row.assign(cloud.positions[i].data(), cloud.positions[i].data() + 3);
    if (normals) {
      row.insert(row.end(), cloud.normals[i].data(), cloud.normals[i].data() + 3);
      row.push_back(0.f);  // curvature
    }
    if (colors) {
      const uint32_t bits = PackRgb(cloud.colors[i]);
      float packed;
      std::memcpy(&packed, &bits, 4);
      row.push_back(packed);
    }
    if (encoding == PcdEncoding::kBinary) {
      out.write(reinterpret_cast<const char*>(row.data()), static_cast<std::streamsize>(row.size() * sizeof(float)));
    } else {
      for (size_t k = 0; k < row.size(); ++k) {
        if (k) out << ' ';
        if (colors && k + 1 == row.size()) {
          out << PackRgb(cloud.colors[i]);
        } else {
          char buf[32];
          std::snprintf(buf, sizeof(buf), "%.9g", row[k]);
          out << buf;
        }
      }
      out << '\n';
    }
  }
  if (!out) return UnavailableError("write failed: '" + path + "'");
  return Status::Ok();
}

}  // namespace prism
