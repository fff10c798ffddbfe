"""Triton's own HTTP client against the service's Open Inference Protocol v2 endpoints.

    pip install "tritonclient[http]"
    python examples/tritonclient_http.py http://127.0.0.1:8000 [MODEL ...]

Prints, per model, the shapes it answered and each design's tip (m); ``--json FILE`` also writes
the designs sent and each model's tendon paths (B, n, 4, 3) in metres, for scripts.
Inputs and outputs travel as binary tensors,
tritonclient's default.
"""

from __future__ import annotations

import argparse
import json
from urllib.parse import urlparse

import numpy as np
import tritonclient.http as triton

# two designs in the README's feature order: E, r, L, 4 offsets, 4 pitches (rad/m), 4 tensions (N)
DESIGNS = np.array([[3.0e10, 1.0e-3, 0.25, 0.008, 0.008, 0.008, 0.008, 0.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0],
                    [2.0e10, 8.0e-4, 0.20, 0.006, 0.007, 0.008, 0.009, 5.0, -5.0, 0.0, 10.0, 1.0, 2.0, 0.5, 0.0]])


def _arguments(default_target: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("target", nargs="?", default=default_target, help="the server (default: %(default)s)")
    parser.add_argument("models", nargs="*", help="models to ask (default: the four operators and exact)")
    parser.add_argument("--json", default=None, help="write the designs and every model's tendon paths here")
    return parser.parse_args()


def main() -> None:
    args = _arguments("http://127.0.0.1:8000")
    url = urlparse(args.target).netloc
    client = triton.InferenceServerClient(url)
    assert client.is_server_live() and client.is_server_ready()
    answers = {}
    for name in args.models or ["deeponet", "deeponet_pose", "fno", "fno_pose", "exact"]:
        meta = client.get_model_metadata(name)
        design = triton.InferInput("design", list(DESIGNS.shape), "FP64")
        design.set_data_from_numpy(DESIGNS)
        outputs = [triton.InferRequestedOutput(o["name"]) for o in meta["outputs"] if o["name"] != "residual"]
        result = client.infer(name, [design], outputs=outputs)
        tendons = result.as_numpy("tendons")
        tips = np.round(result.as_numpy("backbone")[:, -1], 4).tolist()
        print(f"{name}: tendons {tendons.shape}, rotation {result.as_numpy('rotation').shape}, "
              f"in_distribution {result.as_numpy('in_distribution').tolist()}, tips (m) {tips}")
        answers[name] = tendons.tolist()
    if args.json:
        with open(args.json, "w") as out:
            json.dump({"designs": DESIGNS.tolist(), "tendons": answers}, out)


if __name__ == "__main__":
    main()
