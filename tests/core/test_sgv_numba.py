"""The fused CPU kernel (numba) against the numpy reference and the torch path.

``test_sgv.py`` runs its semantics tests with the default backend (numba on CPU); here
both backends are compared case by case, and the backend selection is checked.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_sgv import correspondences, padded_batch, random_rotation, synthetic_candidate

from sgvloc.core.config import SGVConfig
from sgvloc.core.errors import InputError, SgvlocError
from sgvloc.core.sgv import (
    _nn_torch,
    nn_correspondences,
    nn_correspondences_cpu,
    reference_sgv_score,
    resolve_backend,
    sgv_rerank_scores,
    sgv_scores,
    warm_up,
)

pytest.importorskip("numba")

NUMBA = SGVConfig(device="cpu", backend="numba")
TORCH = SGVConfig(device="cpu", backend="torch")


@pytest.fixture(scope="module", autouse=True)
def _warm():
    warm_up(NUMBA)


def test_backend_selection():
    cpu = torch.device("cpu")
    assert resolve_backend(SGVConfig(), cpu) == "numba"
    assert resolve_backend(TORCH, cpu) == "torch"
    assert resolve_backend(NUMBA, cpu) == "numba"
    assert resolve_backend(SGVConfig(), torch.device("cuda")) == "torch"
    with pytest.raises(SgvlocError, match="CPU only"):
        resolve_backend(NUMBA, torch.device("cuda"))
    rng = np.random.default_rng(0)
    src, dst = correspondences(rng, 30, 0.5)
    assert sgv_scores(src[None], dst[None], None, NUMBA).backend == "numba"
    assert sgv_scores(src[None], dst[None], None, TORCH).backend == "torch"
    assert warm_up(TORCH) == 0.0


@pytest.mark.parametrize("diagonal", ["one", "zero"])
@pytest.mark.parametrize("iterations", [1, 5, 12])
def test_random_cases_match_reference_and_torch(diagonal, iterations):
    rng = np.random.default_rng(100 + iterations)
    for n, ratio in [(2, 1.0), (3, 0.0), (17, 0.5), (90, 0.2), (333, 0.1), (512, 0.4)]:
        src, dst = correspondences(rng, n, ratio, noise=rng.uniform(0.0, 0.2))
        cfgs = [
            c.model_copy(update={"diagonal": diagonal, "iterations": iterations})
            for c in (NUMBA, TORCH)
        ]
        fast, slow = (sgv_scores(src[None], dst[None], None, c) for c in cfgs)
        ref = reference_sgv_score(src, dst, 0.4, iterations, diagonal)
        # M holds float32 entries in both kernels: one entry near d_thr between points
        # 30 m away is good to ~2e-5; n >= 10 averages that out below 1e-5.
        rtol = 1e-5 if n >= 10 else 5e-5
        np.testing.assert_allclose(fast.score[0], ref, rtol=rtol, atol=1e-7)
        np.testing.assert_allclose(fast.score[0], slow.score[0], rtol=rtol, atol=1e-7)
        np.testing.assert_allclose(fast.normalised, slow.normalised, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(fast.eigenvalue, slow.eigenvalue, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(fast.v, slow.v, atol=1e-5)


def test_masks_padding_and_batch_match_torch():
    rng = np.random.default_rng(1)
    pairs, src, dst, mask = padded_batch(rng, [90, 40, 64, 3, 1])
    mask[2, 10:20] = False  # holes inside a row too
    src[2, 10:20] = np.nan
    fast = sgv_scores(src, dst, mask, NUMBA)
    slow = sgv_scores(src, dst, mask, TORCH)
    np.testing.assert_array_equal(fast.n, slow.n)
    np.testing.assert_allclose(fast.score, slow.score, rtol=1e-5)
    np.testing.assert_allclose(fast.normalised, slow.normalised, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(fast.v, slow.v, atol=1e-5)
    assert np.all(fast.v[~mask] == 0)
    # Each candidate alone (compacted) scores the same as in the padded batch.
    for i in range(5):
        keep = mask[i]
        alone = sgv_scores(src[i, keep][None], dst[i, keep][None], None, NUMBA)
        np.testing.assert_allclose(alone.score[0], fast.score[i], rtol=1e-6)
        ref = reference_sgv_score(src[i, keep], dst[i, keep], 0.4)
        np.testing.assert_allclose(fast.score[i], ref, rtol=1e-5)


@pytest.mark.parametrize("diagonal", ["one", "zero"])
def test_matrix_free_equals_dense(diagonal):
    rng = np.random.default_rng(2)
    pairs, src, dst, mask = padded_batch(rng, [150, 100, 37, 1], garbage=0.0)
    cfg = NUMBA.model_copy(update={"diagonal": diagonal})
    dense = sgv_scores(src, dst, mask, cfg)
    free = sgv_scores(src, dst, mask, cfg, dense_budget_bytes=0)
    assert (dense.path, free.path) == ("dense", "chunked")
    np.testing.assert_allclose(free.score, dense.score, rtol=1e-6)
    np.testing.assert_allclose(free.normalised, dense.normalised, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(free.v, dense.v, atol=1e-6)
    assert (
        free.score.tobytes()
        == sgv_scores(src, dst, mask, cfg, dense_budget_bytes=0).score.tobytes()
    )


def test_large_n_matrix_free_matches_torch():
    rng = np.random.default_rng(3)
    n = 5000
    pairs = [correspondences(rng, n, r) for r in (0.3, 0.05)]
    src = np.stack([p[0] for p in pairs])
    dst = np.stack([p[1] for p in pairs])
    budget = 64 * 2**20  # M takes 100 MB per candidate: both kernels go matrix-free
    fast = sgv_scores(src, dst, None, NUMBA, dense_budget_bytes=budget)
    slow = sgv_scores(src, dst, None, TORCH, dense_budget_bytes=budget)
    assert fast.path == slow.path == "chunked"
    np.testing.assert_allclose(fast.score, slow.score, rtol=1e-5)
    np.testing.assert_allclose(fast.v, slow.v, atol=1e-5)
    assert fast.normalised[0] == pytest.approx(0.3, abs=0.03)


def test_edge_cases_match_torch():
    for cfg_update in ({}, {"diagonal": "zero"}, {"normalise": "none"}):
        f_cfg, t_cfg = (c.model_copy(update=cfg_update) for c in (NUMBA, TORCH))
        for src, mask in [
            (np.zeros((2, 0, 3)), None),
            (np.ones((1, 1, 3)), None),
            (np.zeros((0, 4, 3)), None),
            (np.random.default_rng(0).normal(size=(2, 5, 3)), np.array([[True] * 5, [False] * 5])),
        ]:
            fast = sgv_scores(src, src * 0.5, mask, f_cfg)
            slow = sgv_scores(src, src * 0.5, mask, t_cfg)
            np.testing.assert_array_equal(fast.n, slow.n)
            np.testing.assert_allclose(fast.score, slow.score, rtol=1e-6, atol=1e-7)
            np.testing.assert_allclose(fast.normalised, slow.normalised, rtol=1e-6, atol=1e-7)
            assert fast.v.shape == slow.v.shape and np.all(np.isfinite(fast.v))
    one = sgv_scores(np.ones((1, 1, 3)), np.zeros((1, 1, 3)), None, NUMBA)
    assert one.score[0] == 1.0 and one.normalised[0] == 0.0
    zero = sgv_scores(
        np.ones((1, 1, 3)), np.zeros((1, 1, 3)), None, NUMBA.model_copy(update={"diagonal": "zero"})
    )
    assert zero.score[0] == 0.0 and np.all(zero.v == 0)


@pytest.mark.parametrize("side", ["src", "dst"])
def test_rigid_invariance(side):
    rng = np.random.default_rng(4)
    src, dst = correspondences(rng, 400, 0.3)
    before = sgv_scores(src[None], dst[None], None, NUMBA)
    rot, t = random_rotation(rng), rng.uniform(-50, 50, size=3)
    moved = lambda p: (p.astype(np.float64) @ rot.T + t).astype(np.float32)  # noqa: E731
    src, dst = (moved(src), dst) if side == "src" else (src, moved(dst))
    after = sgv_scores(src[None], dst[None], None, NUMBA)
    np.testing.assert_allclose(after.score, before.score, rtol=1e-5)


def test_deterministic_and_thread_count_independent():
    numba = pytest.importorskip("numba")
    rng = np.random.default_rng(5)
    pairs, src, dst, mask = padded_batch(rng, [120, 80, 30])
    a = sgv_scores(src, dst, mask, NUMBA)
    b = sgv_scores(src, dst, mask, NUMBA)
    assert a.score.tobytes() == b.score.tobytes() and a.v.tobytes() == b.v.tobytes()
    c = sgv_scores(src, dst, mask, NUMBA, dense_budget_bytes=0)
    before = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        one_a = sgv_scores(src, dst, mask, NUMBA)
        one_c = sgv_scores(src, dst, mask, NUMBA, dense_budget_bytes=0)
    finally:
        numba.set_num_threads(before)
    assert one_a.score.tobytes() == a.score.tobytes()
    assert one_c.score.tobytes() == c.score.tobytes()


def test_input_errors_are_the_same():
    for cfg in (NUMBA, TORCH):
        with pytest.raises(InputError, match="src must have shape"):
            sgv_scores(np.zeros((4, 3)), np.zeros((4, 3)), None, cfg)
        with pytest.raises(InputError, match="dst must have the shape"):
            sgv_scores(np.zeros((1, 4, 3)), np.zeros((1, 5, 3)), None, cfg)
        with pytest.raises(InputError, match="mask must have shape"):
            sgv_scores(np.zeros((1, 4, 3)), np.zeros((1, 4, 3)), np.ones((1, 3), bool), cfg)
        bad = np.zeros((1, 4, 3))
        bad[0, 1, 2] = np.inf
        with pytest.raises(InputError, match="NaN or inf"):
            sgv_scores(bad, np.zeros((1, 4, 3)), None, cfg)
        with pytest.raises(InputError, match="real numbers"):
            sgv_scores(np.zeros((1, 4, 3), bool), np.zeros((1, 4, 3)), None, cfg)
    # torch tensors are accepted by the CPU kernel too
    t = torch.zeros(1, 4, 3)
    assert sgv_scores(t, t, None, NUMBA).n[0] == 4


def test_rerank_scores_match_torch_backend():
    rng = np.random.default_rng(6)
    n, dim = 256, 33
    query_kp = rng.uniform(-30, 30, size=(n, 3)).astype(np.float32)
    query_feats = rng.normal(size=(n, dim)).astype(np.float32)
    cands = [
        synthetic_candidate(rng, query_kp, query_feats, r, n_extra=e)
        for r, e in [(0.0, 40), (0.3, 0), (0.1, 7)]
    ]
    kps = [c[0] for c in cands] + [np.zeros((0, 3), np.float32)]
    fts = [c[1] for c in cands] + [np.zeros((0, dim), np.float32)]
    fast = sgv_rerank_scores(query_kp, query_feats, kps, fts, NUMBA)
    slow = sgv_rerank_scores(query_kp, query_feats, kps, fts, TORCH)
    assert fast.backend == "numba" and slow.backend == "torch"
    np.testing.assert_array_equal(fast.n, [n, n, n, 0])
    np.testing.assert_allclose(fast.score, slow.score, rtol=1e-5)
    np.testing.assert_array_equal(fast.order(), slow.order())


def test_nn_correspondences_cpu_equals_brute_force():
    rng = np.random.default_rng(7)
    k, n, nc, dim = 6, 70, 50, 33
    q = rng.normal(size=(n, dim)).astype(np.float32)
    c = rng.normal(size=(k, nc, dim)).astype(np.float32)
    mask = rng.random((k, nc)) < 0.7
    mask[3] = False
    mask[4] = False
    mask[4, 17] = True  # one real keypoint
    # Padding equal to query features, and negatively correlated real keypoints: padding
    # must lose even where every real similarity is negative.
    c[~mask] = np.resize(q, c[~mask].shape)
    c[5] = -np.resize(q, (nc, dim))
    idx = nn_correspondences(q, c, mask).numpy()
    qn = q / np.linalg.norm(q, axis=1, keepdims=True)
    for b in range(k):
        if not mask[b].any():
            assert np.all(idx[b] == -1)
            continue
        cn = c[b] / np.linalg.norm(c[b], axis=1, keepdims=True)
        d2 = ((qn[:, None] - cn[None]) ** 2).sum(-1)  # [N, Nc]
        d2[:, ~mask[b]] = np.inf
        brute = np.argmin(d2, axis=1)
        np.testing.assert_array_equal(idx[b], brute)
    np.testing.assert_array_equal(nn_correspondences(q, c, mask, budget_bytes=1).numpy(), idx)
    # The torch path (used on CUDA) gives the same answer.
    c0 = torch.as_tensor(np.where(mask[..., None], c, 0.0).astype(np.float32))
    ref = _nn_torch(torch.as_tensor(q), c0, torch.as_tensor(mask), 2**20)
    np.testing.assert_array_equal(ref.numpy(), idx)


def test_kernels_do_not_wait_for_each_other() -> None:
    """While one parallel kernel holds the workqueue lock (here: the test holds it), a
    small batch still runs; under OpenMP a large one does too. One large request must
    never hold up the others."""
    import threading

    import numba

    from sgvloc.core import sgv_numba

    sgv_numba.warm_up()
    rng = np.random.default_rng(1)
    small = rng.uniform(-5, 5, size=(2, 64, 3)).astype(np.float32)
    large = rng.uniform(-5, 5, size=(2, 1200, 3)).astype(np.float32)  # 2.9M entries
    cases = [small] + ([large] if numba.threading_layer() != "workqueue" else [])
    for pts in cases:
        done = threading.Event()

        def run(pts=pts, done=done) -> None:
            mask = np.ones(pts.shape[:2], np.bool_)
            sgv_numba.power_iteration(pts, pts, mask, 0.4, 3, 1.0, 2**40)
            done.set()

        with sgv_numba._LOCK:
            worker = threading.Thread(target=run, daemon=True)
            worker.start()
            assert done.wait(60), f"a batch of {pts.shape[1]} waited for the lock"


def test_nn_correspondences_from_lists_equal_the_padded_search() -> None:
    """The re-ranking path (candidates' own arrays, no padding copy) gives the same
    indices as the padded search, including a candidate without keypoints, and refuses
    NaN the same way."""
    rng = np.random.default_rng(11)
    q = rng.normal(size=(200, 32)).astype(np.float32)
    sizes = [150, 0, 37, 200, 1]
    cands = [rng.normal(size=(m, 32)).astype(np.float32) for m in sizes]
    cands[2][5] = q[7] * 3.0  # an exact match (after normalising) at a known place
    pad = np.zeros((len(sizes), max(sizes), 32), dtype=np.float32)
    mask = np.zeros((len(sizes), max(sizes)), dtype=bool)
    for i, c in enumerate(cands):
        pad[i, : len(c)], mask[i, : len(c)] = c, True
    got = nn_correspondences_cpu(q, cands)
    np.testing.assert_array_equal(got, nn_correspondences(q, pad, mask).numpy())
    assert (got[1] == -1).all() and (got[4] == 0).all() and got[2, 7] == 5
    np.testing.assert_array_equal(nn_correspondences_cpu(q, cands, budget_bytes=1), got)
    cands[3][4, 2] = np.nan
    with pytest.raises(InputError, match="cand_feats"):
        nn_correspondences_cpu(q, cands)
