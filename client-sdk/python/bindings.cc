// Python bindings of libprism_client (module prism_client._native; the package prism_client wraps it).
// Frames go in as numpy (H, W, 3) uint8 RGB arrays; poses, map chunks and the running map come back as
// numpy arrays. Failures raise prism_client.PrismError (code, message, retryable). The GIL is released
// while the SDK waits on the network, so other Python threads run meanwhile.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cstdio>
#include <cstring>
#include <deque>
#include <memory>
#include <string>
#include <unordered_map>
#include <vector>

#include <opencv2/core.hpp>

#include "core/io/colmap_io.h"
#include "core/io/image_io.h"
#include "core/io/sequence.h"
#include "prism/client/client.h"
#include "tools/capture/live_stream.h"
#include "tools/capture/video_source.h"

namespace py = pybind11;
namespace pc = prism::client;

namespace {

py::object g_error_type;  // prism_client.PrismError, set by the package at import

[[noreturn]] void Raise(const pc::Status& status) {
  if (g_error_type) {
    PyErr_SetObject(g_error_type.ptr(),
                    py::make_tuple(pc::CodeName(status.code), status.message, status.retryable).ptr());
    throw py::error_already_set();
  }
  throw std::runtime_error(status.ToString());
}

void Check(const pc::Status& status) {
  if (!status.ok()) Raise(status);
}

// Points -> {"positions": (N, 3) float32, "normals": (N, 3) float32, "colors": (N, 3) uint8}.
py::dict PointsToNumpy(const std::vector<pc::Point>& points) {
  const py::ssize_t n = static_cast<py::ssize_t>(points.size());
  py::array_t<float> positions({n, py::ssize_t{3}}), normals({n, py::ssize_t{3}});
  py::array_t<uint8_t> colors({n, py::ssize_t{3}});
  auto p = positions.mutable_unchecked<2>();
  auto q = normals.mutable_unchecked<2>();
  auto c = colors.mutable_unchecked<2>();
  for (py::ssize_t i = 0; i < n; ++i)
    for (py::ssize_t k = 0; k < 3; ++k) {
      p(i, k) = points[i].position[k];
      q(i, k) = points[i].normal[k];
      c(i, k) = points[i].color[k];
    }
  py::dict d;
  d["positions"] = positions;
  d["normals"] = normals;
  d["colors"] = colors;
  return d;
}

py::dict PoseToDict(const pc::Pose& pose) {
  py::dict d;
  d["frame"] = pose.frame_sequence_number;
  d["timestamp_ns"] = pose.timestamp_ns;
  d["rotation_xyzw"] =
      py::make_tuple(pose.rotation_xyzw[0], pose.rotation_xyzw[1], pose.rotation_xyzw[2], pose.rotation_xyzw[3]);
  d["translation"] = py::make_tuple(pose.translation[0], pose.translation[1], pose.translation[2]);
  d["state"] = pc::TrackingStateName(pose.state);
  d["is_keyframe"] = pose.is_keyframe;
  d["keyframe_id"] = pose.keyframe_id;
  d["refined"] = pose.refined;
  d["metres_per_unit"] = pose.metres_per_unit;
  // How the frame aligned against its keyframe (client.h, TrackingQuality); None when it was not
  // (initialising, lost, relocalised).
  if (pose.has_tracking) {
    py::dict t;
    t["residual_rms"] = pose.tracking.residual_rms;
    t["visible_fraction"] = pose.tracking.visible_fraction;
    t["inlier_fraction"] = pose.tracking.inlier_fraction;
    t["iterations"] = pose.tracking.iterations;
    t["retried"] = pose.tracking.retried;
    t["step"] = pose.tracking.step;
    t["rotation_deg"] = pose.tracking.rotation_deg;
    t["guess_correction"] = pose.tracking.guess_correction;
    d["tracking"] = t;
  } else {
    d["tracking"] = py::none();
  }
  return d;
}

py::dict LiveStatsToDict(const prism::LiveStats& s) {
  py::dict d;
  d["captured"] = s.captured;
  d["sent"] = s.sent;
  d["dropped"] = s.dropped();
  d["skipped_no_credit"] = s.skipped_no_credit;
  d["skipped_stale"] = s.skipped_stale;
  d["frames_per_s"] = s.frames_per_s;
  d["poses"] = s.poses;
  d["chunks"] = s.chunks;
  d["tracking"] = pc::TrackingStateName(s.tracking);
  d["map_points"] = s.map_points;
  d["seconds"] = s.seconds;
  d["end"] = s.end;
  return d;
}

// A core Status as the SDK's (the Python error's code and message).
pc::Status ToClientStatus(const prism::Status& s) {
  pc::Code code = pc::Code::kInternal;
  switch (s.code()) {
    case prism::StatusCode::kInvalidArgument:
    case prism::StatusCode::kOutOfRange:
      code = pc::Code::kInvalidArgument;
      break;
    case prism::StatusCode::kNotFound:
      code = pc::Code::kNotFound;
      break;
    case prism::StatusCode::kFailedPrecondition:
      code = pc::Code::kFailedPrecondition;
      break;
    case prism::StatusCode::kUnavailable:
      code = pc::Code::kUnavailable;
      break;
    default:
      break;
  }
  return {code, s.message(), false};
}

py::dict SummaryToDict(const pc::Summary& s) {
  py::dict d;
  d["frames_received"] = s.frames_received;
  d["frames_dropped"] = s.frames_dropped;
  d["frames_rejected"] = s.frames_rejected;
  d["keyframes"] = s.keyframes;
  d["keyframes_dropped"] = s.keyframes_dropped;
  d["keyframes_failed"] = s.keyframes_failed;
  d["frames_depth_update_skipped"] = s.frames_depth_update_skipped;
  d["chunks_sent"] = s.chunks_sent;
  d["map_points"] = s.map_points;
  d["metres_per_unit"] = s.metres_per_unit;
  d["reason"] = s.reason;
  d["shading_check"] = s.shading_check == pc::Summary::ShadingCheck::kConsistent  ? "consistent"
                       : s.shading_check == pc::Summary::ShadingCheck::kDistorted ? "distorted"
                                                                                  : "not_run";
  d["shading_pair_spread"] = s.shading_pair_spread;
  d["start_check"] = pc::StartCheckName(s.start_check);
  d["start_pair_spread"] = s.start_pair_spread;
  return d;
}

// Event -> (kind, payload): ("pose", dict), ("chunk", dict with keyframe_id, sequence_number,
// replaces_map, draco bytes and the points as arrays), ("error", (code, message, retryable)), ("summary", dict).
py::tuple EventToPython(const pc::Event& e) {
  switch (e.kind) {
    case pc::Event::Kind::kPose:
      return py::make_tuple("pose", PoseToDict(e.pose));
    case pc::Event::Kind::kChunk: {
      py::dict d = PointsToNumpy(e.chunk.points);
      d["keyframe_id"] = e.chunk.keyframe_id;
      d["sequence_number"] = e.chunk.sequence_number;
      d["replaces_map"] = e.chunk.replaces_map;
      d["draco"] = py::bytes(reinterpret_cast<const char*>(e.chunk.draco.data()), e.chunk.draco.size());
      return py::make_tuple("chunk", d);
    }
    case pc::Event::Kind::kError:
      return py::make_tuple("error", py::make_tuple(pc::CodeName(e.error.code), e.error.message, e.error.retryable));
    case pc::Event::Kind::kSummary:
      return py::make_tuple("summary", SummaryToDict(e.summary));
  }
  return py::make_tuple("unknown", py::none());
}

pc::Codec ParseCodec(const std::string& name) {
  if (name == "png") return pc::Codec::kPng;
  if (name == "jpeg") return pc::Codec::kJpeg;
  if (name == "raw") return pc::Codec::kRaw;
  Raise({pc::Code::kInvalidArgument, "codec must be png, jpeg or raw, got '" + name + "'", false});
}

// A session plus the poses it has received (kept here so Python gets them as one array).
class PySession {
 public:
  PySession(const std::string& endpoint, const pc::Rig& rig, const std::string& codec, int jpeg_quality, bool live,
            int chunk_credits, int timeout_ms, const std::string& client_name, const std::string& server_public_key,
            const std::string& client_public_key, const std::string& client_secret_key) {
    pc::SessionOptions options;
    options.codec = ParseCodec(codec);
    options.jpeg_quality = jpeg_quality;
    options.live = live;
    options.chunk_credits = chunk_credits;
    options.timeout_ms = timeout_ms;
    options.client_name = client_name;
    options.server_public_key = server_public_key;
    options.client_public_key = client_public_key;
    options.client_secret_key = client_secret_key;
    pc::Status s;
    {
      py::gil_scoped_release release;
      s = pc::Session::Open(endpoint, rig, options, &session_);
    }
    Check(s);
    width_ = rig.camera.width;
    height_ = rig.camera.height;
  }

  // The arguments in the order of the C++ Session::PushFrame: the time stamp first.
  void PushFrame(int64_t timestamp_ns, py::array_t<uint8_t, py::array::c_style | py::array::forcecast> rgb) {
    if (rgb.ndim() != 3 || rgb.shape(2) != 3)
      Raise({pc::Code::kInvalidArgument, "frame must be an (H, W, 3) uint8 RGB array", false});
    const int h = static_cast<int>(rgb.shape(0)), w = static_cast<int>(rgb.shape(1));
    const uint8_t* data = rgb.data();
    pc::Status s;
    {
      py::gil_scoped_release release;
      s = Live()->PushFrame(timestamp_ns, data, w, h, w * 3);
      Drain();
    }
    Check(s);
  }

  // Streams the colour frames of a sequence folder (TUM layout); returns the frames sent.
  size_t StreamFolder(const std::string& dir, size_t max_frames) {
    prism::StatusOr<prism::Sequence> seq = prism::LoadSequence(dir);
    if (!seq.ok()) Raise({pc::Code::kInvalidArgument, seq.status().ToString(), false});
    size_t sent = 0;
    pc::Status s;
    {
      py::gil_scoped_release release;
      for (size_t i = 0; i < seq->frames.size() && sent < max_frames; ++i) {
        prism::StatusOr<cv::Mat> rgb = seq->ReadRgb(i);
        if (!rgb.ok()) {
          s = {pc::Code::kInvalidArgument, rgb.status().ToString(), false};
          break;
        }
        const cv::Mat& m = *rgb;
        s = Live()->PushFrame(static_cast<int64_t>(seq->frames[i].timestamp_s * 1e9 + 0.5), m.ptr<uint8_t>(), m.cols,
                              m.rows, static_cast<int>(m.step[0]));
        if (!s.ok()) break;
        ++sent;
        Drain();
      }
    }
    Check(s);
    return sent;
  }

  // Captures from `source` (anything cv::VideoCapture opens) and streams it as prism-client stream
  // --source does (tools/capture/live_stream.h); returns the capture's counts. progress(dict) is called
  // about every progress_interval_ms; Ctrl-C stops the capture and returns normally.
  py::dict StreamSource(const std::string& source, int64_t max_frames, bool realtime, py::object exposure,
                        py::object white_balance, bool lock_exposure, bool lock_white_balance,
                        const std::string& record, const std::string& camera_yaml, py::object progress,
                        int progress_interval_ms) {
    prism::VideoSourceOptions capture;
    capture.source = source;
    capture.width = width_;
    capture.height = height_;
    if (!exposure.is_none()) capture.exposure = exposure.cast<double>();
    if (!white_balance.is_none()) capture.white_balance_k = white_balance.cast<double>();
    capture.lock_exposure = lock_exposure;
    capture.lock_white_balance = lock_white_balance;
    prism::StatusOr<std::unique_ptr<prism::VideoSource>> src = [&] {
      py::gil_scoped_release release;
      return prism::VideoSource::Open(capture);
    }();
    if (!src.ok()) Raise(ToClientStatus(src.status()));
    int w = 0, h = 0;
    if (prism::Status s = (*src)->PeekSize(&w, &h); !s.ok()) Raise(ToClientStatus(s));
    if (w != width_ || h != height_)
      Raise({pc::Code::kInvalidArgument,
             "source '" + source + "' gives " + std::to_string(w) + "x" + std::to_string(h) +
                 " frames, but the session's camera is " + std::to_string(width_) + "x" + std::to_string(height_),
             false});
    std::unique_ptr<prism::SequenceRecorder> recorder;
    if (!record.empty()) {
      if (camera_yaml.empty())
        Raise({pc::Code::kInvalidArgument, "record needs camera_yaml (the rig's camera.yaml, copied into it)", false});
      prism::StatusOr<std::unique_ptr<prism::SequenceRecorder>> r =
          prism::SequenceRecorder::Create(record, camera_yaml);
      if (!r.ok()) Raise(ToClientStatus(r.status()));
      recorder = std::move(*r);
    }
    prism::LiveStreamOptions options;
    options.realtime = realtime;
    options.max_frames = max_frames;
    options.width = width_;
    options.height = height_;
    options.progress_interval_ms = progress_interval_ms;
    prism::LiveStream stream(Live(), src->get(), recorder.get(), options);
    bool interrupted = false;
    std::unique_ptr<py::error_already_set> callback_error;
    auto on_progress = [&](const prism::LiveStats& stats) {
      py::gil_scoped_acquire acquire;
      if (PyErr_CheckSignals() != 0) {  // Ctrl-C: stop capturing, close normally
        PyErr_Clear();
        interrupted = true;
        stream.Stop();
      }
      if (progress.is_none() || callback_error) return;
      try {
        progress(LiveStatsToDict(stats));
      } catch (py::error_already_set& e) {
        callback_error = std::make_unique<py::error_already_set>(std::move(e));
        stream.Stop();
      }
    };
    prism::Status st;
    {
      py::gil_scoped_release release;
      st = stream.Run(
          [this](const pc::Event& e) {
            if (e.kind == pc::Event::Kind::kPose) KeepPose(e.pose);
            pending_.push_back(e);
          },
          on_progress);
      if (recorder) {
        const prism::Status r = recorder->Finish();
        if (st.ok()) st = r;
      }
    }
    if (callback_error) throw *callback_error;
    if (!st.ok()) Raise(ToClientStatus(st));
    py::dict d = LiveStatsToDict(stream.stats());
    d["interrupted"] = interrupted;
    d["exposure_locked"] = (*src)->exposure_locked();
    d["white_balance_locked"] = (*src)->white_balance_locked();
    py::list notes;
    for (const std::string& n : (*src)->notes()) notes.append(n);
    d["notes"] = notes;
    if (recorder) {
      d["recorded"] = recorder->written();
      d["record_dropped"] = recorder->dropped();
    }
    return d;
  }

  // Next event or None (waits up to timeout_ms). Events that arrived during stream_folder or close
  // come first, in order; every pose is also kept for poses().
  py::object Poll(int timeout_ms) {
    pc::Event e;
    bool got = false;
    if (!pending_.empty()) {
      e = std::move(pending_.front());
      pending_.pop_front();
      got = true;
    } else {
      {
        py::gil_scoped_release release;
        got = Live()->Poll(&e, timeout_ms);
      }
      if (got && e.kind == pc::Event::Kind::kPose) KeepPose(e.pose);
    }
    if (!got) return py::none();
    return EventToPython(e);
  }

  py::dict Close(int timeout_ms) {
    pc::Summary summary;
    pc::Status s;
    {
      py::gil_scoped_release release;
      s = Live()->Close(timeout_ms, &summary);
      Drain();
    }
    Check(s);
    summary_scale_ = summary.metres_per_unit;
    return SummaryToDict(summary);
  }

  // (N, 8) float64: timestamp_s tx ty tz qx qy qz qw (world_from_camera, TUM order, metres once the
  // server knows the scale), for the poses received so far: tracked ones only by default; keyframes_only
  // keeps the frames the SLAM made keyframes (the images the dense map comes from, e.g. for write_colmap).
  py::array_t<double> Poses(bool tracked_only, bool keyframes_only) const {
    std::vector<const pc::Pose*> rows;
    for (const pc::Pose& p : poses_)
      if ((!tracked_only || p.state == pc::TrackingState::kTracking) && (!keyframes_only || p.is_keyframe))
        rows.push_back(&p);
    // One scale for the whole trajectory (as prism-client writes it): the session's final one from the
    // Summary, else the latest a pose carried; SLAM units while the server has none.
    double s = summary_scale_;
    for (auto it = poses_.rbegin(); s <= 0 && it != poses_.rend(); ++it) s = it->metres_per_unit;
    if (s <= 0) s = 1.0;
    py::array_t<double> out({static_cast<py::ssize_t>(rows.size()), py::ssize_t{8}});
    auto a = out.mutable_unchecked<2>();
    for (size_t i = 0; i < rows.size(); ++i) {
      const pc::Pose& p = *rows[i];
      a(i, 0) = static_cast<double>(p.timestamp_ns) * 1e-9;
      for (int k = 0; k < 3; ++k) a(i, 1 + k) = p.translation[k] * s;
      for (int k = 0; k < 4; ++k) a(i, 4 + k) = p.rotation_xyzw[k];
    }
    return out;
  }

  py::dict Map() const { return PointsToNumpy(Live()->Map()); }
  std::string id() const { return Live()->session_id(); }
  int frame_credits() const { return Live()->frame_credits(); }
  uint64_t bytes_sent() const { return Live()->bytes_sent(); }
  std::pair<int, int> size() const { return {width_, height_}; }

 private:
  // Never null: the constructor raises when Open fails.
  pc::Session* Live() const { return session_.get(); }
  // One pose per frame: a refined pose replaces the frame's earlier one.
  void KeepPose(const pc::Pose& pose) {
    if (pose.refined) {
      auto it = pose_index_.find(pose.frame_sequence_number);
      if (it != pose_index_.end()) {
        poses_[it->second] = pose;
        return;
      }
    }
    pose_index_[pose.frame_sequence_number] = poses_.size();
    poses_.push_back(pose);
  }
  // Moves the events waiting now into pending_ (for Poll) and keeps the poses. Runs without the GIL:
  // only C++ state.
  void Drain() {
    pc::Event e;
    while (session_->Poll(&e, 0)) {
      if (e.kind == pc::Event::Kind::kPose) KeepPose(e.pose);
      pending_.push_back(std::move(e));
    }
  }

  std::unique_ptr<pc::Session> session_;
  std::vector<pc::Pose> poses_;                      // in arrival order of each frame's first pose
  std::unordered_map<uint64_t, size_t> pose_index_;  // frame sequence number -> index in poses_
  std::deque<pc::Event> pending_;                    // received inside StreamFolder/Close, not yet polled
  int width_ = 0, height_ = 0;
  double summary_scale_ = 0;  // metres per SLAM unit from the Summary (0 before Close)
};

}  // namespace

PYBIND11_MODULE(_native, m) {
  m.doc() = "libprism_client bindings (use the prism_client package)";
  m.def("_set_error_type", [](py::object type) { g_error_type = type; });

  py::class_<pc::Camera>(m, "Camera")
      .def(py::init<>())
      .def_readwrite("width", &pc::Camera::width)
      .def_readwrite("height", &pc::Camera::height)
      .def_readwrite("fx", &pc::Camera::fx)
      .def_readwrite("fy", &pc::Camera::fy)
      .def_readwrite("cx", &pc::Camera::cx)
      .def_readwrite("cy", &pc::Camera::cy)
      .def_readwrite("distortion", &pc::Camera::distortion);
  py::class_<pc::Light>(m, "Light")
      .def(py::init<>())
      .def_readwrite("name", &pc::Light::name)
      .def_readwrite("directional", &pc::Light::directional)
      .def_readwrite("position_in_camera", &pc::Light::position_in_camera)
      .def_readwrite("direction_in_camera", &pc::Light::direction_in_camera)
      .def_readwrite("color", &pc::Light::color)
      .def_readwrite("intensity", &pc::Light::intensity);
  py::class_<pc::Rig>(m, "Rig")
      .def(py::init<>())
      .def_readwrite("camera", &pc::Rig::camera)
      .def_readwrite("lights", &pc::Rig::lights)
      .def_readwrite("crosstalk", &pc::Rig::crosstalk);
  m.def(
      "load_rig",
      [](const std::string& path) {
        pc::Rig rig;
        Check(pc::LoadRig(path, &rig));  // the SDK's reader, as C++ clients use it
        return rig;
      },
      py::arg("path"), "Reads a rig calibration (camera.yaml, OpenCV FileStorage) into a Rig.");
  m.def(
      "generate_key_pair",
      []() {
        std::string public_key, secret_key;
        Check(pc::GenerateKeyPair(&public_key, &secret_key));
        return py::make_tuple(public_key, secret_key);
      },
      "A CURVE key pair (public, secret), Z85 text, as `prism-server keygen` makes.");
  m.def(
      "read_image",
      [](const std::string& path) {
        prism::StatusOr<cv::Mat> rgb = prism::ReadRgbImage(path);
        if (!rgb.ok()) Raise({pc::Code::kInvalidArgument, rgb.status().ToString(), false});
        const cv::Mat m = rgb->isContinuous() ? *rgb : rgb->clone();
        py::array_t<uint8_t> out({static_cast<py::ssize_t>(m.rows), static_cast<py::ssize_t>(m.cols), py::ssize_t{3}});
        std::memcpy(out.mutable_data(), m.data, m.total() * 3);
        return out;
      },
      py::arg("path"), "Reads an 8-bit image file as an (H, W, 3) uint8 RGB array.");
  m.def(
      "write_colmap",
      [](const std::string& dir, const pc::Camera& camera,
         py::array_t<double, py::array::c_style | py::array::forcecast> poses, const std::vector<std::string>& names,
         py::object cloud) {
        if (poses.ndim() != 2 || poses.shape(1) != 8)
          Raise({pc::Code::kInvalidArgument, "poses must be an (N, 8) array: t tx ty tz qx qy qz qw", false});
        if (!names.empty() && names.size() != static_cast<size_t>(poses.shape(0)))
          Raise({pc::Code::kInvalidArgument, "names must be empty or one per pose", false});
        prism::ColmapModel model;
        prism::PinholeCamera& c = model.cameras[1];
        c.width = camera.width;
        c.height = camera.height;
        c.fx = camera.fx;
        c.fy = camera.fy;
        c.cx = camera.cx;
        c.cy = camera.cy;
        c.distortion = camera.distortion;
        auto a = poses.unchecked<2>();
        for (py::ssize_t i = 0; i < poses.shape(0); ++i) {
          prism::ColmapImage image;
          image.image_id = static_cast<uint32_t>(i + 1);
          char name[64];
          std::snprintf(name, sizeof(name), "%.6f.png", a(i, 0));
          image.name = names.empty() ? std::string(name) : names[i];
          const prism::Rigid3d world_from_camera(Eigen::Quaterniond(a(i, 7), a(i, 4), a(i, 5), a(i, 6)),
                                                 Eigen::Vector3d(a(i, 1), a(i, 2), a(i, 3)));
          image.cam_from_world = world_from_camera.Inverse();
          model.images.push_back(image);
        }
        if (!cloud.is_none()) {
          py::dict d = cloud.cast<py::dict>();
          auto positions = d["positions"].cast<py::array_t<float, py::array::c_style | py::array::forcecast>>();
          auto colors = d["colors"].cast<py::array_t<uint8_t, py::array::c_style | py::array::forcecast>>();
          if (positions.ndim() != 2 || positions.shape(1) != 3 || colors.ndim() != 2 || colors.shape(1) != 3 ||
              colors.shape(0) != positions.shape(0))
            Raise({pc::Code::kInvalidArgument, "cloud needs positions and colors as (M, 3) arrays", false});
          auto pa = positions.unchecked<2>();
          auto ca = colors.unchecked<2>();
          for (py::ssize_t i = 0; i < positions.shape(0); ++i) {
            model.points.positions.emplace_back(pa(i, 0), pa(i, 1), pa(i, 2));
            model.points.colors.emplace_back(ca(i, 0), ca(i, 1), ca(i, 2));
          }
        }
        const prism::Status st = prism::WriteColmapText(dir, model);
        if (!st.ok()) Raise({pc::Code::kInvalidArgument, st.ToString(), false});
      },
      py::arg("dir"), py::arg("camera"), py::arg("poses"), py::arg("names") = std::vector<std::string>(),
      py::arg("cloud") = py::none(),
      "Writes a COLMAP text model (cameras.txt, images.txt, points3D.txt) of poses (N, 8) seen by camera.");
  m.def(
      "decode_chunk",
      [](py::bytes data) {
        const std::string bytes = data;
        std::vector<pc::Point> points;
        Check(pc::DecodeChunk(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size(), &points));
        return PointsToNumpy(points);
      },
      py::arg("data"), "Decodes a Draco map chunk (.drc bytes) into positions, normals and colours.");

  py::class_<PySession>(m, "Session")
      .def(py::init<const std::string&, const pc::Rig&, const std::string&, int, bool, int, int, const std::string&,
                    const std::string&, const std::string&, const std::string&>(),
           py::arg("endpoint"), py::arg("rig"), py::arg("codec") = "png", py::arg("jpeg_quality") = 95,
           py::arg("live") = false, py::arg("chunk_credits") = 8, py::arg("timeout_ms") = 10000,
           py::arg("client_name") = "prism_client.py", py::arg("server_public_key") = "",
           py::arg("client_public_key") = "", py::arg("client_secret_key") = "")
      .def("push_frame", &PySession::PushFrame, py::arg("timestamp_ns"), py::arg("rgb"))
      .def("stream_folder", &PySession::StreamFolder, py::arg("sequence_dir"), py::arg("max_frames") = size_t(-1))
      .def("stream_source", &PySession::StreamSource, py::arg("source"), py::arg("max_frames") = 0,
           py::arg("realtime") = false, py::arg("exposure") = py::none(), py::arg("white_balance") = py::none(),
           py::arg("lock_exposure") = false, py::arg("lock_white_balance") = false, py::arg("record") = "",
           py::arg("camera_yaml") = "", py::arg("progress") = py::none(), py::arg("progress_interval_ms") = 500)
      .def("poll", &PySession::Poll, py::arg("timeout_ms") = 0)
      .def("close", &PySession::Close, py::arg("timeout_ms") = 300000)
      .def("poses", &PySession::Poses, py::arg("tracked_only") = true, py::arg("keyframes_only") = false)
      .def("map", &PySession::Map)
      .def_property_readonly("id", &PySession::id)
      .def_property_readonly("frame_credits", &PySession::frame_credits)
      .def_property_readonly("bytes_sent", &PySession::bytes_sent)
      .def_property_readonly("size", &PySession::size);
}
