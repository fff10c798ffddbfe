"""The compiled tendon-only path: numba when it is installed, else ``None`` (the solver then uses
its vectorised numpy path, which implements the same method and step control; tested equal)."""

from __future__ import annotations

import os

try:  # numba is a dependency; this guard is the documented fallback for platforms without it
    if os.environ.get("TDCR_KERNEL", "numba") == "numpy":
        raise ImportError("TDCR_KERNEL=numpy")
    from tdcr.physics import _kernel as kernel
except ImportError:
    kernel = None
