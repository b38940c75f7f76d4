"""SpectralGV re-ranking kernel: exact semantics, batching, masks, memory paths, edge cases.

All data are generated here: keypoint clouds with a known inlier set (rigidly moved plus
noise) and random outliers.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sgvloc.core.config import SGVConfig
from sgvloc.core.errors import InputError
from sgvloc.core.sgv import (
    SGVScores,
    nn_correspondences,
    rank,
    reference_compatibility_matrix,
    reference_sgv_score,
    resolve_device,
    sgv_rerank_scores,
    sgv_scores,
)

CPU = SGVConfig(device="cpu")


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random proper rotation ``[3, 3]``."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def correspondences(
    rng: np.random.Generator, n: int, inlier_ratio: float, noise: float = 0.02, extent: float = 30.0
) -> tuple[np.ndarray, np.ndarray]:
    """``src, dst [n, 3]``: the first ``inlier_ratio * n`` pairs agree up to a rigid motion
    and ``noise``; the others are independent random points."""
    src = rng.uniform(-extent, extent, size=(n, 3))
    src[:, 2] *= 0.1  # LiDAR-like: flat in z
    rot, t = random_rotation(rng), rng.uniform(-10, 10, size=3)
    dst = src @ rot.T + t + rng.normal(scale=noise, size=(n, 3))
    m = int(round(inlier_ratio * n))
    dst[m:] = rng.uniform(-extent, extent, size=(n - m, 3))
    return src.astype(np.float32), dst.astype(np.float32)


def score_one(src: np.ndarray, dst: np.ndarray, cfg: SGVConfig = CPU) -> SGVScores:
    return sgv_scores(src[None], dst[None], None, cfg)


# ---------------------------------------------------------------------------------------
# Exact semantics
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("diagonal", ["one", "zero"])
@pytest.mark.parametrize("n,ratio", [(2, 1.0), (7, 0.5), (60, 0.3), (200, 0.1), (150, 0.0)])
def test_matches_numpy_reference_at_default_iterations(n, ratio, diagonal):
    rng = np.random.default_rng(n)
    src, dst = correspondences(rng, n, ratio)
    cfg = SGVConfig(device="cpu", diagonal=diagonal)
    out = score_one(src, dst, cfg)
    ref = reference_sgv_score(src, dst, cfg.d_thr, cfg.iterations, diagonal)
    assert out.path == "dense" and out.n[0] == n
    np.testing.assert_allclose(out.score[0], ref, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(out.eigenvalue[0], ref * n, rtol=1e-5, atol=1e-6)


def test_converges_to_eigh_leading_eigenvector():
    rng = np.random.default_rng(1)
    n = 120
    src, dst = correspondences(rng, n, 0.4)
    m = reference_compatibility_matrix(src, dst, 0.4)  # [n, n]
    evals, evecs = np.linalg.eigh(m)
    u = np.abs(evecs[:, -1])  # Perron vector of a nonnegative matrix
    expected = float(u @ m @ u / n)
    assert expected == pytest.approx(evals[-1] / n, rel=1e-9)
    out = score_one(src, dst, SGVConfig(device="cpu", iterations=50))
    np.testing.assert_allclose(out.score[0], expected, rtol=1e-5)
    # The iterate is the eigenvector too (up to float32 rounding).
    np.testing.assert_allclose(out.v[0], u, atol=1e-4)
    # Five iterations are already close on a well separated inlier cluster.
    five = score_one(src, dst).score[0]
    assert five == pytest.approx(expected, rel=1e-2)
    assert five <= expected * (1 + 1e-6)  # a Rayleigh quotient never exceeds lambda_max


def test_compatibility_matrix_semantics():
    # Two correspondences: lengths 1.0 and 1.2 -> d = 0.2, M_01 = 1 - 0.04 / 0.16 = 0.75.
    src = np.array([[0, 0, 0], [1, 0, 0]], dtype=float)
    dst = np.array([[5, 5, 5], [5, 6.2, 5]], dtype=float)
    m = reference_compatibility_matrix(src, dst, 0.4)
    np.testing.assert_allclose(m, [[1.0, 0.75], [0.75, 1.0]])
    assert reference_compatibility_matrix(src, dst, 0.4, "zero")[0, 0] == 0.0
    # v = [1, 1]/sqrt(2): v^T M v = 1.75, score = 0.875; normalised = 0.75.
    out = score_one(src, dst)
    assert out.score[0] == pytest.approx(0.875, rel=1e-6)
    assert out.normalised[0] == pytest.approx(0.75, rel=1e-6)
    assert reference_sgv_score(src, dst, 0.4) == pytest.approx(0.875)
    # Beyond d_thr the pair is incompatible.
    dst[1, 1] = 5 + 1.5
    assert score_one(src, dst).score[0] == pytest.approx(0.5, rel=1e-6)


def test_config_options_are_respected():
    rng = np.random.default_rng(2)
    src, dst = correspondences(rng, 80, 0.5)
    base = score_one(src, dst)
    raw = score_one(src, dst, SGVConfig(device="cpu", normalise="none"))
    np.testing.assert_allclose(raw.score, base.score * 80, rtol=1e-6)
    zero = score_one(src, dst, SGVConfig(device="cpu", diagonal="zero"))
    np.testing.assert_allclose(
        zero.score[0], reference_sgv_score(src, dst, 0.4, diagonal="zero"), rtol=1e-5
    )
    assert zero.score[0] < base.score[0]
    one_it = score_one(src, dst, SGVConfig(device="cpu", iterations=1))
    np.testing.assert_allclose(one_it.score[0], reference_sgv_score(src, dst, 0.4, 1), rtol=1e-5)
    wide = score_one(src, dst, SGVConfig(device="cpu", d_thr=5.0))
    np.testing.assert_allclose(wide.score[0], reference_sgv_score(src, dst, 5.0), rtol=1e-5)
    assert wide.score[0] > base.score[0]


# ---------------------------------------------------------------------------------------
# Batching, masks, memory paths
# ---------------------------------------------------------------------------------------


def padded_batch(rng: np.random.Generator, sizes: list[int], garbage: float = np.nan):
    """Candidates of different n padded to one batch; padding holds ``garbage``."""
    pairs = [
        correspondences(rng, n, r)
        for n, r in zip(sizes, [0.6, 0.3, 0.0, 0.9, 0.5][: len(sizes)], strict=True)
    ]
    nmax = max(sizes)
    src = np.full((len(sizes), nmax, 3), garbage, dtype=np.float32)
    dst = np.full((len(sizes), nmax, 3), garbage, dtype=np.float32)
    mask = np.zeros((len(sizes), nmax), dtype=bool)
    for i, (s, d) in enumerate(pairs):
        src[i, : len(s)], dst[i, : len(d)], mask[i, : len(s)] = s, d, True
    return pairs, src, dst, mask


def test_batched_equals_per_candidate_and_padding_is_inert():
    rng = np.random.default_rng(3)
    sizes = [90, 40, 64, 3, 1]
    pairs, src, dst, mask = padded_batch(rng, sizes)
    batch = sgv_scores(src, dst, mask, CPU)
    np.testing.assert_array_equal(batch.n, sizes)
    assert batch.v.shape == (5, 90)
    assert np.all(batch.v[~mask] == 0)
    for i, (s, d) in enumerate(pairs):
        alone = score_one(s, d)
        np.testing.assert_allclose(batch.score[i], alone.score[0], rtol=1e-6)
        np.testing.assert_allclose(batch.normalised[i], alone.normalised[0], rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(batch.v[i, : len(s)], alone.v[0], atol=1e-6)
        np.testing.assert_allclose(batch.score[i], reference_sgv_score(s, d, 0.4), rtol=1e-5)
    # Scattering the padding inside the rows changes nothing either.
    perm = rng.permutation(90)
    shuffled = sgv_scores(src[:, perm], dst[:, perm], mask[:, perm], CPU)
    np.testing.assert_allclose(shuffled.score, batch.score, rtol=1e-6)


def test_chunked_path_equals_dense_path():
    rng = np.random.default_rng(4)
    pairs, src, dst, mask = padded_batch(rng, [150, 100, 37], garbage=0.0)
    for diagonal in ("one", "zero"):
        cfg = SGVConfig(device="cpu", chunk_size=16, diagonal=diagonal)
        dense = sgv_scores(src, dst, mask, cfg)
        chunked = sgv_scores(src, dst, mask, cfg, dense_budget_bytes=0)
        assert (dense.path, chunked.path) == ("dense", "chunked")
        np.testing.assert_allclose(chunked.score, dense.score, rtol=1e-6)
        np.testing.assert_allclose(chunked.normalised, dense.normalised, rtol=1e-6)
        np.testing.assert_allclose(chunked.v, dense.v, atol=1e-6)


@pytest.fixture
def one_thread():
    """Run torch single-threaded for the large-n tests.

    Results do not depend on the thread count; on a busy 2-core machine the many short
    parallel regions of the chunked path stall when a second thread is descheduled.
    """
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_large_n_uses_the_chunked_path(one_thread):
    rng = np.random.default_rng(5)
    n = 5000
    pairs = [correspondences(rng, n, r) for r in (0.3, 0.0)]
    src = np.stack([p[0] for p in pairs])
    dst = np.stack([p[1] for p in pairs])
    out = sgv_scores(src, dst, None, CPU, dense_budget_bytes=64 * 2**20)  # M needs 200 MB
    assert out.path == "chunked"
    assert np.all(np.isfinite(out.score)) and np.all(np.isfinite(out.v))
    assert out.score[0] > 10 * out.score[1]
    assert out.normalised[0] == pytest.approx(0.3, abs=0.03)  # ~ inlier ratio
    assert out.normalised[1] < 0.05


def test_n_15000_single_candidate_is_matrix_free(one_thread):
    # M would take 900 MB; the chunked path needs three small tiles.
    rng = np.random.default_rng(6)
    src, dst = correspondences(rng, 15000, 0.2)
    out = score_one(src, dst)
    assert out.path == "chunked"
    assert np.isfinite(out.score[0]) and out.n[0] == 15000
    assert out.score[0] > 0.1  # ~ inlier ratio: 3000 mutually compatible inliers


# ---------------------------------------------------------------------------------------
# Properties: invariance, robustness, determinism
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("side", ["dst", "src"])
def test_rigid_transform_invariance(side):
    rng = np.random.default_rng(7)
    src, dst = correspondences(rng, 256, 0.3)
    before = score_one(src, dst)
    rot, t = random_rotation(rng), rng.uniform(-50, 50, size=3)
    if side == "dst":
        dst = (dst.astype(np.float64) @ rot.T + t).astype(np.float32)
    else:
        src = (src.astype(np.float64) @ rot.T + t).astype(np.float32)
    after = score_one(src, dst)
    np.testing.assert_allclose(after.score, before.score, rtol=1e-5)
    np.testing.assert_allclose(after.normalised, before.normalised, rtol=1e-5)


def synthetic_candidate(
    rng: np.random.Generator,
    query_kp: np.ndarray,
    query_feats: np.ndarray,
    inlier_ratio: float,
    n_extra: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A candidate whose feature-space nearest neighbours realise ``inlier_ratio``.

    Candidate point j carries the feature of query point ``perm[j]`` (plus a little noise);
    its position is the rigidly moved query point for inliers, a random point otherwise.
    ``n_extra`` unrelated points are appended. Returns keypoints, features and the
    ``[N]`` bool mask of query keypoints whose correspondence is an inlier.
    """
    n = len(query_kp)
    perm = rng.permutation(n)
    rot, t = random_rotation(rng), rng.uniform(-5, 5, size=3)
    kp = rng.uniform(-30, 30, size=(n, 3))
    m = int(round(inlier_ratio * n))
    inl = perm[:m]
    kp[:m] = query_kp[inl] @ rot.T + t + rng.normal(scale=0.03, size=(m, 3))
    feats = query_feats[perm] + rng.normal(scale=0.01, size=query_feats.shape)
    kp = np.concatenate([kp, rng.uniform(-30, 30, size=(n_extra, 3))])
    feats = np.concatenate([feats, rng.normal(size=(n_extra, query_feats.shape[1]))])
    inlier = np.zeros(n, dtype=bool)
    inlier[inl] = True
    return kp.astype(np.float32), feats.astype(np.float32), inlier


def test_outlier_robustness_and_reranking():
    rng = np.random.default_rng(8)
    n, dim = 256, 32
    query_kp = rng.uniform(-30, 30, size=(n, 3)).astype(np.float32)
    query_feats = rng.normal(size=(n, dim)).astype(np.float32)
    cand_b = synthetic_candidate(rng, query_kp, query_feats, 0.0, n_extra=40)  # retrieved 1st
    cand_a = synthetic_candidate(rng, query_kp, query_feats, 0.3, n_extra=0)  # retrieved 2nd
    out = sgv_rerank_scores(
        query_kp, query_feats, [cand_b[0], cand_a[0]], [cand_b[1], cand_a[1]], CPU
    )
    np.testing.assert_array_equal(out.n, [n, n])
    assert out.score[1] > 2 * out.score[0]
    assert out.normalised[1] > 0.2 > 0.05 > out.normalised[0]
    np.testing.assert_array_equal(rank(out), [1, 0])
    np.testing.assert_array_equal(out.order(), [1, 0])
    # The leading eigenvector concentrates on A's inlier correspondences.
    inlier = cand_a[2]
    assert np.sum(out.v[1][inlier] ** 2) > 0.9
    top = np.argsort(-out.v[1], kind="stable")[: inlier.sum()]
    assert inlier[top].mean() > 0.9


def test_deterministic_bit_identical():
    rng = np.random.default_rng(9)
    pairs, src, dst, mask = padded_batch(rng, [120, 80, 30])
    a = sgv_scores(src, dst, mask, CPU)
    b = sgv_scores(src, dst, mask, CPU)
    assert a.score.tobytes() == b.score.tobytes()
    assert a.v.tobytes() == b.v.tobytes()
    c = sgv_scores(src, dst, mask, CPU, dense_budget_bytes=0)
    d = sgv_scores(src, dst, mask, CPU, dense_budget_bytes=0)
    assert c.score.tobytes() == d.score.tobytes()


# ---------------------------------------------------------------------------------------
# Edge cases and errors
# ---------------------------------------------------------------------------------------


def test_n_zero_and_n_one_are_defined():
    empty = sgv_scores(np.zeros((2, 0, 3)), np.zeros((2, 0, 3)), None, CPU)
    np.testing.assert_array_equal(empty.score, [0, 0])
    np.testing.assert_array_equal(empty.normalised, [0, 0])
    np.testing.assert_array_equal(empty.n, [0, 0])
    single = sgv_scores(np.ones((1, 1, 3)), np.zeros((1, 1, 3)), None, CPU)
    assert single.score[0] == 1.0 and single.normalised[0] == 0.0
    assert reference_sgv_score(np.ones((1, 3)), np.zeros((1, 3)), 0.4) == 1.0
    zero_diag = SGVConfig(device="cpu", diagonal="zero")
    single0 = sgv_scores(np.ones((1, 1, 3)), np.zeros((1, 1, 3)), None, zero_diag)
    assert single0.score[0] == 0.0 and np.all(np.isfinite(single0.v))
    # A fully masked candidate next to a real one.
    src = np.random.default_rng(0).normal(size=(2, 5, 3))
    mask = np.array([[True] * 5, [False] * 5])
    mixed = sgv_scores(src, src, mask, CPU)
    np.testing.assert_array_equal(mixed.n, [5, 0])
    assert mixed.score[1] == 0.0 and mixed.score[0] == pytest.approx(1.0, rel=1e-6)
    assert mixed.normalised[0] == pytest.approx(1.0, rel=1e-6)  # all pairs compatible
    assert reference_sgv_score(np.zeros((0, 3)), np.zeros((0, 3)), 0.4) == 0.0
    nothing = sgv_scores(np.zeros((0, 4, 3)), np.zeros((0, 4, 3)), None, CPU)
    assert nothing.score.shape == (0,) and rank(nothing).shape == (0,)


def test_normalised_is_comparable_across_n():
    rng = np.random.default_rng(10)
    for ratio in (0.0, 0.5):
        small = score_one(*correspondences(rng, 20, ratio, noise=0.0))
        large = score_one(*correspondences(rng, 400, ratio, noise=0.0))
        # The reference score has a floor of 1/n; the normalised one does not.
        if ratio == 0.0:
            assert small.score[0] >= 1 / 20 and large.score[0] >= 1 / 400
            assert small.normalised[0] < 0.05 and large.normalised[0] < 0.05
        else:
            assert small.normalised[0] == pytest.approx(0.5, abs=0.1)
            assert large.normalised[0] == pytest.approx(0.5, abs=0.05)


def test_rank_is_descending_and_stable():
    np.testing.assert_array_equal(rank(np.array([0.5, 0.7, 0.5, 0.7, 0.1])), [1, 3, 0, 2, 4])
    np.testing.assert_array_equal(rank([0.2, 0.2, 0.2]), [0, 1, 2])
    with pytest.raises(InputError):
        rank(np.zeros((2, 2)))


def test_invalid_inputs_raise_clear_errors():
    with pytest.raises(InputError, match="src must have shape"):
        sgv_scores(np.zeros((4, 3)), np.zeros((4, 3)), None, CPU)
    with pytest.raises(InputError, match="dst must have the shape"):
        sgv_scores(np.zeros((1, 4, 3)), np.zeros((1, 5, 3)), None, CPU)
    with pytest.raises(InputError, match="mask must have shape"):
        sgv_scores(np.zeros((1, 4, 3)), np.zeros((1, 4, 3)), np.ones((1, 3), bool), CPU)
    bad = np.zeros((1, 4, 3))
    bad[0, 2, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        sgv_scores(bad, np.zeros((1, 4, 3)), None, CPU)
    # NaN under the mask is padding, not an error.
    ok = sgv_scores(bad, np.zeros((1, 4, 3)), np.array([[True, True, False, True]]), CPU)
    assert ok.n[0] == 3 and np.isfinite(ok.score[0])
    with pytest.raises(InputError, match="cand_feats"):
        sgv_rerank_scores(
            np.zeros((3, 3)), np.zeros((3, 8)), [np.zeros((2, 3))], [np.zeros((2, 4))]
        )
    with pytest.raises(InputError, match="feature sets"):
        sgv_rerank_scores(np.zeros((3, 3)), np.zeros((3, 8)), [np.zeros((2, 3))], [])


# ---------------------------------------------------------------------------------------
# Correspondences and the convenience wrapper
# ---------------------------------------------------------------------------------------


def test_nn_correspondences_masks_and_empty_candidates():
    rng = np.random.default_rng(11)
    q = rng.normal(size=(6, 4)).astype(np.float32)
    cand = np.zeros((3, 8, 4), dtype=np.float32)
    mask = np.zeros((3, 8), dtype=bool)
    # Candidate 0: the query features reversed, scaled (cosine ignores scale).
    cand[0, :6] = 3.0 * q[::-1]
    mask[0, :6] = True
    # Padding identical to the queries must never be picked.
    cand[0, 6:] = q[:2]
    # Candidate 1: a single keypoint.
    cand[1, 0] = rng.normal(size=4)
    mask[1, 0] = True
    cand[1, 1:7] = q  # padding again
    # Candidate 2: no keypoints at all.
    idx = nn_correspondences(q, cand, mask).numpy()
    np.testing.assert_array_equal(idx[0], [5, 4, 3, 2, 1, 0])
    np.testing.assert_array_equal(idx[1], np.zeros(6))
    np.testing.assert_array_equal(idx[2], -np.ones(6))
    # Chunking over query rows gives the same answer.
    tiny = nn_correspondences(q, cand, mask, budget_bytes=1).numpy()
    np.testing.assert_array_equal(tiny, idx)
    # Equals brute-force L2 on normalised features.
    qn = q / np.linalg.norm(q, axis=1, keepdims=True)
    cn = cand[0, :6] / np.linalg.norm(cand[0, :6], axis=1, keepdims=True)
    brute = np.argmin(((qn[:, None] - cn[None]) ** 2).sum(-1), axis=1)
    np.testing.assert_array_equal(idx[0], brute)


def test_rerank_scores_pads_and_handles_empty_candidates():
    rng = np.random.default_rng(12)
    n, dim = 64, 16
    query_kp = rng.uniform(-30, 30, size=(n, 3)).astype(np.float32)
    query_feats = rng.normal(size=(n, dim)).astype(np.float32)
    cands = [
        synthetic_candidate(rng, query_kp, query_feats, 0.5, n_extra=30),
        (np.zeros((0, 3), np.float32), np.zeros((0, dim), np.float32)),
        synthetic_candidate(rng, query_kp, query_feats, 0.2),
    ]
    out = sgv_rerank_scores(query_kp, query_feats, [c[0] for c in cands], [c[1] for c in cands])
    np.testing.assert_array_equal(out.n, [n, 0, n])
    assert out.score[1] == 0.0 and out.v.shape == (3, n)
    np.testing.assert_array_equal(rank(out), [0, 2, 1])
    # Each candidate scored alone (no padding) gives the same score.
    for i in (0, 2):
        alone = sgv_rerank_scores(query_kp, query_feats, [cands[i][0]], [cands[i][1]], CPU)
        np.testing.assert_allclose(alone.score[0], out.score[i], rtol=1e-6)
        # ... which is the reference on the explicit correspondences.
        idx = nn_correspondences(query_feats, cands[i][1][None]).numpy()[0]
        ref = reference_sgv_score(query_kp, cands[i][0][idx], 0.4)
        np.testing.assert_allclose(alone.score[0], ref, rtol=1e-5)
    # No candidates at all.
    none = sgv_rerank_scores(query_kp, query_feats, [], [], CPU)
    assert none.score.shape == (0,)


def test_resolve_device():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type in ("cpu", "cuda")
    if not torch.cuda.is_available():
        with pytest.raises(Exception, match="CUDA is not available"):
            resolve_device("cuda")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    rng = np.random.default_rng(13)
    pairs, src, dst, mask = padded_batch(rng, [300, 200, 120, 5, 1])
    cpu = sgv_scores(src, dst, mask, CPU)
    gpu = sgv_scores(src, dst, mask, SGVConfig(device="cuda"))
    assert gpu.device.startswith("cuda")
    np.testing.assert_allclose(gpu.score, cpu.score, rtol=1e-5)
    np.testing.assert_allclose(gpu.normalised, cpu.normalised, rtol=1e-5, atol=1e-6)
    gpu_chunked = sgv_scores(src, dst, mask, SGVConfig(device="cuda"), dense_budget_bytes=0)
    assert gpu_chunked.path == "chunked"
    np.testing.assert_allclose(gpu_chunked.score, cpu.score, rtol=1e-5)
    again = sgv_scores(src, dst, mask, SGVConfig(device="cuda"))
    assert again.score.tobytes() == gpu.score.tobytes()
    n, dim = 128, 16
    query_kp = rng.uniform(-30, 30, size=(n, 3)).astype(np.float32)
    query_feats = rng.normal(size=(n, dim)).astype(np.float32)
    cands = [synthetic_candidate(rng, query_kp, query_feats, r) for r in (0.0, 0.4)]
    args = (query_kp, query_feats, [c[0] for c in cands], [c[1] for c in cands])
    a = sgv_rerank_scores(*args, CPU)
    b = sgv_rerank_scores(*args, SGVConfig(device="cuda"))
    np.testing.assert_allclose(b.score, a.score, rtol=1e-5)


def test_read_only_arrays_are_accepted_without_a_warning() -> None:
    """Arrays decoded from MessagePack (np.frombuffer) or memory-mapped are read-only."""
    import warnings

    rng = np.random.default_rng(0)
    q = rng.normal(size=(16, 8)).astype(np.float32)
    c = rng.normal(size=(2, 16, 8)).astype(np.float32)
    ro_q = np.frombuffer(q.tobytes(), np.float32).reshape(q.shape)
    ro_c = np.frombuffer(c.tobytes(), np.float32).reshape(c.shape)
    assert not ro_q.flags.writeable
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = nn_correspondences(ro_q, ro_c)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(nn_correspondences(q, c)))
