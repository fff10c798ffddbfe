"""The Kubernetes manifests of docker/k8s/, validated offline: the Kubernetes kinds with
``kubernetes-validate --strict`` (its bundled schemas), the KServe InferenceService with a JSON
schema: its predictor is a Kubernetes PodSpec (checked against the same bundled, strict schema)
plus KServe's component extension fields."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import jsonschema
import pytest
import yaml

KINDS = {"deployment.yaml": "Deployment", "service.yaml": "Service", "hpa.yaml": "HorizontalPodAutoscaler"}
#: KServe v1beta1 ComponentExtensionSpec fields a predictor may carry beside its PodSpec.
KSERVE_EXTENSION = {"minReplicas": {"type": "integer", "minimum": 0}, "maxReplicas": {"type": "integer", "minimum": 0},
                    "scaleTarget": {"type": "integer"},
                    "scaleMetric": {"enum": ["cpu", "memory", "concurrency", "rps"]},
                    "containerConcurrency": {"type": "integer"}, "timeout": {"type": "integer"},
                    "canaryTrafficPercent": {"type": "integer"}, "labels": {"type": "object"},
                    "annotations": {"type": "object"}}


def _schemas() -> Path:
    import kubernetes_validate

    folders = sorted((Path(kubernetes_validate.__file__).parent / "kubernetes-json-schema").glob("v*-local-strict"))
    return folders[-1]


@pytest.mark.parametrize("name", sorted(KINDS))
def test_kubernetes_kinds_validate_strictly(root, name):
    path = root / "docker" / "k8s" / name
    assert yaml.safe_load(path.read_text())["kind"] == KINDS[name]
    done = subprocess.run([sys.executable, "-m", "kubernetes_validate", "--strict", str(path)], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr


def test_the_validator_rejects_a_typo(root, tmp_path):
    manifest = yaml.safe_load((root / "docker" / "k8s" / "deployment.yaml").read_text())
    manifest["spec"]["template"]["spec"]["containers"][0]["readinesProbe"] = {}  # not a field
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(manifest))
    done = subprocess.run([sys.executable, "-m", "kubernetes_validate", "--strict", str(bad)], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode != 0


def test_probes_ports_and_security(root):
    deployment = yaml.safe_load((root / "docker" / "k8s" / "deployment.yaml").read_text())
    pod = deployment["spec"]["template"]["spec"]
    container = pod["containers"][0]
    assert container["readinessProbe"]["httpGet"]["path"] == "/v2/health/ready"
    assert container["livenessProbe"]["grpc"]["port"] == 8001 and "startupProbe" in container
    assert {p["containerPort"] for p in container["ports"]} == {8000, 8001}
    assert pod["securityContext"]["runAsNonRoot"] and container["securityContext"]["readOnlyRootFilesystem"]
    assert container["resources"]["limits"] and container["resources"]["requests"]
    service = yaml.safe_load((root / "docker" / "k8s" / "service.yaml").read_text())
    assert {p["name"]: p.get("appProtocol") for p in service["spec"]["ports"]} == {"http": "http", "grpc": "grpc"}


def _inference_service_schema() -> jsonschema.Draft202012Validator:
    """An InferenceService schema whose predictor is the bundled strict PodSpec plus KServe's
    extension fields (the bundled definitions inlined as ``$defs``)."""
    folder = _schemas()
    text = (folder / "podspec-v1.json").read_text().replace("/api/_definitions.json#", "#")
    podspec = json.loads(text)
    podspec.pop("$id", None)
    podspec.pop("$schema", None)
    predictor = {**podspec, "properties": {**podspec["properties"], **KSERVE_EXTENSION}}
    definitions = json.loads((folder / "_definitions.json").read_text().replace("/api/_definitions.json#", "#"))
    schema = {"type": "object", "required": ["apiVersion", "kind", "metadata", "spec"], "additionalProperties": False,
              "$defs": definitions["$defs"],
              "properties": {"apiVersion": {"const": "serving.kserve.io/v1beta1"},
                             "kind": {"const": "InferenceService"},
                             "metadata": {"$ref": "#/$defs/io.k8s.apimachinery.pkg.apis.meta.v1.ObjectMeta"},
                             "spec": {"type": "object", "required": ["predictor"], "additionalProperties": False,
                                      "properties": {"predictor": predictor}}}}
    return jsonschema.Draft202012Validator(schema)


def test_inference_service_validates(root):
    manifest = yaml.safe_load((root / "docker" / "k8s" / "inferenceservice.yaml").read_text())
    validator = _inference_service_schema()
    validator.validate(manifest)
    assert manifest["metadata"]["annotations"]["serving.kserve.io/deploymentMode"] == "RawDeployment"
    manifest["spec"]["predictor"]["containers"][0]["imagePullPolcy"] = "Always"  # a typo
    assert not validator.is_valid(manifest)
