"""Measure an older git revision beside this tree (``--against REV`` of the benchmarks that compare
trees): the revision's worktree, and a call run in a fresh interpreter with a tree's ``tdcr`` and
``service`` first on the path.  Ratios within one run, trees in alternating rounds: this VM's speed
drifts by 2x over a day."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def worktree(revision: str) -> Path:
    """A detached worktree of ``revision`` (made once, kept under /tmp for the next run)."""
    tree = Path(f"/tmp/tdcr-against-{revision}")
    if not tree.exists():
        subprocess.run(["git", "worktree", "add", "--detach", str(tree), revision], cwd=ROOT, check=True,
                       capture_output=True)
    return tree


def run_in(root: Path, module: str, expression: str):
    """``expression`` on ``b``, the benchmark ``module`` of this folder (e.g. ``"b.rates(2000, 1, 3)"``),
    evaluated in a new interpreter on the tree ``root``, its JSON answer decoded (``asyncio`` is
    imported for a coroutine's ``asyncio.run``).  ``PYTHONPATH`` names the tree too,
    so that processes the call spawns (a service's solver pool) import the same one."""
    code = (f"import sys; sys.path.insert(0, {str(root)!r}); sys.path.insert(1, {str(ROOT / 'benchmarks')!r}); "
            f"import asyncio, json, {module} as b; print(json.dumps({expression}))")
    env = {**os.environ, "PYTHONPATH": str(root)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=root, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])
