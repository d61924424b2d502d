#!/usr/bin/python3
"""Scripted Python clients (prism_client bindings) against a real prism-server on 127.0.0.1.

  python_client_test.py BUILD_DIR
BUILD_DIR/bin has prism-server, prism-synth and prism-eval; BUILD_DIR/python has the prism_client package.
"""
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import unittest

import numpy as np

BUILD_DIR = None
prism_client = None

# Sanitizer builds (PRISM_SANITIZE, set by CTest from the build's option): the dense stage runs many
# times slower there than the client's credit wait (10 s), its close wait (300 s) and the server's idle
# timeout (30 s) allow, so only there these waits (and the server's stop wait) are stretched. The
# frames and every assertion stay the same; in other builds no argument or flag is added.
WAIT_SCALE = 20 if os.environ.get("PRISM_SANITIZE") else 1
SESSION_WAIT = {} if WAIT_SCALE == 1 else {"timeout_ms": 10000 * WAIT_SCALE}
CLOSE_WAIT = {} if WAIT_SCALE == 1 else {"timeout_ms": 300000 * WAIT_SCALE}
SERVER_WAIT_FLAGS = [] if WAIT_SCALE == 1 else ["--idle-timeout-ms", str(30000 * WAIT_SCALE)]


def binary(name):
    return os.path.join(BUILD_DIR, "bin", name)


def rotation_matrix(q_xyzw):
    x, y, z, w = q_xyzw / np.linalg.norm(q_xyzw)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


class Server:
    """prism-server on tcp://127.0.0.1:* with its metrics listener on a free port; SIGTERM to stop."""

    def __init__(self, data_dir, *flags):
        self.log = open(os.path.join(data_dir + ".log"), "w")
        self.process = subprocess.Popen([binary("prism-server"), "--bind", "tcp://127.0.0.1:*", "--data-dir", data_dir,
                                         "--metrics", "127.0.0.1:0", *flags, *SERVER_WAIT_FLAGS], stdout=subprocess.PIPE,
                                        stderr=self.log, text=True)
        line = json.loads(self.process.stdout.readline())
        self.endpoint, self.metrics = line["endpoint"], line["metrics"]

    def stop(self):
        self.process.terminate()
        code = self.process.wait(timeout=30 * WAIT_SCALE)
        self.process.stdout.close()
        self.log.close()
        return code

    def cleanup(self):
        """Stops the server if a failed test left it running (registered with addCleanup)."""
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=30)
        if not self.process.stdout.closed:
            self.process.stdout.close()
        if not self.log.closed:
            self.log.close()


class PythonClientTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="prism_python_client_test_")
        cls.seq = os.path.join(cls.tmp, "seq")
        cls.frames = 60
        r = subprocess.run([binary("prism-synth"), "--preset", "bunny-multicolor-forward", "--frames", str(cls.frames),
                            "--out", cls.seq], capture_output=True, text=True)
        if r.returncode != 0 and "not found" in r.stdout + r.stderr:
            raise unittest.SkipTest(r.stdout + r.stderr)
        assert r.returncode == 0, r.stdout + r.stderr

    @classmethod
    def tearDownClass(cls):
        shutil.rmtree(cls.tmp)

    def setUp(self):
        self.data = tempfile.mkdtemp(prefix="data_", dir=self.tmp)

    def test_stream_folder_gives_poses_and_a_map_on_the_object(self):
        server = Server(self.data, "--keyframe-queue", "16")
        self.addCleanup(server.cleanup)
        rig = prism_client.load_rig(os.path.join(self.seq, "camera.yaml"))
        self.assertEqual((rig.camera.width, rig.camera.height), (512, 512))
        with prism_client.Session(server.endpoint, rig, **SESSION_WAIT) as session:
            self.assertTrue(session.id)
            self.assertEqual(session.stream_folder(self.seq), self.frames)
            summary = session.close(**CLOSE_WAIT)
            poses, cloud = session.poses(), session.map()
            all_poses = session.poses(tracked_only=False)
            keyframes = session.poses(tracked_only=False, keyframes_only=True)
            # Each frame's alignment against its keyframe (PoseUpdate.tracking), per frame: every frame
            # tracked after the initialisation has it, as roundtrip_test checks for prism-client.
            tracking = {}
            while True:
                event = session.poll(0)
                if event is None:
                    break
                if event[0] == "pose" and event[1]["tracking"] is not None:
                    tracking[event[1]["frame"]] = event[1]["tracking"]
        self.assertGreaterEqual(len(tracking), 40)  # of 60 frames, those after the initialisation
        inliers = [t["inlier_fraction"] for t in tracking.values()]
        self.assertTrue(all(0 < f <= 1 for f in inliers), inliers)
        self.assertTrue(all(t["step"] > 0 and t["iterations"] > 0 for t in tracking.values()))
        self.assertGreaterEqual(float(np.median(inliers)), 0.9)  # a clean rendered scene, as cli_test
        self.assertEqual(server.stop(), 0)
        self.assertEqual(summary["frames_received"], self.frames)
        self.assertEqual(summary["reason"], "closed by client")
        self.assertGreater(summary["metres_per_unit"], 0)
        # The server's check against the co-moving lights' shading: this run is within the SLAM's bar
        # (measured pair spread 0.092, limit 0.16).
        self.assertEqual(summary["shading_check"], "consistent", summary["shading_pair_spread"])
        # The SLAM's start check: this run's first start passes (measured pair spread 0.067, limit 0.18).
        self.assertEqual(summary["start_check"], "passed", summary["start_pair_spread"])
        self.assertGreater(summary["start_pair_spread"], 0)
        self.assertEqual(all_poses.shape, (self.frames, 8))
        self.assertEqual(poses.shape[1], 8)
        self.assertGreaterEqual(len(poses), self.frames // 2)
        self.assertTrue(np.all(np.isfinite(poses)))
        self.assertTrue(np.allclose(np.linalg.norm(poses[:, 4:8], axis=1), 1.0, atol=1e-6))
        self.assertEqual(cloud["positions"].dtype, np.float32)
        self.assertEqual(cloud["colors"].dtype, np.uint8)
        n = len(cloud["positions"])
        self.assertGreater(n, 1000)
        self.assertEqual(cloud["normals"].shape, (n, 3))
        norms = np.linalg.norm(cloud["normals"], axis=1)
        self.assertLess(np.median(np.abs(norms - 1.0)), 1e-2)

        # The keyframes as a COLMAP model named after the sequence's images.
        # Every keyframe pose the server flagged (the first keyframe's frame is flagged by its refined
        # pose at the end of the session).
        self.assertGreater(len(keyframes), 0)
        self.assertLessEqual(len(keyframes), summary["keyframes"])
        self.assertLess(len(keyframes), len(all_poses))
        names = {round(float(t), 3): f for t, f in (line.split() for line in open(os.path.join(self.seq, "rgb.txt"))
                                                    if not line.startswith("#"))}
        colmap = os.path.join(self.tmp, "colmap")
        prism_client.write_colmap(colmap, rig.camera, keyframes, [names[round(k[0], 3)] for k in keyframes], cloud)
        images = [line.split() for line in open(os.path.join(colmap, "images.txt")) if line[0] != "#" and line.strip()]
        self.assertEqual(len(images), len(keyframes))
        self.assertTrue(all(os.path.exists(os.path.join(self.seq, image[9])) for image in images))
        with self.assertRaises(prism_client.PrismError):
            prism_client.write_colmap(colmap, rig.camera, keyframes[:, :7])

        # The map in the ground-truth frame, scored on the object (as roundtrip_test does): Sim(3) from
        # the streamed trajectory, rotation from the camera orientations, scale and translation from
        # the camera centres; then prism-eval on the moved map.
        gt = {round(row[0], 3): row[1:] for row in np.loadtxt(os.path.join(self.seq, "groundtruth.txt"))}
        pairs = [(p, gt[round(p[0], 3)]) for p in poses if round(p[0], 3) in gt]
        self.assertEqual(len(pairs), len(poses))
        source = np.array([p[1:4] for p, _ in pairs])
        target = np.array([g[0:3] for _, g in pairs])
        rotation_sum = sum(rotation_matrix(g[3:7]) @ rotation_matrix(p[4:8]).T for p, g in pairs)
        u, _, vt = np.linalg.svd(rotation_sum)
        d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
        rotation = u @ d @ vt
        centred_source, centred_target = source - source.mean(0), target - target.mean(0)
        scale = np.sum((centred_source @ rotation.T) * centred_target) / np.sum(centred_source ** 2)
        self.assertGreater(scale, 0)
        translation = target.mean(0) - scale * rotation @ source.mean(0)
        aligned = scale * source @ rotation.T + translation
        ate = np.sqrt(np.mean(np.sum((aligned - target) ** 2, axis=1)))
        path = np.sum(np.linalg.norm(np.diff(target, axis=0), axis=1))
        moved = dict(cloud)
        moved["positions"] = (scale * cloud["positions"].astype(np.float64) @ rotation.T + translation).astype(np.float32)
        out = os.path.join(self.tmp, "aligned.ply")
        prism_client.write_ply(out, moved)
        r = subprocess.run([binary("prism-eval"), "cloud", "--object-only", "--sequence", self.seq, "--cloud", out],
                           capture_output=True, text=True)
        self.assertEqual(r.returncode, 0, r.stdout + r.stderr)
        result = json.loads(r.stdout)
        print(f"python client: {len(poses)} tracked poses of {self.frames}, ATE {ate:.4f} m over a {path:.3f} m path, "
              f"{n} map points, accuracy median {result['accuracy_median_m']:.4f} m, F-score {result['fscore']:.3f}",
              file=sys.stderr)
        # The bars of roundtrip_test: a frame or scale mistake puts the map tens of centimetres away.
        max_ate_fraction_of_path = 0.35
        max_map_accuracy_median_m = 0.06
        min_map_fscore = 0.05
        self.assertLess(ate / path, max_ate_fraction_of_path)
        self.assertLess(result["accuracy_median_m"], max_map_accuracy_median_m)
        self.assertGreaterEqual(result["fscore"], min_map_fscore)

    def test_numpy_frames_and_events(self):
        server = Server(self.data)
        self.addCleanup(server.cleanup)
        rig = prism_client.load_rig(os.path.join(self.seq, "camera.yaml"))
        rgb_index = [line.split() for line in open(os.path.join(self.seq, "rgb.txt")) if not line.startswith("#")]
        frames = [(round(float(t) * 1e9), prism_client.read_image(os.path.join(self.seq, f))) for t, f in rgb_index]
        self.assertEqual(frames[0][1].shape, (512, 512, 3))
        self.assertEqual(frames[0][1].dtype, np.uint8)
        kinds = {}
        chunk = None
        with prism_client.Session(server.endpoint, rig, codec="jpeg", **SESSION_WAIT) as session:
            # A generator of numpy frames, as from a camera.
            self.assertEqual(session.stream((t, rgb) for t, rgb in frames[:20]), 20)
            session.close(**CLOSE_WAIT)
            while True:
                event = session.poll(0)
                if event is None:
                    break
                kinds[event[0]] = kinds.get(event[0], 0) + 1
                if event[0] == "chunk" and chunk is None:
                    chunk = event[1]
                if event[0] == "chunk":
                    self.assertIsInstance(event[1]["replaces_map"], bool)
            self.assertEqual(len(session.poses(tracked_only=False)), 20)
            self.assertGreater(session.bytes_sent, 0)
        self.assertEqual(server.stop(), 0)
        self.assertEqual(kinds.get("summary"), 1, kinds)
        self.assertNotIn("error", kinds)
        if chunk is not None:
            decoded = prism_client.decode_chunk(chunk["draco"])
            np.testing.assert_array_equal(decoded["positions"], chunk["positions"])
            np.testing.assert_array_equal(decoded["colors"], chunk["colors"])

    def test_curve_admits_allow_listed_clients_only(self):
        server_public, server_secret = prism_client.generate_key_pair()
        client_public, client_secret = prism_client.generate_key_pair()
        stranger_public, stranger_secret = prism_client.generate_key_pair()
        self.assertEqual(len(server_public), 40)
        self.assertNotEqual(server_public, client_public)
        keys = os.path.join(self.tmp, "server.keys")
        with open(keys, "w") as f:
            f.write(f"public = {server_public}\nsecret = {server_secret}\n")
        allowed = os.path.join(self.tmp, "allowed_clients")
        with open(allowed, "w") as f:
            f.write(client_public + "\n")
        server = Server(self.data, "--curve-keys", keys, "--allowed-clients", allowed)
        self.addCleanup(server.cleanup)
        rig = prism_client.load_rig(os.path.join(self.seq, "camera.yaml"))
        frames = [(i * 33_333_333, prism_client.read_image(os.path.join(self.seq, "rgb", name)))
                  for i, name in enumerate(sorted(os.listdir(os.path.join(self.seq, "rgb")))[:3])]
        with prism_client.Session(server.endpoint, rig, server_public_key=server_public, client_public_key=client_public,
                                  client_secret_key=client_secret) as session:
            self.assertEqual(session.stream(frames), 3)
            session.close()
            self.assertEqual(len(session.poses(tracked_only=False)), 3)
        with self.assertRaises(prism_client.PrismError) as refused:
            prism_client.Session(server.endpoint, rig, server_public_key=server_public, client_public_key=stranger_public,
                                 client_secret_key=stranger_secret, timeout_ms=5000)
        self.assertEqual(refused.exception.code, "UNAUTHENTICATED")
        self.assertEqual(server.stop(), 0)

    def test_errors_raise_prism_error(self):
        server = Server(self.data, "--max-sessions", "1")
        self.addCleanup(server.cleanup)
        rig = prism_client.load_rig(os.path.join(self.seq, "camera.yaml"))
        self.assertEqual(prism_client.allocate(server.metrics)["free"], 1)
        session = prism_client.Session(server.endpoint, rig)
        with self.assertRaises(prism_client.PrismError) as full:
            prism_client.Session(server.endpoint, rig, timeout_ms=5000)
        self.assertEqual(full.exception.code, "RESOURCE_EXHAUSTED")
        with self.assertRaises(prism_client.PrismError) as busy:
            prism_client.allocate(server.metrics)
        self.assertEqual(busy.exception.code, "UNAVAILABLE")
        self.assertTrue(busy.exception.retryable)
        with self.assertRaises(prism_client.PrismError) as shape:
            session.push_frame(0, np.zeros((512, 512), np.uint8))
        self.assertEqual(shape.exception.code, "INVALID_ARGUMENT")
        with self.assertRaises(prism_client.PrismError):
            prism_client.decode_chunk(b"not a draco chunk")
        with self.assertRaises(prism_client.PrismError):
            prism_client.load_rig(os.path.join(self.tmp, "missing.yaml"))
        with self.assertRaises(prism_client.PrismError):
            prism_client.Session(server.endpoint, rig, codec="webp")
        session.close()
        self.assertEqual(server.stop(), 0)


if __name__ == "__main__":
    BUILD_DIR = sys.argv[1]
    sys.path.insert(0, os.path.join(BUILD_DIR, "python"))
    import prism_client  # noqa: E402

    unittest.main(argv=sys.argv[:1], verbosity=2)
