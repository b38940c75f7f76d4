"""The free-space check of a pose estimate: constructed scenes and real scans."""

from __future__ import annotations

import numpy as np
import pytest
from pose_helpers import planar_pose as _T

from sgvloc.core.encoders import EncoderSpec, make_encoder
from sgvloc.core.freespace import (
    MARGIN_M,
    NEIGHBOURS,
    PRIOR_POINTS,
    PRIOR_SHARE,
    RADIUS_M,
    RangeImage,
    thin,
    views_near,
    violation,
)
from sgvloc.core.sequence import KittiSequence


def _corridor(rng: np.random.Generator, n: int = 6000) -> np.ndarray:
    """Points on the two walls of a corridor 8 m wide and 80 m long, around the origin."""
    x = rng.uniform(-40.0, 40.0, n)
    y = np.where(rng.random(n) < 0.5, -4.0, 4.0)
    z = rng.uniform(-1.0, 3.0, n)
    return np.stack([x, y, z], axis=1)


def test_a_point_is_judged_only_where_the_keyframe_saw_up_to_it() -> None:
    wall = np.array([[10.0, 0.0, 0.0], [0.0, 20.0, 0.0]])  # two returns, two rays
    image = RangeImage(wall)
    # on the first ray: in the open space before the wall, on it, behind it
    along = np.array([[4.0, 0.0, 0.0], [10.0 + 0.8 * MARGIN_M, 0.0, 0.0], [15.0, 0.0, 0.0]])
    assert image.judge(along) == (2, 1)  # behind the wall: occluded, not judged
    # a ray with no return says nothing, however near
    assert image.judge(np.array([[0.0, -3.0, 0.0]])) == (0, 0)
    # nothing judged: the prior share, not a clean record; no keyframe at all: unknown
    unseen = np.array([[0.0, -3.0, 0.0]])
    assert violation(unseen, np.eye(4), [(np.eye(4), image)]) == PRIOR_SHARE
    assert violation(unseen, np.eye(4), []) is None


def test_the_right_pose_agrees_with_the_free_space_and_a_shifted_one_does_not() -> None:
    rng = np.random.default_rng(0)
    T_map_kf = _T(3.0, -2.0, 30.0)
    world = _corridor(rng)
    kf_points = (world - T_map_kf[:3, 3]) @ T_map_kf[:3, :3]  # in the keyframe's frame
    image = RangeImage(kf_points)
    T_map_query = _T(8.0, 0.5, 10.0)  # 5 m further down the corridor
    query = (world - T_map_query[:3, 3]) @ T_map_query[:3, :3]
    query = thin(query[np.linalg.norm(query, axis=1) < 25.0])

    def share(T_map_q: np.ndarray) -> float:  # the raw share, before shrinking
        T = np.linalg.solve(T_map_kf, T_map_q)
        judged, contradicting = image.judge(query @ T[:3, :3].T + T[:3, 3])
        assert judged > 50
        return contradicting / judged

    assert share(T_map_query) < 0.02
    # 1.5 m sideways puts a wall into the corridor's open space, either way
    assert share(_T(8.0, 2.0, 10.0)) > 0.5 and share(_T(8.0, -1.0, 10.0)) > 0.5
    # turned 30 degrees: the walls cut through it
    assert share(_T(8.0, 0.5, 40.0)) > 0.5
    # violation() is that share shrunk towards PRIOR_SHARE by PRIOR_POINTS
    T = np.linalg.solve(T_map_kf, T_map_query)
    judged, contradicting = image.judge(query @ T[:3, :3].T + T[:3, 3])
    assert violation(query, T_map_query, [(T_map_kf, image)]) == pytest.approx(
        (contradicting + PRIOR_SHARE * PRIOR_POINTS) / (judged + PRIOR_POINTS)
    )


def test_few_judged_points_say_little() -> None:
    """A pose whose points a keyframe can hardly judge (far off its observed space)
    scores near PRIOR_SHARE, not as a clean fit, though nothing contradicts it."""
    image = RangeImage(np.array([[10.0, 0.0, 0.0]]))
    assert image.judge(np.array([[5.0, 0.0, 0.0]] * 20)) == (20, 20)  # in the open
    clean = np.array([[10.0, 0.0, 0.0]] * 20)  # on the return: judged, consistent
    assert image.judge(clean) == (20, 0)
    v = violation(clean, np.eye(4), [(np.eye(4), image)])
    assert v == pytest.approx(PRIOR_SHARE * PRIOR_POINTS / (20 + PRIOR_POINTS))
    assert v > 0.8 * PRIOR_SHARE


def test_views_are_the_matched_keyframe_and_its_nearest_neighbours() -> None:
    positions = {i: np.array([float(i), 0.0, 0.0]) for i in range(50)}
    ids = views_near(np.array([10.2, 0.0, 0.0]), 40, list(positions), positions.__getitem__)
    assert ids[0] == 40 and len(ids) == NEIGHBOURS
    assert ids[1:] == [10, 11, 9, 12][: NEIGHBOURS - 1]
    far = views_near(np.array([500.0, 0.0, 0.0]), 3, list(positions), positions.__getitem__)
    assert far == [3]  # nobody within RADIUS_M: the matched keyframe alone
    assert RADIUS_M < 490.0
    assert views_near(np.zeros(3), 7, [], positions.__getitem__) == [7]


def test_thin_keeps_one_point_per_voxel() -> None:
    pts = np.repeat(np.array([[0.1, 0.1, 0.1], [5.1, 0.1, 0.1]]), 50, axis=0)
    assert len(thin(pts)) == 2
    assert thin(np.zeros((0, 3))).shape == (0, 3)


@pytest.fixture(scope="module")
def fixture_clouds(balm_mini_dir):
    seq = KittiSequence(balm_mini_dir)
    enc = make_encoder(EncoderSpec())
    return [(f.T_world_sensor, enc.prepare(f.scan().points)) for f in seq]


def test_real_scans_agree_at_their_true_poses_and_not_at_wrong_ones(fixture_clouds) -> None:
    """Each fixture scan against the others near it: a few percent at the ground-truth
    pose, many times that 4 m or 60 degrees off."""
    poses = np.stack([T for T, _ in fixture_clouds])
    images = [RangeImage(c) for _, c in fixture_clouds]
    for q, (T_q, cloud) in enumerate(fixture_clouds):
        others = [i for i in range(len(poses)) if i != q]
        d = np.linalg.norm(poses[others, :3, 3] - T_q[:3, 3], axis=1)
        matched = others[int(np.argmin(d))]
        ids = views_near(T_q[:3, 3], matched, others, lambda i: poses[i, :3, 3])
        views = [(poses[i], images[i]) for i in ids]
        pts = thin(cloud)
        right = violation(pts, T_q, views)
        off = T_q @ _T(4.0, 0.0, 0.0)
        turned = T_q @ _T(0.0, 0.0, 60.0)
        assert right is not None and right < 0.12, (q, right)
        for wrong in (off, turned):
            v = violation(pts, wrong, views)
            assert v is not None and v > 2.5 * right and v > 0.25, (q, right, v)
