"""The compiled solver kernels (numba): the only importer of :mod:`tdcr.physics._kernel`.

numba's on-disk cache must be writable even to be read.  Where ``NUMBA_CACHE_DIR`` is not (the
read-only image, whose kernels were compiled at build time), it is copied once to the temporary
directory and used from there.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile


def _writable_numba_cache() -> None:
    path = os.environ.get("NUMBA_CACHE_DIR")
    if not path or not os.path.isdir(path) or os.access(path, os.W_OK):
        return
    target = os.path.join(tempfile.gettempdir(), "tdcr-numba-cache")
    if not os.path.isdir(target):
        staging = f"{target}.{os.getpid()}"
        shutil.copytree(path, staging)
        with contextlib.suppress(OSError):  # another process was first: use its copy
            os.rename(staging, target)
        shutil.rmtree(staging, ignore_errors=True)
    os.environ["NUMBA_CACHE_DIR"] = target


_writable_numba_cache()
from tdcr.physics import _kernel as kernel  # noqa: E402, F401 - after the cache directory is usable
