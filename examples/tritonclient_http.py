"""Triton's own HTTP client against the service's Open Inference Protocol v2 endpoints.

    pip install "tritonclient[http]"
    python examples/tritonclient_http.py http://127.0.0.1:8000 [MODEL ...]

Prints, per model, the shapes it answered; the last line is JSON for scripts: the designs sent and
each model's tendon paths (B, n, 4, 3) in metres.  Inputs and outputs travel as binary tensors,
tritonclient's default.
"""

from __future__ import annotations

import json
import sys
from urllib.parse import urlparse

import numpy as np
import tritonclient.http as triton

# two designs in the README's feature order: E, r, L, 4 offsets, 4 pitches (rad/m), 4 tensions (N)
DESIGNS = np.array([[3.0e10, 1.0e-3, 0.25, 0.008, 0.008, 0.008, 0.008, 0.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0],
                    [2.0e10, 8.0e-4, 0.20, 0.006, 0.007, 0.008, 0.009, 5.0, -5.0, 0.0, 10.0, 1.0, 2.0, 0.5, 0.0]])


def main() -> None:
    url = urlparse(sys.argv[1] if len(sys.argv) > 1 else "http://127.0.0.1:8000").netloc
    client = triton.InferenceServerClient(url)
    assert client.is_server_live() and client.is_server_ready()
    answers = {}
    for name in sys.argv[2:] or ["deeponet", "deeponet_pose", "fno", "fno_pose", "exact"]:
        meta = client.get_model_metadata(name)
        design = triton.InferInput("design", list(DESIGNS.shape), "FP64")
        design.set_data_from_numpy(DESIGNS)
        outputs = [triton.InferRequestedOutput(o["name"]) for o in meta["outputs"] if o["name"] != "residual"]
        result = client.infer(name, [design], outputs=outputs)
        tendons = result.as_numpy("tendons")
        print(f"{name}: tendons {tendons.shape}, rotation {result.as_numpy('rotation').shape}, "
              f"in_distribution {result.as_numpy('in_distribution').tolist()}")
        answers[name] = tendons.tolist()
    print(json.dumps({"designs": DESIGNS.tolist(), "tendons": answers}))


if __name__ == "__main__":
    main()
