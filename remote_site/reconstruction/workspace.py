"""Scratch arrays reused from frame to frame, one set per thread.

A 320 x 240 frame passes through several ~1 MB intermediates (float frame, colour change,
its blur, slopes, divergence, transform). Allocated afresh per frame they may come back from
the kernel as fresh pages, faulted in on first write: whether they do depends on the
allocator's state (numpy's own temporaries were mostly recycled by malloc; the same arrays
allocated inside the compiled kernels were not: about 640 faults per frame, 40 % of a
frame's time, in an intermediate version of this change). Reused buffers are faulted in
once, whatever else the process does. Only intermediates live here: every array a caller
receives is its own.
"""

from __future__ import annotations

import threading

import numpy as np

__all__ = ["Workspace"]


class Workspace:
    """Named scratch arrays, per thread (a reconstructor may serve several threads)."""

    def __init__(self) -> None:
        self._local = threading.local()

    def get(self, name: str, shape: tuple[int, ...], dtype: type | np.dtype) -> np.ndarray:
        """An uninitialised array for ``name``, the same one on every call with this shape
        and dtype from this thread."""
        arrays: dict[tuple, np.ndarray] = self._local.__dict__.setdefault("arrays", {})
        key = (name, shape, np.dtype(dtype).str)
        array = arrays.get(key)
        if array is None:
            if len(arrays) > 32:  # e.g. many pooling factors in turn: keep it bounded
                arrays.clear()
            array = arrays[key] = np.empty(shape, dtype)
        return array
