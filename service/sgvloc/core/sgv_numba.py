"""SpectralGV on CPU with numba: fused kernels that never hold more than one ``M`` per thread.

The semantics are those of :func:`sgvloc.core.sgv.sgv_scores` (the SpectralGV paper,
eq. 2): for each candidate,
``M_ij = max(0, 1 - (||s_i - s_j|| - ||d_i - d_j||)^2 / d_thr^2)``, ``M_ii`` the
configured diagonal, ``v`` = ``iterations`` normalised power steps from all-ones, and
``lambda = v^T M v``. Masked correspondences are dropped before scoring (each candidate is
compacted to its valid rows), so a padded candidate scores exactly as it would alone.

Two paths, chosen per candidate by the size of its ``M``:

- **dense** (``m^2`` float32 per thread within the budget): one thread per candidate
  (``prange`` over candidates) builds ``M`` row by row (each row one vectorised pass over
  structure-of-arrays coordinates) and runs the matrix products on it while it is hot in
  cache. ``M v`` is accumulated as ``sum_i v_i M[i, :]`` (``M`` is exactly symmetric:
  ``(a - b)^2 == (b - a)^2`` in floating point), i.e. vectorised row updates without any
  floating-point reduction, so no ``fastmath`` is needed and the result does not depend
  on the number of threads. Batches of at most :data:`SERIAL_MAX_ENTRIES` entries run
  on the calling thread (no parallel region to stall on a busy machine).
- **free** (matrix-free, for large ``m`` such as 15000): every product rebuilds the rows;
  rows are split into a fixed number of chunks (``prange``), each accumulating into its
  own vector, summed in a fixed order afterwards: deterministic whatever the thread count,
  ``O(chunks * m)`` memory.

Accumulation is in float64 (``y``, ``v``, ``lambda``); ``M`` entries are float32, as in
the torch path (float64 entries measured 2-2.5x slower; float32 lengths of points 30 m
away are good to ~2e-6 m, so an entry near ``d_thr`` is good to ~2e-5, and a score to
1e-5 relative once a few correspondences average it out). Compilation is cached on
disk (``cache=True``); :func:`warm_up` compiles or loads every kernel on tiny inputs so
that no request pays for it.

Serial kernels (small batches, the usual case) run concurrently from any number of
threads. Parallel kernels take a lock only under numba's ``workqueue`` threading layer
(the fallback where neither OpenMP nor TBB is available), which must not be entered from
two threads at once; under OpenMP (tried first, see below) nothing is serialised, so one
large request never holds up the others.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time

# parallel kernels on OpenMP first (as Open3D and FAISS): numba's default order tries TBB
# first, which warns at the first parallel call where the system's TBB is too old. Read
# when the first parallel kernel launches; a setting of the user's wins.
_LAYER_ORDER = "omp workqueue tbb"
_USER_ORDER = "NUMBA_THREADING_LAYER_PRIORITY" in os.environ
os.environ.setdefault("NUMBA_THREADING_LAYER_PRIORITY", _LAYER_ORDER)

import numpy as np  # noqa: E402
from numba import config as numba_config  # noqa: E402
from numba import get_num_threads, njit, prange, threading_layer  # noqa: E402

if not _USER_ORDER:  # numba may have read its configuration before (imported elsewhere)
    numba_config.THREADING_LAYER_PRIORITY = _LAYER_ORDER.split()

log = logging.getLogger(__name__)

#: Row chunks of the matrix-free path (fixed, so results do not depend on thread count).
FREE_CHUNKS = 16

#: Dense batches with at most this many entries of ``M`` in all run single-threaded
#: (about 1-2 ms of work on one core: k = 20 at n = 256 is 1.3M).
SERIAL_MAX_ENTRIES = 2_000_000

#: serialises parallel kernels under the workqueue layer only (see the module docstring)
_LOCK = threading.Lock()
_WARM = False


def _parallel_guard() -> contextlib.AbstractContextManager:
    """The lock a parallel kernel must hold: none unless the layer is ``workqueue``."""
    try:
        layer = threading_layer()
    except ValueError:  # no parallel kernel has run yet; the first one picks the layer
        return _LOCK
    return _LOCK if layer == "workqueue" else contextlib.nullcontext()


@njit(cache=True, nogil=True)
def _row(sx, sy, sz, dx, dy, dz, i, inv_d2, diag, out):  # pragma: no cover - jitted
    """``out[j] = M_ij`` for all j (float32): one vectorised pass."""
    xi, yi, zi = sx[i], sy[i], sz[i]
    ui, vi, wi = dx[i], dy[i], dz[i]
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for j in range(sx.shape[0]):
        a = np.sqrt((sx[j] - xi) ** 2 + (sy[j] - yi) ** 2 + (sz[j] - zi) ** 2)
        b = np.sqrt((dx[j] - ui) ** 2 + (dy[j] - vi) ** 2 + (dz[j] - wi) ** 2)
        e = a - b
        val = one - e * e * inv_d2
        out[j] = val if val > zero else zero
    out[i] = diag


@njit(cache=True, nogil=True)
def _compact(src, dst, mask, b):  # pragma: no cover - jitted
    """Valid rows of candidate ``b`` as structure-of-arrays ``[6, m]`` plus their indices."""
    n = mask.shape[1]
    m = 0
    for j in range(n):
        if mask[b, j]:
            m += 1
    pts = np.empty((6, m), np.float32)
    idx = np.empty(m, np.int64)
    t = 0
    for j in range(n):
        if mask[b, j]:
            for a in range(3):
                pts[a, t] = src[b, j, a]
                pts[3 + a, t] = dst[b, j, a]
            idx[t] = j
            t += 1
    return pts, idx


@njit(cache=True, nogil=True)
def _normalise(y, v):  # pragma: no cover - jitted
    """``v = y / ||y||`` (``v = 0`` when ``y`` vanishes)."""
    nrm = 0.0
    for i in range(y.shape[0]):
        nrm += y[i] * y[i]
    nrm = np.sqrt(nrm)
    for i in range(y.shape[0]):
        v[i] = y[i] / nrm if nrm > 0.0 else 0.0


@njit(cache=True, nogil=True)
def _dense_one(pts, inv_d2, diag, iterations, v):  # pragma: no cover - jitted
    """Power iteration on one candidate with ``M`` built once; returns ``lambda``."""
    m = pts.shape[1]
    sx, sy, sz, dx, dy, dz = pts[0], pts[1], pts[2], pts[3], pts[4], pts[5]
    mat = np.empty((m, m), np.float32)  # [m, m]
    for i in range(m):
        _row(sx, sy, sz, dx, dy, dz, i, inv_d2, diag, mat[i])
    y = np.zeros(m, np.float64)  # [m]
    for i in range(m):
        v[i] = 1.0
    lam = 0.0
    for it in range(iterations + 1):
        # y = M v = sum_i v_i M[i, :] (M symmetric): row updates, no reduction.
        y[:] = 0.0
        for i in range(m):
            vi = v[i]
            if vi == 0.0:
                continue
            row = mat[i]
            for j in range(m):
                y[j] += vi * row[j]
        if it == iterations:
            for i in range(m):
                lam += v[i] * y[i]
            break
        _normalise(y, v)
    return lam


@njit(cache=True, nogil=True)
def _dense_candidate(src, dst, mask, b, inv_d2, diag, iterations, lam, v_out):  # pragma: no cover
    """Candidate ``b`` on the dense path: writes ``lam[b]`` and ``v_out[b]``."""
    pts, idx = _compact(src, dst, mask, b)
    m = idx.shape[0]
    if m == 0:
        lam[b] = 0.0
        return
    v = np.empty(m, np.float64)
    lam[b] = _dense_one(pts, inv_d2, diag, iterations, v)
    for t in range(m):
        v_out[b, idx[t]] = v[t]


@njit(parallel=True, cache=True, nogil=True)
def _dense_batch(src, dst, mask, dense, inv_d2, diag, iterations, lam, v_out):  # pragma: no cover
    """Candidates with ``dense[b]``, one thread each."""
    for b in prange(src.shape[0]):
        if dense[b]:
            _dense_candidate(src, dst, mask, b, inv_d2, diag, iterations, lam, v_out)


@njit(cache=True, nogil=True)
def _dense_batch_serial(
    src, dst, mask, dense, inv_d2, diag, iterations, lam, v_out
):  # pragma: no cover
    """:func:`_dense_batch` on the calling thread only (small batches)."""
    for b in range(src.shape[0]):
        if dense[b]:
            _dense_candidate(src, dst, mask, b, inv_d2, diag, iterations, lam, v_out)


@njit(parallel=True, cache=True, nogil=True)
def _free_matvec(pts, inv_d2, diag, v, y, parts, buf):  # pragma: no cover - jitted
    """``y = M v`` without storing ``M``: row chunks in parallel, then their sum."""
    m = pts.shape[1]
    chunks = parts.shape[0]
    sx, sy, sz, dx, dy, dz = pts[0], pts[1], pts[2], pts[3], pts[4], pts[5]
    for c in prange(chunks):
        part = parts[c]
        row = buf[c]
        part[:] = 0.0
        r0 = (c * m) // chunks
        r1 = ((c + 1) * m) // chunks
        for i in range(r0, r1):
            vi = v[i]
            if vi == 0.0:
                continue
            _row(sx, sy, sz, dx, dy, dz, i, inv_d2, diag, row)
            for j in range(m):
                part[j] += vi * row[j]
    # Fixed-order sum of the chunks, outside the parallel region: a second region per
    # product costs more than it saves on a busy 2-core machine.
    for j in range(m):  # plain loops: an array expression would be another region
        y[j] = parts[0, j]
    for c in range(1, chunks):
        part = parts[c]
        for j in range(m):
            y[j] += part[j]


def _free_one(
    pts: np.ndarray, inv_d2: np.float32, diag: np.float32, iterations: int
) -> tuple[float, np.ndarray]:
    """Matrix-free power iteration on one compacted candidate ``pts [6, m]``."""
    m = pts.shape[1]
    chunks = max(1, min(FREE_CHUNKS, m))
    parts = np.empty((chunks, m), np.float64)  # [chunks, m]
    buf = np.empty((chunks, m), np.float32)  # [chunks, m] one row of M per chunk
    v = np.ones(m, np.float64)  # [m]
    y = np.empty(m, np.float64)  # [m]
    for _ in range(iterations):
        _free_matvec(pts, inv_d2, diag, v, y, parts, buf)
        norm = float(np.sqrt(np.dot(y, y)))
        v = y / norm if norm > 0.0 else np.zeros(m)
    _free_matvec(pts, inv_d2, diag, v, y, parts, buf)
    return float(np.dot(v, y)), v


def dense_fits(m: int, budget_bytes: int) -> bool:
    """Whether a candidate of ``m`` correspondences takes the dense path: one float32
    ``M [m, m]`` per thread must fit in ``budget_bytes``."""
    return m * m * 4 * get_num_threads() <= budget_bytes


def power_iteration(
    src: np.ndarray,
    dst: np.ndarray,
    mask: np.ndarray,
    d_thr: float,
    iterations: int,
    diag: float,
    budget_bytes: int,
) -> tuple[np.ndarray, np.ndarray, str]:
    """``lambda [k]`` (float64), ``v [k, n]`` (float64, 0 at masked entries) and the path.

    ``src``/``dst`` are ``[k, n, 3]`` float32 (finite where ``mask``), ``mask`` ``[k, n]``
    bool, already validated by the caller. The path is ``"dense"`` if every candidate
    took the dense path, else ``"chunked"``.
    """
    k, n = mask.shape
    src = np.ascontiguousarray(src, dtype=np.float32)
    dst = np.ascontiguousarray(dst, dtype=np.float32)
    mask = np.ascontiguousarray(mask, dtype=np.bool_)
    counts = mask.sum(axis=1)  # [k]
    dense = np.array([dense_fits(int(m), budget_bytes) for m in counts], dtype=np.bool_)
    inv_d2 = np.float32(1.0 / (d_thr * d_thr))
    dg = np.float32(diag)
    lam = np.zeros(k, np.float64)  # [k]
    v = np.zeros((k, n), np.float64)  # [k, n]
    # Small batches run on the calling thread: a parallel region is only as fast as its
    # slowest thread, and on a busy 2-core machine a descheduled one costs a time slice
    # (measured: ~8 ms, dwarfing the work below this size).
    work = int((counts[dense].astype(np.int64) ** 2).sum())
    parallel = work > SERIAL_MAX_ENTRIES
    batch = _dense_batch if parallel else _dense_batch_serial
    with _parallel_guard() if parallel or not dense.all() else contextlib.nullcontext():
        if dense.any():
            batch(src, dst, mask, dense, inv_d2, dg, int(iterations), lam, v)
        for b in np.flatnonzero(~dense):
            pts, idx = _compact(src, dst, mask, b)
            lam[b], vb = _free_one(pts, inv_d2, dg, int(iterations))
            v[b, idx] = vb
    return lam, v, "dense" if dense.all() else "chunked"


def warm_up() -> float:
    """Compile (or load from the on-disk cache) every kernel; returns the seconds taken.

    Call once at start-up (the service and the CLI do) so that the first request does
    not pay for compilation. Idempotent and cheap after the first call.
    """
    global _WARM
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    src = rng.uniform(-5, 5, size=(2, 8, 3)).astype(np.float32)
    dst = src.copy()
    mask = np.ones((2, 8), dtype=np.bool_)
    mask[1, 3] = False
    power_iteration(src, dst, mask, 0.4, 2, 1.0, 2**40)  # dense, serial
    big = np.zeros((2, 1100, 3), dtype=np.float32)
    power_iteration(big, big, np.ones((2, 1100), np.bool_), 0.4, 1, 1.0, 2**40)  # parallel
    power_iteration(src, dst, mask, 0.4, 2, 0.0, 0)  # matrix-free
    took = time.perf_counter() - t0
    if not _WARM:
        log.info("sgv numba kernels ready in %.2f s", took)
    _WARM = True
    return took
