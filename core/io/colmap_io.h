// COLMAP's text model (cameras.txt, images.txt, points3D.txt; colmap.github.io/format.html), so a
// Prism reconstruction opens in COLMAP's GUI and in tools that read COLMAP models (e.g. for
// multi-view stereo, NeRF or Gaussian-splatting training on the keyframe images).
//   cameras.txt  CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]: PINHOLE (fx fy cx cy) without distortion,
//                OPENCV (fx fy cx cy k1 k2 p1 p2) or FULL_OPENCV (... k3 k4 k5 k6) with it.
//   images.txt   IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME (cam_from_world), then a line of 2D
//                points (empty here: no feature tracks are exported).
//   points3D.txt POINT3D_ID X Y Z R G B ERROR TRACK[] (empty tracks).
// Pixel convention: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), Prism (OpenCV) at
// (0, 0): cx and cy differ by 0.5 between the two; reading and writing convert.
#pragma once

#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "core/geometry/camera.h"
#include "core/geometry/point_cloud.h"
#include "core/geometry/rigid3.h"
#include "core/util/status.h"

namespace prism {

struct ColmapImage {
  uint32_t image_id = 0;  // > 0, unique
  uint32_t camera_id = 1;
  std::string name;  // image file name relative to the image folder, no spaces
  Rigid3d cam_from_world;
};

struct ColmapModel {
  std::map<uint32_t, PinholeCamera> cameras;  // by CAMERA_ID
  std::vector<ColmapImage> images;            // in IMAGE_ID order
  PointCloud points;                          // positions and colours (no normals in COLMAP's format)
};

// Writes dir/cameras.txt, dir/images.txt and dir/points3D.txt (dir is created). Every image's
// camera_id must name a camera; names must be non-empty without whitespace.
Status WriteColmapText(const std::string& dir, const ColmapModel& model);
StatusOr<ColmapModel> ReadColmapText(const std::string& dir);

}  // namespace prism
