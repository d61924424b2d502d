#!/usr/bin/python3
"""deploy/validate.py accepts the committed manifests and catches each kind of mistake it claims to.

  deploy_validate_test.py SOURCE_DIR PRISM_SERVER
Each negative case edits a copy of deploy/ in one place and expects validate.py to name the problem.
"""
import os
import shutil
import subprocess
import sys
import tempfile
import unittest

SOURCE_DIR = PRISM_SERVER = None


class DeployValidateTest(unittest.TestCase):
    def setUp(self):
        self.tmp = tempfile.mkdtemp(prefix="prism_deploy_validate_")
        self.deploy = os.path.join(self.tmp, "deploy")
        shutil.copytree(os.path.join(SOURCE_DIR, "deploy"), self.deploy)

    def tearDown(self):
        shutil.rmtree(self.tmp)

    def run_validate(self):
        return subprocess.run([sys.executable, os.path.join(self.deploy, "validate.py"), "--prism-server", PRISM_SERVER],
                              capture_output=True, text=True)

    def edit(self, relative, old, new):
        path = os.path.join(self.deploy, relative)
        with open(path) as f:
            text = f.read()
        self.assertIn(old, text, f"{relative} no longer contains {old!r}: update this test")
        with open(path, "w") as f:
            f.write(text.replace(old, new, 1))

    def expect_problem(self, fragment):
        r = self.run_validate()
        self.assertEqual(r.returncode, 1, r.stdout + r.stderr)
        self.assertIn(fragment, r.stdout, r.stdout + r.stderr)

    def test_committed_manifests_are_valid(self):
        r = self.run_validate()
        self.assertEqual(r.returncode, 0, r.stdout + r.stderr)
        self.assertIn("6 Kubernetes objects", r.stderr)

    def test_misspelt_field(self):
        self.edit("k8s/statefulset.yaml", "readinessProbe:", "readinesProbe:")
        self.expect_problem("unknown field 'readinesProbe'")

    def test_selector_not_matching_pod_labels(self):
        self.edit("k8s/statefulset.yaml", "      app.kubernetes.io/name: prism\n  template",
                  "      app.kubernetes.io/name: prism-x\n  template")
        self.expect_problem("does not match the pod template labels")

    def test_probe_port_names_no_container_port(self):
        self.edit("k8s/statefulset.yaml", "              path: /healthz\n              port: http",
                  "              path: /healthz\n              port: metrics")
        self.expect_problem("livenessProbe port 'metrics' names no container port")

    def test_service_name_must_be_headless(self):
        self.edit("k8s/services.yaml", "  clusterIP: None\n", "")
        self.expect_problem("must be a headless Service")

    def test_bad_quantity(self):
        self.edit("k8s/statefulset.yaml", "memory: 2Gi", "memory: 2GB")
        self.expect_problem("is not a quantity")

    def test_undefined_env_reference(self):
        self.edit("k8s/statefulset.yaml", "$(POD_NAME)", "$(POD)")
        self.expect_problem("$(POD) is not defined before it")

    def test_service_target_port(self):
        self.edit("k8s/services.yaml", "targetPort: zmq", "targetPort: zeromq")
        self.expect_problem("targetPort 'zeromq' names no container port")

    def test_server_config_key_checked_by_prism_server(self):
        self.edit("k8s/configmap.yaml", "max-sessions = 2", "max-session = 2")
        self.expect_problem("server.conf rejected by prism-server")

    def test_config_subpath_must_be_a_configmap_key(self):
        self.edit("k8s/configmap.yaml", "  server.conf: |", "  prism.conf: |")
        self.expect_problem("subPath 'server.conf' is not a key")

    def test_curve_key_file_must_be_in_the_secret(self):
        self.edit("k8s/statefulset.yaml", "/etc/prism/curve/server.keys", "/etc/prism/curve/server.key")
        self.expect_problem("Secret prism-curve has no key 'server.key'")

    def test_file_env_must_be_under_a_mount(self):
        self.edit("k8s/statefulset.yaml", "value: /etc/prism/curve/allowed_clients", "value: /etc/curve/allowed_clients")
        self.expect_problem("PRISM_ALLOWED_CLIENTS = /etc/curve/allowed_clients is not under any volumeMount")

    def test_compose_depends_on_unknown_service(self):
        self.edit("docker-compose.yml", "      prism:\n        condition", "      server:\n        condition")
        self.expect_problem("depends_on 'server': no such service")

    def test_compose_schema(self):
        if not shutil.which("docker-compose"):
            self.skipTest("docker-compose (Debian) not installed: no Compose schema check")
        self.edit("docker-compose.yml", "    stop_signal: SIGTERM", "    stop_signals: SIGTERM")
        self.expect_problem("docker-compose config")


if __name__ == "__main__":
    SOURCE_DIR, PRISM_SERVER = sys.argv[1], sys.argv[2]
    unittest.main(argv=sys.argv[:1], verbosity=2)
