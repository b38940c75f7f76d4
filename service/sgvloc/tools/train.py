"""Training of the learned BEV encoder (:class:`sgvloc.core.bevnet.BEVNet`) on
kitti-bev-style sequences, and export of its weights for the ``learned`` encoder kind.

Training (:func:`train`), seeded and resumable (``checkpoint.pt`` holds model, optimiser,
step and random state): each step samples pairs of scans of one sequence less than
``pos_radius`` apart, rotates each image about the sensor by a random yaw, and from the
ground-truth poses pairs every occupied anchor cell with the cell it falls in in the other
image. Losses:

- local: InfoNCE over sampled corresponding cells (the other sampled cells of the
  positive image are the negatives, hard ones included);
- saliency: binary cross-entropy towards "this cell's descriptor nearest neighbour is its
  true counterpart" (detached), and towards 0 on empty cells;
- global: InfoNCE over the batch (anchor vs positives; other places more than
  ``neg_radius`` away are negatives, closer ones are masked out).

Writes ``checkpoint.pt``, ``curves.png`` (loss and validation curves) and ``log.json``.
CPU by default, CUDA with ``device="cuda"``/``"auto"``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import signal
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import torch
import torch.nn.functional as F

from sgvloc.core.bev import (
    KITTI_BEV,
    crop_image_azimuth,
    level_cloud,
    load_bev_image,
    prepare_points,
    rasterize_cloud,
)
from sgvloc.core.bevnet import (
    CELLS,
    INPUT_SIZE,
    BEVNet,
    cell_to_metres,
    cut_faint,
    metres_to_cell,
    occupied_cells,
    to_input,
)
from sgvloc.core.errors import InputError
from sgvloc.core.files import write_text_whole, write_whole

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------------
# data


@dataclass
class Sequence:
    """One kitti-bev-style sequence in memory: images ``[N, 151, 151]`` uint8, poses."""

    name: str
    images: np.ndarray
    poses: np.ndarray  # [N, 4, 4] T_world_lidar

    @classmethod
    def load(cls, path: str | Path, stride: int = 1) -> Sequence:
        """Read every ``stride``-th scan of a kitti-bev folder (``imgs/*.png``, ``pose.txt``)
        or of a KITTI-layout sequence (``velodyne/``, ``poses.txt``, ``times.txt``, e.g. from
        ``sgvloc synth``), whose scans are levelled and rasterised here as the learned
        encoder does (:func:`sgvloc.core.bev.level_cloud`); their poses are then those of
        the levelled frames.

        Raises :class:`InputError` if the folder is neither layout.
        """
        from sgvloc.core.io import read_scan

        from .evaluation.data import open_sequence

        seq = open_sequence(path)
        paths, poses = seq.paths[::stride], seq.poses[::stride]
        if seq.kind == "bev-images":
            images = [load_bev_image(p) for p in paths]
        else:
            images, poses = [], poses.copy()
            for i, p in enumerate(paths):
                level, R = level_cloud(prepare_points(read_scan(p).points))
                images.append(rasterize_cloud(level).image)
                poses[i, :3, :3] = poses[i, :3, :3] @ R.T  # T_world_levelled
        return cls(Path(path).name, np.stack(images), poses)


def rotate_image(img: np.ndarray, yaw: float) -> np.ndarray:
    """The BEV image of the scan rotated by ``yaw`` (rad) about the sensor (bilinear).

    Destination pixel ``(v', u')`` (row, col) is metric ``p' = R p``; its source is
    ``p = R^T p'``, read bilinearly (zero outside). Pure numpy.
    """
    n = img.shape[0]
    h = KITTI_BEV.half_cells + 0.5  # the sensor's continuous pixel coordinate
    c, s = math.cos(yaw), math.sin(yaw)
    v1, u1 = np.mgrid[0:n, 0:n].astype(np.float64)  # destination rows, cols
    a, b = h - v1, h - u1  # x', y' in pixels
    v = h - (c * a + s * b)  # source row: x = c x' + s y'
    u = h - (-s * a + c * b)  # source col: y = -s x' + c y'
    v0, u0 = np.floor(v).astype(np.int64), np.floor(u).astype(np.int64)
    fv, fu = v - v0, u - u0
    src = np.zeros((n + 2, n + 2), dtype=np.float64)  # one pixel of zeros around
    src[1:-1, 1:-1] = img
    v0 = np.clip(v0 + 1, 0, n)
    u0 = np.clip(u0 + 1, 0, n)
    out = (
        src[v0, u0] * (1 - fv) * (1 - fu)
        + src[v0 + 1, u0] * fv * (1 - fu)
        + src[v0, u0 + 1] * (1 - fv) * fu
        + src[v0 + 1, u0 + 1] * fv * fu
    )
    inside = (v > -1) & (v < n) & (u > -1) & (u < n)
    return np.rint(np.where(inside, out, 0.0)).astype(np.uint8)


def yaw_matrix2(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


@dataclass
class TrainConfig:
    """Settings of :func:`train` (all recorded in ``log.json``)."""

    steps: int = 3000
    batch: int = 8
    lr: float = 1e-3
    seed: int = 0
    pos_radius: float = 3.0
    neg_radius: float = 10.0
    cells_per_pair: int = 256
    temperature: float = 0.07
    width: int = 32
    local_dim: int = 64
    global_dim: int = 256
    val_every: int = 200
    checkpoint_every: int = 200
    device: str = "cpu"
    stride: int = 1
    #: density augmentation: each image's grey levels scaled by a gain in [1 - a, 1 + a] and
    #: a random share (up to ``dropout``) of its occupied pixels removed, so that the model
    #: does not learn one sensor's point density (0 turns it off)
    gain_jitter: float = 0.4
    dropout: float = 0.3
    #: pixels darker than this are zeroed after augmentation (:func:`cut_faint`); the
    #: encoder applies the same cut (stored with the exported weights)
    min_grey: int = 52
    #: field-of-view augmentation: with this probability an image keeps only a horizontal
    #: window of ``fov_min``..``fov_max`` degrees ahead of the sensor (a forward-looking
    #: sensor; :func:`sgvloc.core.bev.crop_image_azimuth`), before its yaw turn (0: off)
    fov_crop: float = 0.0
    fov_min: float = 60.0
    fov_max: float = 120.0
    #: start from these weights (a file of ``sgvloc export-weights``: fine-tuning)
    init: str | None = None
    extra: dict = field(default_factory=dict)


def augment_density(img: np.ndarray, cfg: TrainConfig, rng: np.random.Generator) -> np.ndarray:
    """Random gain on the grey levels and random removal of occupied pixels (uint8 in/out)."""
    if cfg.gain_jitter <= 0 and cfg.dropout <= 0:
        return img
    gain = rng.uniform(1 - cfg.gain_jitter, 1 + cfg.gain_jitter)
    out = np.clip(img.astype(np.float32) * gain, 0, 255)
    out[(img > 0) & (out < 1)] = 1  # a gain never empties an occupied pixel
    if cfg.dropout > 0:
        out[rng.random(img.shape) < rng.uniform(0, cfg.dropout)] = 0
    return out.astype(np.uint8)


def narrow_view(img: np.ndarray, cfg: TrainConfig, rng: np.random.Generator) -> np.ndarray:
    """The image as a forward-looking sensor of a random field of view would see it, with
    probability ``cfg.fov_crop`` (no random draw at all when that is 0)."""
    if cfg.fov_crop > 0 and rng.random() < cfg.fov_crop:
        return crop_image_azimuth(img, float(rng.uniform(cfg.fov_min, cfg.fov_max)))
    return img


def sample_batch(
    seqs: list[Sequence], cfg: TrainConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[tuple[np.ndarray, np.ndarray]], np.ndarray]:
    """Images of anchors and positives ``[B, 151, 151]`` (yaw-augmented), their positions
    in a common frame ``[B, 2]`` (for global negatives), per pair the corresponding cells
    ``(anchor flat cell ids [m], positive flat cell ids [m])``, and the sequence index.
    """
    a_imgs, p_imgs, pos, corr, sid = [], [], [], [], []
    for _ in range(cfg.batch):
        si = int(rng.integers(len(seqs)))
        s = seqs[si]
        xyz = s.poses[:, :3, 3]
        i = int(rng.integers(len(s.images)))
        d = np.linalg.norm(xyz[:, :2] - xyz[i, :2], axis=1)
        cand = np.nonzero((d < cfg.pos_radius) & (np.arange(len(d)) != i))[0]
        j = int(rng.choice(cand)) if len(cand) else i
        ya, yb = rng.uniform(0, 2 * np.pi, 2)
        ia, ib = (
            cut_faint(
                augment_density(rotate_image(narrow_view(s.images[n], cfg, rng), y), cfg, rng),
                cfg.min_grey,
            )
            for n, y in ((i, ya), (j, yb))
        )
        # anchor cells (occupied) -> metres (augmented A) -> A -> B -> augmented B -> cell
        occ = np.zeros((INPUT_SIZE, INPUT_SIZE), bool)
        occ[:151, :151] = ia > 0
        occ = occ.reshape(CELLS, 2, CELLS, 2).any(axis=(1, 3))
        r, c = np.nonzero(occ)
        xy_a = cell_to_metres(r, c) @ yaw_matrix2(ya)  # R^T applied to rows
        T_ba = np.linalg.inv(s.poses[j]) @ s.poses[i]
        xy_b = xy_a @ T_ba[:2, :2].T + T_ba[:2, 3]
        xy_b = xy_b @ yaw_matrix2(yb).T
        rb, cb = metres_to_cell(xy_b)
        ok = (rb >= 0) & (rb < CELLS) & (cb >= 0) & (cb < CELLS)
        occ_b = np.zeros((INPUT_SIZE, INPUT_SIZE), bool)
        occ_b[:151, :151] = ib > 0
        occ_b = occ_b.reshape(CELLS, 2, CELLS, 2).any(axis=(1, 3))
        ok[ok] &= occ_b[rb[ok], cb[ok]]
        ids = np.nonzero(ok)[0]
        if len(ids) > cfg.cells_per_pair:
            ids = rng.choice(ids, cfg.cells_per_pair, replace=False)
        corr.append((r[ids] * CELLS + c[ids], rb[ids] * CELLS + cb[ids]))
        a_imgs.append(ia)
        p_imgs.append(ib)
        pos.append(xyz[i, :2] + 1e5 * si)  # different sequences are far apart
        sid.append(si)
    return np.stack(a_imgs), np.stack(p_imgs), np.stack(pos), corr, np.array(sid)


# ---------------------------------------------------------------------------------------
# losses


def losses(
    model: BEVNet,
    a_imgs: np.ndarray,
    p_imgs: np.ndarray,
    positions: np.ndarray,
    corr: list[tuple[np.ndarray, np.ndarray]],
    cfg: TrainConfig,
    device: torch.device,
) -> dict[str, torch.Tensor]:
    """Local InfoNCE, saliency BCE and global InfoNCE for one batch; ``total`` sums them."""
    x = torch.cat([to_input(a_imgs), to_input(p_imgs)]).to(device)  # [2B, 1, 152, 152]
    g, local, sal = model(x)
    b = len(a_imgs)
    loc = local.flatten(2)  # [2B, D, C*C]
    salf = sal.flatten(1)  # [2B, C*C]
    occ = occupied_cells(x).flatten(1)  # [2B, C*C]
    l_local, l_sal, n_pairs = x.new_zeros(()), x.new_zeros(()), 0
    for k, (ia, ib) in enumerate(corr):
        if len(ia) < 8:
            continue
        ia_t = torch.as_tensor(ia, device=device)
        ib_t = torch.as_tensor(ib, device=device)
        da = loc[k][:, ia_t].T  # [m, D]
        db = loc[b + k][:, ib_t].T  # [m, D]
        logits = da @ db.T / cfg.temperature  # [m, m]
        target = torch.arange(len(ia), device=device)
        l_local = l_local + 0.5 * (
            F.cross_entropy(logits, target) + F.cross_entropy(logits.T, target)
        )
        correct = (logits.argmax(1) == target).float().detach()
        # saliency: matchable cells -> 1, other sampled cells -> 0, empty cells -> 0
        empty = torch.nonzero(~occ[k])[:, 0]
        if len(empty) > len(ia):
            empty = empty[torch.randperm(len(empty), device=device)[: len(ia)]]
        s_logit = torch.cat([salf[k][ia_t], salf[k][empty]])
        s_target = torch.cat([correct, torch.zeros(len(empty), device=device)])
        l_sal = l_sal + F.binary_cross_entropy_with_logits(s_logit, s_target)
        n_pairs += 1
    n_pairs = max(n_pairs, 1)
    l_local, l_sal = l_local / n_pairs, l_sal / n_pairs
    # global: anchors vs positives, far ones are negatives, near ones masked
    pos_t = torch.as_tensor(positions, dtype=torch.float32, device=device)
    dist = torch.cdist(pos_t, pos_t)  # [B, B]
    logits = g[:b] @ g[b:].T / cfg.temperature
    mask = (dist < cfg.neg_radius) & ~torch.eye(b, dtype=torch.bool, device=device)
    logits = logits.masked_fill(mask, -1e4)
    l_global = F.cross_entropy(logits, torch.arange(b, device=device))
    total = l_local + 0.5 * l_sal + l_global
    return {"total": total, "local": l_local, "saliency": l_sal, "global": l_global}


# ---------------------------------------------------------------------------------------
# training loop


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("device 'cuda' requested but CUDA is absent")
    return torch.device(name)


def build_model(cfg: TrainConfig) -> BEVNet:
    return BEVNet(cfg.width, cfg.local_dim, cfg.global_dim)


def load_checkpoint(path: str | Path) -> tuple[BEVNet, dict]:
    """Model (eval mode, CPU) and the checkpoint dictionary from ``checkpoint.pt``;
    :class:`InputError` for a file that is not one (exported weights, say)."""
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
        cfg = TrainConfig(**ckpt["config"])
        model = build_model(cfg)
        model.load_state_dict(ckpt["model"])
    except (OSError, RuntimeError, KeyError, TypeError, ValueError, EOFError) as exc:
        raise InputError(
            f"{path}: not a training checkpoint ({type(exc).__name__}: {exc}); exported "
            "weights go to --init or a map's model_path"
        ) from None
    return model.eval(), ckpt


#: settings a resumed run may change: how long it runs and how often it reports
RESUMABLE_CHANGES = frozenset({"steps", "val_every", "checkpoint_every", "device"})


def _plot(history: list[dict], val: list[dict], path: Path) -> None:
    try:
        import matplotlib
    except ImportError:  # pragma: no cover - the service extra has it
        log.warning("matplotlib is not installed: no %s", path.name)
        return

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    steps = [h["step"] for h in history]
    for key in ("total", "local", "saliency", "global"):
        ax[0].plot(steps, [h[key] for h in history], label=key)
    ax[0].set_xlabel("step")
    ax[0].set_title("training loss")
    ax[0].legend()
    if val:
        for key in ("total", "nn_correct"):
            ax[1].plot([v["step"] for v in val], [v[key] for v in val], "o-", label=key)
        ax[1].legend()
    ax[1].set_xlabel("step")
    ax[1].set_title("validation")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _validate(
    model: BEVNet, val: list[Sequence], cfg: TrainConfig, device: torch.device
) -> dict[str, float]:
    """Loss and the share of correct descriptor nearest neighbours on fixed val batches.
    Draws nothing from torch's random state that training goes on with (validating, or
    when, must not change the training run)."""
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        torch.manual_seed(12345)
        return _validate_batches(model, val, cfg, device)


def _validate_batches(
    model: BEVNet, val: list[Sequence], cfg: TrainConfig, device: torch.device
) -> dict[str, float]:
    rng = np.random.default_rng(12345)
    model.eval()
    totals, correct = [], []
    with torch.no_grad():
        for _ in range(4):
            a, p, pos, corr, _ = sample_batch(val, cfg, rng)
            totals.append(float(losses(model, a, p, pos, corr, cfg, device)["total"]))
            x = torch.cat([to_input(a), to_input(p)]).to(device)
            _, local, _ = model(x)
            loc = local.flatten(2)
            for k, (ia, ib) in enumerate(corr):
                if len(ia) < 8:
                    continue
                da = loc[k][:, torch.as_tensor(ia, device=device)].T
                db = loc[len(a) + k][:, torch.as_tensor(ib, device=device)].T
                hit = (da @ db.T).argmax(1) == torch.arange(len(ia), device=device)
                correct.append(float(hit.float().mean()))
    model.train()
    return {"total": float(np.mean(totals)), "nn_correct": float(np.mean(correct or [0.0]))}


class _NoBar:
    def update(self, _: int) -> None: ...

    def set_postfix(self, **_: object) -> None: ...

    def close(self) -> None: ...


def train(
    train_seqs: list[Sequence],
    out: str | Path,
    cfg: TrainConfig | None = None,
    val_seqs: list[Sequence] | None = None,
    *,
    resume: bool = True,
    progress: bool = True,
) -> Path:
    """Train (or resume) a :class:`BEVNet`; returns the checkpoint path.

    Resumes from ``OUT/checkpoint.pt`` when it exists and ``resume`` is true. Raises
    :class:`InputError` if no training sequence has images.
    """
    cfg = cfg or TrainConfig()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if not train_seqs or not any(len(s.images) for s in train_seqs):
        raise InputError("no training images")
    device = resolve_device(cfg.device)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    model = build_model(cfg)
    if cfg.init:
        from sgvloc.core.encoders.learned import load_weights

        start, _ = load_weights(cfg.init)
        try:
            model.load_state_dict(start.state_dict())
        except RuntimeError as exc:
            raise InputError(f"init: weights {cfg.init!r} do not fit this model: {exc}") from None
    model = model.to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=1e-4)
    ckpt_path = out / "checkpoint.pt"
    step, history, val_hist = 0, [], []
    # what it trains on: a resumed run must go on with the same data
    data = [{"name": seq.name, "scans": len(seq.images)} for seq in train_seqs]
    if resume and ckpt_path.exists():
        try:
            ckpt = torch.load(ckpt_path, map_location=device, weights_only=False)
            was = ckpt["config"]
            changed = sorted(  # a setting the checkpoint does not record is its default
                k
                for k, v in asdict(cfg).items()
                if k not in RESUMABLE_CHANGES and k in was and was[k] != v
            )
            if changed:  # the checkpoint's optimiser, RNG and weights would override them
                raise InputError(
                    f"{ckpt_path}: the run was started with other settings "
                    f"({', '.join(f'{k} {was.get(k)!r} -> {asdict(cfg)[k]!r}' for k in changed)}); "
                    "a resumed run continues the same training: use another OUT or --no-resume"
                )
            if "data" in ckpt and ckpt["data"] != data:
                raise InputError(
                    f"{ckpt_path}: the run was started on other training data "
                    f"({_data_text(ckpt['data'])}, now {_data_text(data)}); a resumed run "
                    "continues the same training: use another OUT or --no-resume"
                )
            model.load_state_dict(ckpt["model"])
            opt.load_state_dict(ckpt["optimizer"])
            step, history, val_hist = ckpt["step"], ckpt["history"], ckpt["val"]
            rng.bit_generator.state = ckpt["rng"]
            torch.set_rng_state(ckpt["torch_rng"].cpu())
        except InputError:
            raise
        except (OSError, RuntimeError, KeyError, ValueError, EOFError) as exc:
            raise InputError(
                f"{ckpt_path}: cannot resume from this checkpoint ({exc}); move it away to "
                "start over"
            ) from None
        log.info("resumed from %s at step %d", ckpt_path, step)
        if step >= cfg.steps:
            log.warning(
                "nothing to train: %s is at step %d, not below --steps %d (give more steps "
                "to go on)",
                ckpt_path,
                step,
                cfg.steps,
            )

    def save() -> None:
        write_whole(
            ckpt_path,
            lambda part: torch.save(
                {
                    "model": model.state_dict(),
                    "optimizer": opt.state_dict(),
                    "step": step,
                    "history": history,
                    "val": val_hist,
                    "rng": rng.bit_generator.state,
                    "torch_rng": torch.get_rng_state(),
                    "config": asdict(cfg),
                    "data": data,
                },
                part,
            ),
        )
        write_text_whole(
            out / "log.json",
            json.dumps(
                {"config": asdict(cfg), "data": data, "history": history, "val": val_hist},
                indent=1,
            ),
        )
        _plot(history, val_hist, out / "curves.png")

    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - the service extra has it
        progress = False

        def tqdm(**_: object) -> _NoBar:  # type: ignore[misc]
            return _NoBar()

    bar = tqdm(total=cfg.steps, initial=step, disable=not progress, unit="step")
    model.train()
    t0 = time.perf_counter()
    saved = step
    with _interruptions_between_steps() as interrupted:
        while step < cfg.steps:
            a, p, pos, corr, _ = sample_batch(train_seqs, cfg, rng)
            parts = losses(model, a, p, pos, corr, cfg, device)
            opt.zero_grad()
            parts["total"].backward()
            opt.step()
            step += 1
            history.append({"step": step, **{k: float(v.detach()) for k, v in parts.items()}})
            bar.update(1)
            bar.set_postfix(loss=f"{history[-1]['total']:.3f}")
            if val_seqs and (step % cfg.val_every == 0 or step == cfg.steps):
                val_hist.append({"step": step, **_validate(model, val_seqs, cfg, device)})
                log.info("step %d validation %s", step, val_hist[-1])
            if step % cfg.checkpoint_every == 0 or step == cfg.steps:
                save()
                saved = step
            if interrupted:  # Ctrl-C or SIGTERM during the step: it is whole, keep it
                bar.close()
                if step > saved:  # weights, optimiser and RNG are all those after ``step``
                    save()
                log.warning("interrupted: step %d is in %s; run again to resume", step, ckpt_path)
                interrupted.stop()
    bar.close()
    if not ckpt_path.exists():
        save()
    log.info("trained %d steps in %.0f s", step, time.perf_counter() - t0)
    return ckpt_path


class _Interrupted:
    """The signal received during a training step (falsy while none came)."""

    def __init__(self) -> None:
        self.signum: int | None = None

    def __bool__(self) -> bool:
        return self.signum is not None

    def stop(self) -> NoReturn:
        if self.signum == signal.SIGINT:
            raise KeyboardInterrupt
        raise SystemExit(128 + (self.signum or 0))


@contextlib.contextmanager
def _interruptions_between_steps() -> Iterator[_Interrupted]:
    """Ctrl-C (SIGINT) and SIGTERM wait for the training step under way to end, so that
    the checkpoint saved then is one state (weights, optimiser, random generators, step);
    a second one stops at once. Outside the main thread the signals are left alone."""
    got = _Interrupted()

    def defer(signum: int, _frame: object) -> None:
        if got:  # asked twice: now
            got.signum = signum
            got.stop()
        got.signum = signum
        log.warning("interrupted: stopping after this step (again to stop now)")

    try:
        before = {sig: signal.signal(sig, defer) for sig in (signal.SIGINT, signal.SIGTERM)}
    except ValueError:  # not the main thread
        yield got
        return
    try:
        yield got
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)


def _data_text(data: list[dict[str, Any]]) -> str:
    return ", ".join(f"{d['name']} ({d['scans']} scans)" for d in data)


def export_weights(checkpoint: str | Path, out: str | Path, note: str = "") -> Path:
    """Write the model of a training checkpoint as a weights file for the ``learned``
    encoder kind (float32 state dict, architecture and training facts; no optimiser).

    Raises :class:`InputError` if the checkpoint is missing.
    """
    from sgvloc.core.encoders.learned import WEIGHTS_FORMAT

    checkpoint, out = Path(checkpoint), Path(out)
    if not checkpoint.is_file():
        raise InputError(f"no checkpoint at {checkpoint}")
    model, ckpt = load_checkpoint(checkpoint)
    cfg = ckpt["config"]
    val = ckpt.get("val") or []
    blob = {
        "format": WEIGHTS_FORMAT,
        "arch": {k: int(cfg.get(k, 0)) for k in ("width", "local_dim", "global_dim", "min_grey")},
        "state_dict": {k: v.float() for k, v in model.state_dict().items()},
        "meta": {
            "steps": int(ckpt["step"]),
            "config": json.dumps(cfg, sort_keys=True),
            "last_validation": json.dumps(val[-1] if val else {}),
            "note": note,
        },
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    write_whole(out, lambda part: torch.save(blob, part))
    return out


def export_onnx(weights: str | Path, out: str | Path | None = None) -> Path:
    """Export the network of a weights file to ONNX (``out``, default beside it with
    suffix ``.onnx``), the file the ``learned`` encoder runs in ONNX Runtime on CPU.

    The batch dimension is dynamic; the file records the weights' SHA-256 (the encoder
    uses it only for those weights). Needs the ``onnx`` and ``onnxscript`` packages.
    Raises :class:`InputError` if the weights cannot be read or the exporter is missing.
    """
    import warnings

    from sgvloc.core.bevnet import INPUT_SIZE
    from sgvloc.core.encoders.learned import ONNX_WEIGHTS_KEY, load_weights, onnx_path
    from sgvloc.core.encoders.torchscript import file_sha256

    weights = Path(weights)
    out = Path(out) if out else onnx_path(weights)
    model, _ = load_weights(weights)
    try:
        import onnx
        import onnxscript  # noqa: F401 - the exporter needs it
    except ImportError as exc:
        raise InputError(
            f"exporting to ONNX needs the onnx and onnxscript packages: {exc}"
        ) from None
    x = torch.zeros(2, 1, INPUT_SIZE, INPUT_SIZE)
    quiet = logging.getLogger("torch.onnx")  # skipped torchvision operators, progress
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            program = torch.onnx.export(
                model,
                (x,),
                input_names=["image"],
                output_names=["global", "local", "saliency"],
                dynamic_shapes=({0: torch.export.Dim("batch", min=1, max=1024)},),
                dynamo=True,
                verbose=False,
            )
    finally:
        quiet.setLevel(level)
    proto = program.model_proto
    onnx.helper.set_model_props(proto, {ONNX_WEIGHTS_KEY: file_sha256(weights)})
    out.parent.mkdir(parents=True, exist_ok=True)
    write_whole(out, lambda part: onnx.save(proto, str(part)))
    return out
