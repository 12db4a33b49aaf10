"""Fused per-frame kernels of the reconstruction (numba): one pass where numpy made several.

Each kernel does exactly the float32 operations, in the same order, as the numpy expression
it replaces (no ``fastmath``, so no reassociation or fused multiply-add), so the results are
the same bit for bit, except the zero-level plane, solved from its 3 x 3 normal equations
instead of an SVD least squares (float64 rounding; after the cast to float32, ~1e-7 mm).
The straightforward numpy versions are kept as the independent reference in
``lab/reconstruction_reference.py``; tests/remote_site/test_reconstruction_fast_path.py
checks each kernel against it over random inputs.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = [
    "DIV_DCT",
    "DIV_DST",
    "DIV_FFT",
    "change_kernel",
    "clipped_counts",
    "divergence_kernel",
    "evidence_kernel",
    "free_subsample_kernel",
    "plane_normal_equations",
    "ratio_kernel",
    "subtract_plane_kernel",
    "tridiagonal_columns_kernel",
    "unchanged_kernel",
]

#: solver codes of :func:`divergence_kernel`
DIV_DCT, DIV_DST, DIV_FFT = 0, 1, 2


@njit(cache=True, nogil=True)
def ratio_kernel(frame: np.ndarray, background: np.ndarray,
                 step: int) -> np.ndarray:  # pragma: no cover - compiled
    """``frame[::step, ::step] / max(background[::step, ::step], 1)`` as a (3, n) float32
    array (one row per channel)."""
    nr = (frame.shape[0] + step - 1) // step
    nc = (frame.shape[1] + step - 1) // step
    ratio = np.empty((3, nr * nc), np.float32)
    one = np.float32(1.0)
    k = 0
    for i in range(nr):
        for j in range(nc):
            for v in range(3):
                ratio[v, k] = frame[i * step, j * step, v] / max(background[i * step, j * step, v],
                                                                 one)
            k += 1
    return ratio


@njit(cache=True, nogil=True)
def unchanged_kernel(ratio: np.ndarray, gain: np.ndarray,
                     tolerance: float) -> np.ndarray:  # pragma: no cover - compiled
    """The columns of ``ratio`` whose every channel is within ``tolerance * gain`` of the gain
    (``|ratio - gain| < tolerance * gain``, float32), as a (3, m) array."""
    n = ratio.shape[1]
    tol = np.empty(3, np.float32)
    for v in range(3):
        tol[v] = np.float32(tolerance) * gain[v]
    keep = np.empty(n, np.bool_)
    count = 0
    for k in range(n):
        ok = (abs(ratio[0, k] - gain[0]) < tol[0]) & (abs(ratio[1, k] - gain[1]) < tol[1]) \
            & (abs(ratio[2, k] - gain[2]) < tol[2])
        keep[k] = ok
        count += ok
    out = np.empty((3, count), np.float32)
    m = 0
    for k in range(n):
        if keep[k]:
            for v in range(3):
                out[v, m] = ratio[v, k]
            m += 1
    return out


@njit(cache=True, nogil=True)
def clipped_counts(image: np.ndarray, step: int, saturation: np.float32,
                   black: np.float32) -> tuple[int, int, int]:  # pragma: no cover - compiled
    """On ``image[::step, ::step]`` ((H, W, 3) float32): the number of pixels with a channel
    ``>= saturation``, of pixels with every channel ``<= black``, and of pixels."""
    rows, cols = image.shape[0], image.shape[1]
    saturated = np.int64(0)
    dark = np.int64(0)
    n = np.int64(0)
    for i in range(0, rows, step):
        for j in range(0, cols, step):
            r, g, b = image[i, j, 0], image[i, j, 1], image[i, j, 2]
            saturated += np.int64((r >= saturation) | (g >= saturation) | (b >= saturation))
            dark += np.int64((r <= black) & (g <= black) & (b <= black))
            n += 1
    return int(saturated), int(dark), int(n)


@njit(cache=True, nogil=True)
def change_kernel(frame: np.ndarray, inv_gain: np.ndarray, inv_bg_pct: np.ndarray,
                  out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out = frame * inv_gain * inv_bg_pct - 100`` per channel, float32, one pass.

    All three (H, W, 3) arrays must be C-contiguous: the loop runs over the flat arrays
    (the 3-D indexing kept LLVM from vectorising it: 1.5x slower).
    """
    n = frame.shape[0] * frame.shape[1]
    src = frame.reshape(n * 3)
    inv_bg = inv_bg_pct.reshape(n * 3)
    dst = out.reshape(n * 3)
    hundred = np.float32(100.0)
    g0, g1, g2 = inv_gain[0], inv_gain[1], inv_gain[2]
    for p in range(n):
        k = 3 * p
        dst[k] = src[k] * g0 * inv_bg[k] - hundred
        dst[k + 1] = src[k + 1] * g1 * inv_bg[k + 1] - hundred
        dst[k + 2] = src[k + 2] * g2 * inv_bg[k + 2] - hundred


@njit(cache=True, nogil=True)
def evidence_kernel(change: np.ndarray, evidence_threshold: np.float32,
                    active_threshold: np.float32
                    ) -> tuple[int, np.ndarray]:  # pragma: no cover - compiled
    """Count of pixels whose max-channel |change| exceeds ``evidence_threshold``, and the
    mask of those above ``active_threshold`` (a pixel with a NaN channel is neither, as
    with numpy's NaN-propagating maximum). ``change`` must be C-contiguous (flat loop, as
    in :func:`change_kernel`: half the time of the 3-D indexed one)."""
    rows, cols = change.shape[0], change.shape[1]
    n = rows * cols
    flat = change.reshape(n * 3)
    active = np.empty(n, np.bool_)
    count = np.int64(0)
    for p in range(n):
        a0, a1, a2 = abs(flat[3 * p]), abs(flat[3 * p + 1]), abs(flat[3 * p + 2])
        m = max(max(a0, a1), a2)
        valid = (a0 == a0) & (a1 == a1) & (a2 == a2)
        count += np.int64(valid & (m > evidence_threshold))
        active[p] = valid & (m > active_threshold)
    return int(count), active.reshape(rows, cols)


@njit(cache=True, nogil=True)
def _border_edges(first: np.floating, last: np.floating, half: np.floating, zero: np.floating,
                  solver: int) -> tuple[np.floating, np.floating]:  # pragma: no cover
    """The two border edge slopes of a line whose end pixel slopes are ``first``, ``last``."""
    if solver == DIV_DST:
        return first, last
    if solver == DIV_FFT:
        wrap = half * (last + first)
        return wrap, wrap
    return zero, zero


@njit(cache=True, nogil=True)
def divergence_kernel(gx: np.ndarray, gy: np.ndarray, pitch: np.floating, solver: int,
                      out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Divergence of the edge slopes of ``gx * pitch``, ``gy * pitch`` into ``out``.

    Edges as in ``poisson``: interior edges average the two pixel slopes; the border edges
    are 0 (DCT), the border pixel's slope (DST) or the wrapped average (FFT). Row by row,
    keeping the previous row's edge slopes, with the same float operations as the numpy
    form ``diff(edges_x, axis=1) + diff(edges_y, axis=0)``. A NaN or Inf slope makes the
    divergence non-finite (the caller checks).
    """
    rows, cols = gx.shape
    dtype = out.dtype.type
    half = dtype(0.5)
    zero = dtype(0.0)
    cur = np.empty(cols, out.dtype)   # py of this row
    nxt = np.empty(cols, out.dtype)   # py of the next row
    top = np.empty(cols, out.dtype)   # edge slopes above this row
    ex = np.empty(cols + 1, out.dtype)
    for j in range(cols):
        cur[j] = dtype(gy[0, j]) * pitch
    if rows > 1:
        for j in range(cols):
            nxt[j] = dtype(gy[rows - 1, j]) * pitch
    for j in range(cols):
        top[j] = _border_edges(cur[j], nxt[j], half, zero, solver)[0]
    for i in range(rows):
        # edges along the row
        p_prev = dtype(gx[i, 0]) * pitch
        p_first = p_prev
        for j in range(1, cols):
            p = dtype(gx[i, j]) * pitch
            ex[j] = half * (p_prev + p)
            p_prev = p
        ex[0], ex[cols] = _border_edges(p_first, p_prev, half, zero, solver)
        # edges below the row
        if i + 1 < rows:
            for j in range(cols):
                nxt[j] = dtype(gy[i + 1, j]) * pitch
            for j in range(cols):
                bottom = half * (cur[j] + nxt[j])
                out[i, j] = (ex[j + 1] - ex[j]) + (bottom - top[j])
                top[j] = bottom
                cur[j] = nxt[j]
        else:
            for j in range(cols):
                first = dtype(gy[0, j]) * pitch
                bottom = _border_edges(first, cur[j], half, zero, solver)[1]
                out[i, j] = (ex[j + 1] - ex[j]) + (bottom - top[j])


@njit(cache=True, nogil=True)
def tridiagonal_columns_kernel(rhs: np.ndarray,
                               inv_pivot: np.ndarray) -> None:  # pragma: no cover - compiled
    """Solve ``(T + k_j I) x = rhs[:, j]`` for every column ``j`` in place (float64 inside).

    ``T`` is the tridiagonal second difference along the rows (off-diagonals 1) whose
    diagonal ``inv_pivot`` was factorised for: the Thomas algorithm with unit off-diagonals
    needs only the inverse pivots ``inv_pivot[i, j] = 1 / (b[i, j] - inv_pivot[i - 1, j])``
    (``poisson._column_factors``). Forward: ``y_i = (rhs_i - y_(i-1)) * inv_pivot_i``;
    back: ``x_i = y_i - inv_pivot_i * x_(i+1)``. The recurrences run down the rows with the
    columns as the inner, independent (vectorisable) loop.
    """
    rows, cols = rhs.shape
    acc = np.zeros(cols, np.float64)
    for i in range(rows):
        for j in range(cols):
            value = (np.float64(rhs[i, j]) - acc[j]) * inv_pivot[i, j]
            acc[j] = value
            rhs[i, j] = value
    for j in range(cols):
        acc[j] = 0.0
    for i in range(rows - 1, -1, -1):
        for j in range(cols):
            value = np.float64(rhs[i, j]) - inv_pivot[i, j] * acc[j]
            acc[j] = value
            rhs[i, j] = value


@njit(cache=True, nogil=True)
def free_subsample_kernel(height: np.ndarray, base: np.float32, threshold: np.float32,
                          radius: int, step: int,
                          integral: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """Subsampled (``[::step, ::step]``) mask of pixels with no raised pixel within
    ``radius`` (a (2r+1)^2 square, clipped at the border): the free gel of the zero level.

    Raised = ``height - base > threshold``. Same as dilating the raised mask with a square
    kernel (OpenCV's default border adds nothing) and subsampling, via an integral image
    written into ``integral`` (int32, (rows + 1, cols + 1), scratch).
    """
    rows, cols = height.shape
    integral[0, :] = 0
    integral[:, 0] = 0
    for i in range(rows):
        run = 0
        for j in range(cols):
            run += (height[i, j] - base) > threshold
            integral[i + 1, j + 1] = integral[i, j + 1] + run
    nr = (rows + step - 1) // step
    nc = (cols + step - 1) // step
    free = np.empty((nr, nc), np.bool_)
    for a in range(nr):
        r0 = max(a * step - radius, 0)
        r1 = min(a * step + radius + 1, rows)
        for b in range(nc):
            c0 = max(b * step - radius, 0)
            c1 = min(b * step + radius + 1, cols)
            total = integral[r1, c1] - integral[r0, c1] - integral[r1, c0] + integral[r0, c0]
            free[a, b] = total == 0
    return free


@njit(cache=True, nogil=True)
def plane_normal_equations(sub: np.ndarray, free: np.ndarray,
                           step: int) -> np.ndarray:  # pragma: no cover - compiled
    """Least-squares plane ``c0 + c1 * col + c2 * row`` through ``sub[free]`` (float64).

    ``sub`` is the height subsampled by ``step``; positions are in full-grid pixels. The
    normal equations are solved in coordinates centred on the free points' mean (well
    conditioned) and the result is shifted back.
    """
    nr, nc = free.shape
    n = 0
    mc = 0.0
    mr = 0.0
    for a in range(nr):
        for b in range(nc):
            if free[a, b]:
                n += 1
                mc += b * step
                mr += a * step
    mc /= n
    mr /= n
    scc = 0.0
    scr = 0.0
    srr = 0.0
    sz = 0.0
    scz = 0.0
    srz = 0.0
    for a in range(nr):
        for b in range(nc):
            if free[a, b]:
                c = b * step - mc
                r = a * step - mr
                z = np.float64(sub[a, b])
                scc += c * c
                scr += c * r
                srr += r * r
                sz += z
                scz += c * z
                srz += r * z
    det = scc * srr - scr * scr
    coef = np.empty(3, np.float64)
    if det <= 0.0:  # free points on one line: fit the mean only (lstsq's minimum norm)
        coef[0] = sz / n
        coef[1] = 0.0
        coef[2] = 0.0
        return coef
    c1 = (scz * srr - srz * scr) / det
    c2 = (srz * scc - scz * scr) / det
    coef[1] = c1
    coef[2] = c2
    coef[0] = sz / n - c1 * mc - c2 * mr
    return coef


@njit(cache=True, nogil=True)
def subtract_plane_kernel(height: np.ndarray, c0: np.float32, c1: np.float32, c2: np.float32,
                          threshold: np.float32
                          ) -> tuple[np.ndarray, np.ndarray, bool]:  # pragma: no cover
    """``height - ((c0 + c1 * col) + c2 * row)`` in float32, its ``> threshold`` mask and
    whether every value is finite, in one pass. The finite check is an integer OR of
    ``value - value != 0`` (NaN for NaN and +-Inf), which vectorises; a float running check
    was one dependent operation per pixel (a third of the kernel's time)."""
    rows, cols = height.shape
    out = np.empty((rows, cols), np.float32)
    mask = np.empty((rows, cols), np.bool_)
    bad = np.int32(0)
    zero = np.float32(0.0)
    for i in range(rows):
        ri = c2 * np.float32(i)
        for j in range(cols):
            value = height[i, j] - ((c0 + c1 * np.float32(j)) + ri)
            out[i, j] = value
            mask[i, j] = value > threshold
            bad |= np.int32((value - value) != zero)
    return out, mask, bad == 0
