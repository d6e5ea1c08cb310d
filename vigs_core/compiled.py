"""Whether the compiled CPU kernels (numba: the rasterizer's, Adam's, the dense BA's linearisation) can be used.

numba is a runtime dependency (requirements/runtime.txt), but every kernel has a tensor version beside it (the
reference, and the path for GPU tensors), so an installation without numba still runs.
"""
from __future__ import annotations

import functools
import importlib.util


@functools.cache
def numba_available() -> bool:
    """True when the numba package can be imported."""
    return importlib.util.find_spec("numba") is not None
