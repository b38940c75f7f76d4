"""The learned BEV encoder with the weights shipped in the package, on the real fixture."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from sgvloc.core.bev import (
    KITTI_BEV,
    LearnedEncoderConfig,
    ground_rotation,
    level_cloud,
    rasterize,
    rasterize_cloud,
)
from sgvloc.core.encoders import EncoderSpec, LearnedEncoder, make_encoder
from sgvloc.core.encoders.learned import shipped_weights_path
from sgvloc.core.encoders.torchscript import file_sha256
from sgvloc.core.errors import EncoderMismatchError, InputError
from sgvloc.core.preprocess import voxel_downsample
from sgvloc.core.sequence import KittiSequence


@pytest.fixture(scope="module")
def enc() -> LearnedEncoder:
    """The learned encoder with the polar/FFT global descriptor alone."""
    spec = EncoderSpec(kind="learned", learned=LearnedEncoderConfig(global_descriptor="polar"))
    return make_encoder(spec)


@pytest.fixture(scope="module")
def scans(balm_mini_dir: Path) -> list[np.ndarray]:
    seq = KittiSequence(balm_mini_dir)
    return [seq[i].scan().points for i in range(len(seq))]


def _yaw(points: np.ndarray, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (points[:, :3] @ R.T).astype(np.float32)


def test_shipped_weights_are_small_and_named_in_the_identity(enc: LearnedEncoder) -> None:
    path = shipped_weights_path()
    assert path.is_file() and path.stat().st_size < 20e6
    assert enc.identity.name == "bevnet"
    assert enc.identity.params["weights_sha256"] == file_sha256(path)[:16]
    assert enc.meta["steps"] > 0  # exported from a real training run
    assert (enc.global_dim, enc.local_dim) == (620, 64)
    # the default global descriptor: polar/FFT and the network's (one pass), merged
    default = make_encoder(EncoderSpec(kind="learned"))
    assert default.config.global_descriptor == "polar+network"
    assert default.config.global_rotations == 1
    assert (default.global_dim, default.blocks, default.local_dim) == (876, (620, 256), 64)


def test_real_scan_gives_finite_features_of_the_documented_shapes(
    enc: LearnedEncoder, scans: list[np.ndarray]
) -> None:
    f = enc.encode(scans[0])
    g, kp, loc = f.global_descriptor, f.keypoints, f.local_features
    assert g.shape == (620,) and np.isfinite(g).all()
    assert np.linalg.norm(g) == pytest.approx(1.0, abs=1e-5)
    n = f.num_keypoints
    assert 32 <= n <= enc.config.num_keypoints
    assert kp.shape == (n, 3) and loc.shape == (n, 64)
    assert np.isfinite(kp).all() and np.isfinite(loc).all()
    np.testing.assert_allclose(np.linalg.norm(loc, axis=1), 1.0, atol=1e-5)
    assert kp[:, 2].any()  # keypoint_z "column_min": heights from the scan's columns
    assert (np.abs(kp[:, :2]) < KITTI_BEV.extent + 1.0).all()
    # deterministic, and the raster of the levelled scan describes the same as the scan,
    # with the keypoints turned back into the sensor frame
    again = enc.encode(scans[0])
    np.testing.assert_array_equal(again.local_features, loc)
    cloud = enc.prepare(scans[0])
    R, _ = ground_rotation(cloud)
    level = voxel_downsample((cloud @ R.T).astype(np.float32), KITTI_BEV.resolution)
    level2, R2 = level_cloud(cloud)
    np.testing.assert_array_equal(R2, R)
    np.testing.assert_array_equal(level2, level)
    img = enc.encode_image(rasterize_cloud(level).image)
    np.testing.assert_allclose(img.global_descriptor, g, atol=1e-6)
    np.testing.assert_allclose(img.keypoints[:, :2], (kp @ R.T)[:, :2], atol=1e-4)
    assert len(np.unique(img.keypoints[:, :2], axis=0)) == n  # one keypoint per cell
    assert not img.keypoints[:, 2].any()  # an image has no heights


def _tilt(points: np.ndarray, deg: float) -> np.ndarray:
    a = math.radians(deg)
    R = np.array(
        [[1.0, 0.0, 0.0], [0.0, math.cos(a), -math.sin(a)], [0.0, math.sin(a), math.cos(a)]]
    )
    return (points[:, :3] @ R.T).astype(np.float32), R


def test_levelling_keeps_features_steady_under_sensor_tilt(
    enc: LearnedEncoder, scans: list[np.ndarray]
) -> None:
    tilted, R = _tilt(scans[5], 15.0)
    unlevelled = make_encoder(EncoderSpec(kind="learned", learned={"level": False}))
    assert unlevelled.identity != enc.identity
    steady = {}
    for name, e in (("level", enc), ("raw", unlevelled)):
        f, ft = e.encode(scans[5]), e.encode(tilted)
        back = ft.keypoints @ R  # the tilted scan's keypoints in the original frame
        d = np.linalg.norm(back[:, None, :] - f.keypoints[None], axis=2).min(axis=1)
        steady[name] = (float(f.global_descriptor @ ft.global_descriptor), float((d < 0.5).mean()))
    assert steady["level"][0] > 0.98 and steady["level"][1] > 0.75
    assert steady["level"][1] > steady["raw"][1] + 0.2  # without levelling: about 0.45


def test_faint_pixels_are_not_described(enc: LearnedEncoder, scans: list[np.ndarray]) -> None:
    """Pixels below the grey level the weights were trained from (ground rings of a tilted
    sensor, object fringes) change nothing."""
    assert enc.min_grey > 0 and enc.meta["min_grey"] == enc.min_grey
    img = rasterize(scans[0]).image
    noisy = img.copy()
    rng = np.random.default_rng(0)
    noisy[(img == 0) & (rng.random(img.shape) < 0.2)] = enc.min_grey - 1
    a, b = enc.encode_image(img), enc.encode_image(noisy)
    np.testing.assert_array_equal(a.keypoints, b.keypoints)
    np.testing.assert_array_equal(a.global_descriptor, b.global_descriptor)


@pytest.fixture(scope="module")
def network_global() -> LearnedEncoder:
    cfg = LearnedEncoderConfig(global_descriptor="network", global_rotations=4)
    return make_encoder(EncoderSpec(kind="learned", learned=cfg))


@pytest.mark.parametrize("which", ["polar", "network"])
@pytest.mark.parametrize("yaw_deg", [17.0, 45.0, 90.0, 133.0, 180.0, 251.0])
def test_global_descriptor_is_nearly_yaw_invariant(
    enc: LearnedEncoder,
    network_global: LearnedEncoder,
    scans: list[np.ndarray],
    which: str,
    yaw_deg: float,
) -> None:
    e = enc if which == "polar" else network_global
    g0 = e.encode(scans[3]).global_descriptor
    g1 = e.encode(_yaw(scans[3], math.radians(yaw_deg))).global_descriptor
    assert g0.shape == ((620,) if which == "polar" else (256,))
    assert 1.0 - float(g0 @ g1) < 0.05


def test_the_network_global_descriptor_is_another_encoder(
    enc: LearnedEncoder, network_global: LearnedEncoder, scans: list[np.ndarray]
) -> None:
    assert network_global.global_dim == 256 and network_global.identity != enc.identity
    a, b = enc.encode(scans[0]), network_global.encode(scans[0])
    np.testing.assert_array_equal(a.keypoints, b.keypoints)  # the same local features
    np.testing.assert_array_equal(a.local_features, b.local_features)


def test_both_global_descriptors_are_two_blocks_of_one_vector(
    enc: LearnedEncoder, network_global: LearnedEncoder, scans: list[np.ndarray]
) -> None:
    """'polar+network' concatenates the two descriptors, each normalised, scaled to unit
    length; its blocks are recorded, and it is an encoder of its own."""
    both = make_encoder(
        EncoderSpec(
            kind="learned",
            learned=LearnedEncoderConfig(global_descriptor="polar+network", global_rotations=4),
        )
    )
    assert both.blocks == (620, 256) and both.global_dim == 876
    assert enc.blocks == (620,) and network_global.blocks == (256,)
    assert both.identity not in (enc.identity, network_global.identity)
    g = both.encode(scans[2]).global_descriptor
    polar = enc.encode(scans[2]).global_descriptor
    net = network_global.encode(scans[2]).global_descriptor
    unit = [x / np.linalg.norm(x) for x in (polar, net)]
    np.testing.assert_allclose(g, np.concatenate(unit) / math.sqrt(2), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(g), 1.0, atol=1e-6)


def test_global_descriptor_tells_places_apart(
    enc: LearnedEncoder, scans: list[np.ndarray], balm_mini_dir: Path
) -> None:
    """Each revisit query of the fixture is on average nearer (cosine) to the database
    scans within 5 m of it than to those more than 10 m away."""
    seq = KittiSequence(balm_mini_dir)
    pos = np.stack([seq[i].T_world_sensor[:3, 3] for i in range(len(seq))])
    g = np.stack([enc.encode(s).global_descriptor for s in scans])
    lines = (balm_mini_dir / "scans.txt").read_text().splitlines()
    roles = [line.split()[1] for line in lines if line and not line.startswith("#")]
    db = [i for i, r in enumerate(roles) if r == "database"]
    for q in (i for i, r in enumerate(roles) if r == "query"):
        d = np.linalg.norm(pos[db] - pos[q], axis=1)
        sim = g[db] @ g[q]
        assert sim[d < 5.0].mean() > sim[d > 10.0].mean()


def test_planar_keypoints_at_cell_centres(enc: LearnedEncoder, scans: list[np.ndarray]) -> None:
    cfg = LearnedEncoderConfig(keypoint_z="zero", keypoint_xy="centre", level=False)
    flat = make_encoder(EncoderSpec(kind="learned", learned=cfg))
    unlevelled = make_encoder(EncoderSpec(kind="learned", learned={"level": False}))
    f, ref = flat.encode(scans[0]), unlevelled.encode(scans[0])
    assert not f.keypoints[:, 2].any() and flat.identity != enc.identity
    # cell centres lie on the 0.8 m grid (odd multiples of 0.4 m); the default centroids
    # stay inside their cell
    k = f.keypoints[:, :2] / 0.4
    np.testing.assert_allclose(k - np.round(k), 0.0, atol=1e-4)  # float32
    assert (np.round(k).astype(int) % 2 == 1).all()
    assert np.abs(ref.keypoints[:, :2] - f.keypoints[:, :2]).max() <= 0.2 + 1e-6


def test_bad_input_is_named(enc: LearnedEncoder) -> None:
    with pytest.raises(InputError, match="expected \\[151, 151\\] uint8"):
        enc.encode_image(np.zeros((100, 100), np.uint8))
    with pytest.raises(InputError, match="empty"):
        enc.encode_image(np.zeros((151, 151), np.uint8))
    with pytest.raises(InputError):
        enc.encode(np.full((10, 3), 100.0, np.float32))  # nothing inside the box
    if not torch.cuda.is_available():
        with pytest.raises(InputError, match="CUDA"):
            make_encoder(EncoderSpec(kind="learned", device="cuda"))


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_gives_the_cpu_features(enc: LearnedEncoder, scans: list[np.ndarray]) -> None:
    gpu = make_encoder(EncoderSpec(kind="learned", device="cuda"))
    a, b = enc.encode(scans[0]), gpu.encode(scans[0])
    np.testing.assert_allclose(a.global_descriptor, b.global_descriptor, atol=1e-3)
    assert a.identity == b.identity


# -- ONNX Runtime ------------------------------------------------------------------------


def _same_features(a, b) -> None:
    assert np.array_equal(a.keypoints, b.keypoints)
    np.testing.assert_allclose(a.local_features, b.local_features, atol=1e-5)
    np.testing.assert_allclose(a.global_descriptor, b.global_descriptor, atol=1e-5)


@pytest.mark.parametrize(
    "config",
    [LearnedEncoderConfig(), LearnedEncoderConfig(global_descriptor="network")],
    ids=["polar global (default)", "network global, 4 rotations"],
)
def test_onnx_and_torch_give_the_same_features(
    scans: list[np.ndarray], config: LearnedEncoderConfig
) -> None:
    onnx = LearnedEncoder(config, runtime="onnx")
    torch_enc = LearnedEncoder(config, runtime="torch")
    assert (onnx.runtime, torch_enc.runtime) == ("onnx", "torch")
    assert onnx.identity == torch_enc.identity  # same weights, same features: one identity
    for scan in scans:
        _same_features(onnx.encode(scan), torch_enc.encode(scan))


def test_auto_runs_the_shipped_weights_in_onnx_runtime(enc: LearnedEncoder) -> None:
    assert enc.runtime == "onnx"  # onnxruntime is a service dependency
    assert make_encoder(EncoderSpec(kind="learned", runtime="torch")).runtime == "torch"


def _other_weights(tmp_path: Path) -> Path:
    blob = torch.load(shipped_weights_path(), map_location="cpu", weights_only=True)
    name = next(iter(blob["state_dict"]))
    blob["state_dict"][name] = blob["state_dict"][name] * 1.01
    path = tmp_path / "other.pt"
    torch.save(blob, path)
    return path


def test_onnx_runtime_needs_an_export_of_these_weights(tmp_path: Path) -> None:
    weights = _other_weights(tmp_path)
    with pytest.raises(InputError, match="no ONNX export"):
        LearnedEncoder(model_path=weights, runtime="onnx")
    assert LearnedEncoder(model_path=weights).runtime == "torch"  # auto falls back
    # an export of other weights beside them is not used
    (tmp_path / "other.onnx").write_bytes(shipped_weights_path().with_suffix(".onnx").read_bytes())
    with pytest.raises(InputError, match="exported from other weights"):
        LearnedEncoder(model_path=weights, runtime="onnx")
    assert LearnedEncoder(model_path=weights).runtime == "torch"
    # a damaged export: auto runs torch, "onnx" says why it cannot
    (tmp_path / "other.onnx").write_bytes(b"not an ONNX model")
    with pytest.raises(InputError, match="cannot be loaded"):
        LearnedEncoder(model_path=weights, runtime="onnx")
    assert LearnedEncoder(model_path=weights).runtime == "torch"
    with pytest.raises(InputError, match="runtime must be one of"):
        LearnedEncoder(runtime="tensorrt")


def test_export_onnx_command_makes_an_export_the_encoder_uses(
    tmp_path: Path, scans: list[np.ndarray]
) -> None:
    from typer.testing import CliRunner

    from sgvloc.cli import app

    weights = _other_weights(tmp_path)
    res = CliRunner().invoke(app, ["export-onnx", str(weights)])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "other.onnx").is_file() and "wrote" in res.output
    onnx = LearnedEncoder(model_path=weights, runtime="onnx")
    _same_features(
        onnx.encode(scans[0]), LearnedEncoder(model_path=weights, runtime="torch").encode(scans[0])
    )


def test_the_shipped_export_is_of_the_shipped_weights() -> None:
    from sgvloc.core.encoders.learned import OnnxNet, onnx_path

    path = onnx_path(shipped_weights_path())
    assert path.is_file() and path.stat().st_size < 5_000_000
    assert OnnxNet.weights_sha256(path) == file_sha256(shipped_weights_path())


def test_a_sparse_scan_gives_fewer_keypoints_not_padded_ones(
    enc: LearnedEncoder, scans: list[np.ndarray]
) -> None:
    """A narrow, short-range crop of a scan has fewer occupied cells than keypoints asked
    for: it yields one keypoint per occupied cell, none repeated, none invented."""
    from sgvloc.core.preprocess import crop_azimuth, crop_range

    full = enc.encode(scans[0])
    sparse_points = crop_range(crop_azimuth(scans[0], 40.0), 0.0, 12.0)
    cloud = enc.prepare(sparse_points)
    sparse = enc.encode_cloud(cloud)
    assert 0 < sparse.num_keypoints < min(full.num_keypoints, enc.config.num_keypoints)
    assert len(np.unique(sparse.keypoints, axis=0)) == sparse.num_keypoints  # no duplicates
    # exactly one keypoint per occupied 0.8 m cell of the (levelled, faint-cut) image
    from sgvloc.core.bevnet import cut_faint, occupied_cells, to_input

    level, _ = level_cloud(cloud, KITTI_BEV)
    image = cut_faint(rasterize_cloud(level, KITTI_BEV).image, enc.min_grey)
    occupied = int(occupied_cells(to_input(image[None]))[0].sum())
    assert enc.config.nms_radius == 0 and sparse.num_keypoints == occupied
    # every keypoint lies in the cropped window (turned back into the sensor frame)
    az = np.degrees(np.arctan2(sparse.keypoints[:, 1], sparse.keypoints[:, 0]))
    assert (np.abs(az) <= 20.0 + 5.0).all()
    assert sparse.local_features.shape == (sparse.num_keypoints, enc.local_dim)


def test_a_query_is_also_described_about_displaced_centres(scans: list[np.ndarray]) -> None:
    """``encode_query``: the polar block about each centre is what a sensor standing there
    would describe (the scan moved by that offset, described about its own sensor: far
    nearer than the plain descriptor, and nearest among the centres); the network block
    and everything else is the plain encoding's."""
    from sgvloc.core.config import RetrievalConfig

    centres = RetrievalConfig(offset_m=4.0, offsets=8).centres()
    assert centres.shape == (8, 2)
    np.testing.assert_allclose(np.linalg.norm(centres, axis=1), 4.0)
    np.testing.assert_allclose(centres[0], [4.0, 0.0])
    assert RetrievalConfig(offset_m=0.0).centres() is None
    both = make_encoder(
        EncoderSpec(
            kind="learned",
            learned=LearnedEncoderConfig(global_descriptor="polar+network", level=False),
        )
    )
    cloud = both.prepare(scans[4])
    plain, query = both.encode_cloud(cloud), both.encode_query(cloud, centres)
    assert plain.global_variants is None and both.encode_query(cloud).global_variants is None
    np.testing.assert_array_equal(query.global_descriptor, plain.global_descriptor)
    np.testing.assert_array_equal(query.local_features, plain.local_features)
    v = query.global_variants
    assert v.shape == (8, both.global_dim) and v.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(v[:, 620:], np.repeat(plain.global_descriptor[None, 620:], 8, 0))
    for k in (0, 3):  # the sensor moved by the centre (a whole number of 0.4 m voxels)
        moved = both.prepare(scans[4][:, :3] - np.array([*np.round(centres[k], 1), 0.0]))
        there = both.encode_cloud(moved).global_descriptor[:620]
        sims = v[:, :620] @ there / np.linalg.norm(v[:, :620], axis=1) / np.linalg.norm(there)
        here = plain.global_descriptor[:620] @ there / np.linalg.norm(plain.global_descriptor[:620])
        assert int(np.argmax(sims)) == k and sims[k] > here + 0.02 and sims[k] > 0.95


def test_fpfh_local_features_keep_the_networks_place_and_take_the_handcrafted_pose_part(
    scans: list[np.ndarray],
) -> None:
    """``local_features="fpfh"``: the global descriptor is the network's on the 0.3 m
    voxel cloud's box-cropped 0.4 m voxels; keypoints and features are exactly the
    handcrafted encoder's; maps made before the option keep their identity; BEV images
    are refused by name; a narrow crop yields fewer FPFH keypoints, none repeated."""
    from sgvloc.core.bev import prepare_points
    from sgvloc.core.encoders import HandcraftedEncoder
    from sgvloc.core.preprocess import crop_azimuth, crop_range

    plain = make_encoder(EncoderSpec(kind="learned"))
    fpfh = make_encoder(EncoderSpec(kind="learned", learned={"local_features": "fpfh"}))
    hand = HandcraftedEncoder()
    # the default's identity does not name the option (the fingerprint of existing maps)
    assert "local_features" not in plain.identity.params["encoder"]
    assert fpfh.identity != plain.identity and fpfh.identity.params["fpfh"] == hand.identity.params
    assert (fpfh.local_dim, fpfh.global_dim) == (hand.local_dim, plain.global_dim)
    cloud = fpfh.prepare(scans[2])
    np.testing.assert_array_equal(cloud, hand.prepare(scans[2]))  # what ICP is given
    f, h = fpfh.encode(scans[2]), hand.encode(scans[2])
    np.testing.assert_array_equal(f.keypoints, h.keypoints)
    np.testing.assert_array_equal(f.local_features, h.local_features)
    net = plain.encode_cloud(prepare_points(cloud, KITTI_BEV))
    np.testing.assert_array_equal(f.global_descriptor, net.global_descriptor)
    assert f.encoder == fpfh.identity
    fpfh.check(f)
    with pytest.raises(EncoderMismatchError):  # never mixed in one map
        plain.check(f)
    with pytest.raises(InputError, match="BEV image has no points"):
        fpfh.encode_image(np.zeros((KITTI_BEV.size, KITTI_BEV.size), np.uint8))
    sparse = crop_range(crop_azimuth(scans[2], 30.0), 0.0, 6.0)
    narrow = fpfh.encode(sparse)
    assert 0 < narrow.num_keypoints == len(fpfh.prepare(sparse)) < f.num_keypoints
    assert len(np.unique(narrow.keypoints, axis=0)) == narrow.num_keypoints
