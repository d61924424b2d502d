#!/usr/bin/python3
"""A minimal client written from the wire contract alone (proto/prism/v1/session.proto and
docs/protocol.md): pyzmq and protobuf code generated here with protoc, no SDK. It streams a short
rendered sequence to a real prism-server, spending and taking back frame credits as the contract says,
rebuilds the voxel map from the chunks (Debian's draco_decoder converts each to PLY), closes, and checks
what the contract promises; then sends what the contract calls invalid and checks the error codes.

  protocol_contract_test.py BUILD_DIR PROTO_DIR PROTOC
BUILD_DIR/bin has prism-server and prism-synth. Exits 77 (skipped) without pyzmq, protobuf or PyYAML
(Debian python3-zmq, python3-protobuf, python3-yaml; scripts/setup.sh installs them).
"""
import json
import math
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import unittest

SKIP = 77
try:
    import yaml
    import zmq
    import google.protobuf  # noqa: F401 (the generated module needs it)
except ImportError as missing:
    print(f"skipped: {missing} (install python3-zmq python3-protobuf python3-yaml)")
    sys.exit(SKIP)

BUILD_DIR = PROTO_DIR = PROTOC = None
pb = None  # prism.v1.session_pb2, generated in setUpClass
WAIT_S = 120 * (20 if os.environ.get("PRISM_SANITIZE") else 1)  # the longest wait for one message


def read_rig(camera_yaml):
    """camera.yaml (OpenCV FileStorage YAML, as prism-synth writes it) -> RigCalibration."""
    with open(camera_yaml) as f:
        text = f.read().replace("%YAML:1.0", "").replace("!!opencv-matrix", "")
    y = yaml.safe_load(text)
    rig = pb.RigCalibration()
    c = rig.camera
    c.width, c.height = y["width"], y["height"]
    c.fx, c.fy, c.cx, c.cy = y["fx"], y["fy"], y["cx"], y["cy"]
    c.distortion.extend(float(v) for v in y["distortion"]["data"])
    for light in y["lights"]:  # red, green, blue
        w = rig.lights.add()
        w.name = light["name"]
        w.type = pb.LightCalibration.TYPE_DIRECTIONAL if light["type"] == "directional" else pb.LightCalibration.TYPE_POINT
        w.position_in_camera.x, w.position_in_camera.y, w.position_in_camera.z = light["position"]
        w.direction_in_camera.x, w.direction_in_camera.y, w.direction_in_camera.z = light["direction"]
        w.color.x, w.color.y, w.color.z = light["color"]
        w.intensity = light["intensity"]
    rig.crosstalk.extend(float(v) for v in y["crosstalk"]["data"])
    return rig


def read_ply_positions(path):
    """Positions of a binary little-endian PLY (draco_decoder's output)."""
    sizes = {"char": "b", "uchar": "B", "short": "h", "ushort": "H", "int": "i", "uint": "I", "float": "f",
             "double": "d"}
    with open(path, "rb") as f:
        assert f.readline().strip() == b"ply"
        count, fields = 0, []
        for line in iter(f.readline, b""):
            words = line.split()
            if words[0] == b"format":
                assert words[1] == b"binary_little_endian", line
            elif words[:2] == [b"element", b"vertex"]:
                count = int(words[2])
            elif words[0] == b"property":
                fields.append((words[2].decode(), sizes[words[1].decode()]))
            elif words[0] == b"end_header":
                break
        layout = "<" + "".join(t for _, t in fields)
        names = [n for n, _ in fields]
        xyz = [names.index("x"), names.index("y"), names.index("z")]
        data = f.read(struct.calcsize(layout) * count)
    return [tuple(v[i] for i in xyz) for v in struct.iter_unpack(layout, data)]


class Server:
    """prism-server on tcp://127.0.0.1:* (the endpoint from its first stdout line); SIGTERM to stop."""

    def __init__(self, data_dir):
        self.log = open(data_dir + ".log", "w")
        self.process = subprocess.Popen([os.path.join(BUILD_DIR, "bin", "prism-server"), "--bind", "tcp://127.0.0.1:*",
                                         "--data-dir", data_dir, "--metrics", "off"], stdout=subprocess.PIPE,
                                        stderr=self.log, text=True)
        self.endpoint = json.loads(self.process.stdout.readline())["endpoint"]

    def stop(self):
        """SIGTERM; the exit code (idempotent: also the cleanup of a failed test)."""
        if self.process.poll() is None:
            self.process.terminate()
        code = self.process.wait(timeout=60)
        self.process.stdout.close()
        self.log.close()
        return code


class Client:
    """One DEALER: envelopes out, (envelope, payload) in."""

    def __init__(self, context, endpoint):
        self.socket = context.socket(zmq.DEALER)
        self.socket.setsockopt(zmq.LINGER, 0)
        self.socket.connect(endpoint)

    def send(self, payload=None, **body):
        env = pb.Envelope(protocol_version=pb.PROTOCOL_VERSION_1, **body)
        parts = [env.SerializeToString()] + ([payload] if payload is not None else [])
        self.socket.send_multipart(parts)

    def receive(self, timeout_s=WAIT_S):
        """The next message as (Envelope, payload or None), or None after timeout_s."""
        if not self.socket.poll(int(timeout_s * 1000)):
            return None
        parts = self.socket.recv_multipart()
        env = pb.Envelope()
        env.ParseFromString(parts[0])
        return env, (parts[1] if len(parts) > 1 else None)

    def expect(self, body, timeout_s=WAIT_S):
        message = self.receive(timeout_s)
        assert message is not None, f"no {body} within {timeout_s} s"
        assert message[0].WhichOneof("body") == body, message[0]
        return getattr(message[0], body)

    def close(self):
        self.socket.close()


class ProtocolContractTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="prism_protocol_contract_test_")
        global pb
        subprocess.run([PROTOC, f"--python_out={cls.tmp}", "-I", PROTO_DIR,
                        os.path.join(PROTO_DIR, "prism", "v1", "session.proto")], check=True)
        sys.path.insert(0, cls.tmp)
        from prism.v1 import session_pb2
        pb = session_pb2
        # 60 frames at 256x192: 13 chunks, and the SLAM's metric scale from the lights runs at the end (at
        # 160x120 it finds no keyframe pair's shading scale; 40 frames there make a single keyframe).
        cls.seq = os.path.join(cls.tmp, "seq")
        subprocess.run([os.path.join(BUILD_DIR, "bin", "prism-synth"), "--preset", "sphere-multicolor-sideways",
                        "--frames", "60", "--size", "256x192", "--out", cls.seq], check=True, capture_output=True)
        cls.context = zmq.Context()

    @classmethod
    def tearDownClass(cls):
        cls.context.term()
        if not os.environ.get("PRISM_KEEP_TEST_DIR"):
            shutil.rmtree(cls.tmp)

    def setUp(self):
        self.server = Server(os.path.join(self.tmp, "data_" + self._testMethodName))
        self.addCleanup(self.server.stop)
        self.client = Client(self.context, self.server.endpoint)
        self.addCleanup(self.client.close)

    def frames(self):
        """(timestamp_ns, PNG bytes) of the rendered sequence, in order."""
        out = []
        with open(os.path.join(self.seq, "rgb.txt")) as index:
            for line in index:
                if line.startswith("#"):
                    continue
                t, name = line.split()
                with open(os.path.join(self.seq, name), "rb") as f:
                    out.append((round(float(t) * 1e9), f.read()))
        return out

    def test_a_session_streamed_by_the_contract(self):
        rig = read_rig(os.path.join(self.seq, "camera.yaml"))
        width, height = rig.camera.width, rig.camera.height
        c = self.client
        c.send(open_session=pb.OpenSession(protocol_version=pb.PROTOCOL_VERSION_1, calibration=rig,
                                           codec=pb.FRAME_CODEC_PNG, client_name="protocol_contract_test",
                                           input_policy=pb.INPUT_POLICY_UPLOAD, initial_chunk_credits=4))
        opened = c.expect("session_opened")
        sid = opened.session_id
        self.assertEqual(opened.input_policy, pb.INPUT_POLICY_UPLOAD)
        self.assertGreater(opened.initial_frame_credits, 0)
        self.assertGreater(opened.map_voxel_m, 0)

        credits = opened.initial_frame_credits  # the balance: -1 per Frame sent, +n per FrameCredits
        poses, refined, chunks, errors, summary = [], [], [], [], None
        last_pose_index = -1  # in `refined`: the refined poses after the last first pose are the end's

        def handle(message):
            nonlocal credits, summary, last_pose_index
            env, payload = message
            kind = env.WhichOneof("body")
            if kind == "frame_credits":
                self.assertEqual(env.frame_credits.session_id, sid)
                self.assertGreater(env.frame_credits.frames, 0)
                credits += env.frame_credits.frames
            elif kind == "pose_update":
                if env.pose_update.refined:
                    refined.append(env.pose_update)
                else:
                    poses.append(env.pose_update)
                    last_pose_index = len(refined)
            elif kind == "map_chunk":
                chunks.append((env.map_chunk, payload))
                c.send(chunk_credits=pb.ChunkCredits(session_id=sid, chunks=1))  # this one is consumed
            elif kind == "error":
                errors.append(env.error)
            elif kind == "session_summary":
                summary = env.session_summary
            else:
                self.fail(f"unexpected {kind}")

        def pump(timeout_s):
            message = c.receive(timeout_s)
            if message is not None:
                handle(message)
            return message is not None

        # The stream: sequence numbers jump forward by 5 from the 30th frame on (a live client dropping
        # frames), and the invalid frames of the contract are sent along the way; each is refused and
        # its credit comes back.
        interval_s = 1.0 / (0.9 * opened.max_frame_rate_hz) if opened.max_frame_rate_hz > 0 else 0
        accepted, invalid = [], []
        next_send = time.monotonic()

        def send_frame(seq, timestamp_ns, png, w=width, h=height):
            nonlocal credits, next_send
            deadline = time.monotonic() + WAIT_S
            while credits <= 0:
                self.assertLess(time.monotonic(), deadline, "no frame credit came back")
                pump(1.0)
            time.sleep(max(0.0, next_send - time.monotonic()))  # keep under max_frame_rate_hz
            next_send = time.monotonic() + interval_s
            c.send(png, frame=pb.Frame(session_id=sid, sequence_number=seq, timestamp_ns=timestamp_ns,
                                       codec=pb.FRAME_CODEC_PNG, width=w, height=h))
            credits -= 1
            while pump(0):
                pass

        frames = self.frames()
        for i, (t, png) in enumerate(frames):
            seq = i if i < 30 else i + 5
            if i == 20:
                send_frame(seq, t, png, w=width + 1)  # a stated size other than the camera's
                invalid.append((seq, "Frame.width"))
            if i == 21:
                send_frame(seq - 1, t, png)  # a duplicate sequence number
                invalid.append((seq - 1, "Frame.sequence_number"))
                send_frame(seq, frames[i - 1][0] - 1, png)  # a timestamp before the last accepted frame's
                invalid.append((seq, "Frame.timestamp_ns"))
            send_frame(seq, t, png, *((0, 0) if i % 2 else (width, height)))  # 0 x 0: size not stated
            accepted.append(seq)

        # Every frame is answered (a pose, or an error naming it) and every credit comes back.
        deadline = time.monotonic() + WAIT_S
        while len(poses) < len(accepted) or len(errors) < len(invalid) or credits < opened.initial_frame_credits:
            self.assertLess(time.monotonic(), deadline, f"{len(poses)} poses, {credits} credits")
            pump(1.0)
        self.assertEqual(credits, opened.initial_frame_credits)
        self.assertEqual([p.frame_sequence_number for p in poses], accepted)
        self.assertEqual([p.timestamp_ns for p in poses], [t for t, _ in frames])
        self.assertEqual([(e.frame_sequence_number, e.code) for e in errors],
                         [(seq, pb.ERROR_CODE_INVALID_ARGUMENT) for seq, _ in invalid])
        for e, (_, field) in zip(errors, invalid):
            self.assertIn(field, e.message)
            self.assertTrue(e.has_frame)
            self.assertFalse(e.session_closed)
            self.assertEqual(e.session_id, sid)

        c.send(close=pb.Close(session_id=sid))
        deadline = time.monotonic() + WAIT_S
        while summary is None:
            self.assertLess(time.monotonic(), deadline, "no SessionSummary")
            pump(1.0)
        self.assertEqual(summary.session_id, sid)
        self.assertEqual(summary.reason, "closed by client")
        self.assertEqual(summary.frames_received, len(accepted))
        self.assertEqual(summary.frames_rejected, len(invalid))
        self.assertEqual(summary.chunks_sent, len(chunks))
        self.assertEqual(len(errors), len(invalid))

        # The world frame is the first frame's camera: its latest pose is the identity.
        first = ([p for p in refined if p.frame_sequence_number == 0] or [poses[0]])[-1].world_from_camera
        self.assertAlmostEqual(first.rotation.w ** 2, 1.0, delta=1e-9)
        self.assertLess(math.hypot(first.translation.x, first.translation.y, first.translation.z), 1e-9)

        # One scale at the end: the refined poses after the last first pose carry the summary's (the
        # session's scale: the SLAM's from the lights, which ran here (shading_check), when it agrees with
        # the dense stage's final estimate, else that estimate; docs/method.md, "Metric scale").
        self.assertNotEqual(summary.shading_check, pb.SHADING_CHECK_NOT_RUN)
        self.assertGreater(summary.metres_per_unit, 0)
        end_refined = refined[last_pose_index:]
        self.assertTrue(end_refined, "the initialisation frames' provisional poses are refined at the end")
        for p in end_refined:
            self.assertEqual(p.metres_per_unit, summary.metres_per_unit, p.frame_sequence_number)
        self.assertTrue(set(p.frame_sequence_number for p in refined) <= set(accepted))

        # The map, rebuilt from the chunks by voxel: numbers increase, each payload has num_points
        # points on the session's grid, and the result is the server's map voxel for voxel in number.
        sequence_numbers = [m.chunk_sequence_number for m, _ in chunks]
        self.assertTrue(chunks, summary)
        self.assertEqual(sequence_numbers, sorted(set(sequence_numbers)))
        self.assertGreaterEqual(sequence_numbers[0], 1)
        voxel, cell = opened.map_voxel_m, opened.map_quantisation_m
        voxel_map, replaced, worst_offset = {}, False, 0.0
        for m, payload in chunks:
            self.assertEqual(len(payload), m.payload_bytes)
            drc = os.path.join(self.tmp, f"chunk_{m.chunk_sequence_number}.drc")
            with open(drc, "wb") as f:
                f.write(payload)
            subprocess.run(["draco_decoder", "-i", drc, "-o", drc + ".ply"], check=True, capture_output=True)
            points = read_ply_positions(drc + ".ply")
            self.assertEqual(len(points), m.num_points)
            if m.replaces_map:
                voxel_map.clear()
                replaced = True
                self.assertEqual(m.keyframe_id, 0)
            for p in points:
                key = tuple(math.floor(x / voxel) for x in p)
                # At the centre of a grid cell, to Draco's float32 dequantisation (under a quarter cell:
                # the voxel is exact).
                for x in p:
                    offset = x / cell - 0.5
                    worst_offset = max(worst_offset, abs(offset - round(offset)))
                voxel_map[key] = p
        self.assertLess(worst_offset, 0.25)
        self.assertTrue(replaced, "the map is rebuilt at the final poses and scale at the end")
        self.assertEqual(len(voxel_map), summary.map_points)
        self.assertEqual(chunks[-1][0].map_points, summary.map_points)
        print(f"contract client: {len(poses)} poses (streamed at {poses[-1].metres_per_unit:.4f} m per unit), "
              f"{len(refined)} refined (the end's at {summary.metres_per_unit:.4f}), {len(chunks)} chunks numbered {sequence_numbers[0]}..{sequence_numbers[-1]}, "
              f"{len(voxel_map)} voxels (points within {worst_offset:.3f} cells of a cell centre), "
              f"errors {[e.code for e in errors]}")

        # After its summary the session is gone (the first NOT_FOUND may answer the last chunk's credit).
        c.send(chunk_credits=pb.ChunkCredits(session_id=sid, chunks=1))
        gone = c.expect("error")
        self.assertEqual((gone.code, gone.session_id, gone.session_closed), (pb.ERROR_CODE_NOT_FOUND, sid, True))
        self.assertEqual(self.server.stop(), 0)

    def test_messages_the_contract_refuses(self):
        c = self.client

        def error(expected_code, **body):
            c.send(**body)
            e = c.expect("error")
            self.assertEqual(e.code, expected_code, e)
            return e

        unknown = "s999-000000000000"
        e = error(pb.ERROR_CODE_NOT_FOUND, chunk_credits=pb.ChunkCredits(session_id=unknown, chunks=4))
        self.assertEqual(e.session_id, unknown)
        self.assertTrue(e.session_closed)
        e = error(pb.ERROR_CODE_NOT_FOUND, close=pb.Close(session_id=unknown))
        self.assertTrue(e.session_closed)
        c.send(b"\x89PNG", frame=pb.Frame(session_id=unknown, sequence_number=0))
        self.assertEqual(c.expect("error").code, pb.ERROR_CODE_NOT_FOUND)
        resume = pb.OpenSession(protocol_version=pb.PROTOCOL_VERSION_1, resume_token="0" * 32)
        resume.resume_session_id = "../../etc"
        error(pb.ERROR_CODE_INVALID_ARGUMENT, open_session=resume)
        resume.resume_session_id = unknown
        self.assertEqual(error(pb.ERROR_CODE_NOT_FOUND, open_session=resume).session_id, unknown)
        # OpenSession's own protocol_version must be 1 too.
        error(pb.ERROR_CODE_VERSION_MISMATCH, open_session=pb.OpenSession(calibration=read_rig(
            os.path.join(self.seq, "camera.yaml"))))
        # A server-to-client body from a client, and an envelope of another version.
        error(pb.ERROR_CODE_INVALID_ARGUMENT, frame_credits=pb.FrameCredits(session_id=unknown, frames=1))
        c.socket.send(pb.Envelope(protocol_version=7, close=pb.Close(session_id=unknown)).SerializeToString())
        self.assertEqual(c.expect("error").code, pb.ERROR_CODE_VERSION_MISMATCH)
        self.assertEqual(self.server.stop(), 0)


if __name__ == "__main__":
    if len(sys.argv) != 4:
        print(__doc__)
        sys.exit(2)
    BUILD_DIR, PROTO_DIR, PROTOC = sys.argv[1:4]
    for tool in (PROTOC, "draco_decoder"):
        if shutil.which(tool) is None:
            print(f"skipped: {tool} not found (install protobuf-compiler and draco)")
            sys.exit(SKIP)
    unittest.main(argv=sys.argv[:1], verbosity=2)
