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
        assert set(res.timings_ms) == {"encode", "retrieve", "rerank", "pose", "verify", "total"}
        assert res.map_version == loc.version
        # ICP ran, so the free-space check did: a true revisit contradicts little
        assert res.evidence.free_space is not None and res.evidence.free_space < 0.1
    plain = loc.localize(scans[queries[0].index], refine="none")
    assert plain.evidence.icp_fitness is None and plain.evidence.free_space is None


def test_the_learned_encoder_with_fpfh_keypoints_localizes(campus):
    """local_features "fpfh" end to end: the network's descriptor retrieves, RANSAC runs
    on FPFH and ICP on the 0.3 m clouds; every revisit is localized within tolerance."""
    _, db, queries, scans = campus
    spec = EncoderSpec(kind="learned", learned={"local_features": "fpfh"})
    loc = Localizer(make_encoder(spec), LocalizerConfig(top_k=10))
    for f in db:
        loc.add_keyframe(f.T_world_sensor, scan=f.scan().points)
    assert loc.keyframe(loc.keyframe_ids()[0]).features.local_features.shape[1] == 33
    for q in queries:
        res = loc.localize(scans[q.index])
        assert res.localized, (q.index, res.reason)
        t_err, r_err = pose_errors(res.T_map_sensor, q.T_world_sensor)
        assert t_err < 2.0 and r_err < 5.0, (q.index, t_err, r_err)
        assert res.evidence.icp_fitness is not None


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
        # sorted by score, except that a keyframe of the same place nearer the query may
        # come first (sgv.tie_tolerance)
        scores = [c.score for c in res.reranked]
        assert scores[1:] == sorted(scores[1:], reverse=True)
        first, top_scored = res.reranked[0], max(res.reranked, key=lambda c: c.score)
        if first is not top_scored:
            here = res.T_map_sensor[:3, 3]
            near = [
                np.linalg.norm(loc.keyframe(c.keyframe_id).T_map_sensor[:3, 3] - here)
                for c in (first, top_scored)
            ]
            assert near[0] < near[1], (q.index, near)


def test_the_nearest_keyframe_of_a_place_answers(tmp_path):
    """Two keyframes see one place: A, 10 m from the query, shares every landmark with
    it; B, 2 m from it, one in twenty fewer. SpectralGV scores A a little higher; with
    the default tie tolerance B comes first and the pose is estimated against it, with
    none A does."""
    rng = np.random.default_rng(7)
    enc = PrecomputedEncoder("toy", 8, 16)
    world = np.column_stack([rng.uniform(-30, 30, (200, 2)), rng.uniform(0, 5, 200)])
    desc = rng.normal(size=(200, 16))
    g = rng.normal(size=8)

    def seen_from(x: float, keep: np.ndarray):
        T = np.eye(4)
        T[0, 3] = x
        return T, enc.from_arrays(g, world[keep] - [x, 0.0, 0.0], desc[keep])

    every = np.arange(200)
    T_a, feats_a = seen_from(0.0, every)
    T_b, feats_b = seen_from(8.0, every[every % 20 != 0])
    _, query = seen_from(10.0, every)
    answers = {}
    for tolerance in (0.1, 0.0):
        config = LocalizerConfig(top_k=2)
        config.sgv.tie_tolerance = tolerance
        loc = Localizer(enc, config)
        a = loc.add_keyframe(T_a, features=feats_a)
        b = loc.add_keyframe(T_b, features=feats_b)
        res = loc.localize(features=query, refine="none")
        scores = {c.keyframe_id: c.score for c in res.reranked}
        assert scores[a] > scores[b] > 0.9 * scores[a]
        assert res.localized and abs(res.T_map_sensor[0, 3] - 10.0) < 1e-3
        answers[tolerance] = (res.keyframe_id, [c.keyframe_id for c in res.reranked])
        assert res.keyframe_id == res.reranked[0].keyframe_id
    assert answers[0.1] == (b, [b, a]) and answers[0.0] == (a, [a, b])


@pytest.mark.parametrize("method", METHODS)
def test_every_rerank_method_runs(campus, method):
    loc, _, queries, scans = campus
    res = loc.localize(scans[queries[0].index], rerank_method=method, top_k=4, refine="none")
    assert res.rerank_method == method
    # the default learned encoder merges the top-4 of its two global descriptors
    assert 4 <= len(res.reranked) <= 8 and len({c.keyframe_id for c in res.reranked}) == len(
        res.reranked
    )
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
    assert np.allclose(a.T_map_sensor_estimate, b.T_map_sensor_estimate)
    assert a.confidence == pytest.approx(b.confidence)
    # ICP needs the raw scan: with features only it is skipped, and says so
    c = loc.localize(features=feats, refine="icp")
    assert c.pose.icp["used"] is False


def test_features_from_another_encoder_are_refused(campus):
    loc, *_ = campus
    other = PrecomputedEncoder("egonn", 256, 128)
    rng = np.random.default_rng(0)
    feats = other.from_arrays(
        rng.normal(size=256), rng.normal(size=(10, 3)), rng.normal(size=(10, 128))
    )
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
        loc.add_keyframes(
            [
                loc.make_keyframe(
                    np.eye(4), scan=db[0].scan().points, keyframe_id=loc.keyframe_ids()[0]
                )
            ]
        )
    assert (len(loc), loc.version) == (n, version)


def test_insert_remove_and_version():
    enc = PrecomputedEncoder("toy", 8, 4)
    loc = Localizer(enc, LocalizerConfig(top_k=3))
    rng = np.random.default_rng(1)

    def feats():
        return enc.from_arrays(
            rng.normal(size=8), rng.normal(size=(20, 3)), rng.normal(size=(20, 4))
        )

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


def test_ids_removed_twice_or_coming_back_and_fresh_ids() -> None:
    """A repeated id is removed once (one version change); an id removed from an HNSW
    index (still held there until it compacts) can be added again, and a fresh id skips
    it and the explicit ids of its own batch."""
    from sgvloc.core.config import RetrievalConfig

    rng = np.random.default_rng(0)
    enc = PrecomputedEncoder("p", 16, 8)

    def kf(loc, x, **kw):
        feats = enc.from_arrays(
            rng.normal(size=16), rng.normal(size=(20, 3)), rng.normal(size=(20, 8))
        )
        T = np.eye(4)
        T[0, 3] = x
        return loc.make_keyframe(T, features=feats, **kw)

    for index, fresh in (("flat", [2, 4, 5]), ("hnsw", [2, 4, 6])):
        loc = Localizer(enc, LocalizerConfig(retrieval=RetrievalConfig(index=index)))
        assert loc.add_keyframes([kf(loc, 0.0, keyframe_id=5), kf(loc, 1.0)]) == [5, 1]
        loc.remove_keyframes([5, 5])
        assert loc.keyframe_ids() == [1] and loc.version == 2
        assert loc.index.ids().tolist() == [1]
        # fresh ids skip the batch's own ids, and with HNSW the removed id it still holds
        batch = [kf(loc, 2.0), kf(loc, 3.0), kf(loc, 4.0), kf(loc, 5.0, keyframe_id=3)]
        assert loc.add_keyframes(batch) == [*fresh, 3]
        if index == "hnsw":
            loc.add_keyframes([kf(loc, 6.0, keyframe_id=5)])  # the removed id comes back
            assert 5 in loc.keyframe_ids() and 5 in loc.index
        with pytest.raises(InputError, match="top_k"):
            loc.localize(features=kf(loc, 0.0).features, top_k=0)


def test_a_keyframe_removed_while_a_seeded_fit_runs(monkeypatch, balm_mini_dir) -> None:
    """The fit runs outside the map's lock; a write that lands meanwhile (here: every
    keyframe removed) leaves the answer as the map was when the submap was taken."""
    import sgvloc.core.localizer as localizer_module
    from sgvloc.core.tracking import Seed

    seq = KittiSequence(balm_mini_dir)
    frames = [seq[i] for i in range(4)]
    loc = Localizer(make_encoder(EncoderSpec(kind="handcrafted")))
    for f in frames:
        loc.add_keyframe(f.T_world_sensor, scan=f.scan().points)
    version = loc.version
    real = localizer_module.register

    def racing(*args, **kwargs):
        out = real(*args, **kwargs)
        loc.remove_keyframes(loc.keyframe_ids())
        return out

    monkeypatch.setattr(localizer_module, "register", racing)
    q = frames[1]
    res = loc.localize(q.scan().points, seed=Seed(q.T_world_sensor, 1.0, 5.0))
    assert res.mode == "tracked" and res.localized and res.map_version == version
    assert loc.keyframe_ids() == [] and res.keyframe_id is not None
    t_err, _ = pose_errors(res.T_map_sensor, q.T_world_sensor)
    assert t_err < 0.5


@pytest.fixture(scope="module")
def elsewhere(tmp_path_factory) -> np.ndarray:
    """A scan of another place: a synthetic town's street, nowhere in the campus map."""
    from sgvloc.tools.synth import SynthConfig, generate

    out = tmp_path_factory.mktemp("town") / "seq"
    generate(out, SynthConfig(scans=2, seed=5), progress=False)
    return KittiSequence(out)[1].scan().points


def test_a_scan_from_another_place_is_rejected_and_keeps_its_estimate(campus, elsewhere):
    loc, *_ = campus
    res = loc.localize(elsewhere)
    assert not res.localized and res.verdict in ("low_confidence", "pose_check")
    assert res.reason and res.T_map_sensor is None and res.T_keyframe_sensor is None
    assert res.T_map_sensor_estimate is not None and res.keyframe_id is not None
    assert res.confidence < res.min_confidence == loc.config.verdict.min_confidence
    assert res.evidence is not None


def test_min_confidence_per_request_changes_the_verdict_and_nothing_else(campus):
    loc, _, queries, scans = campus
    scan = scans[queries[0].index]
    usual = loc.localize(scan)
    strict = loc.localize(scan, min_confidence=1.0)
    lax = loc.localize(scan, min_confidence=0.0)
    assert usual.localized and lax.localized and usual.confidence < 1.0
    assert not strict.localized and strict.verdict == "low_confidence"
    assert "min_confidence 1" in strict.reason and strict.min_confidence == 1.0
    for other in (strict, lax):
        # (Open3D's ICP may differ in the last bits between runs)
        assert other.confidence == pytest.approx(usual.confidence, rel=1e-9)
        assert other.evidence.to_dict() == pytest.approx(usual.evidence.to_dict(), rel=1e-9)
        assert other.keyframe_id == usual.keyframe_id
        np.testing.assert_allclose(
            other.T_map_sensor_estimate, usual.T_map_sensor_estimate, atol=1e-9
        )
        assert [c.keyframe_id for c in other.reranked] == [c.keyframe_id for c in usual.reranked]
    with pytest.raises(InputError, match="min_confidence"):
        loc.localize(scan, min_confidence=1.5)


def test_a_prior_excludes_far_keyframes(campus):
    from sgvloc.core.prior import Prior

    loc, db, queries, scans = campus
    q = queries[0]
    free = loc.localize(scans[q.index])
    true_kf = loc.keyframe(free.keyframe_id).T_map_sensor[:3, 3]
    # a prior around the truth finds the same answer and says how many keyframes it saw
    at = loc.localize(scans[q.index], prior=Prior(tuple(q.T_world_sensor[:2, 3]), 10.0))
    inside = [
        kf for kf in db if np.linalg.norm(kf.T_world_sensor[:2, 3] - q.T_world_sensor[:2, 3]) <= 10
    ]
    assert at.localized and at.keyframe_id == free.keyframe_id
    assert at.prior == {"used": True, "keyframes_in_radius": len(inside)}
    assert len(at.retrieved) == min(len(inside), loc.config.top_k)
    # a prior 8 m away whose 4 m radius leaves the true match out: it is never returned
    away = q.T_world_sensor[:2, 3] + np.array([8.0, 0.0])
    res = loc.localize(scans[q.index], prior=Prior(tuple(away), 4.0))
    ids = {c.keyframe_id for c in res.retrieved}
    assert free.keyframe_id not in ids
    for i in ids:
        assert np.linalg.norm(loc.keyframe(i).T_map_sensor[:2, 3] - away) <= 4.0

    if (
        res.T_map_sensor_estimate is not None
        and np.linalg.norm(res.T_map_sensor_estimate[:2, 3] - away) > 4.0
    ):
        assert not res.localized and res.verdict == "outside_prior"
    assert np.linalg.norm(true_kf[:2] - away) > 4.0
    # nothing inside the radius: a clear answer, not an error
    empty = loc.localize(scans[q.index], prior=Prior((5000.0, 5000.0), 20.0))
    assert not empty.localized and empty.verdict == "no_keyframe_in_prior"
    assert "no keyframe within 20 m" in empty.reason
    assert empty.prior == {"used": True, "keyframes_in_radius": 0} and not empty.retrieved


@pytest.mark.parametrize("method", ["average-qe", "alpha-qe"])
def test_query_expansion_keeps_to_the_prior(method: str) -> None:
    """Query expansion searches a second time: inside the prior's region as well, even
    when a keyframe outside it matches the query best."""
    from sgvloc.core.prior import Prior

    rng = np.random.default_rng(1)
    enc = PrecomputedEncoder("p", 16, 8)
    e = np.eye(16)
    loc = Localizer(enc)

    def add(x: float, g: np.ndarray) -> int:
        T = np.eye(4)
        T[0, 3] = x
        f = enc.from_arrays(g, rng.normal(size=(20, 3)), rng.normal(size=(20, 8)))
        return loc.add_keyframe(T, features=f)

    far = add(100.0, e[0])  # the best match, 100 m from the prior
    near = {add(0.0, e[0] + 2 * e[1]), add(1.0, e[0] + 2 * e[2])}
    query = enc.from_arrays(e[0], rng.normal(size=(20, 3)), rng.normal(size=(20, 8)))
    res = loc.localize(features=query, prior=Prior((0.0, 0.0), 5.0), rerank_method=method)
    assert {c.keyframe_id for c in res.retrieved} == near
    assert {c.keyframe_id for c in res.reranked} == near and far not in near


def test_the_free_space_check_uses_only_the_keyframes_searched(campus):
    """With ``among`` (the self-test's leave-out), the free-space check looks only at
    those keyframes, so that a keyframe left out cannot vouch for the answer."""
    from sgvloc.core.freespace import RangeImage, thin, violation

    loc, _, queries, scans = campus
    scan = scans[queries[0].index]
    whole = loc.localize(scan)
    alone = loc.localize(scan, among=np.array([whole.keyframe_id]))
    assert alone.keyframe_id == whole.keyframe_id
    kf = loc.keyframe(alone.keyframe_id)
    expected = violation(
        thin(loc.encoder.prepare(scan)),
        alone.T_map_sensor_estimate,
        [(kf.T_map_sensor, RangeImage(kf.cloud))],
    )
    assert alone.evidence.free_space == pytest.approx(expected, rel=1e-12)
    assert alone.evidence.free_space != pytest.approx(whole.evidence.free_space, rel=1e-6)


@pytest.mark.parametrize("offset_m", [4.0, 0.0])
@pytest.mark.parametrize(
    "spec", [{"kind": "learned", "learned": {"global_descriptor": "polar"}}, {"kind": "bev"}]
)
def test_a_query_4_m_beside_a_keyframe_retrieves_it(balm_mini_dir, offset_m, spec):
    """Each keyframe's own scan, seen from 4 m beside it (ahead, left, behind, right), as
    a query with top_k 1 and a polar/FFT global descriptor (the learned encoder's, the bev
    encoder's): with the descriptor also
    about centres 4 m away (``retrieval.offset_m``) retrieval finds that keyframe every
    time, and so does the self-test's query of such a scan stored as a keyframe; about
    the sensor only they mostly do not."""
    frames = list(KittiSequence(balm_mini_dir))[:6]
    config = LocalizerConfig(top_k=1)
    config.retrieval.offset_m = offset_m
    loc = Localizer(make_encoder(EncoderSpec.model_validate(spec)), config)
    ids = {loc.add_keyframe(f.T_world_sensor, scan=f.scan().points): f for f in frames}
    found, beside_ids = [], {}
    for kid, f in ids.items():
        for deg in (0, 90, 180, 270):
            a = np.radians(deg)
            beside = f.scan().points[:, :3] - np.array([4.0 * np.cos(a), 4.0 * np.sin(a), 0.0])
            res = loc.localize(beside, refine="none")
            found.append([c.keyframe_id for c in res.retrieved] == [kid])
            if deg == 90:  # the self-test queries a keyframe as such a scan would
                beside_ids[loc.add_keyframe(f.T_world_sensor, scan=beside)] = kid
    among = np.array(sorted(ids))
    for b, kid in beside_ids.items():
        _, res = loc.localize_keyframe(b, among)
        found.append([c.keyframe_id for c in res.retrieved] == [kid])
    if offset_m:
        assert all(found)
    else:
        assert sum(found) < len(found) / 2


def test_a_tracked_fit_outside_the_prior_is_not_accepted(campus):
    """With a seed and a prior, the seeded fit must lie inside the prior's region too:
    here the prior is 100 m away, so the answer falls back to the global search, which
    finds no keyframe there."""
    from sgvloc.core.prior import Prior, yaw_deg
    from sgvloc.core.tracking import Seed

    loc, _, queries, scans = campus
    q = queries[0]
    T = q.T_world_sensor
    prior = Prior((T[0, 3] + 100.0, T[1, 3]), 5.0, yaw_deg=yaw_deg(T))
    res = loc.localize(scans[q.index], prior=prior, seed=Seed(T, 1.0, 5.0))
    assert not res.localized and res.mode == "relocalized"
    assert res.verdict == "no_keyframe_in_prior"
    assert "outside the prior region" in res.tracking["why"]
    # the same seed without the prior tracks
    assert loc.localize(scans[q.index], seed=Seed(T, 1.0, 5.0)).localized


def test_a_failed_tracked_fit_carries_no_confidence(campus):
    """A fit that fails a check (here a scan of one repeated point: too few points) is
    not trusted whatever its fitness says."""
    from sgvloc.core.tracking import Seed

    loc, _, queries, _ = campus
    T = queries[0].T_world_sensor
    one = np.tile(np.append(T[:3, 3] + [5.0, 0.0, 0.0], 1.0), (1000, 1)).astype(np.float32)
    one[:, :3] = (np.linalg.inv(T) @ one.T).T[:, :3]  # the point in the sensor frame
    res = loc.localize(one, seed=Seed(T, 1.0, 5.0))
    assert not res.localized and res.confidence == 0.0


def test_query_expansion_gives_every_candidate_its_similarity() -> None:
    """A keyframe that only the expanded search finds gets its own cosine similarity,
    not NaN (which an answer cannot carry)."""
    rng = np.random.default_rng(2)
    enc = PrecomputedEncoder("p", 3, 8)
    loc = Localizer(enc, LocalizerConfig(qe_k=1))
    kp, f = rng.uniform(-20, 20, (64, 3)), rng.normal(size=(64, 8))
    for x, g in enumerate(([1, 0.3, 0], [0.6, 0, 0.8], [0.55, 0.835, 0])):
        T = np.eye(4)
        T[0, 3] = 10.0 * x
        loc.add_keyframe(T, features=enc.from_arrays(np.array(g, float), kp, f))
    query = enc.from_arrays(np.array([1.0, 0.0, 0.0]), kp, f)
    res = loc.localize(features=query, top_k=2, rerank_method="average-qe")
    found = [c for c in res.reranked if c.retrieval_rank == -1]  # by the expansion only
    assert [c.keyframe_id for c in found] == [3]  # ids count from 1
    assert found[0].similarity == pytest.approx(0.55 / np.linalg.norm([0.55, 0.835]), abs=1e-5)


def test_a_keyframe_without_keypoints_leaves_other_queries_alone() -> None:
    """Features with no keypoints may come with local features of any width ([0, 0]);
    they take the encoder's width, so that a query retrieving them still answers."""
    rng = np.random.default_rng(3)
    enc = PrecomputedEncoder("p", 16, 8)
    loc = Localizer(enc)
    kfs = [enc.from_arrays(rng.normal(size=16), rng.normal(size=(40, 3)), rng.normal(size=(40, 8)))]
    loc.add_keyframe(np.eye(4), features=kfs[0])
    empty = enc.from_arrays(rng.normal(size=16), np.zeros((0, 3)), np.zeros((0, 0)))
    assert empty.local_features.shape == (0, 8)
    loc.add_keyframe(np.eye(4), features=empty)
    for method in ("none", "sgv"):
        res = loc.localize(features=kfs[0], rerank_method=method)
        assert res.localized, res.reason
    res = loc.localize(features=empty)  # a query without keypoints: no estimate, no error
    assert res.verdict == "no_estimate"


def test_a_settings_change_during_a_localization_is_not_mixed_into_it(monkeypatch) -> None:
    """The answer uses one settings change's config and calibration: a change landing
    after the localization read its settings applies to the next one only."""
    import sgvloc.core.localizer as localizer_module
    from sgvloc.core.confidence import Calibration, shipped_calibration

    rng = np.random.default_rng(4)
    enc = PrecomputedEncoder("p", 16, 8)
    loc = Localizer(enc)
    feats = enc.from_arrays(rng.normal(size=16), rng.normal(size=(60, 3)), rng.normal(size=(60, 8)))
    for x in (0.0, 20.0):
        T = np.eye(4)
        T[0, 3] = x
        loc.add_keyframe(T, features=feats)
    before = loc.localize(features=feats)
    never = shipped_calibration("precomputed").to_dict()
    for model in never["models"].values():
        model["bias"] = -50.0  # confidence ~0 whatever the evidence
    never = Calibration.from_dict(never)
    real = localizer_module.check_deadline

    def change_meanwhile(stage: str) -> None:
        if stage == "retrieval" and not swapped:  # after the settings were read
            swapped.append(stage)
            loc.update_settings(loc.config.model_copy(update={"top_k": 1}), never)
        real(stage)

    swapped: list[str] = []
    monkeypatch.setattr(localizer_module, "check_deadline", change_meanwhile)
    during = loc.localize(features=feats)
    assert swapped and during.confidence == before.confidence  # the settings it started with
    assert len(during.retrieved) == len(before.retrieved) == 2
    after = loc.localize(features=feats)
    assert after.confidence < 1e-6 and len(after.retrieved) == 1


def test_a_keyframe_deleted_in_the_store_is_no_answer_and_no_error(campus) -> None:
    """A copy that fetches local features and clouds from the store (a replica keeping
    only poses and global descriptors) may still list a keyframe another replica just
    deleted: localize answers from the other candidates instead of failing, the free-space
    check does without it, and tracking builds its submap without it."""
    from sgvloc.core.cache import FetchCache
    from sgvloc.core.tracking import Seed
    from sgvloc.server.maps import _slim

    loc, db, queries, scans = campus
    copy = Localizer(loc.encoder, loc.config)
    store = {i: loc.keyframe(i) for i in loc.keyframe_ids()}
    copy.add_keyframes([_slim(kf) for kf in store.values()])

    def source() -> FetchCache:  # a fresh cache: what the store holds now
        return FetchCache(lambda ids: {i: store[i] for i in ids if i in store}, 64)

    copy.keyframe_source = source()
    scan = scans[queries[0].index]
    first = copy.localize(scan)
    assert first.localized and first.keyframe_id == loc.localize(scan).keyframe_id
    del store[first.keyframe_id]  # deleted elsewhere; this copy has not caught up
    copy.keyframe_source = source()
    again = copy.localize(scan)
    assert again.keyframe_id != first.keyframe_id
    assert first.keyframe_id not in [c.keyframe_id for c in again.reranked]
    assert again.localized, again.reason  # the next keyframe of the place answers
    tracked = copy.localize(scan, seed=Seed(first.T_map_sensor, 2.0, 10.0))
    assert tracked.localized, tracked.reason
    store.clear()  # every candidate gone: the copy says so and asks for a retry
    copy.keyframe_source = source()
    with pytest.raises(ConflictError, match="catching up"):
        copy.localize(scan)
