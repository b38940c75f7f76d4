"""Learned BEV encoder: a tiny training run on a generated sequence, checkpoint, resume."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from sgvloc.core.bev import (
    LearnedEncoderConfig,
    level_cloud,
    prepare_points,
    rasterize,
    rasterize_cloud,
)
from sgvloc.core.bevnet import cell_to_metres, metres_to_cell
from sgvloc.core.encoders import EncoderSpec, make_encoder
from sgvloc.core.encoders.learned import LearnedEncoder
from sgvloc.core.errors import InputError
from sgvloc.core.io import read_scan
from sgvloc.tools.train import (
    Sequence,
    TrainConfig,
    augment_density,
    build_model,
    export_weights,
    load_checkpoint,
    losses,
    narrow_view,
    rotate_image,
    sample_batch,
    train,
)


def world(seed: int = 0) -> np.ndarray:
    """Static world points ``[P, 3]``: boxes and poles scattered over 80 x 40 m."""
    rng = np.random.default_rng(seed)
    parts = []
    for _ in range(30):
        cx, cy = rng.uniform(-10, 70), rng.uniform(-20, 20)
        sx, sy, h = rng.uniform(1, 5), rng.uniform(1, 5), rng.uniform(1, 6)
        m = 800
        s, face = rng.uniform(-0.5, 0.5, m), rng.integers(0, 4, m)
        lx = np.where(face < 2, s * sx, np.where(face == 2, 0.5, -0.5) * sx)
        ly = np.where(face < 2, np.where(face == 0, 0.5, -0.5) * sy, s * sy)
        parts.append(np.c_[cx + lx, cy + ly, rng.uniform(-1.7, h, m)])
    for _ in range(60):
        cx, cy = rng.uniform(-10, 70), rng.uniform(-20, 20)
        m = 120
        parts.append(np.c_[np.full(m, cx), np.full(m, cy), rng.uniform(-1.7, 3.0, m)])
    return np.concatenate(parts)


def make_sequence(n: int = 12) -> Sequence:
    """Scans along x with a slow yaw drift, rasterised in each sensor frame."""
    pts = world()
    images, poses = [], []
    for i in range(n):
        yaw = 0.15 * i
        T = np.eye(4)
        T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        T[:2, 3] = [2.0 * i, 0.3 * i]
        local = (pts - T[:3, 3]) @ T[:3, :3]  # world -> sensor: R^T (p - t)
        images.append(rasterize(local).image)
        poses.append(T)
    return Sequence("synthetic", np.stack(images), np.stack(poses))


def tiny_config(steps: int) -> TrainConfig:
    return TrainConfig(
        steps=steps,
        batch=2,
        cells_per_pair=32,
        width=8,
        local_dim=16,
        global_dim=32,
        lr=3e-3,
        val_every=steps,
        checkpoint_every=steps,
        pos_radius=4.5,
    )


@pytest.fixture(scope="module")
def seq() -> Sequence:
    return make_sequence()


def test_sequences_load_from_images_and_from_scans(seq: Sequence, tmp_path: Path) -> None:
    import cv2

    from sgvloc.core.io import write_kitti_bin

    pts = world()
    (tmp_path / "scans" / "velodyne").mkdir(parents=True)
    (tmp_path / "bev" / "imgs").mkdir(parents=True)
    for i, T in enumerate(seq.poses[:4]):
        local = (pts - T[:3, 3]) @ T[:3, :3]
        write_kitti_bin(tmp_path / "scans" / "velodyne" / f"{i:06d}.bin", local)
        cv2.imwrite(str(tmp_path / "bev" / "imgs" / f"{i:06d}.png"), seq.images[i])
    lines = "\n".join(" ".join(f"{v:.9f}" for v in T[:3].ravel()) for T in seq.poses[:4])
    (tmp_path / "scans" / "poses.txt").write_text(lines + "\n")
    (tmp_path / "scans" / "times.txt").write_text("0\n0.1\n0.2\n0.3\n")
    (tmp_path / "bev" / "pose.txt").write_text(lines + "\n")
    got = Sequence.load(tmp_path / "bev", stride=2)
    np.testing.assert_array_equal(got.images, seq.images[:4:2])
    np.testing.assert_allclose(got.poses, seq.poses[:4:2], atol=1e-6)
    # scans are levelled as the learned encoder does, and their poses follow
    got = Sequence.load(tmp_path / "scans", stride=2)
    for j, i in enumerate((0, 2)):
        scan = read_scan(tmp_path / "scans" / "velodyne" / f"{i:06d}.bin").points
        level, R = level_cloud(prepare_points(scan))
        np.testing.assert_array_equal(got.images[j], rasterize_cloud(level).image)
        np.testing.assert_allclose(got.poses[j, :3, :3] @ R, seq.poses[i, :3, :3], atol=1e-6)
        assert (got.images[j] == seq.images[i]).mean() > 0.95  # the scans are nearly level
    with pytest.raises(InputError):
        Sequence.load(tmp_path)  # neither layout


def test_tilted_scans_load_as_level_images(seq: Sequence, tmp_path: Path) -> None:
    from sgvloc.core.io import write_kitti_bin

    a = math.radians(12.0)
    tilt = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    g = np.mgrid[-10:70:0.5, -20:20:0.5].reshape(2, -1).T
    pts = np.concatenate([world(), np.c_[g, np.full(len(g), -1.65)]])  # with a ground
    (tmp_path / "velodyne").mkdir()
    poses = []
    for i, T in enumerate(seq.poses[:2]):
        Tt = T.copy()
        Tt[:3, :3] = T[:3, :3] @ tilt.T  # the sensor rolled by 12 degrees
        poses.append(Tt)
        local = (pts - Tt[:3, 3]) @ Tt[:3, :3]
        write_kitti_bin(tmp_path / "velodyne" / f"{i:06d}.bin", local)
    lines = "\n".join(" ".join(f"{v:.9f}" for v in T[:3].ravel()) for T in poses)
    (tmp_path / "poses.txt").write_text(lines + "\n")
    (tmp_path / "times.txt").write_text("0\n0.1\n")
    got = Sequence.load(tmp_path)
    for i in range(2):
        # levelled: close to the untilted image, with the untilted pose
        assert (got.images[i] == seq.images[i]).mean() > 0.9
        R = got.poses[i, :3, :3].T @ seq.poses[i, :3, :3]
        assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) < 1.0


def test_rotation_and_cell_mapping_are_consistent(seq: Sequence) -> None:
    img = seq.images[3]
    # rotating by a yaw and back keeps most of the occupied pixels
    back = rotate_image(rotate_image(img, 0.7), -0.7)
    assert ((back > 0) & (img > 0)).sum() > 0.6 * (img > 0).sum()
    # output cells are 0.8 m: x = 10.1 lies in [9.6, 10.4), x = 0.1 in [0, 0.8)
    r, c = metres_to_cell(np.array([[10.1, 0.1], [0.1, 10.1]]))
    np.testing.assert_allclose(cell_to_metres(r, c), [[10.0, 0.4], [0.4, 10.0]], atol=1e-9)
    # corresponding cells of a sampled pair show the same structure
    a, p, _, corr, _ = sample_batch([seq], tiny_config(1), np.random.default_rng(0))
    for k, (ia, ib) in enumerate(corr):
        assert len(ia) >= 8
        pad = np.zeros((2, 152, 152))
        pad[0, :151, :151], pad[1, :151, :151] = a[k], p[k]
        cells = pad.reshape(2, 76, 2, 76, 2).max(axis=(2, 4)).reshape(2, -1)
        assert (cells[0, ia] > 0).all() and (cells[1, ib] > 0).all()


def test_tiny_training_lowers_the_loss_and_checkpoints(seq: Sequence, tmp_path: Path) -> None:
    cfg = tiny_config(8)
    fixed = sample_batch([seq], cfg, np.random.default_rng(99))
    torch.manual_seed(cfg.seed)
    before_model = build_model(cfg)  # train() starts from the same seeded weights
    with torch.no_grad():
        before = float(losses(before_model, *fixed[:4], cfg, torch.device("cpu"))["total"])
    ckpt = train([seq], tmp_path, cfg, [seq], progress=False)
    assert ckpt.is_file() and (tmp_path / "curves.png").is_file()
    assert (tmp_path / "log.json").is_file()
    model, state = load_checkpoint(ckpt)
    model.train()  # batch statistics, as in training
    with torch.no_grad():
        after = float(losses(model, *fixed[:4], cfg, torch.device("cpu"))["total"])
    assert after < before
    assert state["step"] == 8 and len(state["history"]) == 8 and state["val"]
    # the checkpoint loads into an encoder with finite features of the documented shapes
    net = LearnedEncoderConfig(num_keypoints=64, global_descriptor="network")
    enc = LearnedEncoder.from_model(model, net, "test", min_grey=cfg.min_grey)
    f = enc.encode_image(seq.images[0])
    assert f.global_descriptor.shape == (32,)
    assert 1 <= f.num_keypoints <= 64
    assert f.keypoints.shape == (f.num_keypoints, 3) and f.local_features.shape[1] == 16
    assert np.isfinite(f.local_features).all() and np.all(f.keypoints[:, 2] == 0)
    # resuming continues from the saved step
    train([seq], tmp_path, tiny_config(9), progress=False)
    _, state2 = load_checkpoint(ckpt)
    assert state2["step"] == 9 and len(state2["history"]) == 9
    assert state2["history"][:8] == state["history"]
    assert not list(tmp_path.glob("*.tmp"))  # saved beside, then renamed
    # a resume continues the same training: other settings are refused, not half applied
    with pytest.raises(InputError, match="lr 0.003 -> 1e-05"):
        train([seq], tmp_path, replace(tiny_config(10), lr=1e-5), progress=False)
    # and on the same data: another sequence (or a part of it) is refused
    other = Sequence("other", seq.images[:10], seq.poses[:10])
    with pytest.raises(InputError, match=r"other training data \(synthetic \(12 scans\)"):
        train([other], tmp_path, tiny_config(10), progress=False)
    assert json.loads((tmp_path / "log.json").read_text())["data"] == [
        {"name": "synthetic", "scans": 12}
    ]
    # an exported weights file (or anything else) is not a checkpoint
    weights = export_weights(ckpt, tmp_path / "w.pt")
    with pytest.raises(InputError, match="not a training checkpoint"):
        load_checkpoint(weights)
    # a checkpoint cut short (a save interrupted before saves were atomic) is a clear error
    ckpt.write_bytes(ckpt.read_bytes()[:20_000])
    with pytest.raises(InputError, match="cannot resume from this checkpoint"):
        train([seq], tmp_path, tiny_config(10), progress=False)


def test_an_interrupted_run_resumes_as_if_never_stopped(
    seq: Sequence, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C (a real SIGINT) in the middle of a step lets that step end, saves it whole
    (weights, optimiser, random generators) and stops; a run again resumes after it and
    trains exactly as an uninterrupted run does."""
    import signal

    import sgvloc.tools.train as training

    whole = train([seq], tmp_path / "whole", tiny_config(8), progress=False)
    _, reference = load_checkpoint(whole)

    real, calls = training.losses, []

    def interrupting(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        calls.append(1)
        if len(calls) == 4:  # the 4th step, after its batch was drawn
            signal.raise_signal(signal.SIGINT)
        return real(*args, **kwargs)

    monkeypatch.setattr(training, "losses", interrupting)
    before = signal.getsignal(signal.SIGINT)  # SIG_IGN when started in the background
    with pytest.raises(KeyboardInterrupt):
        train([seq], tmp_path / "cut", tiny_config(8), progress=False)
    _, state = load_checkpoint(tmp_path / "cut" / "checkpoint.pt")
    assert state["step"] == 4 and len(state["history"]) == 4
    assert signal.getsignal(signal.SIGINT) is before  # put back
    monkeypatch.setattr(training, "losses", real)
    train([seq], tmp_path / "cut", tiny_config(8), progress=False)
    _, resumed = load_checkpoint(tmp_path / "cut" / "checkpoint.pt")
    assert resumed["history"] == reference["history"]


def test_exported_weights_make_a_learned_encoder_of_their_own(
    seq: Sequence, tmp_path: Path
) -> None:
    ckpt = train([seq], tmp_path, tiny_config(2), progress=False)
    weights = export_weights(ckpt, tmp_path / "w.pt", note="tiny")
    net = LearnedEncoderConfig(global_descriptor="network")
    spec = EncoderSpec(kind="learned", model_path=str(weights), learned=net)
    enc = make_encoder(spec)
    assert (enc.global_dim, enc.local_dim) == (32, 16)
    assert enc.meta["steps"] == 2 and enc.meta["note"] == "tiny"
    assert enc.min_grey == TrainConfig().min_grey  # the training cut travels with the weights
    f = enc.encode_image(seq.images[1])
    assert f.encoder == enc.identity and f.global_descriptor.shape == (32,)
    # the identity follows the weights' bytes: other weights are another encoder
    assert enc.identity != make_encoder(EncoderSpec(kind="learned")).identity
    # a training checkpoint is not a weights file; a missing file is named
    with pytest.raises(InputError, match="export-weights"):
        make_encoder(EncoderSpec(kind="learned", model_path=str(ckpt)))
    with pytest.raises(InputError, match="does not exist"):
        make_encoder(EncoderSpec(kind="learned", model_path=str(tmp_path / "nope.pt")))


def test_density_augmentation_keeps_the_shape_of_the_image(seq: Sequence) -> None:
    img = seq.images[0]
    cfg = TrainConfig(gain_jitter=0.4, dropout=0.3)
    out = augment_density(img, cfg, np.random.default_rng(0))
    assert out.shape == img.shape and out.dtype == np.uint8
    assert not (out[img == 0]).any()  # nothing appears where nothing was
    kept = (out > 0).sum() / (img > 0).sum()
    assert 0.6 < kept <= 1.0
    off = TrainConfig(gain_jitter=0.0, dropout=0.0)
    assert augment_density(img, off, np.random.default_rng(0)) is img


def test_field_of_view_augmentation_keeps_a_window_ahead(seq: Sequence) -> None:
    """narrow_view keeps exactly what a forward-looking sensor of 60-120 deg sees (the
    eval's crop), with the configured probability; off, it draws nothing at all."""
    from sgvloc.core.bev import crop_image_azimuth, pixel_to_metres

    img = seq.images[0]
    cfg = TrainConfig(fov_crop=1.0)
    out = narrow_view(img, cfg, np.random.default_rng(0))
    assert out.shape == img.shape and 0 < (out > 0).sum() < (img > 0).sum()
    r, c = np.nonzero(out)
    xy = pixel_to_metres(r, c)
    assert np.abs(np.degrees(np.arctan2(xy[:, 1], xy[:, 0]))).max() <= 60.0  # <= 120 deg wide
    for seed in range(3):  # the same crop as the eval's --fov, at the width drawn
        draw = np.random.default_rng(seed)
        draw.random()
        width = draw.uniform(60.0, 120.0)
        got = narrow_view(img, cfg, np.random.default_rng(seed))
        assert np.array_equal(got, crop_image_azimuth(img, width))
    half = TrainConfig(fov_crop=0.5)
    rng = np.random.default_rng(1)
    cropped = sum(narrow_view(img, half, rng) is not img for _ in range(200))
    assert 70 < cropped < 130
    rng = np.random.default_rng(2)
    assert narrow_view(img, TrainConfig(), rng) is img
    assert rng.random() == np.random.default_rng(2).random()  # default training unchanged


def test_training_can_start_from_exported_weights(seq: Sequence, tmp_path: Path) -> None:
    ckpt = train([seq], tmp_path / "a", tiny_config(2), progress=False)
    weights = export_weights(ckpt, tmp_path / "w.pt")
    start, _ = load_checkpoint(ckpt)
    cfg = tiny_config(1)
    cfg.init, cfg.seed = str(weights), 7  # another seed: the weights must come from init
    zero = TrainConfig(**{**cfg.__dict__, "steps": 0, "checkpoint_every": 1})
    ckpt0 = train([seq], tmp_path / "b", zero, progress=False)
    model, _ = load_checkpoint(ckpt0)
    for (k, a), b in zip(start.state_dict().items(), model.state_dict().values(), strict=True):
        assert torch.equal(a, b), k
    wrong = TrainConfig(**{**cfg.__dict__, "width": 16})
    with pytest.raises(InputError, match="do not fit"):
        train([seq], tmp_path / "c", wrong, progress=False)


def test_validation_does_not_change_the_training_run(seq: Sequence, tmp_path: Path) -> None:
    """Validating draws nothing from the random state training goes on with: the same
    seed trains the same model with validation as without."""
    cfg = replace(tiny_config(4), val_every=2)
    with_val = train([seq], tmp_path / "a", cfg, [seq], progress=False)
    without = train([seq], tmp_path / "b", cfg, None, progress=False)
    (a, sa), (b, sb) = load_checkpoint(with_val), load_checkpoint(without)
    assert [h["total"] for h in sa["history"]] == [h["total"] for h in sb["history"]]
    for pa, pb in zip(a.state_dict().values(), b.state_dict().values(), strict=True):
        assert torch.equal(pa, pb)
