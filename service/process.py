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
        ``wait_for_paths``: also wait until ``/readyz`` lists none of these solver paths
        (``"displacement"``, ``"loaded"``: :data:`tdcr.physics.exact.PATHS`) under ``compiling``: the
        solver processes compile them after they say ready (a request on one says 503 "starting"
        until then, about two minutes on a machine's first start), for up to :data:`PATHS_TIMEOUT_S` more.
        ``root``: the source tree whose ``tdcr`` and ``service`` it runs (another revision's worktree
        for a benchmark's ``--against``; its solver processes import the same tree)."""
        if wait_for_paths:
            from tdcr.physics.exact import PATHS  # (the solver's import, only where it is asked for)

            unknown = set(wait_for_paths) - set(PATHS)
            if unknown:
                raise ValueError(f"wait_for_paths: unknown solver paths {sorted(unknown)}; they are {list(PATHS)}")
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
        ready = self._wait(time.monotonic() + ready_timeout_s, lambda r: not (wait_for_solver and r["starting"]))
        if ready and wait_for_paths:  # the solver up, and none of the paths listed as still compiling
            ready = self._wait(time.monotonic() + PATHS_TIMEOUT_S, lambda r: "exact" not in r["starting"] and not (
                set(wait_for_paths) & set(r["compiling"].get("exact", ()))))
        if not ready:
            self.stop(check=False)
            raise RuntimeError(f"server did not become ready: {self.log()[-3000:]}")

    def _wait(self, deadline: float, done) -> bool:
        """Poll ``/readyz`` until it answers 200 with a body (dict) that ``done`` accepts; False if the
        server exits or the ``deadline`` (``time.monotonic()``) passes first."""
        while time.monotonic() < deadline and self.proc.poll() is None:
            try:
                with urllib.request.urlopen(self.url + "/readyz", timeout=2) as r:
                    if r.status == 200 and done(json.loads(r.read())):
                        return True
            except (urllib.error.URLError, ConnectionError, TimeoutError):  # (503 is an HTTPError: not ready)
                pass
            time.sleep(0.2)
        return False

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
