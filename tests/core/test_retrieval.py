"""FAISS wrapper: stable ids, removal, persistence, all three index kinds."""

import threading

import numpy as np
import pytest

from sgvloc.core.config import RetrievalConfig
from sgvloc.core.errors import ConflictError, InputError, NotFoundError
from sgvloc.core.retrieval import FaissIndex, SearchHit, merge_hits, retrieve

KINDS = ["flat", "ivf", "hnsw"]


def _vectors(n: int, dim: int = 32, seed: int = 0) -> np.ndarray:
    x = np.random.default_rng(seed).normal(size=(n, dim)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _index(kind: str, dim: int = 32) -> FaissIndex:
    return FaissIndex(dim, RetrievalConfig(index=kind, nlist=4, nprobe=4))


@pytest.mark.parametrize("kind", KINDS)
def test_search_returns_stable_ids_and_exact_self_match(kind):
    x = _vectors(400)
    ids = np.arange(10_000, 10_400)
    index = _index(kind)
    index.add(ids[:150], x[:150])
    index.add(ids[150:], x[150:])  # ivf: crosses the training size here
    assert len(index) == 400
    assert index.kind == kind
    for row in (0, 199, 399):
        hit = index.search(x[row], 5)[0][0]
        assert hit.id == ids[row]
        assert hit.similarity == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize("kind", KINDS)
def test_remove_hides_the_id_and_keeps_the_others(kind):
    x = _vectors(300)
    ids = np.arange(300) * 7 + 3
    index = _index(kind)
    index.add(ids, x)
    index.remove([ids[10], ids[20]])
    assert len(index) == 298
    assert ids[10] not in index.ids()
    hits = index.search(x[10], 10)[0]
    assert ids[10] not in [h.id for h in hits]
    assert index.search(x[11], 1)[0][0].id == ids[11]  # other ids did not shift
    with pytest.raises(NotFoundError):
        index.remove([ids[10]])


@pytest.mark.parametrize("kind", KINDS)
def test_save_load_roundtrip(kind, tmp_path):
    x = _vectors(300, seed=1)
    ids = np.arange(500, 800)
    index = _index(kind)
    index.add(ids, x)
    index.remove([ids[3]])
    path = tmp_path / "map.faiss"
    index.save(path)
    loaded = FaissIndex.load(path)
    assert loaded.kind == kind
    assert np.array_equal(loaded.ids(), index.ids())
    for row in (0, 150, 299):
        assert loaded.search(x[row], 3)[0][0].id == ids[row]
    assert not list(tmp_path.glob("*.tmp"))


def test_a_snapshot_that_cannot_be_written_leaves_the_last_one(tmp_path):
    """A write that fails (here: past the process's file size limit, as on a full disk)
    raises and leaves the previous snapshot whole: FAISS's own writer only printed the
    error, and the truncated file replaced the good one."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent(
        f"""
        import resource, signal
        import numpy as np
        from sgvloc.core.retrieval import FaissIndex

        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG)
        rng = np.random.default_rng(0)
        index = FaissIndex(32)
        index.add(np.arange(10), rng.normal(size=(10, 32)).astype(np.float32))
        path = {str(tmp_path / "map.faiss")!r}
        index.save(path)
        index.add(np.arange(10, 5010), rng.normal(size=(5000, 32)).astype(np.float32))
        resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))
        try:
            index.save(path)
        except OSError as exc:
            print("refused", exc.errno)
        """
    )
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("refused"), run.stdout + run.stderr
    assert len(FaissIndex.load(tmp_path / "map.faiss")) == 10
    assert not list(tmp_path.glob("*.tmp"))


def test_corrupt_snapshot_is_refused(tmp_path):
    index = _index("flat")
    index.add(np.arange(3), _vectors(3))
    path = tmp_path / "map.faiss"
    index.save(path)
    path.write_bytes(b"garbage" * 10)
    with pytest.raises(InputError, match="map.faiss"):
        FaissIndex.load(path)


def test_bad_inputs():
    index = _index("flat", dim=8)
    with pytest.raises(InputError, match=r"\[M, 8\]"):
        index.add([1], np.ones((1, 9), np.float32))
    with pytest.raises(InputError, match="NaN"):
        index.add([1], np.full((1, 8), np.nan, np.float32))
    with pytest.raises(InputError, match="zeros"):
        index.add([1], np.zeros((1, 8), np.float32))
    index.add([1], np.ones((1, 8), np.float32))
    with pytest.raises(ConflictError):
        index.add([1], np.ones((1, 8), np.float32))
    assert len(index) == 1
    with pytest.raises(InputError):
        index.search(np.ones(8), 0)


def test_fewer_vectors_than_k_and_empty_index():
    index = _index("flat", dim=8)
    assert index.search(np.ones(8), 5) == [[]]
    index.add([4, 5], _vectors(2, dim=8))
    assert len(index.search(np.ones(8), 5)[0]) == 2


def test_concurrent_search_and_add_agree():
    x = _vectors(2000, seed=3)
    index = _index("flat")
    index.add(np.arange(1000), x[:1000])
    errors = []

    def searcher():
        try:
            for row in range(0, 1000, 10):
                assert index.search(x[row], 1)[0][0].id == row
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    def writer():
        for start in range(1000, 2000, 100):
            index.add(np.arange(start, start + 100), x[start : start + 100])

    threads = [threading.Thread(target=searcher) for _ in range(3)] + [
        threading.Thread(target=writer)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert len(index) == 2000


def _two_blocks(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vectors of two unit blocks (12-D and 20-D) concatenated and scaled to unit length."""
    a, b = _vectors(n, 12, seed), _vectors(n, 20, seed + 1)
    return a, b, np.hstack([a, b]) / np.sqrt(2)


@pytest.mark.parametrize("kind", KINDS)
def test_merged_retrieval_unites_each_blocks_top_k(kind):
    """Merging returns each keyframe once: exactly the union of each block's own top-k
    (never fewer candidates than either alone), ordered by the whole descriptor."""
    a, b, x = _two_blocks(300)
    ids = np.arange(5000, 5300)
    index = _index(kind, dim=32)
    index.add(ids, x)
    qa, qb, q = _two_blocks(5, seed=7)
    for row in range(5):
        for k in (1, 5, 20):
            hits = retrieve(index, q[row], k, (12, 20), "merge")
            got = [h.id for h in hits]
            assert len(got) == len(set(got))
            top_a = set(ids[np.argsort(-(a @ qa[row]))[:k]].tolist())
            top_b = set(ids[np.argsort(-(b @ qb[row]))[:k]].tolist())
            if kind == "flat":  # exact search: exactly the union
                assert set(got) == top_a | top_b
            assert len(got) >= k
            sims = [h.similarity for h in hits]
            assert sims == sorted(sims, reverse=True)
            whole = x[np.searchsorted(ids, got)] @ q[row]
            np.testing.assert_allclose(sims, whole, atol=1e-5)
        # one block, or combine="concat": the whole descriptor's plain top-k
        plain = [h.id for h in index.search(q[row], 10)[0]]
        assert [h.id for h in retrieve(index, q[row], 10, (32,), "merge")] == plain
        assert [h.id for h in retrieve(index, q[row], 10, (12, 20), "concat")] == plain


def test_merged_retrieval_keeps_to_a_prior_selection_and_checks_blocks():
    a, b, x = _two_blocks(200)
    index = _index("flat", dim=32)
    index.add(np.arange(200), x)
    among = np.arange(0, 200, 7)
    hits = retrieve(index, x[3], 10, (12, 20), "merge", among=among)
    assert hits and {h.id for h in hits} <= set(among.tolist())
    with pytest.raises(InputError, match="blocks"):
        retrieve(index, x[3], 10, (12, 19), "merge")


def test_merge_hits_orders_the_union_and_breaks_ties_by_id():
    one = [SearchHit(4, 0.9), SearchHit(2, 0.5), SearchHit(9, 0.1)]
    two = [SearchHit(7, 0.5), SearchHit(4, 0.9), SearchHit(1, 0.8)]
    assert [h.id for h in merge_hits([one, two], 2)] == [4, 2, 7]
    assert [h.id for h in merge_hits([one, two], 3)] == [4, 1, 2, 7, 9]
    assert merge_hits([[], []], 5) == []


@pytest.mark.parametrize("kind", KINDS)
def test_variants_rank_each_keyframe_by_its_best_similarity(kind):
    """A query's descriptor about displaced centres (variants of the first block only):
    that block's candidates are the top-k of each keyframe's best similarity over the
    query and its variants, each once; the other block's stay its own; the hits keep
    the query descriptor's similarity."""
    a, b, x = _two_blocks(300)
    ids = np.arange(300)
    index = _index(kind, dim=32)
    index.add(ids, x)
    qa, qb, q = _two_blocks(1, seed=7)
    moved = _vectors(4, 12, seed=9)  # the first block about four other centres
    variants = np.hstack([moved, np.repeat(qb, 4, axis=0)]) / np.sqrt(2)
    for k in (1, 5, 20):
        lists = index.search_blocks(q[0], k, (12, 20), variants=variants)
        best = np.max(np.vstack([qa, moved]) @ a.T, axis=0)  # [300]
        got_a = [h.id for h in lists[0]]
        assert len(got_a) == len(set(got_a)) == k
        if kind == "flat":
            assert got_a == np.argsort(-best, kind="stable")[:k].tolist()
            assert [h.id for h in lists[1]] == np.argsort(-(b @ qb[0]))[:k].tolist()
        whole = x[got_a] @ q[0]
        np.testing.assert_allclose([h.similarity for h in lists[0]], whole, atol=1e-5)
        merged = retrieve(index, q[0], k, (12, 20), "merge", variants=variants)
        assert len(merged) >= k and len({h.id for h in merged}) == len(merged)
        if kind == "flat":
            assert {h.id for h in merged} == set(got_a) | {h.id for h in lists[1]}
    # variants equal to the query change nothing; neither do none at all
    same = np.repeat(q, 3, axis=0)
    for k in (1, 10):
        plain = retrieve(index, q[0], k, (12, 20), "merge")
        assert retrieve(index, q[0], k, (12, 20), "merge", variants=same) == plain
        assert retrieve(index, q[0], k, (12, 20), "merge", variants=np.zeros((0, 32))) == plain


def test_variants_of_a_one_block_descriptor_and_a_prior_selection():
    x = _vectors(200)
    index = _index("flat")
    index.add(np.arange(200), x)
    q, variants = _vectors(1, seed=3)[0], _vectors(8, seed=4)
    best = np.max(np.vstack([q, variants]) @ x.T, axis=0)
    hits = retrieve(index, q, 10, (32,), "merge", variants=variants)
    assert [h.id for h in hits] == np.argsort(-best, kind="stable")[:10].tolist()
    np.testing.assert_allclose([h.similarity for h in hits], x[[h.id for h in hits]] @ q, 1e-5)
    among = np.arange(0, 200, 5)
    hits = retrieve(index, q, 10, (32,), "concat", among=among, variants=variants)
    assert [h.id for h in hits] == among[np.argsort(-best[among], kind="stable")[:10]].tolist()


@pytest.mark.parametrize("kind", KINDS)
def test_a_selection_is_searched_exactly_in_bounded_chunks(kind, monkeypatch):
    """Among selected ids: the exact top-k of the selection (ties to the lower id), also
    when IVF and HNSW compare it a few vectors at a time; unsorted ids with repeats and
    removed or unknown ids are taken as the set they name; a selection of every live id
    answers as the whole map."""
    import sgvloc.core.retrieval as retrieval

    monkeypatch.setattr(retrieval, "AMONG_CHUNK", 7)
    x = _vectors(300, seed=3)
    ids = np.arange(300) * 3 + 5
    index = _index(kind)
    index.add(ids, x)
    index.remove(ids[10])
    q = _vectors(1, seed=4)
    sims = x @ q[0]
    chosen = ids[(np.arange(300) % 4 == 1) | (np.arange(300) < 20)]
    messy = np.concatenate([chosen[::-1], chosen[:30], [ids[10], 10_000]])
    expect = [int(i) for i in chosen[np.argsort(-sims[(chosen - 5) // 3], kind="stable")]]
    expect = [i for i in expect if i != ids[10]][:12]
    hits = index.search(q, 12, among=messy)[0]
    assert [h.id for h in hits] == expect
    assert [h.similarity for h in hits] == pytest.approx(
        [float(sims[(i - 5) // 3]) for i in expect], abs=1e-5
    )
    live = np.array([i for i in ids if i != ids[10]])
    assert index.search(q, 12, among=live) == index.search(q, 12)
    # a keyframe added after the selection was made is not in it
    index.add(np.array([2000]), q)
    assert 2000 not in {h.id for h in index.search(q, 12, among=live)[0]}
    assert index.search(q, 1)[0][0].id == 2000
