#!/usr/bin/python3
"""The Docker image's entrypoint (deploy/docker/entrypoint.sh) on the host, against this build's
prism-server: the PRISM_* environment becomes flags, flags win over it, CURVE keys are passed through,
and other commands run unchanged.

  entrypoint_test.py SOURCE_DIR BUILD_DIR
"""
import json
import os
import subprocess
import sys
import tempfile
import unittest

SOURCE_DIR = BUILD_DIR = None


class EntrypointTest(unittest.TestCase):
    def setUp(self):
        self.tmp = tempfile.TemporaryDirectory(prefix="prism_entrypoint_test_")
        self.env = dict(os.environ, PATH=os.path.join(BUILD_DIR, "bin") + ":" + os.environ["PATH"],
                        PRISM_BIND="tcp://127.0.0.1:*", PRISM_METRICS="127.0.0.1:0",
                        PRISM_DATA_DIR=os.path.join(self.tmp.name, "data"))
        self.entrypoint = os.path.join(SOURCE_DIR, "deploy", "docker", "entrypoint.sh")

    def tearDown(self):
        self.tmp.cleanup()

    def start(self, *args, **env):
        process = subprocess.Popen(["sh", self.entrypoint, *args], env=dict(self.env, **env), stdout=subprocess.PIPE,
                                   stderr=subprocess.PIPE, text=True)
        line = process.stdout.readline()
        if not line:
            process.wait(timeout=10)
            return process, None
        return process, json.loads(line)

    def stop(self, process):
        process.terminate()
        code = process.wait(timeout=30)
        process.stdout.close()
        process.stderr.close()
        return code

    def allocate(self, started):
        r = subprocess.run([os.path.join(BUILD_DIR, "bin", "prism-probe"), started["metrics"] + "/allocate"],
                           capture_output=True, text=True)
        return json.loads(r.stdout)

    def test_environment_becomes_flags_and_flags_win(self):
        process, started = self.start(PRISM_ADVERTISE="tcp://prism-1.prism-pods.ns.svc.cluster.local:5555",
                                      PRISM_MAX_SESSIONS="2")
        self.assertIsNotNone(started)
        self.assertTrue(started["endpoint"].startswith("tcp://127.0.0.1:"))
        allocation = self.allocate(started)
        self.assertEqual(allocation["endpoint"], "tcp://prism-1.prism-pods.ns.svc.cluster.local:5555")
        self.assertEqual(allocation["sessions_capacity"], 2)
        self.assertEqual(self.stop(process), 0)
        self.assertTrue(os.path.isdir(self.env["PRISM_DATA_DIR"]))

        process, started = self.start("prism-server", "--max-sessions", "3", PRISM_MAX_SESSIONS="2")
        self.assertEqual(self.allocate(started)["sessions_capacity"], 3)
        self.assertEqual(self.stop(process), 0)

    def test_config_file_from_the_environment(self):
        config = os.path.join(self.tmp.name, "server.conf")
        with open(config, "w") as f:
            f.write("max-sessions = 5\n")
        process, started = self.start(PRISM_CONFIG=config)
        self.assertEqual(self.allocate(started)["sessions_capacity"], 5)
        self.assertEqual(self.stop(process), 0)

    def test_curve_keys_are_passed_through(self):
        keys = os.path.join(self.tmp.name, "server.keys")
        r = subprocess.run([os.path.join(BUILD_DIR, "bin", "prism-server"), "keygen", "--out", keys],
                           capture_output=True, text=True)
        self.assertEqual(r.returncode, 0, r.stderr)
        # Keys without an allow-list: the server refuses to start and says why.
        process, started = self.start(PRISM_CURVE_KEYS=keys)
        self.assertIsNone(started)
        self.assertNotEqual(process.returncode, 0)
        self.assertIn("allowed_clients", process.stderr.read())
        process.stdout.close()
        process.stderr.close()
        allowed = os.path.join(self.tmp.name, "allowed_clients")
        with open(allowed, "w") as f:
            f.write("# nobody yet\n")
        process, started = self.start(PRISM_CURVE_KEYS=keys, PRISM_ALLOWED_CLIENTS=allowed)
        self.assertIsNotNone(started)
        self.assertEqual(self.stop(process), 0)

    def test_other_commands_run_unchanged(self):
        r = subprocess.run(["sh", self.entrypoint, "prism-probe", "--help"], env=self.env, capture_output=True,
                           text=True)
        self.assertEqual(r.returncode, 0, r.stderr)
        self.assertIn("usage: prism-probe", r.stdout)
        r = subprocess.run(["sh", self.entrypoint, "sh", "-c", "echo $PRISM_DATA_DIR"], env=self.env,
                           capture_output=True, text=True)
        self.assertEqual(r.stdout.strip(), self.env["PRISM_DATA_DIR"])


if __name__ == "__main__":
    SOURCE_DIR, BUILD_DIR = sys.argv[1], sys.argv[2]
    unittest.main(argv=sys.argv[:1], verbosity=2)
