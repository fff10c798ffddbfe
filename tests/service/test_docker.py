"""Docker artefacts: compose against the Compose spec, the Dockerfile's rules, and the image built and
run for real (scripts/docker-test.sh: non-root, read-only, Triton's clients over HTTP and gRPC on one
container and on 2 compose replicas) where a Docker engine can be had."""

from __future__ import annotations

import json
import re

import jsonschema
import pytest
import yaml


def _validate(compose: dict, schema: dict) -> None:
    """Validate against the Compose spec as the draft it names: its ``$schema``
    (``https://json-schema.org/draft-07/schema``, without the ``#``) is not a URI jsonschema knows,
    so ``jsonschema.validate`` fell back to its latest draft with a DeprecationWarning."""
    assert "draft-07" in schema["$schema"]
    jsonschema.Draft7Validator.check_schema(schema)
    jsonschema.Draft7Validator(schema).validate(compose)


def test_compose_file_is_valid_and_limited(root, data):
    compose = yaml.safe_load((root / "docker" / "compose.yaml").read_text())
    schema = json.loads((data / "compose-spec.json").read_text())
    _validate(compose, schema)
    svc = compose["services"]["tdcr"]
    assert "/readyz" in " ".join(svc["healthcheck"]["test"])
    limits = svc["deploy"]["resources"]["limits"]
    assert float(limits["cpus"]) > 0 and limits["memory"].endswith(("M", "G"))
    assert svc["deploy"]["replicas"] >= 1
    # HTTP and gRPC on loopback only; no fixed host port, so replicas can scale
    assert svc["ports"] == ["127.0.0.1::8000", "127.0.0.1::8001"]


def test_invalid_compose_is_rejected_by_the_schema(root, data):
    compose = yaml.safe_load((root / "docker" / "compose.yaml").read_text())
    compose["services"]["tdcr"]["healthchek"] = compose["services"]["tdcr"].pop("healthcheck")  # a typo
    schema = json.loads((data / "compose-spec.json").read_text())
    try:
        _validate(compose, schema)
    except jsonschema.ValidationError:
        return
    raise AssertionError("the schema accepted an unknown service key")


def test_dockerfile_is_slim_nonroot_healthchecked_and_installs_like_the_readme(root):
    text = (root / "docker" / "Dockerfile").read_text()
    assert re.search(r"^ARG BASE_IMAGE=python:3\.\d+-slim$", text, re.M)
    assert re.search(r"^USER (?!root|0\b)\w+", text, re.M)
    assert "HEALTHCHECK" in text and "/readyz" in text
    install = re.search(r"&& (scripts/setup\.sh \w[\w,]*)", text).group(1)
    run_sh = (root / "scripts" / "run.sh").read_text()
    assert install in run_sh, "the image must install exactly as the README's run command does"
    code = "\n".join(line for line in text.splitlines() if not line.lstrip().startswith("#"))
    assert "train" not in install and "torch" not in code


def test_serving_install_does_not_pull_torch(root):
    import tomllib

    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    serve = " ".join(project["optional-dependencies"]["serve"] + project["dependencies"])
    assert "torch" not in serve and "onnxruntime" in serve


@pytest.mark.slow
def test_the_image_runs_for_real(docker_check):
    """scripts/docker-test.sh end to end (run beside the suite from its collection: tests/conftest.py's
    DockerCheck).  Skips (with the reason) only where no Docker engine can be had: not root, or the
    engine or the base image cannot be set up; past that, it must pass."""
    base, done = docker_check.results()
    if base is None or base.returncode != 0:
        pytest.skip(f"no Docker engine or base image here: {'' if base is None else base.stderr.strip()[-500:]}")
    assert done is not None and done.returncode == 0, (done.stdout + done.stderr)[-4000:]
    assert done.stdout.count("ok: ") == 3 and "all container checks passed" in done.stdout
