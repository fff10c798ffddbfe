"""Where one design's answer spends its time inside the service (issue #34), without the network:
the data plane of a started service answers one-design OIP v2 gRPC requests on the router ``auto``
in process, as the gRPC server's event loop does, and each stage is timed (prints a table).

    python benchmarks/one_design_path.py [--requests 1000] [--against REV]

Rows (medians over ``--requests`` different Table I designs, 42 points, after a warm-up):
- ``DataPlane.infer``: the whole answer, as the gRPC codec's ``ModelInfer`` awaits it (decode, the
  router's choice, the solve, encode, metrics);
- its parts, each on its own: the codec's ``decode`` (the one validation path), ``solve_request``
  (the exact answer of the decoded request) and ``tdcr.solve`` of the design (the physics API), and
  the compiled kernel alone on prepared inputs (what the rest is overhead on).

``--against REV`` measures a git revision's tree beside this one, in alternating rounds in processes
of their own (ratios within one run: this VM's speed drifts by 2x over a day), e.g. ``--against
01caad9``, the tree before this path was trimmed.  Whatever the rows, the transport's own cost (a
no-op gRPC call: ``benchmarks/fast_paths.py``) comes on top.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import platform
import time

import numpy as np
from against import ROOT, run_in, worktree  # benchmarks/ is the script's folder

#: The rows every tree measures (``--against`` compares them); the kernel row is this tree's only.
SHARED_ROWS = ("DataPlane.infer (the whole answer)", "decode (validation)", "solve_request", "tdcr.solve")


def _median_ms(fn, items) -> float:
    times = []
    for item in items:
        started = time.perf_counter()
        fn(item)
        times.append(time.perf_counter() - started)
    return 1e3 * float(np.median(times))


async def _measure(requests: int) -> dict[str, float]:
    """Median ms of each row on this interpreter's ``tdcr`` and ``service`` (the tree first on
    ``sys.path``)."""
    from service.grpc_server import CODEC
    from service.model import InferenceRequest
    from service.settings import Settings
    from service.state import ServiceState, start
    from tdcr.clients.loadtest import grpc_request
    from tdcr.physics import solve
    from tdcr.physics.exact import solve_request
    from tdcr.robot.design_space import sample_designs

    state = ServiceState.create(Settings())
    await start(state)
    try:
        plane = state.plane
        routed = plane.repository.models["auto"]
        features = sample_designs(requests + 50, seed=8).features()
        wire = [grpc_request("auto", f[None, :], None) for f in features]
        fractions = np.linspace(0.0, 1.0, 42)

        async def infer(message):
            return await plane.infer("auto", InferenceRequest(message, CODEC), version="", protocol="grpc",
                                     endpoint="ModelInfer")

        for message in wire[:50]:  # warm-up: the kernels loaded, caches filled
            await infer(message)
        times = []
        for message in wire[50:]:
            started = time.perf_counter()
            await infer(message)
            times.append(time.perf_counter() - started)
        decoded = [CODEC.decode(InferenceRequest(m, CODEC).payload, routed.spec) for m in wire[50:]]
        tasks = [d.task for d in decoded]
        rows = {SHARED_ROWS[0]: 1e3 * float(np.median(times)),
                SHARED_ROWS[1]: _median_ms(lambda m: CODEC.decode(InferenceRequest(m, CODEC).payload, routed.spec),
                                           wire[50:]),
                SHARED_ROWS[2]: _median_ms(solve_request, tasks),
                SHARED_ROWS[3]: _median_ms(lambda t: solve(t.groups[0].designs, fractions), tasks)}
        try:  # this tree's kernel on prepared inputs (the internals of older trees differ)
            from tdcr.physics import cosserat

            designs = tasks[0].groups[0].designs
            opts = cosserat.SolverOptions()
            edges = cosserat._base_edges(fractions, opts.max_step)
            kernel, rods, grid, tols, out = cosserat._kernel_inputs(designs, cosserat.material(designs), edges,
                                                                    fractions, opts, loaded=False)
            rows["the compiled kernel alone"] = _median_ms(lambda _: kernel.solve_batch(rods, grid, tols, out), tasks)
        except AttributeError:
            pass
        return rows
    finally:
        plane.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--requests", type=int, default=1000)
    parser.add_argument("--against", help="a git revision measured beside this tree, in alternating rounds")
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, CPython {platform.python_version()}; "
          f"one Table I design, 42 points, median of {args.requests}")
    if args.against is None:
        ours, theirs = asyncio.run(_measure(args.requests)), None
    else:
        tree, call = worktree(args.against), f"asyncio.run(b._measure({args.requests}))"
        rounds = [(run_in(tree, "one_design_path", call), run_in(ROOT, "one_design_path", call)) for _ in range(3)]
        theirs = {k: min(r[0][k] for r in rounds) for k in SHARED_ROWS}
        ours = {k: min(r[1][k] for r in rounds) for k in rounds[0][1]}
    head = f" | {args.against} (ms) | ratio" if theirs else ""
    print(f"\n| stage | this tree (ms){head} |\n|---|---:{'|---:|---:' if theirs else ''}|")
    for label, value in ours.items():
        old = f" | {theirs[label]:.3f} | {value / theirs[label]:.2f}" if theirs and label in theirs else \
            (" | | " if theirs else "")
        print(f"| {label} | {value:.3f}{old} |")
    if theirs:
        print("\n(best of 3 alternating rounds for each tree)")


if __name__ == "__main__":  # the solver's processes are spawned: they import this module
    main()
