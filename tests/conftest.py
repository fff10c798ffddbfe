"""Shared fixtures of the three groups (tests/unit, tests/service, tests/peers): paths, the
independent C++ reference solutions, design batches from JSON, and tiny trained models.  Test
modules import nothing from each other: what they share is here."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import threading
from pathlib import Path

import pytest

from tdcr.api.validation import Limits, validate_json

ROOT = Path(__file__).resolve().parents[1]
#: the small reference files the suite reads (copies of shared/'s, tests/data/README.md)
DATA = ROOT / "tests" / "data"
SHARED = Path(os.environ.get("TDCR_SHARED", ROOT.parent / "shared"))

#: Small hyperparameters that train in seconds, per model.
TINY = {
    "deeponet": {"branch_width": 16, "trunk_width": 16, "p": 8},
    "deeponet_pose": {"branch_width": 16, "trunk_width": 16, "p": 8},
    "fno": {"width": 16},
    "fno_pose": {"width": 16},
    "deeponet_pose_loaded": {"branch_width": 16, "trunk_width": 16, "p": 8},
    "fno_pose_loaded": {"width": 16},
}


#: each folder of tests/ is a group, marked by its name (``pytest -m unit``, ``-m "not service"``)
GROUPS = ("unit", "service", "peers")


def pytest_collection_modifyitems(config, items):
    """Mark every test with its folder's group; a test outside the groups' folders is an error.  A
    test of the built Docker image goes last: its check runs beside the suite from collection
    (DockerCheck)."""
    for item in items:
        group = Path(str(item.fspath)).parent.name
        if group not in GROUPS:
            raise pytest.UsageError(f"{item.nodeid}: tests live in tests/{{{','.join(GROUPS)}}}/")
        item.add_marker(getattr(pytest.mark, group))
    items.sort(key=_uses_the_image)  # stable: the others keep their order


def _uses_the_image(item) -> bool:
    """Whether a test waits for the Docker image's check (it takes the ``docker_check`` fixture)."""
    return "docker_check" in getattr(item, "fixturenames", ())


class DockerCheck:
    """scripts/docker-base.sh, then scripts/docker-test.sh, each to its end, in a thread of this
    session: the image's build and containers take minutes, mostly on a core that the suite (one
    process, one thread at a time) leaves idle, so they run beside the other tests from the end of
    collection.  :meth:`results` waits for both; ``None`` for a step that did not run (the base
    failed, or the session ended first)."""

    STEPS = ("scripts/docker-base.sh", "scripts/docker-test.sh")

    def __init__(self, root: Path, timeout: float = 900.0):
        self.root, self.timeout = root, timeout
        self.done: list[subprocess.CompletedProcess | None] = [None, None]
        self._process: subprocess.Popen | None = None
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name="docker-check", daemon=True)

    @staticmethod
    def possible() -> str | None:
        """Why no Docker engine can be had here (None: it can be tried)."""
        if os.geteuid() != 0 or not shutil.which("apt-get") and not shutil.which("dockerd"):
            return "needs root (or a running engine) to install and start Docker"
        return None

    def start(self) -> DockerCheck:
        self._thread.start()
        return self

    def _run(self) -> None:
        for i, step in enumerate(self.STEPS):
            if self._stopped:
                return
            self._process = subprocess.Popen(["bash", step], cwd=self.root, stdout=subprocess.PIPE,
                                             stderr=subprocess.PIPE, text=True, start_new_session=True)
            try:
                out, err = self._process.communicate(timeout=self.timeout)
            except subprocess.TimeoutExpired:
                self.stop()
                out, err = self._process.communicate()
                err += f"\n{step} ran past {self.timeout:.0f} s"
            self.done[i] = subprocess.CompletedProcess(self._process.args, self._process.returncode, out, err)
            if self._process.returncode != 0:
                return

    def results(self) -> list[subprocess.CompletedProcess | None]:
        self._thread.join()
        return self.done

    def stop(self) -> None:
        """End the running step and its children (the session ends)."""
        self._stopped = True
        if self._process is not None and self._process.poll() is None:
            os.killpg(self._process.pid, signal.SIGTERM)


#: Where the session keeps its DockerCheck.
DOCKER_KEY = pytest.StashKey[DockerCheck]()


def pytest_collection_finish(session):
    """Start the Docker image's check beside the suite when a test of it is to run (see DockerCheck)."""
    if session.config.option.collectonly or DockerCheck.possible() is not None:
        return
    if any(_uses_the_image(item) for item in session.items):
        session.config.stash[DOCKER_KEY] = DockerCheck(ROOT).start()


def pytest_sessionfinish(session):
    check = session.config.stash.get(DOCKER_KEY, None)
    if check is not None:
        check.stop()


@pytest.fixture(scope="session")
def docker_check(request) -> DockerCheck:
    """The session's :class:`DockerCheck` (started at collection; here if the test was not collected
    with the rest); skips with the reason where no Docker engine can be had."""
    reason = DockerCheck.possible()
    if reason is not None:
        pytest.skip(reason)
    stash = request.config.stash
    if DOCKER_KEY not in stash:
        stash[DOCKER_KEY] = DockerCheck(ROOT).start()
    return stash[DOCKER_KEY]


@pytest.fixture(scope="session")
def root() -> Path:
    """The repository root."""
    return ROOT


@pytest.fixture(scope="session")
def data() -> Path:
    """tests/data: the reference files (the suite needs nothing outside the clone)."""
    return DATA


@pytest.fixture(scope="session")
def shared() -> Path | None:
    """The shared/ folder beside the checkout (or ``$TDCR_SHARED``), None where there is none."""
    return SHARED if SHARED.exists() else None


@pytest.fixture(scope="session")
def example_request(root) -> dict:
    """examples/request.json: two designs at 5 points."""
    return json.loads((root / "examples" / "request.json").read_text())


@pytest.fixture(scope="session")
def reference_cases(data) -> list[dict]:
    """The independent solver's cases (there are 22; an empty file fails here, not silently later)."""
    cases = json.loads((data / "cosserat_cases.json").read_text())["cases"]
    assert len(cases) >= 20, f"expected the 22 reference cases, found {len(cases)}"
    return cases


@pytest.fixture(scope="session")
def designs_from_json():
    """``f(list of design dicts) -> DesignBatch`` through the one validation path (one tendon count)."""
    def convert(designs: list[dict]):
        request = validate_json({"designs": designs}, target="solver", limits=Limits(max_designs=10**6))
        assert len(request.groups) == 1
        return request.groups[0].designs

    return convert


@pytest.fixture(scope="session")
def tiny_hyperparameters() -> dict:
    return TINY


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory):
    """A 150-design solver dataset on disk."""
    from training import dataset

    out = tmp_path_factory.mktemp("data") / "tiny"
    dataset.generate(out, dataset.GenerateConfig(n=150, seed=2, shard_size=50), workers=1, progress=False)
    return out


@pytest.fixture(scope="session")
def tiny_models(tiny_data, tmp_path_factory):
    """All four operators, tiny, trained for 2 epochs and exported: ``(runs dir, models dir)``."""
    pytest.importorskip("torch")
    from training.operators.export import export_run
    from training.operators.models import REGISTRY
    from training.operators.train import make_config, train

    root = tmp_path_factory.mktemp("runs")
    models = root / "models"
    for name in REGISTRY:
        cfg = make_config(name, "tuned", epochs=2, batch_size=40, hyperparameters=TINY[name])
        train(cfg, tiny_data, root / name, progress=False, monitor_designs=20)
        export_run(root / name, models)
    return root, models


@pytest.fixture(scope="session")
def run_triton_example(root):
    """Run ``examples/tritonclient_<protocol>.py`` against a server in its own process (Triton's
    stubs and ours cannot share one) and check its tendon paths on every model against /predict
    and /exact of the server at ``url`` (rtol 1e-6)."""
    import subprocess
    import sys
    import tempfile

    import httpx
    import numpy as np

    from tdcr.robot.designs import DesignBatch

    def run(protocol: str, target: str, url: str, models: list[str]) -> None:
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "answer.json"
            done = subprocess.run([sys.executable, f"examples/tritonclient_{protocol}.py", target, "--json", str(out)],
                                  cwd=root, capture_output=True, text=True, timeout=300)
            assert done.returncode == 0, done.stderr[-3000:]
            assert len(done.stdout) < 4000, "the example prints a summary, not its arrays"
            answer = json.loads(out.read_text())
        assert set(answer["tendons"]) == {*models, "exact"}
        body = {"designs": DesignBatch.from_features(np.array(answer["designs"])).to_dicts()}
        exact = httpx.post(url + "/exact", json=body, timeout=60).json()["results"]
        np.testing.assert_allclose(answer["tendons"]["exact"], [r["tendons"] for r in exact], rtol=1e-6, atol=1e-9)
        for model in models:
            ref = httpx.post(url + "/predict", json=body | {"model": model}).json()["results"]
            np.testing.assert_allclose(answer["tendons"][model], [r["tendons"] for r in ref], rtol=1e-6, atol=1e-9)

    return run
