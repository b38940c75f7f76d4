"""Encoders: handcrafted (polar grid + FPFH), precomputed features, TorchScript plug-in."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pydantic
import pytest
from scipy.spatial import cKDTree

from sgvloc.core.config import HandcraftedEncoderConfig, PreprocessConfig
from sgvloc.core.encoders import (
    Encoder,
    EncoderSpec,
    HandcraftedEncoder,
    LearnedEncoder,
    PrecomputedEncoder,
    TorchScriptEncoder,
    make_encoder,
)
from sgvloc.core.encoders.handcrafted import (
    _smallest_eigenpairs,
    fpfh_at,
    normals_and_saliency,
    polar_grid,
    select_keypoints,
)
from sgvloc.core.errors import EncoderMismatchError, InputError
from sgvloc.core.features import Features
from sgvloc.core.preprocess import GROUND_FIT, preprocess

# ---------------------------------------------------------------------------------------
# synthetic scenes


def make_scene(seed: int, n_ground: int = 12000) -> np.ndarray:
    """A LiDAR-like scan ``[P, 4]`` (x y z intensity) around a sensor at the origin.

    Ground plane with range-decreasing density, box-shaped buildings (vertical faces) and
    poles, all with 2 cm noise; about 25k points. ``seed`` picks the layout.
    """
    rng = np.random.default_rng(seed)
    parts = []
    # ground: uniform radius -> density ~ 1/r, like a spinning LiDAR
    r = rng.uniform(2.0, 45.0, n_ground)
    t = rng.uniform(0.0, 2 * np.pi, n_ground)
    parts.append(np.c_[r * np.cos(t), r * np.sin(t), np.full(n_ground, -1.7)])
    # buildings: vertical faces of yawed boxes
    for _ in range(rng.integers(6, 10)):
        cr, ct = rng.uniform(8.0, 35.0), rng.uniform(0.0, 2 * np.pi)
        cx, cy = cr * np.cos(ct), cr * np.sin(ct)
        sx, sy, h, yaw = (
            rng.uniform(3, 10),
            rng.uniform(3, 10),
            rng.uniform(3, 12),
            rng.uniform(0, np.pi),
        )
        m = 1200
        s = rng.uniform(-0.5, 0.5, m)
        face = rng.integers(0, 4, m)
        lx = np.where(face < 2, s * sx, np.where(face == 2, 0.5, -0.5) * sx)
        ly = np.where(face < 2, np.where(face == 0, 0.5, -0.5) * sy, s * sy)
        c, si = np.cos(yaw), np.sin(yaw)
        parts.append(
            np.c_[cx + c * lx - si * ly, cy + si * lx + c * ly, rng.uniform(-1.7, h - 1.7, m)]
        )
    # poles
    for _ in range(rng.integers(10, 20)):
        cr, ct = rng.uniform(4.0, 30.0), rng.uniform(0.0, 2 * np.pi)
        m = 150
        a = rng.uniform(0.0, 2 * np.pi, m)
        parts.append(
            np.c_[
                cr * np.cos(ct) + 0.15 * np.cos(a),
                cr * np.sin(ct) + 0.15 * np.sin(a),
                rng.uniform(-1.7, rng.uniform(2.0, 6.0), m),
            ]
        )
    xyz = np.concatenate(parts)
    xyz += rng.normal(0.0, 0.02, xyz.shape)
    intensity = rng.uniform(0.0, 1.0, (len(xyz), 1))
    return np.hstack([xyz, intensity]).astype(np.float32)


def rotate_z(points: np.ndarray, deg: float) -> np.ndarray:
    """Rotate the xyz columns of a scan about z (the sensor's vertical axis)."""
    t = np.radians(deg)
    rot = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
    out = points.copy()
    out[:, :3] = (points[:, :3].astype(np.float64) @ rot.T).astype(np.float32)
    return out


def cosine_distance(a: np.ndarray, b: np.ndarray) -> float:
    return 1.0 - float(a @ b) / float(np.linalg.norm(a) * np.linalg.norm(b))


@pytest.fixture(scope="module")
def scene() -> np.ndarray:
    return make_scene(1)


@pytest.fixture(scope="module")
def encoder() -> HandcraftedEncoder:
    return HandcraftedEncoder()


@pytest.fixture(scope="module")
def scene_features(encoder: HandcraftedEncoder, scene: np.ndarray) -> Features:
    return encoder.encode(scene)


# ---------------------------------------------------------------------------------------
# handcrafted


def test_handcrafted_shapes_dtypes_finite(encoder, scene_features):
    f = scene_features
    cfg = HandcraftedEncoderConfig()
    assert encoder.global_dim == cfg.rings * (cfg.sectors // 2 + 1)
    assert encoder.local_dim == 33
    assert f.global_descriptor.shape == (encoder.global_dim,)
    assert f.keypoints.shape == (cfg.num_keypoints, 3)
    assert f.local_features.shape == (cfg.num_keypoints, 33)
    for arr in (f.global_descriptor, f.keypoints, f.local_features):
        assert arr.dtype == np.float32
        assert np.isfinite(arr).all()
    assert np.linalg.norm(f.global_descriptor) == pytest.approx(1.0, abs=1e-5)
    norms = np.linalg.norm(f.local_features, axis=1)
    assert np.allclose(norms[norms > 0], 1.0, atol=1e-5)
    assert (norms > 0).mean() > 0.9  # FPFH is not degenerate on a real-like scene
    assert f.encoder == encoder.identity
    encoder.check(f)  # its own features pass


def test_keypoints_are_distinct_points_of_the_downsampled_cloud(encoder, scene, scene_features):
    pts = preprocess(scene, encoder.preprocess_config)
    kp = scene_features.keypoints
    assert len(np.unique(kp, axis=0)) == len(kp)
    # every keypoint is one of the preprocessed points
    d, _ = cKDTree(pts).query(kp)
    assert d.max() < 1e-5
    # non-maximum suppression: at most one keypoint per 1 m voxel while voxels remain
    cells = np.floor(kp / 1.0).astype(np.int64)
    assert len(np.unique(cells, axis=0)) == len(kp)


def test_handcrafted_deterministic(scene, scene_features):
    again = HandcraftedEncoder().encode(scene.copy())
    np.testing.assert_array_equal(again.global_descriptor, scene_features.global_descriptor)
    np.testing.assert_array_equal(again.keypoints, scene_features.keypoints)
    np.testing.assert_array_equal(again.local_features, scene_features.local_features)
    assert again.encoder == scene_features.encoder


def test_only_an_encoder_that_removes_the_ground_records_how(scene) -> None:
    """The ground fit is part of the identity of maps that remove the ground (their
    features depend on it) and of no other map, whose fingerprints stay as they were."""
    plain = HandcraftedEncoder()
    ground = HandcraftedEncoder(preprocess_config=PreprocessConfig(remove_ground=True))
    assert "ground_fit" not in plain.identity.params
    assert ground.identity.params["ground_fit"] == GROUND_FIT
    a, b = ground.encode(scene), ground.encode(scene.copy())  # deterministic
    np.testing.assert_array_equal(a.keypoints, b.keypoints)


@pytest.mark.parametrize("deg", [37.0, 90.0, 180.0, 253.3, -11.7])
def test_global_descriptor_yaw_invariant(encoder, scene, scene_features, deg):
    rotated = encoder.encode(rotate_z(scene, deg))
    assert cosine_distance(rotated.global_descriptor, scene_features.global_descriptor) < 0.05


def test_global_descriptor_separates_places(encoder, scene, scene_features):
    self_dist = max(
        cosine_distance(
            encoder.encode(rotate_z(scene, d)).global_descriptor, scene_features.global_descriptor
        )
        for d in (37.0, 180.0)
    )
    for seed in (2, 3):
        other = encoder.encode(make_scene(seed))
        other_dist = cosine_distance(other.global_descriptor, scene_features.global_descriptor)
        assert other_dist > 3 * self_dist
        assert other_dist > 0.01


def test_polar_grid_soft_assignment_conserves_mass_and_shifts_with_yaw():
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-30, 30, (500, 2)), np.zeros(500)]
    inside = np.hypot(pts[:, 0], pts[:, 1]) < 40.0
    grid = polar_grid(pts, rings=10, sectors=12, max_radius=40.0)
    assert grid.sum() == pytest.approx(inside.sum())
    # rotating by exactly one sector width shifts the grid by one sector
    rotated = rotate_z(pts.astype(np.float32), 30.0).astype(np.float64)
    np.testing.assert_allclose(
        polar_grid(rotated, 10, 12, 40.0), np.roll(grid, 1, axis=1), atol=1e-4
    )


def test_keypoint_count_respected(scene):
    enc = HandcraftedEncoder(HandcraftedEncoderConfig(num_keypoints=40))
    f = enc.encode(scene)
    assert f.keypoints.shape == (40, 3)
    assert f.local_features.shape == (40, 33)


def test_fewer_points_than_keypoints_returns_all():
    # 30 points 2 m apart in a line: the voxel grid keeps them all
    x = np.arange(30, dtype=np.float32) * 2.0 + 2.0
    scan = np.c_[x, np.zeros(30), np.zeros(30)].astype(np.float32)
    f = HandcraftedEncoder().encode(scan)
    assert f.keypoints.shape == (30, 3)
    assert f.local_features.shape == (30, 33)
    assert np.isfinite(f.local_features).all()
    assert sorted(f.keypoints[:, 0].tolist()) == pytest.approx(x.tolist(), abs=1e-5)


def test_select_keypoints_ranks_and_suppresses():
    pts = np.array([[0.1, 0, 0], [0.2, 0, 0], [5.0, 0, 0], [9.0, 0, 0]], dtype=np.float32)
    sal = np.array([0.5, 0.9, 0.1, 0.2])
    # points 0 and 1 share a voxel: 1 wins it, 0 only comes after the other voxels
    assert select_keypoints(pts, sal, 4, 1.0).tolist() == [1, 3, 2, 0]
    assert select_keypoints(pts, sal, 2, 1.0).tolist() == [1, 3]


def test_smallest_eigenpairs_match_eigh(rng):
    a = rng.normal(size=(200, 3, 3))
    cov = a @ a.transpose(0, 2, 1)  # [200, 3, 3] symmetric positive semi-definite
    special = np.array(
        [
            np.eye(3) * 2.0,  # isotropic: every vector is an eigenvector
            np.diag([4.0, 1.0, 0.0]),  # plane: normal is z
            np.diag([0.0, 0.0, 5.0]),  # line: repeated smallest eigenvalue
            np.zeros((3, 3)),
        ]
    )
    cov = np.concatenate([cov, special])
    lam0, vec = _smallest_eigenpairs(cov)
    evals, evecs = np.linalg.eigh(cov)
    np.testing.assert_allclose(lam0, np.maximum(evals[:, 0], 0), atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(vec, axis=1), 1.0, atol=1e-9)
    # an eigenvector of the smallest eigenvalue: cov v = lam0 v
    resid = np.einsum("mij,mj->mi", cov, vec) - lam0[:, None] * vec
    assert np.abs(resid).max() < 1e-8
    np.testing.assert_allclose(np.abs(vec[201]), [0, 0, 1], atol=1e-12)


def test_fpfh_rows_follow_the_requested_order(scene):
    pts = preprocess(scene, PreprocessConfig())
    normals, _ = normals_and_saliency(pts, 0.75)
    idx = np.array([700, 3, 250, 3, 1200, 42])  # unsorted, with a repeat
    rows = fpfh_at(pts, normals, idx, 1.5)
    assert rows.shape == (6, 33)
    for r, i in enumerate(idx):
        np.testing.assert_array_equal(rows[r], fpfh_at(pts, normals, np.array([i]), 1.5)[0])
    assert not np.array_equal(rows[0], rows[1])


@pytest.mark.parametrize(
    "scan",
    [
        np.zeros((0, 4), dtype=np.float32),
        np.full((100, 4), np.nan, dtype=np.float32),
        np.zeros((10, 2), dtype=np.float32),
        np.array([[50.0, 0.0, 0.0]] * 5, dtype=np.float32),  # nothing inside max_radius
    ],
    ids=["empty", "all-nan", "2-columns", "beyond-max-radius"],
)
def test_handcrafted_bad_scan_raises(encoder, scan):
    with pytest.raises(InputError):
        encoder.encode(scan)


def test_identity_covers_every_parameter(encoder):
    params = encoder.identity.params
    assert params["encoder"] == HandcraftedEncoderConfig().model_dump()
    assert params["preprocess"] == PreprocessConfig().model_dump()
    assert HandcraftedEncoder().identity == encoder.identity
    other_pre = HandcraftedEncoder(preprocess_config=PreprocessConfig(voxel_size=0.5))
    other_enc = HandcraftedEncoder(HandcraftedEncoderConfig(fpfh_radius=1.0))
    assert other_pre.identity != encoder.identity
    assert other_enc.identity != encoder.identity
    assert other_pre.identity.fingerprint != other_enc.identity.fingerprint


def test_check_refuses_other_encoder_and_wrong_dims(encoder, scene, scene_features):
    small = HandcraftedEncoder(HandcraftedEncoderConfig(num_keypoints=16))
    with pytest.raises(EncoderMismatchError):
        encoder.check(small.encode(scene))
    f = scene_features
    bad_global = Features(f.global_descriptor[:-1], f.keypoints, f.local_features, f.encoder)
    with pytest.raises(InputError, match="global_descriptor"):
        encoder.check(bad_global)
    bad_local = Features(f.global_descriptor, f.keypoints, f.local_features[:, :10], f.encoder)
    with pytest.raises(InputError, match="local_features"):
        encoder.check(bad_local)
    bad_count = Features(f.global_descriptor, f.keypoints[:-1], f.local_features, f.encoder)
    with pytest.raises(InputError, match="local_features"):
        encoder.check(bad_count)


# real data (committed fixture, tests/fixtures/balm_mini)


def _load_bin(path: Path) -> np.ndarray:
    return np.fromfile(path, dtype=np.float32).reshape(-1, 4)


@pytest.fixture(scope="module")
def balm_scans(request) -> list[np.ndarray]:
    try:
        root = request.getfixturevalue("balm_mini_dir")
    except pytest.FixtureLookupError:
        pytest.skip("balm_mini fixture not available")
    files = sorted(Path(root, "velodyne").glob("*.bin"))
    if not files:
        pytest.skip("balm_mini fixture has no scans")
    return [_load_bin(p) for p in files]


@pytest.mark.parametrize("deg", [37.0, 90.0, 180.0])
def test_yaw_invariance_on_real_scan(encoder, balm_scans, deg):
    scan = balm_scans[0]
    a = encoder.encode(scan).global_descriptor
    b = encoder.encode(rotate_z(scan, deg)).global_descriptor
    assert cosine_distance(a, b) < 0.05


@pytest.mark.parametrize(("i", "j"), [(0, 1), (13, 11)])
def test_fpfh_matches_on_real_revisit(encoder, balm_scans, balm_mini_dir, i, j):
    """Feature nearest neighbours agree with the ground-truth pose far above chance."""
    poses = np.loadtxt(Path(balm_mini_dir, "poses.txt")).reshape(-1, 3, 4)
    t_world = np.tile(np.eye(4), (len(poses), 1, 1))
    t_world[:, :3] = poses
    t_j_i = np.linalg.inv(t_world[j]) @ t_world[i]  # maps scan i into scan j's frame
    fi, fj = encoder.encode(balm_scans[i]), encoder.encode(balm_scans[j])
    ki = fi.keypoints @ t_j_i[:3, :3].T + t_j_i[:3, 3]  # [N, 3] in frame j
    sim = fi.local_features @ fj.local_features.T  # [N, N] cosine
    nn = sim.argmax(axis=1)
    inliers = int((np.linalg.norm(ki - fj.keypoints[nn], axis=1) < 1.0).sum())
    # chance: expected hits if the match were a random keypoint of j
    dist = np.linalg.norm(ki[:, None, :] - fj.keypoints[None, :, :], axis=2)  # [N, N]
    chance = float((dist < 1.0).mean()) * len(ki)
    assert inliers >= 15
    assert inliers > 5 * chance


# ---------------------------------------------------------------------------------------
# precomputed


@pytest.fixture
def pre() -> PrecomputedEncoder:
    return PrecomputedEncoder("egonn", global_dim=256, local_dim=128)


def test_precomputed_good_input(pre, rng):
    f = pre.from_arrays(rng.normal(size=256), rng.normal(size=(64, 3)), rng.normal(size=(64, 128)))
    assert f.encoder.name == "precomputed:egonn"
    assert f.encoder.params == {"global_dim": 256, "local_dim": 128}
    assert f.global_descriptor.dtype == np.float32
    assert np.linalg.norm(f.global_descriptor) == pytest.approx(1.0, abs=1e-5)
    assert f.local_features.shape == (64, 128)
    pre.check(f)


def test_precomputed_encode_refuses_scans(pre, scene):
    with pytest.raises(InputError, match="precomputed"):
        pre.encode(scene)


@pytest.mark.parametrize(
    ("field", "g", "k", "f"),
    [
        ("global_descriptor", (255,), (64, 3), (64, 128)),  # wrong global dim
        ("local_features", (256,), (64, 3), (64, 127)),  # wrong local dim
        ("keypoints", (256,), (64, 2), (64, 128)),  # wrong keypoint columns
        ("global_descriptor", (1, 256), (64, 3), (64, 128)),  # wrong ndim
        ("local_features", (256,), (64, 3), (64 * 128,)),  # wrong ndim
        ("local_features", (256,), (64, 3), (63, 128)),  # mismatched counts
    ],
)
def test_precomputed_bad_shapes(pre, rng, field, g, k, f):
    with pytest.raises(InputError, match=field):
        pre.from_arrays(rng.normal(size=g), rng.normal(size=k), rng.normal(size=f))


@pytest.mark.parametrize("field", ["global_descriptor", "keypoints", "local_features"])
def test_precomputed_nan_names_field(pre, rng, field):
    arrays = {
        "global_descriptor": rng.normal(size=256),
        "keypoints": rng.normal(size=(8, 3)),
        "local_features": rng.normal(size=(8, 128)),
    }
    arrays[field].flat[3] = np.nan
    with pytest.raises(InputError, match=field):
        pre.from_arrays(**arrays)


def test_precomputed_identity_depends_on_name_and_dims(pre):
    assert PrecomputedEncoder("egonn", 256, 128).identity == pre.identity
    assert PrecomputedEncoder("logg3d", 256, 128).identity != pre.identity
    assert PrecomputedEncoder("egonn", 256, 64).identity != pre.identity


# ---------------------------------------------------------------------------------------
# spec and factory


def test_spec_round_trip_and_factory(tmp_path):
    spec = EncoderSpec()
    assert isinstance(make_encoder(spec), LearnedEncoder)  # the default
    assert isinstance(make_encoder(EncoderSpec(kind="handcrafted")), HandcraftedEncoder)
    spec2 = EncoderSpec.model_validate_json(spec.model_dump_json())
    assert make_encoder(spec2).identity == make_encoder(spec).identity
    p = make_encoder(EncoderSpec(kind="precomputed", name="egonn", global_dim=256, local_dim=128))
    assert isinstance(p, PrecomputedEncoder) and isinstance(p, Encoder)
    assert p.global_dim == 256 and p.local_dim == 128


def test_spec_requires_kind_fields():
    with pytest.raises(pydantic.ValidationError, match="local_dim"):
        EncoderSpec(kind="precomputed", name="egonn", global_dim=256)
    with pytest.raises(pydantic.ValidationError, match="model_path"):
        EncoderSpec(kind="torchscript")
    with pytest.raises(pydantic.ValidationError):
        EncoderSpec(kind="other")


# ---------------------------------------------------------------------------------------
# torchscript

try:  # torch comes with the service extra; only these tests need it
    import torch
except ImportError:  # pragma: no cover
    torch = None

needs_torch = pytest.mark.skipif(torch is None, reason="torch is not installed")
# torch.jit.script/save are deprecated upstream but are exactly the plug-in format
jit_ok = pytest.mark.filterwarnings("ignore:`torch.jit:DeprecationWarning")

if torch is not None:

    class TinyNet(torch.nn.Module):
        """First ``n`` points as keypoints, an MLP for local features, max-pool for global."""

        def __init__(self, n: int = 16, d: int = 8, g: int = 12, declare_dims: bool = True):
            super().__init__()
            self.n = n
            if declare_dims:
                self.global_dim = g
                self.local_dim = d
            self.mlp = torch.nn.Sequential(
                torch.nn.Linear(4, 16), torch.nn.ReLU(), torch.nn.Linear(16, d)
            )
            self.head = torch.nn.Linear(d, g)

        def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            feats = self.mlp(x)  # [P, d]
            g = self.head(torch.max(feats, dim=0)[0])  # [g]
            return g, x[: self.n, :3], feats[: self.n]

    class BadNet(torch.nn.Module):
        """Returns keypoints with 2 columns."""

        def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            return x[0], x[:4, :2], x[:4]


def save_scripted(module, path: Path, seed: int = 0) -> Path:
    torch.manual_seed(seed)
    for p in module.parameters():
        torch.nn.init.normal_(p)
    torch.jit.script(module).save(str(path))
    return path


@needs_torch
@jit_ok
def test_torchscript_round_trip(tmp_path, scene):
    path = save_scripted(TinyNet(), tmp_path / "tiny.pt")
    enc = make_encoder(EncoderSpec(kind="torchscript", model_path=str(path)))
    assert isinstance(enc, TorchScriptEncoder)
    assert (enc.global_dim, enc.local_dim) == (12, 8)
    f = enc.encode(scene)
    assert f.global_descriptor.shape == (12,)
    assert f.keypoints.shape == (16, 3) and f.local_features.shape == (16, 8)
    # the model saw the preprocessed cloud: its first points are the keypoints
    pts = preprocess(scene, PreprocessConfig())
    np.testing.assert_allclose(f.keypoints, pts[:16], atol=1e-6)
    enc.check(f)
    np.testing.assert_array_equal(enc.encode(scene).local_features, f.local_features)
    params = enc.identity.params
    assert len(params["model_sha256"]) == 64
    assert params["preprocess"] == PreprocessConfig().model_dump()


@needs_torch
@jit_ok
def test_torchscript_dims_probed_when_not_declared(tmp_path, scene):
    path = save_scripted(TinyNet(n=5, d=6, g=7, declare_dims=False), tmp_path / "nodims.pt")
    enc = TorchScriptEncoder(path)
    assert (enc.global_dim, enc.local_dim) == (7, 6)
    assert enc.encode(scene).local_features.shape == (5, 6)


@needs_torch
@jit_ok
def test_torchscript_different_model_different_identity(tmp_path):
    a = TorchScriptEncoder(save_scripted(TinyNet(), tmp_path / "a.pt", seed=0))
    b = TorchScriptEncoder(save_scripted(TinyNet(), tmp_path / "b.pt", seed=1))
    a2 = TorchScriptEncoder(tmp_path / "a.pt", PreprocessConfig())
    assert a.identity.fingerprint != b.identity.fingerprint
    assert a.identity == a2.identity
    a_vox = TorchScriptEncoder(tmp_path / "a.pt", PreprocessConfig(voxel_size=0.5))
    assert a_vox.identity != a.identity


@needs_torch
@jit_ok
def test_torchscript_features_refused_by_handcrafted(tmp_path, encoder, scene):
    enc = TorchScriptEncoder(save_scripted(TinyNet(), tmp_path / "tiny.pt"))
    with pytest.raises(EncoderMismatchError):
        encoder.check(enc.encode(scene))


@needs_torch
@jit_ok
def test_torchscript_missing_file(tmp_path):
    missing = tmp_path / "nope.pt"
    with pytest.raises(InputError, match="nope.pt"):
        make_encoder(EncoderSpec(kind="torchscript", model_path=str(missing)))


@needs_torch
@jit_ok
def test_torchscript_corrupt_file(tmp_path):
    bad = tmp_path / "corrupt.pt"
    bad.write_bytes(b"this is not a torchscript archive")
    with pytest.raises(InputError, match="corrupt.pt"):
        TorchScriptEncoder(bad)


@needs_torch
@jit_ok
def test_torchscript_wrong_output_shapes(tmp_path):
    path = tmp_path / "bad.pt"
    torch.jit.script(BadNet()).save(str(path))
    with pytest.raises(InputError, match=r"keypoints \[4, 2\]"):
        TorchScriptEncoder(path)


@needs_torch
@jit_ok
@pytest.mark.gpu
@pytest.mark.skipif(torch is None or not torch.cuda.is_available(), reason="needs CUDA")
def test_torchscript_on_cuda_matches_cpu(tmp_path, scene):
    path = save_scripted(TinyNet(), tmp_path / "tiny.pt")
    cpu = TorchScriptEncoder(path, device="cpu").encode(scene)
    gpu_enc = TorchScriptEncoder(path, device="cuda")
    assert gpu_enc.device.type == "cuda"
    gpu = gpu_enc.encode(scene)
    assert gpu.encoder == cpu.encoder  # the device is not part of the identity
    np.testing.assert_array_equal(gpu.keypoints, cpu.keypoints)
    np.testing.assert_allclose(gpu.local_features, cpu.local_features, rtol=1e-3, atol=1e-3)
    np.testing.assert_allclose(gpu.global_descriptor, cpu.global_descriptor, atol=1e-4)


def test_repeated_keypoints_are_kept_once() -> None:
    """Padding to a fixed count (zero keypoints with zero features) repeats one row; it is
    kept once, as it would otherwise match itself as a perfectly consistent cluster."""
    enc = PrecomputedEncoder("p", 4, 2)
    rng = np.random.default_rng(0)
    kp, lf = rng.normal(size=(5, 3)), rng.normal(size=(5, 2))
    padded_kp = np.vstack([kp[:2], np.zeros((6, 3)), kp[2:], kp[:1]])
    padded_lf = np.vstack([lf[:2], np.zeros((6, 2)), lf[2:], lf[:1]])
    f = enc.from_arrays(np.ones(4), padded_kp, padded_lf)
    assert f.num_keypoints == 6  # five distinct rows and one zero row, in their order
    assert np.allclose(f.keypoints, np.vstack([kp[:2], np.zeros((1, 3)), kp[2:]]))
    assert np.allclose(f.local_features, np.vstack([lf[:2], np.zeros((1, 2)), lf[2:]]))
    # the same keypoint with another feature is another row
    g = enc.from_arrays(np.ones(4), np.zeros((2, 3)), np.array([[0.0, 1.0], [1.0, 0.0]]))
    assert g.num_keypoints == 2
