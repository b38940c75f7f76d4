"""Handcrafted BEV encoder: shapes, determinism, yaw invariance, correct matches, identity."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("cv2")

from sgvloc.core.bev import BEVEncoderConfig  # noqa: E402
from sgvloc.core.encoders import BEVEncoder, EncoderSpec, HandcraftedEncoder, make_encoder  # noqa: E402
from sgvloc.core.encoders.bev import orb_bits_to_float  # noqa: E402
from sgvloc.core.errors import EncoderMismatchError, InputError  # noqa: E402
from sgvloc.core.localizer import Localizer  # noqa: E402


def make_scene(seed: int) -> np.ndarray:
    """A scan ``[P, 4]`` around the origin: flat ground, yawed box buildings, poles, trees."""
    rng = np.random.default_rng(seed)
    parts = []
    r, t = rng.uniform(1.0, 24.0, 8000), rng.uniform(0, 2 * np.pi, 8000)
    parts.append(np.c_[r * np.cos(t), r * np.sin(t), np.full(8000, -1.7)])
    for _ in range(8):
        cr, ct = rng.uniform(6.0, 20.0), rng.uniform(0, 2 * np.pi)
        cx, cy = cr * np.cos(ct), cr * np.sin(ct)
        sx, sy, h, yaw = rng.uniform(2, 8), rng.uniform(2, 8), rng.uniform(2, 8), rng.uniform(0, 3)
        m = 2500
        s, face = rng.uniform(-0.5, 0.5, m), rng.integers(0, 4, m)
        lx = np.where(face < 2, s * sx, np.where(face == 2, 0.5, -0.5) * sx)
        ly = np.where(face < 2, np.where(face == 0, 0.5, -0.5) * sy, s * sy)
        c, si = np.cos(yaw), np.sin(yaw)
        parts.append(np.c_[cx + c * lx - si * ly, cy + si * lx + c * ly, rng.uniform(-1.7, h, m)])
    for _ in range(25):
        cr, ct = rng.uniform(3.0, 22.0), rng.uniform(0, 2 * np.pi)
        rad = rng.uniform(0.1, 1.2)
        m = 300
        a, rr = rng.uniform(0, 2 * np.pi, m), rad * np.sqrt(rng.uniform(0, 1, m))
        parts.append(
            np.c_[
                cr * np.cos(ct) + rr * np.cos(a),
                cr * np.sin(ct) + rr * np.sin(a),
                rng.uniform(-1.7, rng.uniform(1.0, 5.0), m),
            ]
        )
    xyz = np.concatenate(parts) + rng.normal(0, 0.02, (sum(len(p) for p in parts), 3))
    return np.c_[xyz, rng.uniform(0, 1, len(xyz))].astype(np.float32)


def yaw_matrix(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


@pytest.fixture(scope="module")
def scene() -> np.ndarray:
    return make_scene(3)


def test_shapes_dtypes_and_spec(scene: np.ndarray) -> None:
    enc = make_encoder(EncoderSpec(kind="bev"))
    assert isinstance(enc, BEVEncoder)
    f = enc.encode(scene)
    assert f.global_descriptor.shape == (enc.global_dim,) == (20 * 31,)
    assert f.global_descriptor.dtype == np.float32
    assert np.linalg.norm(f.global_descriptor) == pytest.approx(1.0, abs=1e-5)
    n = f.num_keypoints
    assert 50 <= n <= 256
    assert f.keypoints.shape == (n, 3) and f.local_features.shape == (n, 256)
    assert f.keypoints.dtype == np.float32 and f.local_features.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(f.local_features, axis=1), 1.0, atol=1e-5)
    assert np.all(f.keypoints[:, 2] == 0.0)
    assert np.all(np.abs(f.keypoints[:, :2]) < 26.0)
    enc.check(f)
    # SIFT variant: 128-dim RootSIFT rows
    sift = make_encoder(EncoderSpec(kind="bev", bev={"detector": "sift"}))
    fs = sift.encode(scene)
    assert fs.local_features.shape[1] == 128 == sift.local_dim
    assert fs.num_keypoints > 10
    np.testing.assert_allclose(np.linalg.norm(fs.local_features, axis=1), 1.0, atol=1e-5)
    assert sift.identity != enc.identity


def test_deterministic(scene: np.ndarray) -> None:
    a = BEVEncoder().encode(scene)
    b = BEVEncoder().encode(scene[::-1].copy())  # point order does not matter
    np.testing.assert_allclose(a.global_descriptor, b.global_descriptor, atol=1e-6)
    np.testing.assert_allclose(a.keypoints, b.keypoints, atol=1e-5)
    np.testing.assert_array_equal(a.local_features, b.local_features)


@pytest.mark.parametrize("deg", [17.0, 90.0, 143.0, 251.0])
def test_global_descriptor_is_yaw_invariant(scene: np.ndarray, deg: float) -> None:
    enc = BEVEncoder()
    g0 = enc.encode(scene).global_descriptor
    rotated = scene.copy()
    rotated[:, :3] = scene[:, :3] @ yaw_matrix(deg).T
    g1 = enc.encode(rotated).global_descriptor
    assert 1.0 - float(g0 @ g1) < 0.05
    # and it tells another place apart
    other = enc.encode(make_scene(11)).global_descriptor
    assert 1.0 - float(g0 @ other) > 1.0 - float(g0 @ g1)


def test_local_matches_survive_rotation_and_translation(scene: np.ndarray) -> None:
    """Nearest-neighbour matches land within 1 m once the true motion is applied."""
    R, t = yaw_matrix(40.0), np.array([1.3, -0.7, 0.0])
    moved = scene.copy()
    moved[:, :3] = scene[:, :3] @ R.T + t  # T_moved_scene
    enc = BEVEncoder()
    fa, fb = enc.encode(scene), enc.encode(moved)
    nn = (fa.local_features @ fb.local_features.T).argmax(axis=1)
    pred = fa.keypoints @ R.T + t
    err = np.linalg.norm((pred - fb.keypoints[nn])[:, :2], axis=1)
    assert (err < 1.0).mean() > 0.3


def test_encode_image_matches_scan_path(scene: np.ndarray) -> None:
    enc = BEVEncoder()
    img = enc.raster(scene).image
    a, b = enc.encode(scene), enc.encode_image(img)
    np.testing.assert_allclose(a.global_descriptor, b.global_descriptor, atol=1e-6)
    np.testing.assert_allclose(a.keypoints, b.keypoints, atol=1e-6)
    with pytest.raises(InputError, match="expected"):
        enc.encode_image(img[:100])
    with pytest.raises(InputError, match="expected"):
        enc.encode_image(img.astype(np.float32))
    with pytest.raises(InputError, match="empty"):
        enc.encode_image(np.zeros_like(img))


def test_column_mean_height(scene: np.ndarray) -> None:
    enc = BEVEncoder(BEVEncoderConfig(keypoint_z="column_mean"))
    f = enc.encode(scene)
    assert np.any(f.keypoints[:, 2] != 0.0)
    assert np.all((f.keypoints[:, 2] > -2.0) & (f.keypoints[:, 2] < 8.5))
    assert enc.identity != BEVEncoder().identity


def test_identity_covers_parameters() -> None:
    base = BEVEncoder().identity
    assert BEVEncoder(BEVEncoderConfig(num_keypoints=128)).identity != base
    assert BEVEncoder(BEVEncoderConfig(blur_sigma=0.0)).identity != base
    assert BEVEncoder(BEVEncoderConfig(raster={"resolution": 0.5})).identity != base
    assert BEVEncoder().identity == base
    assert base.params["encoder"]["raster"]["resolution"] == 0.4


def test_orb_bits_to_float_ranks_like_hamming() -> None:
    rng = np.random.default_rng(0)
    d = rng.integers(0, 256, size=(20, 32), dtype=np.uint8)
    f = orb_bits_to_float(d)
    ham = np.unpackbits(d[:, None, :] ^ d[None, :, :], axis=2).sum(axis=2)  # [20, 20]
    sq = ((f[:, None, :] - f[None, :, :]) ** 2).sum(axis=2)
    np.testing.assert_allclose(sq, ham / 64.0, atol=1e-5)


def test_bev_features_refused_by_a_handcrafted_map(scene: np.ndarray) -> None:
    feats = BEVEncoder().encode(scene)
    loc = Localizer(HandcraftedEncoder())
    with pytest.raises(EncoderMismatchError):
        loc.make_keyframe(np.eye(4), features=feats)
    with pytest.raises(EncoderMismatchError):
        HandcraftedEncoder().check(feats)
    # and the other way round
    hand = HandcraftedEncoder().encode(scene)
    with pytest.raises(EncoderMismatchError):
        Localizer(BEVEncoder()).make_keyframe(np.eye(4), features=hand)


def test_empty_scan_is_refused() -> None:
    enc = BEVEncoder()
    flat = np.c_[np.random.default_rng(0).uniform(-20, 20, (500, 2)), np.full(500, -1.7)]
    with pytest.raises(InputError, match="empty"):
        enc.encode(flat)  # ground only: every column is one voxel
    with pytest.raises(InputError):
        enc.encode(np.array([[100.0, 0.0, 0.0]]))


def test_polar_descriptor_about_displaced_centres() -> None:
    """About a centre c, the polar/FFT descriptor of an image is that of the image moved
    so that c is the sensor (every centre at once, each as alone); about the sensor it is
    the plain descriptor."""
    from sgvloc.core.bev import KITTI_BEV
    from sgvloc.core.encoders.bev import polar_fft_descriptor, polar_fft_descriptors

    rng = np.random.default_rng(3)
    image = np.zeros((KITTI_BEV.size, KITTI_BEV.size), np.uint8)
    rows, cols = rng.integers(40, 111, size=(2, 600))  # within 14 m of the sensor
    image[rows, cols] = rng.integers(30, 256, size=600)
    shifts = [(10, 0), (0, -10), (-7, 7), (0, 0)]  # pixels: 4 m ahead, 4 m left, ...
    centres = np.array(
        [[dr * KITTI_BEV.resolution, dc * KITTI_BEV.resolution] for dr, dc in shifts]
    )
    got = polar_fft_descriptors(image, centres)
    assert got.shape == (4, 620) and got.dtype == np.float32
    for row, (dr, dc) in zip(got, shifts, strict=True):
        moved = np.roll(image, (dr, dc), axis=(0, 1))  # nothing wraps: content is central
        np.testing.assert_allclose(row, polar_fft_descriptor(moved), atol=1e-5)
    np.testing.assert_array_equal(got[3], polar_fft_descriptor(image))
    assert polar_fft_descriptors(image, np.zeros((0, 2))).shape == (0, 620)


def test_the_bev_encoder_describes_a_query_about_displaced_centres(scene: np.ndarray) -> None:
    from sgvloc.core.config import RetrievalConfig
    from sgvloc.core.encoders.bev import polar_fft_descriptors

    enc = BEVEncoder()
    cloud = enc.prepare(scene)
    centres = RetrievalConfig().centres()
    plain, query = enc.encode_cloud(cloud), enc.encode_query(cloud, centres)
    assert plain.global_variants is None
    np.testing.assert_array_equal(query.global_descriptor, plain.global_descriptor)
    np.testing.assert_array_equal(query.local_features, plain.local_features)
    image = enc.raster(scene).image
    want = polar_fft_descriptors(image, centres)
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    np.testing.assert_allclose(query.global_variants, want, atol=1e-6)
    assert enc.encode_image(image, centres=centres).global_variants.shape == (8, enc.global_dim)
