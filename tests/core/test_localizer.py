"""The whole pipeline on real scans: encode -> retrieve -> re-rank -> pose."""

import numpy as np
import pytest

from sgvloc.core.config import LocalizerConfig
from sgvloc.core.encoders import EncoderSpec, PrecomputedEncoder, make_encoder
from sgvloc.core.errors import ConflictError, EncoderMismatchError, InputError, NotFoundError
from sgvloc.core.localizer import Localizer
from sgvloc.core.rerank import METHODS
from sgvloc.core.sequence import KittiSequence


def pose_errors(T_est, T_gt):
    cos = (np.trace(T_est[:3, :3].T @ T_gt[:3, :3]) - 1.0) / 2.0
    return float(np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3])), float(
        np.degrees(np.arccos(np.clip(cos, -1, 1)))
    )


@pytest.fixture(scope="module")
def campus(balm_mini_dir):
    seq = KittiSequence(balm_mini_dir)
    roles = [
        line.split()[1]
        for line in (balm_mini_dir / "scans.txt").read_text().splitlines()
        if line and not line.startswith("#")
    ]
    db = [f for f, r in zip(seq, roles, strict=True) if r == "database"]
    queries = [f for f, r in zip(seq, roles, strict=True) if r == "query"]
    loc = Localizer(make_encoder(EncoderSpec()), LocalizerConfig(top_k=10))
    for f in db:
        loc.add_keyframe(f.T_world_sensor, scan=f.scan().points, metadata={"index": f.index})
    scans = {f.index: f.scan().points for f in queries}
    return loc, db, queries, scans


def test_revisit_queries_localize_within_tolerance(campus):
    loc, db, queries, scans = campus
    for q in queries:
        res = loc.localize(scans[q.index])
        assert res.localized, (q.index, res.reason)
        t_err, r_err = pose_errors(res.T_map_sensor, q.T_world_sensor)
        assert t_err < 2.0 and r_err < 5.0, (q.index, t_err, r_err)
        # frames compose: T_map_sensor = T_map_keyframe @ T_keyframe_sensor
        T_map_kf = loc.keyframe(res.keyframe_id).T_map_sensor
        assert np.allclose(res.T_map_sensor, T_map_kf @ res.T_keyframe_sensor)
        assert set(res.timings_ms) == {"encode", "retrieve", "rerank", "pose", "total"}
        assert res.map_version == loc.version


def test_sgv_puts_a_true_revisit_first(campus):
    loc, _, queries, scans = campus
    for q in queries:
        res = loc.localize(scans[q.index], rerank_method="sgv")
        best = loc.keyframe(res.reranked[0].keyframe_id).T_map_sensor
        assert np.linalg.norm(best[:3, 3] - q.T_world_sensor[:3, 3]) < 5.0, q.index
        # the re-ranked list is a permutation of the retrieved one, sorted by score
        assert sorted(c.keyframe_id for c in res.reranked) == sorted(
            c.keyframe_id for c in res.retrieved
        )
        scores = [c.score for c in res.reranked]
        assert scores == sorted(scores, reverse=True)


@pytest.mark.parametrize("method", METHODS)
def test_every_rerank_method_runs(campus, method):
    loc, _, queries, scans = campus
    res = loc.localize(scans[queries[0].index], rerank_method=method, top_k=4, refine="none")
    assert res.rerank_method == method
    assert 1 <= len(res.reranked) <= 4
    assert all(np.isfinite(c.score) for c in res.reranked)
    if method == "none":
        assert [c.keyframe_id for c in res.reranked] == [c.keyframe_id for c in res.retrieved]
        assert not res.top1_changed


def test_precomputed_features_give_the_same_answer(campus):
    loc, _, queries, scans = campus
    feats = loc.encode(scans[queries[1].index])
    a = loc.localize(features=feats, refine="none")
    b = loc.localize(scans[queries[1].index], refine="none")
    assert a.keyframe_id == b.keyframe_id
    assert np.allclose(a.T_map_sensor, b.T_map_sensor)
    # ICP needs the raw scan: with features only it is skipped, and says so
    c = loc.localize(features=feats, refine="icp")
    assert c.pose.icp["used"] is False


def test_features_from_another_encoder_are_refused(campus):
    loc, *_ = campus
    other = PrecomputedEncoder("egonn", 256, 128)
    rng = np.random.default_rng(0)
    feats = other.from_arrays(rng.normal(size=256), rng.normal(size=(10, 3)),
                              rng.normal(size=(10, 128)))
    version = loc.version
    with pytest.raises(EncoderMismatchError, match="egonn"):
        loc.add_keyframe(np.eye(4), features=feats)
    with pytest.raises(EncoderMismatchError):
        loc.localize(features=feats)
    assert loc.version == version


def test_bad_calls(campus):
    loc, db, _, scans = campus
    n, version = len(loc), loc.version
    with pytest.raises(InputError, match="rigid"):
        loc.add_keyframe(np.diag([2.0, 1, 1, 1]), scan=db[0].scan().points)
    with pytest.raises(InputError, match="exactly one"):
        loc.add_keyframe(np.eye(4))
    with pytest.raises(InputError, match="empty"):
        loc.add_keyframe(np.eye(4), scan=np.zeros((0, 3), np.float32))
    with pytest.raises(InputError, match="re-ranking method"):
        loc.localize(next(iter(scans.values())), rerank_method="magic")
    with pytest.raises(NotFoundError):
        loc.remove_keyframe(999_999)
    with pytest.raises(ConflictError):
        loc.add_keyframes([loc.make_keyframe(np.eye(4), scan=db[0].scan().points,
                                             keyframe_id=loc.keyframe_ids()[0])])
    assert (len(loc), loc.version) == (n, version)


def test_insert_remove_and_version():
    enc = PrecomputedEncoder("toy", 8, 4)
    loc = Localizer(enc, LocalizerConfig(top_k=3))
    rng = np.random.default_rng(1)

    def feats():
        return enc.from_arrays(rng.normal(size=8), rng.normal(size=(20, 3)),
                               rng.normal(size=(20, 4)))

    empty = loc.localize(features=feats())
    assert not empty.localized and "no keyframes" in empty.reason
    a = loc.add_keyframe(np.eye(4), features=feats())
    b = loc.add_keyframe(np.eye(4), features=feats(), keyframe_id=100)
    assert (a, b) == (1, 100) and loc.version == 2 and len(loc) == 2
    # a batch is all-or-nothing: the duplicate id 100 rejects the whole batch
    batch = [loc.make_keyframe(np.eye(4), features=feats()) for _ in range(2)]
    batch.append(loc.make_keyframe(np.eye(4), features=feats(), keyframe_id=100))
    with pytest.raises(ConflictError):
        loc.add_keyframes(batch)
    assert len(loc) == 2 and len(loc.index) == 2
    loc.remove_keyframe(a)
    assert loc.version == 3 and loc.keyframe_ids() == [100]
    with pytest.raises(NotFoundError):
        loc.keyframe(a)
