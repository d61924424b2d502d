"""Python client of prism-server (bindings of libprism_client).

    import prism_client
    rig = prism_client.load_rig("sequence/camera.yaml")
    with prism_client.Session("tcp://127.0.0.1:5555", rig) as session:
        session.stream_folder("sequence")          # or session.stream((t_ns, rgb) for ...) with numpy frames
        # or live: Session(..., live=True) and session.stream_source("/dev/video0", lock_exposure=True,
        #          lock_white_balance=True, record="capture", camera_yaml="camera.yaml")
        summary = session.close()
        poses = session.poses()                    # (N, 8): t tx ty tz qx qy qz qw, world_from_camera
        cloud = session.map()                      # positions/normals (N, 3) float32, colors (N, 3) uint8

With CURVE (a server started with --curve-keys/--allowed-clients): Session(..., server_public_key=...,
client_public_key=..., client_secret_key=...); generate_key_pair() makes a client's keys. A key the
server does not admit raises PrismError("UNAUTHENTICATED").

stream_source(source, ...) captures from anything OpenCV's VideoCapture opens (a V4L2 device path or
index, a video file, a GStreamer pipeline, an RTSP URL) as `prism-client stream --source` does: RGB
frames time-stamped at capture, frames the server has no room for dropped (a video file waits instead),
exposure and white balance locked where the driver allows (docs/rig.md), optionally recorded as a
sequence folder; it returns the capture's counts and calls progress(dict) on the way.

Errors raise PrismError (code, message, retryable).
"""
import json
import urllib.error
import urllib.request

from . import _native
from ._native import Camera, Light, Rig, decode_chunk, generate_key_pair, load_rig, read_image, write_colmap

__all__ = ["Camera", "Light", "Rig", "Session", "PrismError", "load_rig", "read_image", "decode_chunk", "write_colmap", "generate_key_pair", "allocate",
           "write_ply"]


class PrismError(Exception):
    """A failed call: code (e.g. "RESOURCE_EXHAUSTED"), readable message, and whether a retry may work."""

    def __init__(self, code, message, retryable=False):
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message
        self.retryable = retryable


_native._set_error_type(PrismError)


class Session(_native.Session):
    """An open session (the constructor connects and waits for SessionOpened). See the module doc."""

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None and not getattr(self, "_closed", False):
            self.close()
        return False

    def close(self, timeout_ms=300000):
        summary = super().close(timeout_ms)
        self._closed = True
        return summary

    def stream(self, frames):
        """Sends (timestamp_ns, rgb) pairs, rgb an (H, W, 3) uint8 array; returns the frames sent.
        Events received on the way wait for poll() (poses() has the poses, map() the running map)."""
        sent = 0
        for timestamp_ns, rgb in frames:
            self.push_frame(int(timestamp_ns), rgb)
            sent += 1
        return sent

    def drain(self):
        """Handles every event waiting now; returns them as (kind, payload) tuples."""
        events = []
        while True:
            event = self.poll(0)
            if event is None:
                return events
            events.append(event)


def allocate(url, timeout_s=5.0):
    """Asks a prism-server's HTTP listener (e.g. the prism-allocate Service in Kubernetes) where a new
    session should go: {"endpoint": "tcp://...", "free": n, ...}. Raises PrismError("UNAVAILABLE")
    when that server is full or draining (ask again: a Service sends the next request elsewhere)."""
    try:
        with urllib.request.urlopen(url.rstrip("/") + "/allocate", timeout=timeout_s) as response:
            return json.loads(response.read().decode())
    except urllib.error.HTTPError as e:
        raise PrismError("UNAVAILABLE", e.read().decode().strip() or str(e), True) from None
    except (urllib.error.URLError, OSError) as e:
        raise PrismError("UNAVAILABLE", str(e), True) from None


def write_ply(path, cloud):
    """Writes a map() / decode_chunk() dict as a binary little-endian PLY (positions, normals, colours)."""
    import numpy as np

    n = len(cloud["positions"])
    vertex = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"),
                                ("nz", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, k in enumerate(("x", "y", "z")):
        vertex[k] = cloud["positions"][:, i]
        vertex["n" + k] = cloud["normals"][:, i]
    for i, k in enumerate(("red", "green", "blue")):
        vertex[k] = cloud["colors"][:, i]
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % n +
              "".join("property float %s\n" % k for k in ("x", "y", "z", "nx", "ny", "nz")) +
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    with open(path, "wb") as f:
        f.write(header.encode())
        f.write(vertex.tobytes())
