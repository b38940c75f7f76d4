"""ICP (point-to-plane or point-to-point) and its fitness pass, compiled with numba and
run without the GIL.

small_gicp's Python bindings hold the interpreter lock for the whole of a registration
and of a nearest-neighbour batch: while one worker thread refines a pose (the longest
stage of a localization after the network), every other worker waits for the lock
instead of running on its own core. The same computation here releases it, so
concurrent localizations refine in parallel.

- :func:`build_tree`: a KD-tree over a keyframe cloud, stored as flat arrays (leaves of at
  most :data:`LEAF` points, split at the median of the widest axis), the cloud and its
  normals reordered leaf by leaf. Built once per keyframe and cached by the caller.
- :func:`nearest`: the exact nearest tree point to a query point within a radius.
- :meth:`Tree.align`: Gauss-Newton on ``sum (n_q . (T p - q))^2`` (point-to-plane) or
  ``sum |T p - q|^2`` (point-to-point) over the source points whose nearest target
  point ``q`` (normal ``n_q``) lies within the correspondence distance, correspondences
  found again at every iteration; a step is ``T <- Exp(delta) T`` (rotation by
  Rodrigues' formula, then translation), and the loop stops once a step moves less than
  ``stop_m`` and turns less than ``stop_rad``, or after ``max_iterations``.
- :meth:`Tree.fit_quality`: fitness (share of points with a target point within the
  distance) and RMSE of those, over every point, and with normals the mean ``n n^T`` of
  the matched target points' normals (what :func:`sgvloc.core.pose.constraint` reads).

Every sum is over :data:`CHUNKS` fixed ranges of the points, each summed in order and
added in chunk order; on spare cores (:mod:`sgvloc.core.cores`) helper threads compute
some of the chunks, which changes who adds, not what: the same inputs give the same pose
bit for bit at any thread count.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from . import cores

#: points per KD-tree leaf (8, 16, 32, 64 tried: 32 and 64 fastest on the fixture)
LEAF = 32
#: depth bound of the search stack (a median split halves every level: 2^64 points)
_STACK = 64
#: the points' share of the sums: fixed ranges, added in order, whichever threads
#: compute them (:func:`sgvloc.core.cores.split`)
CHUNKS = 8


@njit(cache=True, nogil=True)
def build_tree(pts: np.ndarray):  # pragma: no cover - compiled
    """KD-tree of ``pts`` ``[M, 3]`` float64: ``(order, lo, hi, axis, split, left, right)``
    where node ``k`` covers ``order[lo[k]:hi[k]]``, ``axis[k]`` is -1 for a leaf, and the
    left child holds the points with coordinate <= ``split[k]`` on ``axis[k]``."""
    m = pts.shape[0]
    order = np.arange(m)
    cap = 2 * (m // (LEAF // 2) + 1)  # leaves hold at least LEAF // 2 points
    lo = np.empty(cap, np.int64)
    hi = np.empty(cap, np.int64)
    axis = np.full(cap, -1, np.int64)
    split = np.zeros(cap, np.float64)
    left = np.full(cap, -1, np.int64)
    right = np.full(cap, -1, np.int64)
    lo[0], hi[0] = 0, m
    nodes = 1
    todo = np.empty(cap, np.int64)
    todo[0] = 0
    top = 1
    while top > 0:
        top -= 1
        k = todo[top]
        a, b = lo[k], hi[k]
        if b - a <= LEAF:
            continue
        best, width = 0, -1.0
        for d in range(3):
            vmin, vmax = np.inf, -np.inf
            for i in range(a, b):
                v = pts[order[i], d]
                vmin = min(vmin, v)
                vmax = max(vmax, v)
            if vmax - vmin > width:
                best, width = d, vmax - vmin
        sub = order[a:b].copy()
        keys = np.empty(b - a, np.float64)
        for i in range(b - a):
            keys[i] = pts[sub[i], best]
        sort = np.argsort(keys, kind="mergesort")  # stable: the same tree every time
        for i in range(b - a):
            order[a + i] = sub[sort[i]]
        mid = a + (b - a) // 2
        axis[k], split[k] = best, pts[order[mid - 1], best]
        lo[nodes], hi[nodes], lo[nodes + 1], hi[nodes + 1] = a, mid, mid, b
        todo[top], todo[top + 1] = nodes, nodes + 1
        top += 2
        left[k], right[k] = nodes, nodes + 1
        nodes += 2
    return order, lo[:nodes], hi[:nodes], axis[:nodes], split[:nodes], left[:nodes], right[:nodes]


@njit(cache=True, nogil=True)
def nearest(tp, lo, hi, axis, split, left, right, x, y, z, r2):  # pragma: no cover
    """(index into ``tp``, squared distance) of the tree point nearest to ``(x, y, z)``
    among those within squared distance ``r2``; (-1, inf) when there is none. ``tp`` is
    the cloud in tree order (``pts[order]``)."""
    stack = np.empty(_STACK, np.int64)
    gaps = np.empty(_STACK, np.float64)
    return _nearest(tp, lo, hi, axis, split, left, right, x, y, z, r2, stack, gaps)


@njit(cache=True, nogil=True)
def _nearest(tp, lo, hi, axis, split, left, right, x, y, z, r2, stack, gaps):  # pragma: no cover
    """:func:`nearest` with the caller's search stack (``stack`` nodes, ``gaps`` their
    squared distances to the query's slab), so that a loop over points allocates once."""
    best_i, best = -1, np.inf
    stack[0], gaps[0] = 0, 0.0
    top = 1
    while top > 0:
        top -= 1
        k, gap = stack[top], gaps[top]
        if gap > r2 or gap >= best:
            continue
        d = axis[k]
        if d < 0:
            for i in range(lo[k], hi[k]):
                dx, dy, dz = tp[i, 0] - x, tp[i, 1] - y, tp[i, 2] - z
                s = dx * dx + dy * dy + dz * dz
                if s < best:
                    best_i, best = i, s
            continue
        q = x if d == 0 else (y if d == 1 else z)
        diff = q - split[k]
        near, far = (left[k], right[k]) if diff <= 0.0 else (right[k], left[k])
        stack[top], gaps[top] = far, max(gap, diff * diff)
        stack[top + 1], gaps[top + 1] = near, gap
        top += 2
    if best > r2:
        return -1, np.inf
    return best_i, best


@njit(cache=True, nogil=True)
def _match(tp, lo, hi, axis, split, left, right, pts, i, T, r2, stack, gaps):  # pragma: no cover
    """Point ``pts[i]`` moved by ``T`` and its nearest tree point within ``sqrt(r2)``:
    ``(x, y, z, index into tp or -1, squared distance)``."""
    p0, p1, p2 = pts[i, 0], pts[i, 1], pts[i, 2]
    x = T[0, 0] * p0 + T[0, 1] * p1 + T[0, 2] * p2 + T[0, 3]
    y = T[1, 0] * p0 + T[1, 1] * p1 + T[1, 2] * p2 + T[1, 3]
    z = T[2, 0] * p0 + T[2, 1] * p1 + T[2, 2] * p2 + T[2, 3]
    j, s = _nearest(tp, lo, hi, axis, split, left, right, x, y, z, r2, stack, gaps)
    return x, y, z, j, s


@njit(cache=True, nogil=True)
def _fit_chunk(
    tp, tn, lo, hi, axis, split, left, right, pts, T, r2, start, stop
):  # pragma: no cover
    """Over ``pts[start:stop]`` moved by ``T``: (points with a tree point within
    ``sqrt(r2)``, sum of their squared distances, ``[6]`` sum of ``n n^T`` over their
    matched tree points' normals ``tn``: xx, yy, zz, xy, xz, yz)."""
    inliers, total = 0, 0.0
    moment = np.zeros(6)
    stack, gaps = np.empty(_STACK, np.int64), np.empty(_STACK, np.float64)
    for i in range(start, stop):
        _x, _y, _z, j, s = _match(tp, lo, hi, axis, split, left, right, pts, i, T, r2, stack, gaps)
        if j >= 0:
            inliers += 1
            total += s
            nx, ny, nz = tn[j, 0], tn[j, 1], tn[j, 2]
            moment[0] += nx * nx
            moment[1] += ny * ny
            moment[2] += nz * nz
            moment[3] += nx * ny
            moment[4] += nx * nz
            moment[5] += ny * nz
    return inliers, total, moment


@njit(cache=True, nogil=True)
def _exp_rotation(w0, w1, w2):  # pragma: no cover - compiled
    """Rotation matrix of the rotation vector ``w`` (Rodrigues)."""
    theta = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    K = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])
    if theta < 1e-12:
        return np.eye(3) + K
    K = K / theta
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


@njit(cache=True, nogil=True)
def _compose(R, t0, t1, t2, T):  # pragma: no cover - compiled
    """``[R | t] @ T`` for a rigid ``T`` [4, 4]."""
    out = np.eye(4)
    for a in range(3):
        for b in range(4):
            out[a, b] = R[a, 0] * T[0, b] + R[a, 1] * T[1, b] + R[a, 2] * T[2, b]
    out[0, 3] += t0
    out[1, 3] += t1
    out[2, 3] += t2
    return out


@njit(cache=True, nogil=True)
def _accumulate(H, g, J, e):  # pragma: no cover - compiled
    """Add one residual ``e`` with Jacobian row ``J`` to the normal equations (upper
    triangle of ``H``)."""
    for a in range(6):
        g[a] += J[a] * e
        for b in range(a, 6):
            H[a, b] += J[a] * J[b]


@njit(cache=True, nogil=True)
def _normal_equations(
    tp, tn, lo, hi, axis, split, left, right, src, T, plane, r2, start, stop
):  # pragma: no cover - compiled
    """``(H, g, matched)`` of one Gauss-Newton step over ``src[start:stop]`` under ``T``:
    the upper triangle of ``sum J^T J``, ``sum J^T e`` and the number of points with a
    correspondence, point-to-plane if ``plane`` else point-to-point."""
    H = np.zeros((6, 6))
    g = np.zeros(6)
    J = np.empty(6)
    matched = 0
    stack, gaps = np.empty(_STACK, np.int64), np.empty(_STACK, np.float64)
    for i in range(start, stop):
        x, y, z, j, _s = _match(tp, lo, hi, axis, split, left, right, src, i, T, r2, stack, gaps)
        if j < 0:
            continue
        matched += 1
        if plane:
            n0, n1, n2 = tn[j, 0], tn[j, 1], tn[j, 2]
            e = n0 * (x - tp[j, 0]) + n1 * (y - tp[j, 1]) + n2 * (z - tp[j, 2])
            # d e / d(rotation vector, translation) of T <- Exp(delta) T: (p x n, n)
            J[0], J[1], J[2] = y * n2 - z * n1, z * n0 - x * n2, x * n1 - y * n0
            J[3], J[4], J[5] = n0, n1, n2
            _accumulate(H, g, J, e)
            continue
        # point to point: the three rows of [-[p]x | I] against p - q
        J[0], J[1], J[2], J[3], J[4], J[5] = 0.0, z, -y, 1.0, 0.0, 0.0
        _accumulate(H, g, J, x - tp[j, 0])
        J[0], J[1], J[2], J[3], J[4], J[5] = -z, 0.0, x, 0.0, 1.0, 0.0
        _accumulate(H, g, J, y - tp[j, 1])
        J[0], J[1], J[2], J[3], J[4], J[5] = y, -x, 0.0, 0.0, 0.0, 1.0
        _accumulate(H, g, J, z - tp[j, 2])
    return H, g, matched


@njit(cache=True, nogil=True)
def _step(H, g, T, right=False):  # pragma: no cover - compiled
    """Solve the step of the summed normal equations and apply it: ``(T', moved m,
    turned rad)``; ``T <- Exp(delta) T``, or with ``right`` ``T <- T Exp(delta)`` (a step
    in the source's frame)."""
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
        H[a, a] += 1e-9  # keeps a degenerate system (a plane alone) solvable
    delta = -np.linalg.solve(H, g)
    R = _exp_rotation(delta[0], delta[1], delta[2])
    moved = np.sqrt(delta[3] ** 2 + delta[4] ** 2 + delta[5] ** 2)
    turned = np.sqrt(delta[0] ** 2 + delta[1] ** 2 + delta[2] ** 2)
    if right:  # T [R | t] = [T_R R | T_R t + T_t]
        step = _compose(R, delta[3], delta[4], delta[5], np.eye(4))
        return T @ step, moved, turned
    return _compose(R, delta[3], delta[4], delta[5], T), moved, turned


@njit(cache=True, nogil=True)
def _fit_serial(tp, tn, lo, hi, axis, split, left, right, pts, T, r2, bounds):  # pragma: no cover
    """:func:`_fit_chunk` over every chunk of ``bounds`` ``[k, 2]``, added in chunk order
    (the same arithmetic as :meth:`Tree.fit_quality` on several threads)."""
    inliers, total = 0, 0.0
    moment = np.zeros(6)
    for c in range(bounds.shape[0]):
        n, s, m = _fit_chunk(
            tp, tn, lo, hi, axis, split, left, right, pts, T, r2, bounds[c, 0], bounds[c, 1]
        )
        inliers += n
        total += s
        moment += m
    return inliers, total, moment


@njit(cache=True, nogil=True)
def _align_serial(
    tp,
    tn,
    lo,
    hi,
    axis,
    split,
    left,
    right,
    src,
    T0,
    plane,
    r2,
    bounds,
    max_iterations,
    stop_m,
    stop_rad,
):  # pragma: no cover - compiled
    """The whole of :meth:`Tree.align` on the calling thread, lock released once: the
    same chunk sums in the same order as with helper threads."""
    T = T0.copy()
    iterations = 0
    for _ in range(max_iterations):
        iterations += 1
        H, g, matched = np.zeros((6, 6)), np.zeros(6), 0
        for c in range(bounds.shape[0]):
            a, b = bounds[c, 0], bounds[c, 1]
            h, v, m = _normal_equations(
                tp, tn, lo, hi, axis, split, left, right, src, T, plane, r2, a, b
            )
            H += h
            g += v
            matched += m
        if matched == 0:
            break
        T, moved, turned = _step(H, g, T)
        if moved < stop_m and turned < stop_rad:
            break
    return T, iterations


def _chunks(n: int) -> list[tuple[int, int]]:
    """:data:`CHUNKS` index ranges over ``n`` points (fewer when there are fewer points)."""
    k = max(1, min(CHUNKS, n))
    return [(n * c // k, n * (c + 1) // k) for c in range(k)]


class Tree:
    """A keyframe cloud ready for :meth:`align` and :meth:`fit_quality`:
    its KD-tree and, with ``normals``, its normals, all in tree order."""

    def __init__(self, cloud: np.ndarray, normals: np.ndarray | None = None) -> None:
        pts = np.ascontiguousarray(cloud, dtype=np.float64)
        order, *self.nodes = build_tree(pts)
        self.points = np.ascontiguousarray(pts[order])
        self.normals = (
            None if normals is None else np.ascontiguousarray(normals[order], dtype=np.float64)
        )

    def fit_quality(
        self, pts: np.ndarray, T: np.ndarray, max_distance: float
    ) -> tuple[float, float, np.ndarray | None]:
        """(fitness, RMSE, moment) of ``pts`` ``[N, 3]`` moved by ``T``: the share with a
        tree point within ``max_distance``, the root mean squared distance of those (0 if
        none), and the ``[3, 3]`` mean of ``n n^T`` over their nearest tree points'
        normals (None without normals or matches)."""
        p = np.ascontiguousarray(pts, dtype=np.float64)
        T = np.ascontiguousarray(T, dtype=np.float64)
        r2 = max_distance * max_distance
        normals = self.points if self.normals is None else self.normals
        chunks = _chunks(len(p))
        if cores.threads() == 1:  # one call, the lock released once
            bounds = np.array(chunks, dtype=np.int64)
            inliers, total, m = _fit_serial(self.points, normals, *self.nodes, p, T, r2, bounds)
        else:
            parts = cores.split(
                lambda c: _fit_chunk(self.points, normals, *self.nodes, p, T, r2, c[0], c[1]),
                chunks,
            )
            inliers, total, m = 0, 0.0, np.zeros(6)
            for n, s, mc in parts:
                inliers += n
                total += s
                m = m + mc
        if inliers == 0:
            return 0.0, 0.0, None
        moment = None
        if self.normals is not None:
            xx, yy, zz, xy, xz, yz = m / inliers
            moment = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
        return inliers / len(p), float(np.sqrt(total / inliers)), moment

    def align(
        self,
        src: np.ndarray,
        T0: np.ndarray,
        max_distance: float,
        max_iterations: int,
        stop_m: float,
        stop_rad: float,
        plane: bool = True,
    ) -> tuple[np.ndarray, int]:
        """ICP of ``src`` ``[N, 3]`` onto this cloud from ``T0``: ``(T, iterations)`` (see
        the module docstring)."""
        if plane and self.normals is None:
            raise ValueError("point-to-plane ICP needs the target's normals")
        src = np.ascontiguousarray(src, dtype=np.float64)
        normals = self.points if self.normals is None else self.normals
        T = np.ascontiguousarray(T0, dtype=np.float64).copy()
        r2 = max_distance * max_distance
        chunks = _chunks(len(src))
        if cores.threads() == 1:  # one call: a busy service re-takes the lock once
            T, iterations = _align_serial(
                self.points,
                normals,
                *self.nodes,
                src,
                T,
                plane,
                r2,
                np.array(chunks, dtype=np.int64),
                max_iterations,
                stop_m,
                stop_rad,
            )
            return T, int(iterations)
        iterations = 0
        for _ in range(max_iterations):
            iterations += 1
            T_now = T
            parts = cores.split(
                lambda c, T_now=T_now: _normal_equations(
                    self.points, normals, *self.nodes, src, T_now, plane, r2, c[0], c[1]
                ),
                chunks,
            )
            H, g = np.zeros((6, 6)), np.zeros(6)
            for h, v, _ in parts:
                H += h
                g += v
            if sum(m for _, _, m in parts) == 0:
                break
            T, moved, turned = _step(H, g, T)
            if moved < stop_m and turned < stop_rad:
                break
        return T, iterations


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel on a tiny cloud."""
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1.0, 1.0, size=(40, 3))
    normals = np.tile([0.0, 0.0, 1.0], (40, 1))
    tree = Tree(pts, normals)
    for plane in (True, False):
        tree.align(pts[:10], np.eye(4), 1.0, 2, 1e-3, 1e-3, plane)
    tree.fit_quality(pts, np.eye(4), 1.0)
