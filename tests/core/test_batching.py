"""Dynamic batching: concurrent localizations share network forwards and SGV kernel
calls, and get exactly the answers they get alone (real scans, real encoder)."""

from __future__ import annotations

import contextlib
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from sgvloc.core import batching
from sgvloc.core.batching import MicroBatcher
from sgvloc.core.config import LocalizerConfig
from sgvloc.core.encoders import EncoderSpec, make_encoder
from sgvloc.core.localizer import Localizer
from sgvloc.core.sequence import KittiSequence


@pytest.fixture(autouse=True)
def _no_batcher_left():
    batching.reset()
    yield
    batching.reset()


def _threads(fns, localizations: bool = False) -> list:
    """Run ``fns`` on threads started together. ``localizations``: each thread counts as
    a localization under way (batching.localizing) before any starts, as the localizer's
    own count would once all had begun, so that a busy machine starting one thread late
    cannot split the batch the test is about."""
    out = [None] * len(fns)
    start = threading.Barrier(len(fns))

    def run(i: int) -> None:
        with batching.localizing() if localizations else contextlib.nullcontext():
            start.wait()
            out[i] = fns[i]()

    ts = [threading.Thread(target=run, args=(i,)) for i in range(len(fns))]
    for t in ts:
        t.start()
    for t in ts:
        t.join(60)
    return out


def test_callers_share_one_batch_and_get_their_own_results() -> None:
    b = MicroBatcher(wait_ms=5000, max_size=8)
    calls = []

    def square_all(items: list[int]) -> list[int]:
        calls.append(list(items))
        return [x * x for x in items]

    def one(x: int):
        def f():
            with b.localizing():
                time.sleep(0.01 * x)  # arrive one after another
                return b.run("forward", "key", x, square_all)

        return f

    assert _threads([one(x) for x in range(1, 5)]) == [1, 4, 9, 16]
    assert len(calls) == 1 and sorted(calls[0]) == [1, 2, 3, 4]
    assert b.stats["forward"] == {"batches": 1, "items": 4, "largest": 4, "waited_out": 0}


def test_a_lone_caller_does_not_wait_and_a_full_batch_runs_at_once() -> None:
    b = MicroBatcher(wait_ms=5000, max_size=2)
    with b.localizing():
        assert b.run("forward", "k", 3, lambda xs: [x + 1 for x in xs]) == 4
    assert b.stats["forward"]["waited_out"] == 0  # nobody else under way: no wait

    def one(x: int):
        def f():
            with b.localizing():
                time.sleep(0.05)  # all four under way before the first arrives
                return b.run("forward", "k", x, lambda xs: [len(xs)] * len(xs))

        return f

    # four callers, batches of at most two
    assert _threads([one(x) for x in range(4)]) == [2, 2, 2, 2]
    assert b.stats["forward"]["largest"] == 2


def test_nobody_waits_for_a_localization_already_past_the_stage() -> None:
    b = MicroBatcher(wait_ms=5000, max_size=8)
    past = threading.Event()
    done = threading.Event()

    def busy_elsewhere() -> None:  # ran its forward, now in a long later stage
        with b.localizing():
            b.run("forward", "k", 0, lambda xs: xs)
            past.set()
            done.wait(30)

    t = threading.Thread(target=busy_elsewhere)
    t.start()
    try:
        assert past.wait(10)
        with b.localizing():
            assert b.run("forward", "k", 1, lambda xs: xs) == 1
    finally:
        done.set()
        t.join(10)
    # neither batch waited out its 5 s for the peer that was past the stage
    assert b.stats["forward"] == {"batches": 2, "items": 2, "largest": 1, "waited_out": 0}


def test_a_failure_reaches_every_member_of_the_batch() -> None:
    b = MicroBatcher(wait_ms=5000, max_size=4)

    def boom(items):
        raise ValueError("bad batch")

    def one():
        with b.localizing():
            time.sleep(0.05)
            try:
                b.run("forward", "k", 1, boom)
            except ValueError as exc:
                return str(exc)
        return "no error"

    assert _threads([one, one, one]) == ["bad batch"] * 3


def test_different_keys_never_share_a_batch() -> None:
    b = MicroBatcher(wait_ms=300, max_size=8)

    def one(key: str):
        def f():
            with b.localizing():
                time.sleep(0.05)
                return b.run("forward", key, key, lambda xs: ["".join(xs)] * len(xs))

        return f

    assert _threads([one("a"), one("b")]) == ["a", "b"]
    assert b.stats["forward"]["batches"] == 2


def test_bad_settings_are_refused() -> None:
    with pytest.raises(ValueError):
        MicroBatcher(wait_ms=-1, max_size=4)
    with pytest.raises(ValueError):
        MicroBatcher(wait_ms=1, max_size=0)


# -- the localizer on real scans ---------------------------------------------------------


@pytest.fixture(scope="module")
def two_maps(balm_mini_dir: Path):
    """Two maps of the fixture's database scans, each with its own encoder instance."""
    seq = KittiSequence(balm_mini_dir)
    roles = [
        ln.split()[1]
        for ln in (balm_mini_dir / "scans.txt").read_text().splitlines()
        if ln and not ln.startswith("#")
    ]
    maps = []
    for _ in range(2):
        loc = Localizer(make_encoder(EncoderSpec()), LocalizerConfig(top_k=6))
        for f, r in zip(seq, roles, strict=True):
            if r == "database":
                loc.add_keyframe(f.T_world_sensor, scan=f.scan().points)
        maps.append(loc)
    queries = [f.scan().points for f, r in zip(seq, roles, strict=True) if r == "query"]
    return maps, queries


def _key(res) -> tuple:
    return (
        res.localized,
        res.keyframe_id,
        res.confidence,
        None if res.T_map_sensor is None else res.T_map_sensor.tobytes(),
        tuple((c.keyframe_id, c.score) for c in res.reranked),
        res.reason,
    )


def test_batched_answers_equal_unbatched_ones_across_maps(two_maps) -> None:
    maps, queries = two_maps
    jobs = [(m, q) for q in queries for m in range(2)]  # every query on both maps
    alone = [
        _key(maps[m].localize(queries[q]))
        for m, q in [(m, i) for i in range(len(queries)) for m in range(2)]
    ]
    b = batching.configure(wait_ms=5000, max_size=8)
    together = _threads(
        [lambda m=m, q=q: _key(maps[m].localize(q)) for m, q in jobs], localizations=True
    )
    assert together == alone
    for stage in ("forward", "sgv"):
        s = b.stats[stage]
        assert s["items"] == len(jobs) and s["largest"] > 1, b.stats
        assert s["batches"] < len(jobs)


def test_two_maps_share_one_forward_and_one_sgv_call(two_maps) -> None:
    maps, queries = two_maps
    alone = [_key(maps[m].localize(queries[0])) for m in range(2)]
    b = batching.configure(wait_ms=10_000, max_size=8)
    together = _threads(
        [lambda m=m: _key(maps[m].localize(queries[0])) for m in range(2)], localizations=True
    )
    assert together == alone
    assert b.stats["forward"] == {"batches": 1, "items": 2, "largest": 2, "waited_out": 0}
    assert b.stats["sgv"] == {"batches": 1, "items": 2, "largest": 2, "waited_out": 0}


def test_wait_zero_is_the_unbatched_path(two_maps) -> None:
    maps, queries = two_maps
    before = [_key(maps[0].localize(q)) for q in queries[:3]]
    b = batching.configure(wait_ms=0, max_size=8)
    assert batching.current() is None  # every stage calls straight through
    after = _threads(
        [lambda q=q: _key(maps[0].localize(q)) for q in queries[:3]], localizations=True
    )
    assert after == before and b.stats == {}


def test_auto_is_off_without_cuda() -> None:
    import torch

    b = batching.configure(wait_ms=None, max_size=8)
    assert b.wait_ms == (batching.CUDA_WAIT_MS if torch.cuda.is_available() else 0.0)
    assert np.isfinite(b.wait_ms)


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_one_sgv_call_scores_several_queries_as_separate_calls(backend: str) -> None:
    """The batched SGV path: queries with different k and n padded into one call give
    each query's own scores (numba: exactly; torch: to float rounding)."""
    import torch

    from sgvloc.core.config import SGVConfig
    from sgvloc.core.sgv import _scores_many, sgv_scores

    rng = np.random.default_rng(0)
    cfg = SGVConfig(backend=backend)
    items = []
    for k, n in ((3, 40), (5, 64), (2, 17)):
        src = rng.uniform(-20, 20, (k, n, 3)).astype(np.float32)
        dst = src + rng.normal(0, 0.3, (k, n, 3)).astype(np.float32)
        mask = rng.random((k, n)) < 0.9
        if backend == "torch":
            src, dst, mask = torch.from_numpy(src), torch.from_numpy(dst), torch.from_numpy(mask)
        items.append((src, dst, mask))
    batched = _scores_many(items, cfg, 1 << 26)
    for (src, dst, mask), got in zip(items, batched, strict=True):
        alone = sgv_scores(src, dst, mask, cfg)
        tol = 0 if backend == "numba" else 1e-5
        np.testing.assert_allclose(got.score, alone.score, rtol=tol, atol=tol)
        np.testing.assert_allclose(got.v, alone.v, rtol=tol, atol=tol)
        assert np.array_equal(got.n, alone.n)
