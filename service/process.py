"""A real server in its own process on a free loopback port: for tests, benchmarks and scripts.

    with ServerProcess(models_dir, exact_timeout_s=5) as server:
        httpx.get(server.url + "/readyz")

Settings are passed as ``TDCR_*`` environment variables; the server's log goes to a file (an
unread pipe would fill up and block the server).
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: What ``stop`` finds in the log of a server that raised an unhandled exception.
UNHANDLED = "Exception in ASGI application"
#: How long ``wait_for_paths`` waits, s, from /readyz: a machine's first start compiles the solver's
#: other paths after it says ready (about 75 s each on 2 cores, README), from the cache at once later.
PATHS_TIMEOUT_S = 360.0
#: A shipped request that runs each solver path (tdcr.physics.exact.PATHS; the hardening tests check
#: that each runs its path), for ``wait_for_paths``.
PATH_EXAMPLES = {"tendon": "request.json", "loaded": "request_loaded.json", "displacement": "ftdcr_v4_fitted.json"}


def child_pids(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (Linux ``/proc``)."""
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == pid:
                kids.append(int(stat.parent.name))
        except (OSError, ValueError, IndexError):
            continue
    return kids


def solver_pids(pid: int) -> list[int]:
    """The /exact solver processes of the server ``pid`` (not multiprocessing's resource tracker)."""
    out = []
    for kid in child_pids(pid):
        try:
            if b"spawn_main" in Path(f"/proc/{kid}/cmdline").read_bytes():
                out.append(kid)
        except OSError:
            continue
    return out


def free_ports(n: int) -> list[int]:
    """``n`` distinct free loopback ports: all bound at once, so that the system cannot hand out one
    twice (two ports picked one after the other can be equal: the HTTP and gRPC servers then clash)."""
    with contextlib.ExitStack() as stack:
        sockets = [stack.enter_context(socket.socket()) for _ in range(n)]
        for s in sockets:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in sockets]


def free_port() -> int:
    """One free loopback port."""
    return free_ports(1)[0]


class ServerProcess:
    """``tdcr serve`` (as the README runs it) with ``TDCR_<KEY>=value`` for each setting.

    Blocks until ``/readyz`` answers 200, and the solver's model too (``RuntimeError`` with the log's
    tail if they never do).
    """

    def __init__(self, models_dir: str | Path, *, ready_timeout_s: float = 90.0, grpc: bool = True,
                 wait_for_solver: bool = True, wait_for_paths: tuple[str, ...] = (), root: Path = ROOT,
                 **settings):
        """``grpc``: also serve gRPC, on a free port (``grpc_target``); ``wait_for_solver``: also wait
        for the solver (``exact`` ready: on a machine's first start it compiles after /readyz);
        ``wait_for_paths``: also wait until ``/exact`` answers the shipped example of each of these solver
        paths (``"displacement"``, ``"loaded"``: :data:`PATH_EXAMPLES`), which the solver
        processes compile after they say ready (503 "starting" until then, about two minutes on a
        machine's first start), for up to :data:`PATHS_TIMEOUT_S` more.
        ``root``: the source tree whose ``tdcr`` and ``service`` it runs (another revision's worktree
        for a benchmark's ``--against``; its solver processes import the same tree)."""
        unknown = set(wait_for_paths) - set(PATH_EXAMPLES)
        if unknown:
            raise ValueError(f"wait_for_paths: unknown solver paths {sorted(unknown)}; they are {list(PATH_EXAMPLES)}")
        self.port, self.grpc_port = free_ports(2) if grpc else (free_port(), 0)
        self.url = f"http://127.0.0.1:{self.port}"
        self.grpc_target = f"127.0.0.1:{self.grpc_port}"
        env = {**os.environ, "TDCR_MODELS_DIR": str(models_dir),
               **{f"TDCR_{k.upper()}": str(v) for k, v in settings.items()}}
        if root != ROOT:
            env["PYTHONPATH"] = str(root)
        self.log_path = Path(tempfile.mkstemp(prefix="tdcr-server-", suffix=".log")[1])
        with self.log_path.open("wb") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "tdcr.cli", "serve", "--host", "127.0.0.1", "--port", str(self.port),
                 "--grpc-port", str(self.grpc_port), "--log-level", "warning"],
                cwd=root, env=env, stdout=log, stderr=subprocess.STDOUT)
        try:
            if self._wait_ready(time.monotonic() + ready_timeout_s, wait_for_solver) and self._wait_for_paths(
                    wait_for_paths, time.monotonic() + PATHS_TIMEOUT_S):
                return
            problem = "server did not become ready"
        except RuntimeError as e:
            problem = str(e)
        self.stop(check=False)
        raise RuntimeError(f"{problem}: {self.log()[-3000:]}")

    def _wait_ready(self, deadline: float, wait_for_solver: bool) -> bool:
        """Poll ``/readyz`` until it answers 200 (and lists no solver model as starting, with
        ``wait_for_solver``); False if the server exits or the ``deadline`` (``time.monotonic()``) passes."""
        while time.monotonic() < deadline and self.proc.poll() is None:
            try:
                with urllib.request.urlopen(self.url + "/readyz", timeout=2) as r:
                    if r.status == 200 and not (wait_for_solver and json.loads(r.read()).get("starting")):
                        return True
            except (urllib.error.URLError, ConnectionError, TimeoutError):
                pass
            time.sleep(0.2)
        return False

    def _wait_for_paths(self, paths: tuple[str, ...], deadline: float) -> bool:
        """Post the shipped example of each solver path of ``paths`` (:data:`PATH_EXAMPLES`) to ``/exact``
        until it answers 200, waiting out each 503 (its ``Retry-After``) and each failed connection; False
        if the server exits or the ``deadline`` (``time.monotonic()``) passes first.  Any other answer
        raises ``RuntimeError`` with its body."""
        for path in paths:
            body = (ROOT / "examples" / PATH_EXAMPLES[path]).read_bytes()
            while True:
                request = urllib.request.Request(self.url + "/exact", data=body,
                                                 headers={"Content-Type": "application/json"})
                try:
                    with urllib.request.urlopen(request, timeout=60):
                        break
                except urllib.error.HTTPError as e:
                    if e.code != 503:
                        raise RuntimeError(f"/exact on the {path} path: {e.code} {e.read()[:500]!r}") from None
                    wait = float(e.headers.get("Retry-After") or 1.0)
                except (urllib.error.URLError, ConnectionError, TimeoutError):
                    if self.proc.poll() is not None:
                        return False
                    wait = 1.0
                if time.monotonic() + wait > deadline:
                    return False
                time.sleep(wait)
        return True

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self, *, check: bool = True) -> None:
        """SIGTERM (as ``docker stop`` sends), SIGKILL after 20 s; with ``check``, fail on a log that
        shows an unhandled exception."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if check and UNHANDLED in self.log():
            raise AssertionError(self.log()[-5000:])

    def __enter__(self) -> ServerProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.stop(check=exc[0] is None)
