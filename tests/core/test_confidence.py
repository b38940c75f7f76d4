"""The evidence behind an answer, the calibrated confidence and the verdict."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from pose_helpers import planar_pose as _T

from sgvloc.core.confidence import (
    PROFILE_FEATURES,
    PROFILES,
    Calibration,
    Evidence,
    LogisticModel,
    SpectralCandidate,
    decide,
    gather_evidence,
    nearest_of_place,
    poses_agree,
    rigid_fit,
    shared_view,
    shipped_calibration,
    spectral_pose,
)
from sgvloc.core.errors import InputError
from sgvloc.core.pose import PoseResult
from sgvloc.core.prior import Prior
from sgvloc.tools.calibrate import evidence_matrix, fit_logistic

GOOD = Evidence(
    sgv=0.3,
    sgv_margin=0.2,
    similarity=0.9,
    inliers=60,
    inlier_ratio=0.5,
    icp_fitness=0.85,
    icp_rmse=0.25,
    free_space=0.02,
    icp_constraint=0.25,
    agreement=3,
    offset_m=1.0,
)


@pytest.mark.parametrize("kind", ["learned", "handcrafted", "bev", "precomputed"])
def test_the_shipped_calibration_loads_for_every_encoder_kind(kind: str) -> None:
    cal = shipped_calibration(kind)
    assert "icp" in cal.models and set(cal.models) <= set(PROFILES)
    assert cal.encoder_kind in ("learned", kind)
    for profile, model in cal.models.items():
        assert model.features == list(PROFILE_FEATURES[profile])  # every current input
        assert all(w >= 0 for w in model.weights)
    assert 0.0 <= cal.confidence(GOOD) <= 1.0


_RISING = [
    ("inliers", [3, 8, 20, 60, 200]),
    ("sgv_margin", [0.0, 0.02, 0.05, 0.1, 0.3]),
    ("sgv", [0.02, 0.05, 0.1, 0.3, 0.6]),
    ("inlier_ratio", [0.05, 0.1, 0.2, 0.5, 0.9]),
    ("agreement", [0, 1, 2, 3]),
]


@pytest.mark.parametrize(
    "profile, field, values",
    [(p, *r) for p in ("planar", "none", "icp") for r in _RISING]
    + [
        ("icp", "icp_fitness", [0.1, 0.3, 0.5, 0.7, 0.95]),
        ("icp", "free_space", [0.6, 0.3, 0.1, 0.03, 0.0]),  # less contradiction: better
        ("icp", "icp_constraint", [0.0, 0.02, 0.05, 0.15, 0.3]),
    ],
)
def test_confidence_rises_with_the_evidence(profile: str, field: str, values: list) -> None:
    cal = shipped_calibration("learned")
    base = GOOD
    if profile != "icp":
        base = dataclasses.replace(
            GOOD,
            icp_fitness=None,
            icp_rmse=None,
            free_space=None,
            icp_constraint=None,
            planar=profile == "planar",
        )
    assert base.profile == profile
    # from weak evidence elsewhere, so that the probability is not saturated at 1
    weak = dataclasses.replace(
        base, sgv=0.06, sgv_margin=0.01, inliers=6, inlier_ratio=0.12, agreement=0
    )
    if base.icp_fitness is not None:
        weak = dataclasses.replace(
            weak, icp_fitness=0.45, icp_rmse=0.45, free_space=0.15, icp_constraint=0.1
        )
    conf = [cal.confidence(dataclasses.replace(weak, **{field: v})) for v in values]
    assert all(b >= a for a, b in zip(conf, conf[1:], strict=False)), conf
    # lower RMSE and a smaller offset are better evidence too
    if profile == "icp":
        assert cal.confidence(dataclasses.replace(weak, icp_rmse=0.2)) >= cal.confidence(
            dataclasses.replace(weak, icp_rmse=0.6)
        )


def test_the_shared_view_of_two_discs() -> None:
    assert shared_view(0.0) == pytest.approx(1.0)
    assert shared_view(50.0) == 0.0 and shared_view(80.0) == 0.0  # two radii apart
    # one radius apart: the lens is 2/3 - sqrt(3)/(2 pi) of the disc
    assert shared_view(10.0, radius_m=10.0) == pytest.approx(2 / 3 - 3**0.5 / (2 * np.pi))
    views = [shared_view(d) for d in (0.0, 5.0, 10.0, 20.0, 30.0, 45.0)]
    assert all(b < a for a, b in zip(views, views[1:], strict=False))


def test_planar_inliers_count_more_in_a_smaller_common_view_up_to_a_bound() -> None:
    cal = shipped_calibration("learned")
    weak = Evidence(
        sgv=0.06, sgv_margin=0.01, similarity=0.8, inliers=12, inlier_ratio=0.15, planar=True
    )
    conf = [cal.confidence(dataclasses.replace(weak, offset_m=d)) for d in (0.0, 8.0, 16.0)]
    assert conf[0] < conf[1] < conf[2], conf
    # from about 20 m (a common view of half the disc) the offset adds nothing more
    far = [cal.confidence(dataclasses.replace(weak, offset_m=d)) for d in (21.0, 35.0, 60.0)]
    assert far[0] == far[1] == far[2] > conf[2]
    # 3-D answers do not take the offset in
    three_d = dataclasses.replace(weak, planar=False)
    assert cal.confidence(three_d) == cal.confidence(dataclasses.replace(three_d, offset_m=16.0))


def test_strong_evidence_is_confident_and_weak_evidence_is_not() -> None:
    cal = shipped_calibration("learned")
    weak = Evidence(
        sgv=0.04,
        sgv_margin=0.0,
        similarity=0.8,
        inliers=4,
        inlier_ratio=0.06,
        icp_fitness=0.2,
        icp_rmse=0.6,
        free_space=0.4,
        agreement=0,
        offset_m=12.0,
    )
    assert cal.confidence(GOOD) > 0.9
    assert cal.confidence(weak) < 0.1


def test_fit_keeps_weights_non_negative_and_separates() -> None:
    rng = np.random.default_rng(0)
    n = 400
    y = rng.random(n) < 0.4
    ev = [
        Evidence(
            sgv=float(rng.normal(0.3 if t else 0.05, 0.05)),
            sgv_margin=float(rng.normal(0.15 if t else 0.0, 0.05)),
            # the similarity runs against intuition in these data: the fit must not use it
            similarity=float(rng.normal(0.7 if t else 0.9, 0.05)),
            inliers=int(rng.integers(30, 90) if t else rng.integers(3, 12)),
            inlier_ratio=float(rng.uniform(0.3, 0.8) if t else rng.uniform(0.05, 0.2)),
            agreement=int(rng.integers(1, 4) if t else 0),
        )
        for t in y
    ]
    feats = PROFILE_FEATURES["none"]
    model = fit_logistic(evidence_matrix(ev, feats), y, list(feats))
    assert all(w >= 0 for w in model.weights)
    assert model.weights[feats.index("similarity")] == 0.0
    assert model.weights[feats.index("log_inliers")] > 0
    p = np.array([model.predict(e) for e in ev])
    assert p[y].min() > 0.5 > p[~y].max()
    with pytest.raises(InputError, match="both correct and wrong"):
        fit_logistic(evidence_matrix(ev[:5], feats), np.ones(5, bool), list(feats))


def test_calibration_round_trips_and_refuses_damage(tmp_path) -> None:
    cal = shipped_calibration("learned")
    path = tmp_path / "cal.json"
    cal.save(path)
    back = Calibration.load(path)
    assert back.fingerprint == cal.fingerprint and back.confidence(GOOD) == cal.confidence(GOOD)
    d = json.loads(path.read_text())
    with pytest.raises(InputError, match="format"):
        Calibration.from_dict({**d, "format": "other"})
    bad = json.loads(path.read_text())
    bad["models"]["icp"]["weights"][0] = -1.0
    with pytest.raises(InputError, match="non-negative"):
        Calibration.from_dict(bad)
    bad = json.loads(path.read_text())
    bad["models"]["icp"]["features"][0] = "nonsense"
    with pytest.raises(InputError, match="unknown feature"):
        Calibration.from_dict(bad)
    for field, value in [("bias", "x"), ("bias", float("nan")), ("mean", float("inf"))]:
        bad = json.loads(path.read_text())
        m = bad["models"]["icp"]
        if field == "bias":
            m["bias"] = value
        else:
            m[field][0] = value
        # (NaN round-trips through JSON: a request body can carry it)
        with pytest.raises(InputError, match=f"models.icp: {field} must hold finite numbers"):
            Calibration.from_dict(json.loads(json.dumps(bad)))
    with pytest.raises(InputError, match="cannot read"):
        Calibration.load(tmp_path / "missing.json")
    m = LogisticModel(["sgv"], [0.0], [1.0], [2.0], 0.0)
    # a calibration without the answer's profile falls back to one whose inputs exist
    only_none = Calibration("x", "learned", {"none": m})
    assert only_none.confidence(GOOD) == pytest.approx(1 / (1 + np.exp(-0.6)))
    planar = dataclasses.replace(GOOD, icp_fitness=None, planar=True)
    assert only_none.model_for(planar) is m
    with pytest.raises(InputError, match="without ICP"):
        Calibration("x", "learned", {"icp": m})  # an ICP model cannot answer without ICP
    with pytest.raises(InputError, match="unknown profile"):
        Calibration("x", "learned", {"none": m, "gps": m})


def test_spectral_pose_recovers_a_transform_among_outliers() -> None:
    rng = np.random.default_rng(3)
    q = rng.uniform(-20, 20, size=(80, 3))
    T = _T(4.0, -2.0, 30.0)
    cand = q @ T[:3, :3].T + T[:3, 3]  # candidate keypoint i is query keypoint i moved
    matches = np.arange(80)
    matches[50:] = rng.integers(0, 80, size=30)  # 30 wrong matches
    v = np.where(np.arange(80) < 50, 1.0, 0.05)  # SGV weights the inlier cluster
    est = spectral_pose(q, cand, matches, v)
    assert est is not None and poses_agree(est, T, 1e-6, 1e-6)
    assert spectral_pose(q, cand, np.full(80, -1), v) is None
    assert spectral_pose(q, cand, matches, np.zeros(80)) is None
    assert poses_agree(rigid_fit(q[:50], cand[:50]), T, 1e-6, 1e-6)


def test_gather_evidence_margin_and_agreement() -> None:
    poses = {1: _T(0, 0), 2: _T(1, 0), 3: _T(30, 0), 4: _T(2, 0)}
    T_kf_q = _T(0.5, 0.0, 2.0)
    T_map_q = poses[1] @ T_kf_q
    spectral = {
        1: SpectralCandidate(0.4, T_kf_q),
        2: SpectralCandidate(0.3, np.linalg.inv(poses[2]) @ T_map_q),  # agrees
        3: SpectralCandidate(0.1, _T(0, 0)),  # another place: the margin's reference
        4: SpectralCandidate(0.35, _T(9, 9)),  # near the top-1 but a different pose
    }
    pose = PoseResult(
        T_kf_q,
        100,
        40,
        0.4,
        0.2,
        "localized",
        "ok",
        True,
        {"used": True, "fitness": 0.8, "inlier_rmse": 0.3},
    )
    asked = []

    def free_space(T_map_query: np.ndarray) -> float:
        asked.append(T_map_query)
        return 0.07

    ev = gather_evidence(
        [1, 2, 3, 4],
        spectral,
        poses.__getitem__,
        similarity=0.9,
        pose=pose,
        T_kf_query=T_kf_q,
        free_space=free_space,
    )
    # the free-space check is asked about the estimate in the map, once
    assert len(asked) == 1 and np.allclose(asked[0], T_map_q) and ev.free_space == 0.07
    assert ev.sgv == pytest.approx(0.4)
    assert ev.sgv_margin == pytest.approx(0.3)  # 0.4 - 0.1: candidates 2, 4 are near
    assert ev.agreement == 1
    assert (ev.inliers, ev.inlier_ratio, ev.icp_fitness, ev.icp_rmse) == (40, 0.4, 0.8, 0.3)
    assert ev.offset_m == pytest.approx(0.5) and ev.profile == "icp"
    none = gather_evidence(
        [1],
        spectral,
        poses.__getitem__,
        similarity=0.9,
        pose=None,
        T_kf_query=None,
        free_space=free_space,
    )
    assert (none.inliers, none.icp_fitness, none.profile) == (0, None, "none")
    assert none.free_space is None and len(asked) == 1  # no ICP: not asked


def test_the_nearest_keyframe_of_the_place_comes_first() -> None:
    # keyframes along a road; the query stands at x = 10
    poses = {i: _T(float(x), 0.0) for i, x in enumerate([4.0, 9.0, 12.0, 40.0, 9.5, 3.0])}

    def seen_from(i: int, score: float, shift: float = 0.0) -> SpectralCandidate:
        """What SpectralGV says of keyframe i: the query's pose (moved by shift m)."""
        return SpectralCandidate(score, np.linalg.inv(poses[i]) @ _T(10.0 + shift, 0.0))

    spectral = {
        0: seen_from(0, 0.40),  # the top-1, 6 m from the query
        1: seen_from(1, 0.37),  # 1 m away, within 10 % of the top-1's score
        2: seen_from(2, 0.38),  # 2 m away
        3: seen_from(3, 0.39, shift=30.0),  # another place
        4: seen_from(4, 0.20),  # 0.5 m away but scored far below
        5: SpectralCandidate(0.395, None),  # no pose of its own
    }
    kf = poses.__getitem__
    assert nearest_of_place([0, 3, 2, 1, 4, 5], spectral, kf, 0.1, 1.0) == [1, 0, 3, 2, 4, 5]
    # a tolerance that 1 misses (0.37 < 0.94 * 0.40) leaves 2; none at all keeps the order
    assert nearest_of_place([0, 3, 2, 1, 4, 5], spectral, kf, 0.06, 1.0) == [2, 0, 3, 1, 4, 5]
    assert nearest_of_place([0, 3, 2, 1, 4, 5], spectral, kf, 0.0, 1.0) == [0, 3, 2, 1, 4, 5]
    # 4 is the nearest, but only a tolerance of one half admits its score
    assert nearest_of_place([0, 4, 1], spectral, kf, 0.5, 1.0)[0] == 4
    # only the next five candidates are looked at
    assert nearest_of_place([0, 3, 3, 3, 3, 3, 1], spectral, kf, 0.1, 1.0)[0] == 0
    # another place, however near its keyframe seems, never takes the first place
    far = {**spectral, 3: SpectralCandidate(0.40, _T(0.1, 0.0))}
    assert nearest_of_place([0, 3], far, kf, 0.1, 1.0) == [0, 3]
    # a keyframe less than gain_m (1 m here) nearer is no reason to move
    close = {0: seen_from(1, 0.40), 4: seen_from(4, 0.40)}
    kf14 = {0: poses[1], 4: poses[4]}.__getitem__
    assert nearest_of_place([0, 4], close, kf14, 0.1, 1.0) == [0, 4]
    assert nearest_of_place([0, 4], close, kf14, 0.1, 0.4) == [4, 0]
    assert nearest_of_place([0, 4], close, kf14, 0.1, 0.0) == [4, 0]
    assert nearest_of_place([0, 3, 2, 1, 4, 5], spectral, kf, 0.1, 5.5) == [0, 3, 2, 1, 4, 5]
    # a top-1 without a SpectralGV pose stays
    assert nearest_of_place([5, 1], spectral, kf, 0.1, 1.0) == [5, 1]
    assert nearest_of_place([], spectral, kf, 0.1, 1.0) == []


def test_decide_orders_the_reasons() -> None:
    ok = PoseResult(np.eye(4), 50, 30, 0.6, 0.2, "localized", "30 inliers")
    bad = PoseResult(np.eye(4), 50, 3, 0.06, 0.2, "not_localized", "3 inliers < min_inliers 10")
    assert decide(0.9, 0.5, ok, np.eye(4)).code == "localized"
    assert decide(0.4, 0.5, ok, np.eye(4)).code == "low_confidence"
    assert decide(0.9, 0.5, bad, np.eye(4)).code == "pose_check"
    assert decide(0.9, 0.5, ok, None).code == "no_estimate"
    assert decide(float("nan"), 0.5, ok, np.eye(4)).code == "low_confidence"
    far = Prior((100.0, 0.0), 10.0)
    v = decide(0.9, 0.5, ok, np.eye(4), far)
    assert (v.localized, v.code) == (False, "outside_prior") and "100.0 m" in v.reason
    near = Prior((1.0, 1.0), 10.0, yaw_deg=170.0)
    assert decide(0.9, 0.5, ok, np.eye(4), near).code == "outside_prior"
    assert decide(0.9, 0.5, ok, np.eye(4), Prior((1.0, 1.0), 10.0, yaw_deg=20.0)).localized
