"""GICP and VGICP of a scan against a submap, compiled with numba and run without the GIL.

Tracking (:mod:`sgvloc.core.tracking`) registers every streamed scan against the map
around its seed. small_gicp's Python binding holds the interpreter lock for the whole of
a registration, so concurrent tracked scans waited for each other; the same computation
here releases it.

- :func:`voxel_centroids`: the centroid of each occupied voxel (a voxel grid filter),
  in the order of the voxels' packed keys.
- :func:`normals`: per point, the direction of least spread of its ``k`` nearest
  neighbours, facing the sensor (the normals of point-to-plane ICP's targets).
- :func:`covariances`: per point, the covariance of its ``k`` nearest neighbours,
  regularised to a plane (eigenvalues ``EPS, 1, 1`` on its eigenvectors, as GICP does):
  ``I - (1 - EPS) n n^T`` with ``n`` the direction of least spread.
- :class:`GaussianVoxels`: a cloud's Gaussian voxels (the mean of the points in each
  voxel and the mean of their covariances), looked up by the voxel a point falls in.
- :meth:`Cloud.align` / :meth:`GaussianVoxels.align` (:func:`_register`): Gauss-Newton
  on the GICP cost ``sum r^T (C_q + R C_p R^T)^-1 r`` with ``r = T p - q``, the target
  point ``q`` the nearest submap point within the correspondence distance (GICP) or the
  mean of the voxel ``T p`` falls in, if that mean is within it (VGICP); a step is
  ``T <- Exp(delta) T`` and the loop stops once a step moves less than ``stop_m`` and
  turns less than ``stop_rad``, or after ``max_iterations``. Each returns the pose, the
  iterations, the Hessian of the last linearisation (rotation first, then translation)
  and its number of correspondences.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from .icp_numba import _STACK, _nearest, _step, build_tree

#: the smallest eigenvalue of a regularised covariance (the others are 1)
EPS = 1e-3
#: a point needs this many neighbours for a covariance of its own (else the identity)
MIN_NEIGHBOURS = 5
#: a key packs a voxel's three indices, counted from the cloud's lowest voxel, in 21 bits
#: each: a cloud may span up to 2^21 voxels per axis (629 km at 0.3 m), wherever it lies
_SPAN = 1 << 21


@njit(cache=True, nogil=True)
def _key(ix, iy, iz, origin):  # pragma: no cover - compiled
    """The key of voxel ``(ix, iy, iz)`` counted from ``origin`` [3]; -1 outside the span."""
    dx, dy, dz = ix - origin[0], iy - origin[1], iz - origin[2]
    if dx < 0 or dy < 0 or dz < 0 or dx >= _SPAN or dy >= _SPAN or dz >= _SPAN:
        return np.int64(-1)
    return (dx << 42) | (dy << 21) | dz


@njit(cache=True, nogil=True)
def _keys(pts, res):  # pragma: no cover - compiled
    """(keys [N], origin [3]: the lowest voxel index per axis) of the points' voxels."""
    n = pts.shape[0]
    cells = np.empty((n, 3), np.int64)
    origin = np.zeros(3, np.int64)
    for i in range(n):
        for a in range(3):
            cells[i, a] = np.int64(np.floor(pts[i, a] / res))
            if i == 0 or cells[i, a] < origin[a]:
                origin[a] = cells[i, a]
    keys = np.empty(n, np.int64)
    for i in range(n):
        keys[i] = _key(cells[i, 0], cells[i, 1], cells[i, 2], origin)
        if keys[i] < 0:
            raise ValueError("the cloud spans more than 2^21 voxels along an axis")
    return keys, origin


@njit(cache=True, nogil=True)
def voxel_centroids(pts, res):  # pragma: no cover - compiled
    """The centroids ``[V, 3]`` of the points ``pts`` ``[N, 3]`` float64 in each voxel of
    size ``res``, in the order of the voxels' keys (the same cloud gives the same array)."""
    keys, _origin = _keys(pts, res)
    order = np.argsort(keys, kind="mergesort")
    out = np.empty((pts.shape[0], 3))
    v, i, n = 0, 0, pts.shape[0]
    while i < n:
        j, sx, sy, sz = i, 0.0, 0.0, 0.0
        while j < n and keys[order[j]] == keys[order[i]]:
            p = order[j]
            sx += pts[p, 0]
            sy += pts[p, 1]
            sz += pts[p, 2]
            j += 1
        c = j - i
        out[v, 0], out[v, 1], out[v, 2] = sx / c, sy / c, sz / c
        v += 1
        i = j
    return out[:v].copy()


@njit(cache=True, nogil=True)
def _knn(tp, lo, hi, axis, split, left, right, x, y, z, bi, bd, stack, gaps):  # pragma: no cover
    """The ``len(bi)`` tree points nearest to ``(x, y, z)``, nearest first, into ``bi``
    (indices into ``tp``) and ``bd`` (squared distances); returns how many were found."""
    k = bi.shape[0]
    for a in range(k):
        bi[a], bd[a] = -1, np.inf
    found = 0
    stack[0], gaps[0] = 0, 0.0
    top = 1
    while top > 0:
        top -= 1
        node, gap = stack[top], gaps[top]
        if gap >= bd[k - 1]:
            continue
        d = axis[node]
        if d < 0:
            for i in range(lo[node], hi[node]):
                dx, dy, dz = tp[i, 0] - x, tp[i, 1] - y, tp[i, 2] - z
                s = dx * dx + dy * dy + dz * dz
                if s < bd[k - 1]:
                    a = k - 1
                    while a > 0 and bd[a - 1] > s:
                        bd[a], bi[a] = bd[a - 1], bi[a - 1]
                        a -= 1
                    bd[a], bi[a] = s, i
                    found = min(found + 1, k)
            continue
        q = x if d == 0 else (y if d == 1 else z)
        diff = q - split[node]
        near, far = (left[node], right[node]) if diff <= 0.0 else (right[node], left[node])
        stack[top], gaps[top] = far, max(gap, diff * diff)
        stack[top + 1], gaps[top + 1] = near, gap
        top += 2
    return found


@njit(cache=True, nogil=True)
def _least_spread(a00, a01, a02, a11, a12, a22):  # pragma: no cover - compiled
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix (closed
    form; ``eigh`` when the closed form is ill-conditioned)."""
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    if p2 <= 1e-30:  # a multiple of the identity: any direction
        return 0.0, 0.0, 1.0
    p = np.sqrt(p2 / 6.0)
    b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
    b01, b02, b12 = a01 / p, a02 / p, a12 / p
    det = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02)
    r = 0.5 * (det + b02 * (b01 * b12 - b11 * b02))
    r = min(1.0, max(-1.0, r))
    lam = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * np.pi / 3.0)  # the smallest
    # the null direction of A - lam I: the longest cross product of two of its rows
    r0 = (a00 - lam, a01, a02)
    r1 = (a01, a11 - lam, a12)
    r2 = (a02, a12, a22 - lam)
    best, n0, n1, n2 = -1.0, 0.0, 0.0, 1.0
    for u, v in ((r0, r1), (r0, r2), (r1, r2)):
        c0 = u[1] * v[2] - u[2] * v[1]
        c1 = u[2] * v[0] - u[0] * v[2]
        c2 = u[0] * v[1] - u[1] * v[0]
        s = c0 * c0 + c1 * c1 + c2 * c2
        if s > best:
            best, n0, n1, n2 = s, c0, c1, c2
    if best <= 1e-12 * p2 * p2:  # two smallest eigenvalues (nearly) equal
        w, vec = np.linalg.eigh(
            np.array([[a00, a01, a02], [a01, a11, a12], [a02, a12, a22]], dtype=np.float64)
        )
        return vec[0, 0], vec[1, 0], vec[2, 0]
    s = np.sqrt(best)
    return n0 / s, n1 / s, n2 / s


@njit(cache=True, nogil=True)
def _least_spread_of_neighbours(tp, lo, hi, axis, split, left, right, k):  # pragma: no cover
    """Per point of ``tp`` (tree order) the unit direction of least spread of its ``k``
    nearest neighbours (itself included) ``[M, 3]``, and whether it had
    :data:`MIN_NEIGHBOURS` of them ``[M]``."""
    m = tp.shape[0]
    out = np.zeros((m, 3))
    ok = np.zeros(m, np.bool_)
    bi = np.empty(k, np.int64)
    bd = np.empty(k, np.float64)
    stack, gaps = np.empty(_STACK, np.int64), np.empty(_STACK, np.float64)
    for i in range(m):
        x, y, z = tp[i, 0], tp[i, 1], tp[i, 2]
        n = _knn(tp, lo, hi, axis, split, left, right, x, y, z, bi, bd, stack, gaps)
        if n >= MIN_NEIGHBOURS:
            out[i, 0], out[i, 1], out[i, 2] = _least_spread(*_spread(tp, bi, n))
            ok[i] = True
    return out, ok


@njit(cache=True, nogil=True)
def covariances(tp, lo, hi, axis, split, left, right, k):  # pragma: no cover - compiled
    """Plane-regularised covariance ``[M, 3, 3]`` of each point of ``tp`` (tree order)
    from its ``k`` nearest neighbours (itself included); the identity for a point with
    fewer than :data:`MIN_NEIGHBOURS`."""
    u, ok = _least_spread_of_neighbours(tp, lo, hi, axis, split, left, right, k)
    out = np.empty((tp.shape[0], 3, 3))
    f = 1.0 - EPS
    for i in range(tp.shape[0]):
        if not ok[i]:
            out[i] = np.eye(3)
            continue
        for a in range(3):
            for b in range(3):
                out[i, a, b] = (1.0 if a == b else 0.0) - f * u[i, a] * u[i, b]
    return out


@njit(cache=True, nogil=True)
def normals(tp, lo, hi, axis, split, left, right, k):  # pragma: no cover - compiled
    """Unit normal ``[M, 3]`` of each point of ``tp`` (tree order, in its sensor's frame):
    the direction of least spread of its ``k`` nearest neighbours (itself included),
    turned to face the sensor at the origin; zero for a point with fewer than
    :data:`MIN_NEIGHBOURS` (small_gicp's normal estimation)."""
    u, _ok = _least_spread_of_neighbours(tp, lo, hi, axis, split, left, right, k)
    for i in range(tp.shape[0]):
        if tp[i, 0] * u[i, 0] + tp[i, 1] * u[i, 1] + tp[i, 2] * u[i, 2] > 0.0:
            u[i, 0], u[i, 1], u[i, 2] = -u[i, 0], -u[i, 1], -u[i, 2]
    return u


@njit(cache=True, nogil=True)
def _spread(tp, bi, n):  # pragma: no cover - compiled
    """The covariance (upper triangle) of the points ``tp[bi[:n]]``."""
    mx, my, mz = 0.0, 0.0, 0.0
    for a in range(n):
        j = bi[a]
        mx += tp[j, 0]
        my += tp[j, 1]
        mz += tp[j, 2]
    mx, my, mz = mx / n, my / n, mz / n
    c00 = c01 = c02 = c11 = c12 = c22 = 0.0
    for a in range(n):
        j = bi[a]
        dx, dy, dz = tp[j, 0] - mx, tp[j, 1] - my, tp[j, 2] - mz
        c00 += dx * dx
        c01 += dx * dy
        c02 += dx * dz
        c11 += dy * dy
        c12 += dy * dz
        c22 += dz * dz
    return c00 / n, c01 / n, c02 / n, c11 / n, c12 / n, c22 / n


@njit(cache=True, nogil=True)
def _gaussian_voxels(pts, covs, res):  # pragma: no cover - compiled
    """(sorted keys [V], their origin [3] (:func:`_keys`), means [V, 3], mean covariances
    [V, 3, 3]) of the points' voxels."""
    keys, origin = _keys(pts, res)
    order = np.argsort(keys, kind="mergesort")
    n = pts.shape[0]
    ukeys = np.empty(n, np.int64)
    means = np.empty((n, 3))
    vcovs = np.empty((n, 3, 3))
    v, i = 0, 0
    while i < n:
        j = i
        s = np.zeros(3)
        c = np.zeros((3, 3))
        while j < n and keys[order[j]] == keys[order[i]]:
            p = order[j]
            s += pts[p]
            c += covs[p]
            j += 1
        ukeys[v] = keys[order[i]]
        means[v] = s / (j - i)
        vcovs[v] = c / (j - i)
        v += 1
        i = j
    return ukeys[:v].copy(), origin, means[:v].copy(), vcovs[:v].copy()


@njit(cache=True, nogil=True)
def _accumulate(H, g, T, x, y, z, rx, ry, rz, Cp, Cq, M, A):  # pragma: no cover - compiled
    """Add the GICP term of one correspondence to ``H`` and ``g``, in the source's frame
    (the step is ``T <- T Exp(delta)``, so that map coordinates far from the origin do
    not reach the normal equations): the source point ``(x, y, z)`` with covariance
    ``Cp``, the world residual ``r = T p - q`` and the target's covariance ``Cq``;
    ``M`` [3, 3] and ``A`` [3, 6] are scratch space. Returns False for a singular term."""
    # the residual in the source's frame: R^T r
    ux = T[0, 0] * rx + T[1, 0] * ry + T[2, 0] * rz
    uy = T[0, 1] * rx + T[1, 1] * ry + T[2, 1] * rz
    uz = T[0, 2] * rx + T[1, 2] * ry + T[2, 2] * rz
    rx, ry, rz = ux, uy, uz
    # M = R^T Cq
    for a in range(3):
        for b in range(3):
            M[a, b] = T[0, a] * Cq[0, b] + T[1, a] * Cq[1, b] + T[2, a] * Cq[2, b]
    # S = Cp + M R (symmetric), then its inverse Om (cofactors)
    s00 = Cp[0, 0] + M[0, 0] * T[0, 0] + M[0, 1] * T[1, 0] + M[0, 2] * T[2, 0]
    s01 = Cp[0, 1] + M[0, 0] * T[0, 1] + M[0, 1] * T[1, 1] + M[0, 2] * T[2, 1]
    s02 = Cp[0, 2] + M[0, 0] * T[0, 2] + M[0, 1] * T[1, 2] + M[0, 2] * T[2, 2]
    s11 = Cp[1, 1] + M[1, 0] * T[0, 1] + M[1, 1] * T[1, 1] + M[1, 2] * T[2, 1]
    s12 = Cp[1, 2] + M[1, 0] * T[0, 2] + M[1, 1] * T[1, 2] + M[1, 2] * T[2, 2]
    s22 = Cp[2, 2] + M[2, 0] * T[0, 2] + M[2, 1] * T[1, 2] + M[2, 2] * T[2, 2]
    i00 = s11 * s22 - s12 * s12
    i01 = s02 * s12 - s01 * s22
    i02 = s01 * s12 - s02 * s11
    i11 = s00 * s22 - s02 * s02
    i12 = s01 * s02 - s00 * s12
    i22 = s00 * s11 - s01 * s01
    det = s00 * i00 + s01 * i01 + s02 * i02
    if not det > 1e-300:
        return False
    o00, o01, o02 = i00 / det, i01 / det, i02 / det
    o11, o12, o22 = i11 / det, i12 / det, i22 / det
    # J = [-[p]x | I] with p = (x, y, z), the source point: rows (0, z, -y | 1 0 0),
    # (-z, 0, x | 0 1 0), (y, -x, 0 | 0 0 1); A = Om J
    A[0, 0] = -o01 * z + o02 * y
    A[0, 1] = o00 * z - o02 * x
    A[0, 2] = -o00 * y + o01 * x
    A[1, 0] = -o11 * z + o12 * y
    A[1, 1] = o01 * z - o12 * x
    A[1, 2] = -o01 * y + o11 * x
    A[2, 0] = -o12 * z + o22 * y
    A[2, 1] = o02 * z - o22 * x
    A[2, 2] = -o02 * y + o12 * x
    A[0, 3], A[0, 4], A[0, 5] = o00, o01, o02
    A[1, 3], A[1, 4], A[1, 5] = o01, o11, o12
    A[2, 3], A[2, 4], A[2, 5] = o02, o12, o22
    # H += J^T A, g += A^T r
    for b in range(6):
        a0, a1, a2 = A[0, b], A[1, b], A[2, b]
        H[0, b] += y * a2 - z * a1
        H[1, b] += z * a0 - x * a2
        H[2, b] += x * a1 - y * a0
        H[3, b] += a0
        H[4, b] += a1
        H[5, b] += a2
        g[b] += a0 * rx + a1 * ry + a2 * rz
    return True


@njit(cache=True, nogil=True)
def _register(
    voxels,
    tp,
    tc,
    lo,
    hi,
    axis,
    split,
    left,
    right,
    keys,
    origin,
    means,
    vcovs,
    res,
    src,
    sc,
    T0,
    r2,
    max_iterations,
    stop_m,
    stop_rad,
):  # pragma: no cover - compiled
    """GICP of ``src`` ``[N, 3]`` (covariances ``sc``) from ``T0`` onto the tree points
    ``tp`` (covariances ``tc``, tree order) or, with ``voxels``, VGICP onto Gaussian
    voxels of size ``res`` (sorted ``keys`` counted from ``origin``, ``means``,
    ``vcovs``); the other target's
    arrays are not read. ``(T, iterations, H, correspondences)``."""
    T = T0.copy()
    H = np.zeros((6, 6))
    used, iterations = 0, 0
    stack, gaps = np.empty(_STACK, np.int64), np.empty(_STACK, np.float64)
    M, A = np.empty((3, 3)), np.empty((3, 6))
    for _ in range(max_iterations):
        iterations += 1
        H = np.zeros((6, 6))
        g = np.zeros(6)
        used = 0
        for i in range(src.shape[0]):
            p0, p1, p2 = src[i, 0], src[i, 1], src[i, 2]
            x = T[0, 0] * p0 + T[0, 1] * p1 + T[0, 2] * p2 + T[0, 3]
            y = T[1, 0] * p0 + T[1, 1] * p1 + T[1, 2] * p2 + T[1, 3]
            z = T[2, 0] * p0 + T[2, 1] * p1 + T[2, 2] * p2 + T[2, 3]
            if voxels:  # the mean of the voxel the point falls in, if near enough
                ix, iy = np.int64(np.floor(x / res)), np.int64(np.floor(y / res))
                key = _key(ix, iy, np.int64(np.floor(z / res)), origin)
                v = np.searchsorted(keys, key)
                if key < 0 or v >= keys.shape[0] or keys[v] != key:
                    continue
                rx, ry, rz = x - means[v, 0], y - means[v, 1], z - means[v, 2]
                if rx * rx + ry * ry + rz * rz > r2:
                    continue
                used += _accumulate(H, g, T, p0, p1, p2, rx, ry, rz, sc[i], vcovs[v], M, A)
                continue
            j, _s = _nearest(tp, lo, hi, axis, split, left, right, x, y, z, r2, stack, gaps)
            if j < 0:
                continue
            rx, ry, rz = x - tp[j, 0], y - tp[j, 1], z - tp[j, 2]
            used += _accumulate(H, g, T, p0, p1, p2, rx, ry, rz, sc[i], tc[j], M, A)
        if used == 0:
            break
        T, moved, turned = _step(H.copy(), g, T, True)
        if moved < stop_m and turned < stop_rad:
            break
    return T, iterations, H, used


@njit(cache=True, nogil=True)
def nearest_squared(tp, lo, hi, axis, split, left, right, src, T):  # pragma: no cover
    """Squared distance ``[N]`` from each point of ``src`` moved by ``T`` to its nearest
    tree point."""
    out = np.empty(src.shape[0])
    stack, gaps = np.empty(_STACK, np.int64), np.empty(_STACK, np.float64)
    for i in range(src.shape[0]):
        p0, p1, p2 = src[i, 0], src[i, 1], src[i, 2]
        x = T[0, 0] * p0 + T[0, 1] * p1 + T[0, 2] * p2 + T[0, 3]
        y = T[1, 0] * p0 + T[1, 1] * p1 + T[1, 2] * p2 + T[1, 3]
        z = T[2, 0] * p0 + T[2, 1] * p1 + T[2, 2] * p2 + T[2, 3]
        _j, s = _nearest(tp, lo, hi, axis, split, left, right, x, y, z, np.inf, stack, gaps)
        out[i] = s
    return out


#: the unused target's arrays of a registration (:func:`_register`)
_NO_VOXELS = (
    np.zeros(0, np.int64),
    np.zeros(3, np.int64),
    np.zeros((0, 3)),
    np.zeros((0, 3, 3)),
    1.0,
)
_NO_POINTS = (
    np.zeros((0, 3)),
    np.zeros((0, 3, 3)),
    *(np.zeros(1, np.int64),) * 3,
    np.zeros(1),
    *(np.zeros(1, np.int64),) * 2,
)


def _run(src, T0, max_distance, max_iterations, stop_m, stop_rad) -> tuple:
    """The arguments of a registration kernel after its target's: the source and the
    loop's settings, typed for the compiled code."""
    T0 = np.ascontiguousarray(T0, dtype=np.float64)
    stop = (int(max_iterations), float(stop_m), float(stop_rad))
    return (src.points, src.covs, T0, float(max_distance) ** 2, *stop)


@dataclass
class Cloud:
    """Points in KD-tree order with their tree and GICP covariances."""

    points: np.ndarray  # [M, 3] float64, tree order
    nodes: tuple  # the tree's arrays (icp_numba.build_tree)
    covs: np.ndarray  # [M, 3, 3]

    @classmethod
    def of(cls, pts: np.ndarray, neighbours: int) -> Cloud:
        pts = np.ascontiguousarray(pts, dtype=np.float64).reshape(-1, 3)
        order, *nodes = build_tree(pts)
        tp = np.ascontiguousarray(pts[order])
        return cls(tp, tuple(nodes), covariances(tp, *nodes, int(neighbours)))

    def __len__(self) -> int:
        return len(self.points)

    def align(self, src: Cloud, T0, max_distance, max_iterations, stop_m, stop_rad):
        """GICP of ``src`` onto this cloud: ``(T, iterations, H, correspondences)``."""
        run = _run(src, T0, max_distance, max_iterations, stop_m, stop_rad)
        return _register(False, self.points, self.covs, *self.nodes, *_NO_VOXELS, *run)

    def nearest_squared(self, pts: np.ndarray, T: np.ndarray) -> np.ndarray:
        """Squared distance of each of ``pts`` moved by ``T`` to its nearest point here."""
        return nearest_squared(
            self.points,
            *self.nodes,
            np.ascontiguousarray(pts, dtype=np.float64),
            np.ascontiguousarray(T, dtype=np.float64),
        )


@dataclass
class GaussianVoxels:
    """A cloud's Gaussian voxels of size ``res`` (VGICP's target)."""

    res: float
    keys: np.ndarray  # sorted (:func:`_keys`)
    origin: np.ndarray  # [3] the lowest voxel index per axis, which keys count from
    means: np.ndarray
    covs: np.ndarray

    @classmethod
    def of(cls, cloud: Cloud, res: float) -> GaussianVoxels:
        return cls(float(res), *_gaussian_voxels(cloud.points, cloud.covs, float(res)))

    def __len__(self) -> int:
        return len(self.keys)

    def align(self, src: Cloud, T0, max_distance, max_iterations, stop_m, stop_rad):
        """VGICP of ``src`` onto these voxels: ``(T, iterations, H, correspondences)``."""
        run = _run(src, T0, max_distance, max_iterations, stop_m, stop_rad)
        target = (self.keys, self.origin, self.means, self.covs, self.res)
        return _register(True, *_NO_POINTS, *target, *run)


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel on a tiny cloud."""
    rng = np.random.default_rng(0)
    pts = rng.uniform(-3.0, 3.0, size=(60, 3))
    cloud = Cloud.of(voxel_centroids(pts, 0.1), 10)
    voxels = GaussianVoxels.of(cloud, 2.0)
    cloud.align(cloud, np.eye(4), 1.0, 2, 1e-3, 1e-3)
    voxels.align(cloud, np.eye(4), 1.0, 2, 1e-3, 1e-3)
    cloud.nearest_squared(cloud.points, np.eye(4))
