#!/usr/bin/python3
"""Offline checks of Prism's deployment files (no cluster, no Docker daemon, no network).

  deploy/validate.py [--prism-server BIN] [--compose FILE] [--k8s DIR]

Kubernetes (deploy/k8s/*.yaml): a schema subset for the kinds used here (unknown or misspelt fields,
missing required fields, value types, DNS-1123 names, quantities) plus the cross-references a schema
cannot see: the StatefulSet's serviceName is a headless Service, selectors match the pod labels,
Service targetPorts and probe ports name container ports, volume mounts name volumes, ConfigMap and
Secret references resolve (a subPath names a ConfigMap key), $(VAR) references are defined earlier.
With --prism-server, the ConfigMap's server.conf is loaded by the real prism-server.

Compose (deploy/docker-compose.yml): `docker-compose config -q` (its bundled Compose schema) when
installed, plus depends_on, volumes, healthcheck and image references.

Prints one line per problem and exits 1 when there is any, 0 otherwise.
"""
import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile

import yaml

DNS1123_LABEL = re.compile(r"^[a-z0-9]([-a-z0-9]*[a-z0-9])?$")
DNS1123_SUBDOMAIN = re.compile(r"^[a-z0-9]([-a-z0-9]*[a-z0-9])?(\.[a-z0-9]([-a-z0-9]*[a-z0-9])?)*$")
QUANTITY = re.compile(r"^[0-9]+(\.[0-9]+)?(m|k|M|G|T|P|E|Ki|Mi|Gi|Ti|Pi|Ei)?$")
ENV_NAME = re.compile(r"^[-._a-zA-Z][-._a-zA-Z0-9]*$")
# Environment variables of the image's entrypoint that name files.
FILE_ENV = {"PRISM_CONFIG", "PRISM_CURVE_KEYS", "PRISM_ALLOWED_CLIENTS"}

# The schema subset: for each object path, its allowed fields -> (type, required). A type is a Python
# type, a nested schema name, or ("list", item). Anything not listed is an unknown field (a typo, or a
# field these manifests were not meant to use).
ANY = object()
SCHEMAS = {
    "ObjectMeta": {"name": (str, True), "namespace": (str, False), "labels": (dict, False),
                   "annotations": (dict, False)},
    "TemplateMeta": {"labels": (dict, True), "annotations": (dict, False)},
    "Service": {"apiVersion": (str, True), "kind": (str, True), "metadata": ("ObjectMeta", True),
                "spec": ("ServiceSpec", True)},
    "ServiceSpec": {"type": (str, False), "clusterIP": (str, False), "publishNotReadyAddresses": (bool, False),
                    "selector": (dict, True), "ports": (("list", "ServicePort"), True),
                    "sessionAffinity": (str, False)},
    "ServicePort": {"name": (str, True), "port": (int, True), "targetPort": (ANY, False), "protocol": (str, False),
                    "nodePort": (int, False)},
    "ConfigMap": {"apiVersion": (str, True), "kind": (str, True), "metadata": ("ObjectMeta", True),
                  "data": (dict, True)},
    "Secret": {"apiVersion": (str, True), "kind": (str, True), "metadata": ("ObjectMeta", True),
               "type": (str, False), "stringData": (dict, False), "data": (dict, False)},
    "Kustomization": {"apiVersion": (str, True), "kind": (str, True), "resources": (("list", str), True)},
    "StatefulSet": {"apiVersion": (str, True), "kind": (str, True), "metadata": ("ObjectMeta", True),
                    "spec": ("StatefulSetSpec", True)},
    "StatefulSetSpec": {"serviceName": (str, True), "replicas": (int, False), "podManagementPolicy": (str, False),
                        "selector": ("LabelSelector", True), "template": ("PodTemplate", True),
                        "volumeClaimTemplates": (("list", "PVC"), False), "updateStrategy": (dict, False)},
    "LabelSelector": {"matchLabels": (dict, True)},
    "PodTemplate": {"metadata": ("TemplateMeta", True), "spec": ("PodSpec", True)},
    "PodSpec": {"containers": (("list", "Container"), True), "volumes": (("list", "Volume"), False),
                "terminationGracePeriodSeconds": (int, False), "securityContext": ("PodSecurityContext", False),
                "serviceAccountName": (str, False)},
    "PodSecurityContext": {"runAsNonRoot": (bool, False), "runAsUser": (int, False), "runAsGroup": (int, False),
                           "fsGroup": (int, False)},
    "Container": {"name": (str, True), "image": (str, True), "imagePullPolicy": (str, False),
                  "command": (("list", str), False), "args": (("list", str), False), "env": (("list", "EnvVar"), False),
                  "ports": (("list", "ContainerPort"), False), "readinessProbe": ("Probe", False),
                  "livenessProbe": ("Probe", False), "startupProbe": ("Probe", False),
                  "resources": ("Resources", False), "volumeMounts": (("list", "VolumeMount"), False)},
    "EnvVar": {"name": (str, True), "value": (str, False), "valueFrom": ("EnvVarSource", False)},
    "EnvVarSource": {"fieldRef": ("FieldRef", False), "secretKeyRef": (dict, False), "configMapKeyRef": (dict, False)},
    "FieldRef": {"fieldPath": (str, True)},
    "ContainerPort": {"name": (str, True), "containerPort": (int, True), "protocol": (str, False)},
    "Probe": {"httpGet": ("HTTPGet", True), "initialDelaySeconds": (int, False), "periodSeconds": (int, False),
              "timeoutSeconds": (int, False), "failureThreshold": (int, False), "successThreshold": (int, False)},
    "HTTPGet": {"path": (str, True), "port": (ANY, True)},
    "Resources": {"requests": (dict, True), "limits": (dict, False)},
    "VolumeMount": {"name": (str, True), "mountPath": (str, True), "subPath": (str, False), "readOnly": (bool, False)},
    "Volume": {"name": (str, True), "configMap": ("ConfigMapVolume", False), "secret": ("SecretVolume", False),
               "emptyDir": (dict, False)},
    "ConfigMapVolume": {"name": (str, True), "optional": (bool, False), "defaultMode": (int, False)},
    "SecretVolume": {"secretName": (str, True), "optional": (bool, False), "defaultMode": (int, False)},
    "PVC": {"metadata": ("ObjectMeta", True), "spec": ("PVCSpec", True)},
    "PVCSpec": {"accessModes": (("list", str), True), "resources": ("Resources", True),
                "storageClassName": (str, False)},
}
API_VERSIONS = {"Service": "v1", "ConfigMap": "v1", "Secret": "v1", "StatefulSet": "apps/v1",
                "Kustomization": "kustomize.config.k8s.io/v1beta1"}


class Report:
    def __init__(self):
        self.problems = []

    def add(self, where, message):
        self.problems.append(f"{where}: {message}")


def check_schema(node, schema_name, where, report):
    schema = SCHEMAS[schema_name]
    if not isinstance(node, dict):
        report.add(where, f"expected a mapping ({schema_name}), got {type(node).__name__}")
        return
    for key in node:
        if key not in schema:
            report.add(where, f"unknown field '{key}' in {schema_name}")
    for key, (kind, required) in schema.items():
        if key not in node:
            if required:
                report.add(where, f"missing required field '{key}' in {schema_name}")
            continue
        check_value(node[key], kind, f"{where}.{key}", report)


def check_value(value, kind, where, report):
    if kind is ANY:
        return
    if isinstance(kind, tuple):
        if not isinstance(value, list):
            report.add(where, f"expected a list, got {type(value).__name__}")
            return
        for i, item in enumerate(value):
            check_value(item, kind[1], f"{where}[{i}]", report)
    elif isinstance(kind, str):
        check_schema(value, kind, where, report)
    elif kind is int and isinstance(value, bool) or not isinstance(value, kind):
        report.add(where, f"expected {kind.__name__}, got {type(value).__name__} ({value!r})")


def load_k8s(directory, report):
    docs = []
    for name in sorted(os.listdir(directory)):
        if not name.endswith((".yaml", ".yml")):
            continue
        path = os.path.join(directory, name)
        try:
            with open(path) as f:
                for i, doc in enumerate(yaml.safe_load_all(f)):
                    if doc is not None:
                        docs.append((f"{name}#{i}", doc))
        except yaml.YAMLError as e:
            report.add(name, f"not valid YAML: {e}")
    return docs


def check_k8s(directory, prism_server, report):
    docs = load_k8s(directory, report)
    by_kind = {}
    for where, doc in docs:
        kind = doc.get("kind") if isinstance(doc, dict) else None
        if kind not in SCHEMAS or kind not in API_VERSIONS:
            report.add(where, f"unknown or unsupported kind {kind!r}")
            continue
        if doc.get("apiVersion") != API_VERSIONS[kind]:
            report.add(where, f"{kind} needs apiVersion {API_VERSIONS[kind]}, got {doc.get('apiVersion')!r}")
        check_schema(doc, kind, where, report)
        name = (doc.get("metadata") or {}).get("name", "")
        if kind != "Kustomization" and not DNS1123_SUBDOMAIN.match(str(name)):
            report.add(where, f"metadata.name {name!r} is not a DNS-1123 name")
        by_kind.setdefault(kind, []).append((where, doc))

    def named(kind, name):
        return next((d for _, d in by_kind.get(kind, []) if d.get("metadata", {}).get("name") == name), None)

    for where, kust in by_kind.get("Kustomization", []):
        for resource in kust.get("resources", []):
            if not os.path.exists(os.path.join(directory, resource)):
                report.add(where, f"resource {resource} does not exist")

    for where, svc in by_kind.get("Service", []):
        for port in svc.get("spec", {}).get("ports", []) or []:
            if isinstance(port, dict) and not (isinstance(port.get("port"), int) and 0 < port["port"] < 65536):
                report.add(where, f"port {port.get('port')!r} not in 1..65535")

    for where, sts in by_kind.get("StatefulSet", []):
        spec = sts.get("spec", {})
        template = spec.get("template", {})
        labels = template.get("metadata", {}).get("labels", {}) or {}
        match = spec.get("selector", {}).get("matchLabels", {}) or {}
        if not match or any(labels.get(k) != v for k, v in match.items()):
            report.add(where, f"selector {match} does not match the pod template labels {labels}")
        headless = named("Service", spec.get("serviceName"))
        if headless is None:
            report.add(where, f"serviceName {spec.get('serviceName')!r} names no Service in {directory}")
        elif headless.get("spec", {}).get("clusterIP") != "None":
            report.add(where, f"serviceName {spec.get('serviceName')!r} must be a headless Service (clusterIP: None)")
        pod = template.get("spec", {})
        volumes = {v.get("name"): v for v in pod.get("volumes", []) or [] if isinstance(v, dict)}
        claims = {c.get("metadata", {}).get("name") for c in spec.get("volumeClaimTemplates", []) or []
                  if isinstance(c, dict)}
        for claim in spec.get("volumeClaimTemplates", []) or []:
            storage = claim.get("spec", {}).get("resources", {}).get("requests", {}).get("storage")
            if not QUANTITY.match(str(storage)):
                report.add(where, f"volumeClaimTemplate {claim.get('metadata', {}).get('name')}: storage "
                                  f"{storage!r} is not a quantity")
        for vname, volume in volumes.items():
            if "configMap" in volume:
                cm = volume["configMap"]
                if named("ConfigMap", cm.get("name")) is None and not cm.get("optional"):
                    report.add(where, f"volume {vname}: ConfigMap {cm.get('name')!r} is not defined")
            if "secret" in volume:
                secret = volume["secret"]
                if named("Secret", secret.get("secretName")) is None and not secret.get("optional"):
                    report.add(where, f"volume {vname}: Secret {secret.get('secretName')!r} is not defined "
                                      "(and not optional)")
        all_ports = {}
        for container in pod.get("containers", []) or []:
            if not isinstance(container, dict):
                continue
            cwhere = f"{where} container {container.get('name')}"
            ports = {p.get("name"): p.get("containerPort") for p in container.get("ports", []) or []
                     if isinstance(p, dict)}
            all_ports.update(ports)
            for pname in ports:
                if not DNS1123_LABEL.match(str(pname)) or len(str(pname)) > 15:
                    report.add(cwhere, f"port name {pname!r} is not an IANA service name")
            for probe_name in ("readinessProbe", "livenessProbe", "startupProbe"):
                probe = container.get(probe_name)
                if not isinstance(probe, dict):
                    continue
                http = probe.get("httpGet", {}) or {}
                port = http.get("port")
                if isinstance(port, str) and port not in ports:
                    report.add(cwhere, f"{probe_name} port {port!r} names no container port")
                if isinstance(port, int) and port not in ports.values():
                    report.add(cwhere, f"{probe_name} port {port} is not a container port")
                if not str(http.get("path", "")).startswith("/"):
                    report.add(cwhere, f"{probe_name} path must start with '/'")
            if "readinessProbe" not in container or "livenessProbe" not in container:
                report.add(cwhere, "needs a readinessProbe and a livenessProbe")
            resources = container.get("resources", {}) or {}
            for section in ("requests", "limits"):
                for key, quantity in (resources.get(section) or {}).items():
                    if key not in ("cpu", "memory", "ephemeral-storage"):
                        report.add(cwhere, f"resources.{section}: unknown resource {key!r}")
                    if not QUANTITY.match(str(quantity)):
                        report.add(cwhere, f"resources.{section}.{key} = {quantity!r} is not a quantity")
            if not {"cpu", "memory"} <= set((resources.get("requests") or {}).keys()):
                report.add(cwhere, "resources.requests needs cpu and memory")
            defined = set()
            for env in container.get("env", []) or []:
                if not isinstance(env, dict):
                    continue
                if not ENV_NAME.match(str(env.get("name"))):
                    report.add(cwhere, f"env name {env.get('name')!r} is invalid")
                for ref in re.findall(r"\$\(([^)]*)\)", str(env.get("value", ""))):
                    if ref not in defined:
                        report.add(cwhere, f"env {env.get('name')}: $({ref}) is not defined before it")
                defined.add(env.get("name"))
            # Files the server is pointed at (config, CURVE keys) must lie under a mount, and a Secret
            # mounted there must have the key named by the file.
            mounts = [m for m in container.get("volumeMounts", []) or [] if isinstance(m, dict)]
            for env in container.get("env", []) or []:
                if not isinstance(env, dict) or env.get("name") not in FILE_ENV:
                    continue
                path = str(env.get("value", ""))
                mount = next((m for m in mounts if path == m.get("mountPath") or
                              path.startswith(str(m.get("mountPath", "")).rstrip("/") + "/")), None)
                if mount is None:
                    report.add(cwhere, f"env {env['name']} = {path} is not under any volumeMount")
                    continue
                volume = volumes.get(mount.get("name"), {})
                if "secret" in volume and path != mount.get("mountPath"):
                    secret = named("Secret", volume["secret"].get("secretName"))
                    key = path[len(str(mount["mountPath"]).rstrip("/")) + 1:]
                    if secret is not None and key not in {**(secret.get("data") or {}), **(secret.get("stringData") or {})}:
                        report.add(cwhere, f"env {env['name']}: Secret {secret['metadata']['name']} has no key {key!r}")
            for mount in container.get("volumeMounts", []) or []:
                if not isinstance(mount, dict):
                    continue
                mname = mount.get("name")
                if mname not in volumes and mname not in claims:
                    report.add(cwhere, f"volumeMount {mname!r} names no volume or volumeClaimTemplate")
                elif mname in volumes and "configMap" in volumes[mname] and "subPath" in mount:
                    cm = named("ConfigMap", volumes[mname]["configMap"].get("name"))
                    if cm is not None and mount["subPath"] not in (cm.get("data") or {}):
                        report.add(cwhere, f"volumeMount {mname}: subPath {mount['subPath']!r} is not a key of "
                                           f"ConfigMap {cm['metadata']['name']}")
        for swhere, svc in by_kind.get("Service", []):
            selector = svc.get("spec", {}).get("selector", {}) or {}
            if selector and all(labels.get(k) == v for k, v in selector.items()):
                for port in svc.get("spec", {}).get("ports", []) or []:
                    target = port.get("targetPort", port.get("port")) if isinstance(port, dict) else None
                    if isinstance(target, str) and target not in all_ports:
                        report.add(swhere, f"targetPort {target!r} names no container port of StatefulSet "
                                           f"{sts['metadata']['name']}")
                    if isinstance(target, int) and target not in all_ports.values():
                        report.add(swhere, f"targetPort {target} is no container port of StatefulSet "
                                           f"{sts['metadata']['name']}")

    # The server's config file, read by the real prism-server (unknown keys and bad values fail).
    if prism_server:
        for where, cm in by_kind.get("ConfigMap", []):
            conf = (cm.get("data") or {}).get("server.conf")
            if conf is None:
                continue
            with tempfile.NamedTemporaryFile("w", suffix=".conf", delete=False) as f:
                f.write(conf)
            try:
                r = subprocess.run([prism_server, "--config", f.name, "--check"], capture_output=True, text=True)
                if r.returncode != 0:
                    report.add(where, f"server.conf rejected by prism-server: {r.stderr.strip()}")
            finally:
                os.unlink(f.name)
    return len(docs)


def check_compose(path, report):
    try:
        with open(path) as f:
            doc = yaml.safe_load(f)
    except (OSError, yaml.YAMLError) as e:
        report.add(path, f"cannot read: {e}")
        return False
    used_schema = False
    compose = shutil.which("docker-compose")
    if compose:
        r = subprocess.run([compose, "-f", path, "config", "-q"], capture_output=True, text=True,
                           env=dict(os.environ, DOCKER_HOST="unix:///nonexistent"))
        used_schema = True
        if r.returncode != 0:
            report.add(path, f"docker-compose config: {r.stderr.strip()}")
    services = doc.get("services") if isinstance(doc, dict) else None
    if not isinstance(services, dict) or not services:
        report.add(path, "no services")
        return used_schema
    volumes = doc.get("volumes") or {}
    built_images = {s.get("image") for s in services.values() if isinstance(s, dict) and "build" in s}
    for name, svc in services.items():
        where = f"{path} service {name}"
        if not isinstance(svc, dict):
            report.add(where, "not a mapping")
            continue
        if "image" not in svc and "build" not in svc:
            report.add(where, "needs image or build")
        if "build" not in svc and svc.get("image", "").startswith("prism:") and svc.get("image") not in built_images:
            report.add(where, f"image {svc.get('image')} is built by no service")
        depends = svc.get("depends_on") or {}
        for dep, cond in (depends.items() if isinstance(depends, dict) else ((d, None) for d in depends)):
            if dep not in services:
                report.add(where, f"depends_on {dep!r}: no such service")
            elif isinstance(cond, dict) and cond.get("condition") == "service_healthy" and \
                    "healthcheck" not in services[dep]:
                report.add(where, f"depends_on {dep} service_healthy but {dep} has no healthcheck")
        for volume in svc.get("volumes") or []:
            source = str(volume).split(":")[0]
            if not source.startswith((".", "/")) and source not in volumes:
                report.add(where, f"named volume {source!r} is not declared under volumes")
        health = svc.get("healthcheck")
        if health is not None:
            test = health.get("test")
            if not (isinstance(test, list) and test and test[0] in ("CMD", "CMD-SHELL", "NONE")) and \
                    not isinstance(test, str):
                report.add(where, "healthcheck.test must be a string or a list starting with CMD/CMD-SHELL/NONE")
    return used_schema


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--k8s", default=os.path.join(here, "k8s"))
    parser.add_argument("--compose", default=os.path.join(here, "docker-compose.yml"))
    parser.add_argument("--prism-server", default="", help="prism-server binary that loads the ConfigMap's server.conf")
    args = parser.parse_args()
    report = Report()
    n = check_k8s(args.k8s, args.prism_server, report)
    schema = check_compose(args.compose, report)
    for p in report.problems:
        print(p)
    print(f"validate: {n} Kubernetes objects, compose {'with docker-compose schema' if schema else 'structure only'}, "
          f"{len(report.problems)} problems", file=sys.stderr)
    return 1 if report.problems else 0


if __name__ == "__main__":
    sys.exit(main())
