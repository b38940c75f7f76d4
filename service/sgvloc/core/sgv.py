"""Spectral Geometric Verification (SpectralGV): registration-free re-ranking scores.

For a query and each of its k retrieved candidates, local-feature correspondences
``c_i = (x_i, y_i)`` (query keypoint, candidate keypoint) are scored by how well they
preserve pairwise lengths (the SpectralGV paper, eq. 2):

- ``d_ij = | ||x_i - x_j|| - ||y_i - y_j|| |``;
- ``M_ij = max(0, 1 - d_ij^2 / d_thr^2)``, ``M_ii = 1`` (reference) or 0;
- ``v`` = leading eigenvector of ``M`` by power iteration from the all-ones vector
  (``iterations`` steps, L2-normalised at each step);
- score ``s = v^T M v / n``; candidates are re-ordered by descending ``s``.

Public pieces:

- :func:`nn_correspondences`: nearest neighbour in feature space, batched and masked;
- :func:`sgv_scores`: the batched production scorer: a fused numba kernel on CPU
  (:mod:`sgvloc.core.sgv_numba`) or batched torch (CPU or CUDA), chosen by
  ``SGVConfig.backend``; both float32 entries of ``M``, same semantics;
- :func:`warm_up`: compile/load the numba kernels at start-up (no first-request cost);
- :func:`sgv_rerank_scores`: numpy convenience that pads candidates, matches features and
  scores them;
- :func:`rank`: stable descending order of the scores;
- :func:`reference_sgv_score` / :func:`reference_compatibility_matrix`: plain numpy
  reference for one candidate, used by the tests and as executable documentation.

Differences from the paper's code (all deliberate, none changes a score by more than
float rounding in the normal case):

- the paper's power iteration divides by ``norm + 1e-6`` and stops early once two
  iterates are ``allclose``; here every step divides by the exact norm and exactly
  ``iterations`` steps run (measured on 200 random cases: relative difference in ``s``
  at most 2e-6, float32 rounding included);
- ``n = 0`` gives ``s = 0`` (the paper's code returns NaN);
- padded correspondences (masks) contribute nothing, so candidates with different ``n``
  are scored in one batch as they would be alone (to float rounding);
- ``M`` is never built from a ``[k, n, n, 3]`` broadcast: lengths are accumulated one
  coordinate at a time (exact, unlike the Gram trick in float32), and above a memory
  budget (:data:`DENSE_BUDGET_BYTES`) ``M v`` is computed tile by tile without ever
  holding the whole ``M``: ``n = 15000`` needs about 12 MiB of scratch on CPU.

Edge cases: ``n = 0`` gives ``score = normalised = 0`` and ``v = 0``; ``n = 1`` gives
``score = 1`` with ``diagonal="one"`` (``M = [[1]]``) and 0 with ``diagonal="zero"``, and
``normalised = 0`` (a single correspondence carries no geometric evidence).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
import torch

from .config import SGVConfig
from .errors import ConflictError, InputError

log = logging.getLogger(__name__)

# torch computes float sqrt on CPU with oneMKL's VML, which picks its kernel on the first
# call and can run a low-accuracy one for part of that call (relative errors to 3e-4,
# seen here as wrong SGV scores in the first call of a process; pytorch/pytorch#188792).
# One call on a single element settles the choice before any real one.
torch.ones(1).sqrt_()

#: Largest ``M`` (``k * n * n`` float32, bytes) that :func:`sgv_scores` keeps in memory.
#: Above it the chunked (matrix-free) path runs: ``M v`` block-row-wise, rebuilding each
#: block at every power iteration, in three scratch tiles of memory whatever ``n`` is.
DENSE_BUDGET_BYTES = 256 * 2**20

# Entries per block of rows of M (three float32 scratch buffers of this size): about
# 4 MiB each stays in cache on CPU (measured 1.5-2.5x faster than whole-matrix passes,
# and few enough parallel regions that a busy machine does not stall the thread pool);
# larger on CUDA, where kernel launches dominate small blocks.
_BLOCK_ENTRIES = 2**20
_BLOCK_ENTRIES_CUDA = 2**24

#: Budget (bytes) of the ``[k, rows, Nc]`` similarity block in :func:`nn_correspondences`.
NN_BUDGET_BYTES = 64 * 2**20

_F32_BYTES = 4


def resolve_device(name: str = "auto") -> torch.device:
    """Map a device setting to a :class:`torch.device`.

    ``"auto"`` picks CUDA when available, else CPU; ``"cpu"``; ``"cuda"`` or ``"cuda:N"``
    requires CUDA and raises :class:`ConflictError` naming the setting when it is missing
    (a map's settings that this machine cannot run, not a bad request).
    """
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError) as exc:
        raise InputError(f"unknown torch device {name!r}") from exc
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConflictError(
            f"device {name!r} requested but CUDA is not available here: use 'auto' (CUDA "
            "when present) or 'cpu'"
        )
    return device


def numba_available() -> bool:
    """Whether the numba kernel (:mod:`sgvloc.core.sgv_numba`) can be imported."""
    try:
        from . import sgv_numba  # noqa: F401
    except ImportError:
        return False
    return True


def resolve_backend(cfg: SGVConfig, device: torch.device) -> Literal["torch", "numba"]:
    """The kernel that :func:`sgv_scores` runs for ``cfg`` on ``device``.

    ``"auto"``: numba on CPU when importable, else torch; ``"numba"`` requires a CPU
    device and numba, and raises :class:`ConflictError` naming the problem otherwise.
    """
    if cfg.backend == "torch":
        return "torch"
    if device.type != "cpu":
        if cfg.backend == "numba":
            raise ConflictError(
                f"SGV backend 'numba' runs on CPU only, but the device is {str(device)!r}; "
                "use backend 'torch' or 'auto' on CUDA"
            )
        return "torch"
    if numba_available():
        return "numba"
    if cfg.backend == "numba":
        raise ConflictError("SGV backend 'numba' requested but numba is not installed")
    return "torch"


def check_runnable(cfg: SGVConfig) -> None:
    """Raise :class:`ConflictError` when this machine cannot run ``cfg``'s device and
    backend (CUDA asked for and absent, numba on CUDA or not installed), so that a map's
    settings are refused when they are given rather than at every localization."""
    resolve_backend(cfg, resolve_device(cfg.device))


def warm_up(cfg: SGVConfig | None = None) -> float:
    """Prepare the SGV kernel of ``cfg`` so that no request pays for compilation.

    With the numba backend this compiles the kernels, or loads them from numba's on-disk
    cache (a fraction of a second); with torch it does nothing. Returns seconds taken.
    Call it at start-up (service, CLI, benchmarks).
    """
    cfg = cfg or SGVConfig()
    if resolve_backend(cfg, resolve_device(cfg.device)) != "numba":
        return 0.0
    from .sgv_numba import warm_up as _warm_up

    return _warm_up()


@dataclass(frozen=True)
class SGVScores:
    """SpectralGV result for k candidates (numpy arrays, candidate order as given).

    - ``score`` ``[k]`` float32: the reference score ``s = v^T M v / n`` (``cfg.normalise
      == "n"``) or ``v^T M v`` (``"none"``), with ``v`` unit-norm. Candidates are ranked by
      it (:func:`rank`). With ``M_ii = 1`` it lies in ``[1/n, 1]``: its floor ``1/n`` depends
      on ``n``, so it compares candidates fairly only at equal ``n`` (true for re-ranking,
      where every candidate gets one correspondence per query keypoint).
    - ``normalised`` ``[k]`` float32: ``clip((lambda - m_ii) / (n - 1), 0, 1)``, 0 when
      ``n <= 1``, where ``lambda = v^T M v`` and ``m_ii`` is the diagonal value (1 or 0).
      Since ``v >= 0`` is unit-norm, the diagonal always contributes exactly ``m_ii`` to
      ``lambda`` and the off-diagonal part is at most ``n - 1``; removing the diagonal and
      dividing by ``n - 1`` maps "no compatible pair" to 0 and "all pairs perfectly
      compatible" to 1 whatever ``n`` is. For a perfectly consistent cluster of ``m``
      inliers among incompatible outliers it equals ``(m - 1) / (n - 1)``, about the
      inlier ratio. Use it to compare or threshold scores across different ``n``.
    - ``eigenvalue`` ``[k]`` float32: ``lambda = v^T M v`` (Rayleigh quotient).
    - ``n`` ``[k]`` int64: valid correspondences per candidate.
    - ``v`` ``[k, n_max]`` float32: the power-iteration estimate of the leading eigenvector
      (0 at masked entries); large entries mark likely inlier correspondences.
    - ``path``: ``"dense"`` (``M`` built once) or ``"chunked"`` (matrix-free, blocks of
      rows rebuilt at every iteration).
    - ``device``: where it ran, e.g. ``"cpu"``.
    - ``backend``: the kernel that ran: ``"numba"`` or ``"torch"``.
    - ``matches`` ``[k, n_max]`` int64 or None: from :func:`sgv_rerank_scores`, the
      candidate keypoint matched to each query keypoint (-1: none), aligned with ``v``.
    """

    score: np.ndarray
    normalised: np.ndarray
    eigenvalue: np.ndarray
    n: np.ndarray
    v: np.ndarray
    path: Literal["dense", "chunked"]
    device: str
    backend: str = "torch"
    matches: np.ndarray | None = None

    def order(self) -> np.ndarray:
        """Candidate indices by descending ``score``, ties in the given order."""
        return rank(self)


def rank(scores: SGVScores | np.ndarray | Sequence[float]) -> np.ndarray:
    """Indices that sort ``scores`` in descending order; stable (ties keep input order).

    ``scores`` is an :class:`SGVScores` (its ``score`` is used) or a 1-D array.
    """
    values = scores.score if isinstance(scores, SGVScores) else np.asarray(scores)
    if values.ndim != 1:
        raise InputError(f"scores must be 1-D, got shape {list(values.shape)}")
    return np.argsort(-values.astype(np.float64), kind="stable")


# --------------------------------------------------------------------------------------
# Correspondences
# --------------------------------------------------------------------------------------


def _as_tensor(x: Any, name: str, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``x`` (numpy, torch or nested sequence) as a tensor of ``dtype`` on ``device``."""
    try:
        a = x if isinstance(x, torch.Tensor) else np.asarray(x)
        if isinstance(a, np.ndarray) and not a.flags.writeable:
            a = a.copy()  # torch cannot share read-only memory (decoded MessagePack, mmap)
        t = torch.as_tensor(a)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} is not a numeric array: {exc}") from exc
    if dtype != torch.bool and (t.dtype == torch.bool or t.is_complex()):
        raise InputError(f"{name} must be real numbers, got dtype {t.dtype}")
    return t.to(device=device, dtype=dtype)


def nn_correspondences(
    query_feats: Any,
    cand_feats: Any,
    cand_mask: Any | None = None,
    *,
    device: str | torch.device | None = None,
    budget_bytes: int = NN_BUDGET_BYTES,
) -> torch.Tensor:
    """Nearest candidate keypoint in feature space for every query keypoint.

    Features are L2-normalised, and the nearest neighbour by L2 distance is the one of
    largest cosine similarity; ties go to the lowest index. Padding (``cand_mask`` False)
    is never chosen.

    Args:
        query_feats: ``[N, D]`` query local features.
        cand_feats: ``[k, Nc_max, D]`` candidate features, padded.
        cand_mask: ``[k, Nc_max]`` bool, True for real keypoints (None: all real).
        device: torch device (default: that of ``cand_feats`` if a tensor, else CPU).
        budget_bytes: bound on the ``[k, rows, Nc_max]`` similarity block; query rows are
            processed in chunks to stay below it.

    Returns:
        ``[k, N]`` int64 (on ``device``): index into the candidate's keypoints, or -1 for
        every query keypoint of a candidate with no real keypoint (those correspondences
        are invalid and the candidate's ``n`` is 0).
    """
    if device is None:
        dev = cand_feats.device if isinstance(cand_feats, torch.Tensor) else torch.device("cpu")
    else:
        dev = resolve_device(device) if isinstance(device, str) else device
    q = _as_tensor(query_feats, "query_feats", torch.float32, dev)  # [N, D]
    c = _as_tensor(cand_feats, "cand_feats", torch.float32, dev)  # [k, Nc, D]
    if q.ndim != 2:
        raise InputError(f"query_feats must have shape [N, D], got {list(q.shape)}")
    if c.ndim != 3 or c.shape[2] != q.shape[1]:
        raise InputError(f"cand_feats must have shape [k, Nc, D={q.shape[1]}], got {list(c.shape)}")
    k, nc = c.shape[0], c.shape[1]
    if cand_mask is None:
        mask = torch.ones(k, nc, dtype=torch.bool, device=dev)  # [k, Nc]
    else:
        mask = _as_tensor(cand_mask, "cand_mask", torch.bool, dev)
        if tuple(mask.shape) != (k, nc):
            raise InputError(f"cand_mask must have shape [{k}, {nc}], got {list(mask.shape)}")
    if not bool(torch.isfinite(q).all()):
        raise InputError("query_feats contain NaN or inf")
    c = torch.where(mask[..., None], c, 0.0)  # padding may hold anything
    if not bool(torch.isfinite(c).all()):
        raise InputError("cand_feats contain NaN or inf")

    n = q.shape[0]
    idx = torch.full((k, n), -1, dtype=torch.int64, device=dev)  # [k, N]
    if k == 0 or n == 0 or nc == 0:
        return idx
    if dev.type == "cpu":
        return torch.from_numpy(_nn_numpy(q.numpy(), c.numpy(), mask.numpy(), budget_bytes))
    return _nn_torch(q, c, mask, budget_bytes)


def _nn_torch(
    q: torch.Tensor, c: torch.Tensor, mask: torch.Tensor, budget_bytes: int
) -> torch.Tensor:
    """Torch body of :func:`nn_correspondences` (CUDA); ``c`` is zero at padding."""
    k, nc, n = c.shape[0], c.shape[1], q.shape[0]
    idx = torch.full((k, n), -1, dtype=torch.int64, device=c.device)  # [k, N]

    # L2-normalise: on unit vectors ||a - b||^2 = 2 - 2 a.b, so argmin L2 = argmax cosine.
    q = q / torch.linalg.vector_norm(q, dim=1, keepdim=True).clamp_min(1e-12)  # [N, D]
    c = c / torch.linalg.vector_norm(c, dim=2, keepdim=True).clamp_min(1e-12)  # [k, Nc, D]
    ct = c.transpose(1, 2)  # [k, D, Nc]
    pad = ~mask[:, None, :]  # [k, 1, Nc]

    # Similarity in blocks of query rows so that [k, rows, Nc] stays within the budget.
    rows = max(1, budget_bytes // max(1, k * nc * _F32_BYTES))
    for r0 in range(0, n, rows):
        sim = torch.matmul(q[r0 : r0 + rows], ct)  # [k, rows, Nc]
        sim.masked_fill_(pad, float("-inf"))
        idx[:, r0 : r0 + rows] = sim.argmax(dim=2)

    # Candidates without keypoints have no correspondences.
    idx[~mask.any(dim=1)] = -1
    return idx


#: Entries of one similarity block of the CPU nearest-neighbour search (cache-sized).
_NN_BLOCK_ENTRIES = 2**20

#: Similarity given to padding: below any cosine similarity (>= -1) of real keypoints.
_PAD_SIMILARITY = -3.0


def _nn_numpy(q: np.ndarray, c: np.ndarray, mask: np.ndarray, budget_bytes: int) -> np.ndarray:
    """CPU body of :func:`nn_correspondences`, same answers (see :func:`_nn_gemm`)."""
    k, nc, dim = c.shape
    cn = c / np.maximum(np.linalg.norm(c, axis=2, keepdims=True), 1e-12)  # [k, Nc, D]
    ce = np.empty((k, nc, dim + 1), dtype=np.float32)  # [k, Nc, D + 1]
    ce[..., :dim], ce[..., dim] = cn, np.where(mask, 0.0, _PAD_SIMILARITY)
    ct = np.ascontiguousarray(ce.reshape(k * nc, dim + 1).T)  # [D + 1, k * Nc]
    return _nn_gemm(q, ct, k, nc, mask.any(axis=1), budget_bytes)


def nn_correspondences_cpu(
    query_feats: np.ndarray, cand_feats: Sequence[np.ndarray], budget_bytes: int = NN_BUDGET_BYTES
) -> np.ndarray:
    """:func:`nn_correspondences` on CPU from the candidates' own ``[Nc_i, D]`` arrays, the
    same answers without padding them first: each candidate is normalised and written
    once, straight into the transposed block the GEMM reads (re-ranking calls this once
    per localization with 20-50 candidates). Returns ``[k, N]`` int64 numpy."""
    q = np.asarray(query_feats, dtype=np.float32)  # [N, D]
    k, dim = len(cand_feats), q.shape[1]
    nc = max((len(f) for f in cand_feats), default=0)
    if k == 0 or len(q) == 0 or nc == 0:
        return np.full((k, len(q)), -1, dtype=np.int64)
    if not np.isfinite(q).all():
        raise InputError("query_feats contain NaN or inf")
    ct = np.zeros((dim + 1, k * nc), dtype=np.float32)  # [D + 1, k * Nc]
    ct[dim] = _PAD_SIMILARITY
    for i, f in enumerate(cand_feats):
        f = np.asarray(f, dtype=np.float32)  # [Nc_i, D]
        cols = slice(i * nc, i * nc + len(f))
        ct[:dim, cols] = (f / np.maximum(np.linalg.norm(f, axis=1, keepdims=True), 1e-12)).T
        ct[dim, cols] = 0.0
    if not np.isfinite(ct).all():  # a NaN or inf feature leaves NaN after normalising
        raise InputError("cand_feats contain NaN or inf")
    real = np.array([len(f) > 0 for f in cand_feats])
    return _nn_gemm(q, ct, k, nc, real, budget_bytes)


def _nn_gemm(
    q: np.ndarray, ct: np.ndarray, k: int, nc: int, real: np.ndarray, budget_bytes: int
) -> np.ndarray:
    """Nearest candidate keypoint per query row: one GEMM per block of query rows against
    all candidates at once, ``[rows, D + 1] x [D + 1, k * Nc]``. ``ct`` holds the candidates'
    unit features, transposed, with an extra row (0 for real keypoints,
    ``_PAD_SIMILARITY`` for padding) met by a 1 in each query row, so that padding never
    wins without a masking pass. Blocks stay cache-sized; argmax takes the first (lowest)
    index on ties. ``real``: ``[k]`` whether the candidate has any keypoint (else -1)."""
    n, dim = q.shape
    qe = np.empty((n, dim + 1), dtype=np.float32)  # [N, D + 1]
    qe[:, :dim] = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    qe[:, dim] = 1.0
    cts, qt = torch.from_numpy(ct), torch.from_numpy(qe)
    block = min(budget_bytes // _F32_BYTES, _NN_BLOCK_ENTRIES)
    rows = max(1, block // (k * nc))
    idx = np.empty((k, n), dtype=np.int64)  # [k, N]
    with torch.inference_mode():
        for r0 in range(0, n, rows):
            # GEMM in torch (measured 1.5-2x faster than numpy's multi-threaded OpenBLAS on
            # 2 busy cores), argmax in numpy (3x faster than torch's on this shape).
            sim = torch.mm(qt[r0 : r0 + rows], cts).numpy().reshape(-1, k, nc)  # [rows, k, Nc]
            idx[:, r0 : r0 + rows] = sim.argmax(axis=2).T
    idx[~real] = -1  # candidates without keypoints have no correspondences
    return idx


# --------------------------------------------------------------------------------------
# Numpy reference (one candidate)
# --------------------------------------------------------------------------------------


def reference_compatibility_matrix(
    src: np.ndarray, dst: np.ndarray, d_thr: float, diagonal: Literal["one", "zero"] = "one"
) -> np.ndarray:
    """``M [n, n]`` float64 of the SpectralGV paper (eq. 2), one candidate (numpy, small n).

    ``d_ij = | ||src_i - src_j|| - ||dst_i - dst_j|| |``,
    ``M_ij = max(0, 1 - d_ij^2 / d_thr^2)``, ``M_ii = 1`` (``diagonal="one"``) or 0.
    """
    src = np.asarray(src, dtype=np.float64).reshape(-1, 3)  # [n, 3]
    dst = np.asarray(dst, dtype=np.float64).reshape(-1, 3)  # [n, 3]
    if src.shape != dst.shape:
        raise InputError(f"src and dst differ in shape: {src.shape} vs {dst.shape}")
    ds = np.linalg.norm(src[:, None, :] - src[None, :, :], axis=-1)  # [n, n]
    dd = np.linalg.norm(dst[:, None, :] - dst[None, :, :], axis=-1)  # [n, n]
    d = np.abs(ds - dd)  # [n, n]
    m = np.maximum(0.0, 1.0 - d**2 / d_thr**2)  # [n, n]
    np.fill_diagonal(m, 1.0 if diagonal == "one" else 0.0)
    return m


def reference_sgv_score(
    src: np.ndarray,
    dst: np.ndarray,
    d_thr: float,
    iterations: int = 5,
    diagonal: Literal["one", "zero"] = "one",
) -> float:
    """SpectralGV score of one candidate, written as plainly as possible (numpy, float64).

    ``M`` from :func:`reference_compatibility_matrix`; ``v = ones``; ``iterations`` times
    ``v = M v / ||M v||``; score ``v^T M v / n``. ``n = 0`` returns 0.0 (the paper's code
    gives NaN); if ``M v`` vanishes (``diagonal="zero"`` and no compatible pair) ``v``
    becomes 0 and the score 0.0. Builds ``[n, n, 3]`` arrays: small ``n`` only.
    """
    m = reference_compatibility_matrix(src, dst, d_thr, diagonal)  # [n, n]
    n = m.shape[0]
    if n == 0:
        return 0.0
    v = np.ones(n)  # [n]
    for _ in range(iterations):
        v = m @ v
        norm = np.linalg.norm(v)
        v = v / norm if norm > 0 else np.zeros(n)
    return float(v @ m @ v / n)


# --------------------------------------------------------------------------------------
# Batched scorer
# --------------------------------------------------------------------------------------


def _tiles(k: int, n: int, target: int, max_rows: int) -> list[tuple[int, int, int, int]]:
    """Split ``M [k, n, n]`` into tiles ``(b0, b1, r0, r1)`` of about ``target`` entries.

    A tile is either whole candidates (``r0:r1 = 0:n``) or rows of one candidate, so that
    ``M[b0:b1, r0:r1]`` is contiguous. Rows per tile never exceed ``max_rows``.
    """
    rows = max(1, min(n, max_rows, target // max(1, n)))
    if rows == n:
        per = max(1, target // max(1, n * n))
        return [(b0, min(k, b0 + per), 0, n) for b0 in range(0, k, per)]
    return [(b, b + 1, r0, min(n, r0 + rows)) for b in range(k) for r0 in range(0, n, rows)]


class _CompatTiles:
    """Builds tiles of the compatibility matrices ``M`` of k candidates.

    ``src``/``dst`` are ``[k, n, 3]`` with masked rows zeroed. Pairwise lengths are
    accumulated one coordinate at a time, ``sum_a (p_ia - p_ja)^2``, exact to float32
    rounding of the distance itself. (The Gram form ``||a||^2 + ||b||^2 - 2ab`` loses
    centimetres for points tens of metres from the origin, the size of ``d_thr`` itself,
    and the ``[k, n, n, 3]`` broadcast needs gigabytes.) A tile uses three float32 scratch
    buffers of the largest tile's size, allocated once and reused; tiles of about
    ``_BLOCK_ENTRIES`` entries stay in cache, which makes the ~17 elementwise passes
    several times faster than over a whole ``[k, n, n]`` matrix.

    Masks are not applied here: rows and columns of masked correspondences hold finite
    garbage, and the power iteration keeps ``v`` zero there, which is the same as zeroing
    them (``D M D v = D (M v)`` for a 0/1 diagonal ``D`` and ``v = D v``).
    """

    def __init__(
        self,
        src: torch.Tensor,
        dst: torch.Tensor,
        tiles: list[tuple[int, int, int, int]],
        d_thr: float,
        diag: float,
    ) -> None:
        self.src = src.transpose(1, 2).contiguous()  # [k, 3, n]
        self.dst = dst.transpose(1, 2).contiguous()  # [k, 3, n]
        self.n, self.d_thr, self.diag = src.shape[1], d_thr, diag
        size = max(((b1 - b0) * (r1 - r0) * self.n for b0, b1, r0, r1 in tiles), default=0)
        self.bufs = [torch.empty(size, device=src.device) for _ in range(3)]
        self.one = torch.ones((), device=src.device)

    @staticmethod
    def _lengths(
        pts: torch.Tensor, r0: int, r1: int, c0: int, out: torch.Tensor, tmp: torch.Tensor
    ) -> torch.Tensor:
        """``out[b, i, j] = ||p[b, r0 + i] - p[b, c0 + j]||``; ``pts [b, 3, n]``."""
        for axis in range(3):
            x = pts[:, axis]  # [b, n]
            torch.sub(x[:, r0:r1, None], x[:, None, c0:], out=out if axis == 0 else tmp)
            if axis == 0:
                out.square_()
            else:
                out.addcmul_(tmp, tmp)
        return out.sqrt_()  # [b, c, n - c0]

    def tile(
        self, b0: int, b1: int, r0: int, r1: int, c0: int = 0, out: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``M[b0:b1, r0:r1, c0:]``, ``[b, c, n - c0]``, written to ``out`` (contiguous) if
        given, else to a scratch buffer that the next call overwrites."""
        shape = (b1 - b0, r1 - r0, self.n - c0)
        size = shape[0] * shape[1] * shape[2]
        ds, dd, tmp = (buf[:size].view(shape) for buf in self.bufs)
        # Pairwise lengths on each side.
        self._lengths(self.src[b0:b1], r0, r1, c0, ds, tmp)  # [b, c, n - c0]
        self._lengths(self.dst[b0:b1], r0, r1, c0, dd, tmp)  # [b, c, n - c0]
        # M_ij = max(0, 1 - d_ij^2 / d_thr^2) with d_ij = ds - dd (its sign is squared away).
        d = ds.sub_(dd)  # [b, c, n - c0]
        m = torch.addcmul(
            self.one, d, d, value=-1.0 / self.d_thr**2, out=tmp if out is None else out
        )
        m.clamp_(min=0.0)  # [b, c, n - c0]
        # Exact diagonal: entry (i, r0 + i) of M is (i, r0 - c0 + i) of the tile.
        m.diagonal(offset=r0 - c0, dim1=1, dim2=2).fill_(self.diag)
        return m


def _check_batch(
    src: Any, dst: Any, mask: Any | None, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Validate and move ``src``/``dst`` ``[k, n, 3]`` and ``mask`` ``[k, n]``."""
    s = _as_tensor(src, "src", torch.float32, device)
    d = _as_tensor(dst, "dst", torch.float32, device)
    if s.ndim != 3 or s.shape[2] != 3:
        raise InputError(f"src must have shape [k, n, 3], got {list(s.shape)}")
    if d.shape != s.shape:
        raise InputError(f"dst must have the shape of src {list(s.shape)}, got {list(d.shape)}")
    k, n = s.shape[0], s.shape[1]
    if mask is None:
        m = torch.ones(k, n, dtype=torch.bool, device=device)
    else:
        m = _as_tensor(mask, "mask", torch.bool, device)
        if tuple(m.shape) != (k, n):
            raise InputError(f"mask must have shape [{k}, {n}], got {list(m.shape)}")
    # Masked entries may hold anything (padding, NaN): zero them, then check the rest.
    s = torch.where(m[..., None], s, 0.0)
    d = torch.where(m[..., None], d, 0.0)
    if not (bool(torch.isfinite(s).all()) and bool(torch.isfinite(d).all())):
        raise InputError("src/dst contain NaN or inf at valid (unmasked) correspondences")
    return s.contiguous(), d.contiguous(), m


def _as_array(x: Any, name: str, dtype: type) -> np.ndarray:
    """``x`` (numpy, torch or nested sequence) as a numpy array of ``dtype``."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    try:
        a = np.asarray(x)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} is not a numeric array: {exc}") from exc
    if a.dtype.kind not in "biuf":
        raise InputError(f"{name} must be real numbers, got dtype {a.dtype}")
    if dtype is not np.bool_ and a.dtype.kind == "b":
        raise InputError(f"{name} must be real numbers, got dtype {a.dtype}")
    return a.astype(dtype, copy=False)


def _check_batch_numpy(
    src: Any, dst: Any, mask: Any | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_check_batch` in numpy (same checks and messages) for the CPU kernel."""
    s = _as_array(src, "src", np.float32)
    d = _as_array(dst, "dst", np.float32)
    if s.ndim != 3 or s.shape[2] != 3:
        raise InputError(f"src must have shape [k, n, 3], got {list(s.shape)}")
    if d.shape != s.shape:
        raise InputError(f"dst must have the shape of src {list(s.shape)}, got {list(d.shape)}")
    k, n = s.shape[0], s.shape[1]
    if mask is None:
        m = np.ones((k, n), dtype=np.bool_)
    else:
        m = _as_array(mask, "mask", np.bool_)
        if m.shape != (k, n):
            raise InputError(f"mask must have shape [{k}, {n}], got {list(m.shape)}")
    # Masked entries may hold anything (padding, NaN): zero them, then check the rest.
    if not m.all():
        s = np.where(m[..., None], s, np.float32(0.0))
        d = np.where(m[..., None], d, np.float32(0.0))
    if not (np.isfinite(s).all() and np.isfinite(d).all()):
        raise InputError("src/dst contain NaN or inf at valid (unmasked) correspondences")
    return s, d, m


def _sgv_scores_numba(
    src: Any, dst: Any, mask: Any | None, cfg: SGVConfig, dense_budget_bytes: int
) -> SGVScores:
    """:func:`sgv_scores` with the fused CPU kernel (:mod:`sgvloc.core.sgv_numba`)."""
    from .sgv_numba import power_iteration

    s, d, m = _check_batch_numpy(src, dst, mask)  # [k, n, 3], [k, n, 3], [k, n]
    diag = 1.0 if cfg.diagonal == "one" else 0.0
    lam, v, path = power_iteration(
        s, d, m, cfg.d_thr, cfg.iterations, diag, dense_budget_bytes
    )  # [k] float64, [k, n] float64
    counts = m.sum(axis=1).astype(np.int64)  # [k]
    nf = counts.astype(np.float64)  # [k]
    score = lam / np.maximum(nf, 1.0) if cfg.normalise == "n" else lam  # [k]
    normalised = np.where(
        counts > 1, np.clip((lam - diag) / np.maximum(nf - 1.0, 1.0), 0.0, 1.0), 0.0
    )  # [k]
    log.debug("sgv: k=%d n=%d path=%s backend=numba", m.shape[0], m.shape[1], path)
    return SGVScores(
        score=score.astype(np.float32),
        normalised=normalised.astype(np.float32),
        eigenvalue=lam.astype(np.float32),
        n=counts,
        v=v.astype(np.float32),
        path=path,
        device="cpu",
        backend="numba",
    )


def sgv_scores(
    src: Any,
    dst: Any,
    mask: Any | None = None,
    cfg: SGVConfig | None = None,
    *,
    dense_budget_bytes: int = DENSE_BUDGET_BYTES,
) -> SGVScores:
    """SpectralGV scores of k candidates in one batch (torch, float32, deterministic).

    Args:
        src: ``[k, n, 3]`` query-side points of each correspondence (numpy or torch).
        dst: ``[k, n, 3]`` candidate-side points.
        mask: ``[k, n]`` bool, True for real correspondences (None: all real). Masked
            entries are ignored, whatever they hold: a padded candidate scores exactly
            like the unpadded one; ``n`` per candidate is ``mask.sum()``.
        cfg: :class:`SGVConfig` (``d_thr``, ``iterations``, ``diagonal``, ``normalise``,
            ``chunk_size``, ``device``, ``backend``); defaults if None. The backend
            (:func:`resolve_backend`) is the fused numba kernel on CPU by default, torch
            on CUDA or when asked for.
        dense_budget_bytes: torch: if ``M`` (``k * n * n`` float32) fits, it is built once
            ("dense" path); otherwise ``M v`` is computed block-row-wise, rebuilding each
            block at every iteration ("chunked"). Both give the same scores. Tiles of ``M``
            hold at most ``cfg.chunk_size`` rows and about 2^20 entries (2^24 on CUDA), so
            the chunked path needs three such float32 tiles besides the ``[k, n]`` vectors.
            numba: a candidate's ``M`` (``n_valid^2`` float32) is built once if one per
            thread fits, else its rows are rebuilt at every product (matrix-free,
            ``O(16 n)`` memory); ``path`` is "chunked" if any candidate went that way.

    Returns:
        :class:`SGVScores` (numpy arrays). See the module docstring for edge cases.
    """
    cfg = cfg or SGVConfig()
    device = resolve_device(cfg.device)
    if resolve_backend(cfg, device) == "numba":
        return _sgv_scores_numba(src, dst, mask, cfg, dense_budget_bytes)
    s, d, m = _check_batch(src, dst, mask, device)  # [k, n, 3], [k, n, 3], [k, n]
    k, n = m.shape
    valid = m.to(torch.float32)  # [k, n]
    counts = m.sum(dim=1)  # [k]
    diag = 1.0 if cfg.diagonal == "one" else 0.0

    # Choose the path: dense if M [k, n, n] fits the budget; cache-sized tiles either way.
    dense = k * n * n * _F32_BYTES <= dense_budget_bytes
    target = _BLOCK_ENTRIES_CUDA if device.type == "cuda" else _BLOCK_ENTRIES
    tiles = _tiles(k, n, target, cfg.chunk_size)
    path: Literal["dense", "chunked"] = "dense" if dense else "chunked"
    log.debug("sgv: k=%d n=%d path=%s tiles=%d device=%s", k, n, path, len(tiles), device)

    with torch.inference_mode():
        builder = _CompatTiles(s, d, tiles, cfg.d_thr, diag)
        if dense:
            # M built once, tile by tile, then reused by every iteration.
            mat = torch.empty(k, n, n, device=device)  # [k, n, n]
            for b0, b1, r0, r1 in tiles:
                builder.tile(b0, b1, r0, r1, out=mat[b0:b1, r0:r1])

            # M is exactly symmetric (|a - b| = |b - a| in floating point), so M v = (v^T M)^T;
            # the row-vector form runs several times faster than bmm with one column.
            def matvec(x: torch.Tensor) -> torch.Tensor:
                return torch.bmm(x[:, None, :], mat)[:, 0].mul_(valid)  # [k, n]

        else:
            # Matrix-free: every product rebuilds M tile by tile. Row tiles of one candidate
            # cover only columns r0: (the upper triangle); by symmetry each such tile also
            # gives the transposed contribution of the rows below, halving the work.
            def matvec(x: torch.Tensor) -> torch.Tensor:
                out = torch.zeros_like(x)  # [k, n]
                for b0, b1, r0, r1 in tiles:
                    if r1 - r0 == n:  # whole candidates
                        m = builder.tile(b0, b1, 0, n)  # [b, n, n]
                        out[b0:b1] = torch.bmm(x[b0:b1, None, :], m)[:, 0]  # [b, n]
                        continue
                    m = builder.tile(b0, b1, r0, r1, c0=r0)  # [1, c, n - r0]
                    # Rows r0:r1 of M v: M[r0:r1, :r0] v[:r0] came from earlier tiles.
                    out[b0:b1, r0:r1] += torch.bmm(m, x[b0:b1, r0:, None])[..., 0]  # [1, c]
                    # Rows r1: of M v, through M[r1:, r0:r1] = M[r0:r1, r1:]^T.
                    out[b0:b1, r1:] += torch.bmm(x[b0:b1, None, r0:r1], m[:, :, r1 - r0 :])[:, 0]
                return out.mul_(valid)  # [k, n]

        # Power iteration from all-ones (zero at padding), normalised at every step; a
        # vanishing M v (n = 0, or diagonal "zero" with no compatible pair) gives v = 0.
        v = valid.clone()  # [k, n]
        for _ in range(cfg.iterations):
            w = matvec(v)  # [k, n]
            norm = torch.linalg.vector_norm(w, dim=1, keepdim=True)  # [k, 1]
            v = w / norm.clamp_min(torch.finfo(torch.float32).tiny)  # [k, n]

        # Rayleigh quotient lambda = v^T M v, then the scores.
        lam = (v * matvec(v)).sum(dim=1)  # [k]
        nf = counts.to(torch.float32)  # [k]
        score = lam / nf.clamp_min(1.0) if cfg.normalise == "n" else lam  # [k]
        normalised = torch.where(
            counts > 1, ((lam - diag) / (nf - 1.0).clamp_min(1.0)).clamp(0.0, 1.0), 0.0
        )  # [k]

    return SGVScores(
        score=score.cpu().numpy().astype(np.float32),
        normalised=normalised.cpu().numpy().astype(np.float32),
        eigenvalue=lam.cpu().numpy().astype(np.float32),
        n=counts.cpu().numpy().astype(np.int64),
        v=v.cpu().numpy().astype(np.float32),
        path=path,
        device=str(device),
    )


# --------------------------------------------------------------------------------------
# Convenience: keypoints + features in, scores out
# --------------------------------------------------------------------------------------


def sgv_rerank_scores(
    query_kp: np.ndarray,
    query_feats: np.ndarray,
    cand_kps: Sequence[np.ndarray],
    cand_feats: Sequence[np.ndarray],
    cfg: SGVConfig | None = None,
    *,
    dense_budget_bytes: int = DENSE_BUDGET_BYTES,
) -> SGVScores:
    """Score k retrieved candidates against a query from keypoints and local features.

    Candidates are padded to a common size with masks (never truncated); each query
    keypoint is matched to its feature-space nearest neighbour in each candidate
    (:func:`nn_correspondences`), giving ``src = query_kp`` and ``dst = cand_kp[nn]`` for
    all candidates, which :func:`sgv_scores` then scores in one batch. A candidate with no
    keypoints gets ``n = 0`` and score 0.

    Args:
        query_kp: ``[N, 3]`` query keypoints (metres).
        query_feats: ``[N, D]`` query local features.
        cand_kps: k arrays ``[Nc, 3]``, one per candidate, in retrieval order.
        cand_feats: k arrays ``[Nc, D]``, matching ``cand_kps``.
        cfg: :class:`SGVConfig`; defaults if None.
        dense_budget_bytes: see :func:`sgv_scores`.

    Returns:
        :class:`SGVScores`; ``v`` is ``[k, N]``, aligned with the query keypoints.
    """
    cfg = cfg or SGVConfig()
    device = resolve_device(cfg.device)
    qk = np.asarray(query_kp, dtype=np.float32)  # [N, 3]
    qf = np.asarray(query_feats, dtype=np.float32)  # [N, D]
    if qk.ndim != 2 or qk.shape[1] != 3:
        raise InputError(f"query_kp must have shape [N, 3], got {list(qk.shape)}")
    if qf.ndim != 2 or qf.shape[0] != qk.shape[0]:
        raise InputError(f"query_feats must have shape [N={qk.shape[0]}, D], got {list(qf.shape)}")
    if len(cand_kps) != len(cand_feats):
        raise InputError(
            f"got {len(cand_kps)} candidate keypoint sets but {len(cand_feats)} feature sets"
        )
    kps = [np.asarray(a, dtype=np.float32) for a in cand_kps]
    fts = [np.asarray(a, dtype=np.float32) for a in cand_feats]
    if not len(qk):  # no query keypoints: the width of the candidates' features will do
        width = next((f.shape[1] for f in fts if f.ndim == 2 and len(f)), qf.shape[1])
        qf = np.zeros((0, width), dtype=np.float32)
    n, dim, k = qk.shape[0], qf.shape[1], len(cand_kps)

    # Pad the candidates: [k, Nc_max, 3] keypoints, [k, Nc_max, D] features, [k, Nc_max] mask.
    for i, (a, f) in enumerate(zip(kps, fts, strict=True)):
        if a.ndim != 2 or a.shape[1] != 3:
            raise InputError(f"cand_kps[{i}] must have shape [Nc, 3], got {list(a.shape)}")
        if f.ndim == 2 and not len(a) and not len(f):  # no keypoints: any width is empty
            fts[i] = f = np.zeros((0, dim), dtype=np.float32)
        if f.ndim != 2 or f.shape != (a.shape[0], dim):
            raise InputError(
                f"cand_feats[{i}] must have shape [{a.shape[0]}, {dim}], got {list(f.shape)}"
            )
    nc_max = max((len(a) for a in kps), default=0)
    kp_pad = np.zeros((k, nc_max, 3), dtype=np.float32)  # [k, Nc_max, 3]
    for i, a in enumerate(kps):
        kp_pad[i, : len(a)] = a

    # Correspondences: nearest candidate keypoint in feature space, per query keypoint.
    if device.type == "cpu":
        idx = torch.from_numpy(nn_correspondences_cpu(qf, fts))  # [k, N]
    else:
        ft_pad = np.zeros((k, nc_max, dim), dtype=np.float32)  # [k, Nc_max, D]
        cmask = np.zeros((k, nc_max), dtype=bool)  # [k, Nc_max]
        for i, f in enumerate(fts):
            ft_pad[i, : len(f)], cmask[i, : len(f)] = f, True
        idx = nn_correspondences(qf, ft_pad, cmask, device=device)  # [k, N]
    valid = idx >= 0  # [k, N]

    if resolve_backend(cfg, device) == "numba":
        # CPU kernel: gather in numpy, no torch round trip.
        idx_np = idx.numpy()  # [k, N]
        if nc_max > 0:
            dst_np = kp_pad[np.arange(k)[:, None], np.maximum(idx_np, 0)]  # [k, N, 3]
        else:
            dst_np = np.zeros((k, n, 3), dtype=np.float32)
        src_np = np.broadcast_to(qk[None], (k, n, 3))  # [k, N, 3]
        res = _scores(src_np, dst_np, valid.numpy(), cfg, dense_budget_bytes)
        return replace(res, matches=idx_np.astype(np.int64))

    # src = query keypoints (same for all k), dst = the matched candidate keypoints.
    kp_t = torch.as_tensor(kp_pad, device=device)  # [k, Nc_max, 3]
    gather = idx.clamp_min(0)[..., None].expand(k, n, 3)  # [k, N, 3]
    dst = (
        torch.gather(kp_t, 1, gather) if nc_max > 0 else torch.zeros(k, n, 3, device=device)
    )  # [k, N, 3]
    src = torch.as_tensor(qk, device=device)[None].expand(k, n, 3)  # [k, N, 3]

    # Score all candidates in one batch.
    res = _scores(src, dst, valid, cfg, dense_budget_bytes)
    return replace(res, matches=idx.cpu().numpy().astype(np.int64))


def _scores(src: Any, dst: Any, mask: Any, cfg: SGVConfig, budget: int) -> SGVScores:
    """:func:`sgv_scores` of one query's candidates, in one kernel call with concurrent
    localizations' candidates when dynamic batching is on (:mod:`sgvloc.core.batching`)."""
    from . import batching

    batcher = batching.current()
    if batcher is None:
        return sgv_scores(src, dst, mask, cfg, dense_budget_bytes=budget)
    key = (cfg.model_dump_json(), budget, type(src).__name__)
    return batcher.run("sgv", key, (src, dst, mask), lambda items: _scores_many(items, cfg, budget))


def _scores_many(items: list[tuple[Any, Any, Any]], cfg: SGVConfig, budget: int) -> list[SGVScores]:
    """Several queries' ``(src [k, n, 3], dst, mask [k, n])`` scored in one call: padded
    to the largest n (masked entries do not count), stacked along k, split again."""
    n = max(m.shape[1] for _, _, m in items)
    if isinstance(items[0][0], torch.Tensor):

        def pad(a: Any, width: int) -> Any:  # zeros (False for the mask) after column n
            return torch.cat([a, a.new_zeros((a.shape[0], width, *a.shape[2:]))], dim=1)

        cat = torch.cat
    else:

        def pad(a: Any, width: int) -> Any:
            return np.pad(a, [(0, 0), (0, width)] + [(0, 0)] * (a.ndim - 2))

        cat = np.concatenate
    padded = [[pad(a, n - m.shape[1]) for a in (s, d, m)] for s, d, m in items]
    srcs, dsts, masks = zip(*padded, strict=True)
    res = sgv_scores(cat(srcs), cat(dsts), cat(masks), cfg, dense_budget_bytes=budget)
    out, k0 = [], 0
    for _, _, m in items:
        k, width = m.shape
        sl = slice(k0, k0 + k)
        out.append(
            replace(
                res,
                score=res.score[sl],
                normalised=res.normalised[sl],
                eigenvalue=res.eigenvalue[sl],
                n=res.n[sl],
                v=res.v[sl, :width],
            )
        )
        k0 += k
    return out
