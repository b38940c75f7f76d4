"""``sgvloc eval-track``: stream a sequence through the service's tracking path.

A map is built from a subset of a KITTI-layout sequence (every Nth scan, or the scans of
the first SECONDS) in a temporary data directory through the map manager (the code the
HTTP routes call), then every scan of the sequence is localized in order by the SDK's
:class:`~sgvloc_client.tracking.MotionModel` (the same seeds as
:class:`~sgvloc_client.Tracker`), and compared with the ground truth.

Figures: per-scan position and rotation error of every accepted fix (median, p95, ATE),
availability (share of scans within ``coverage_m`` of a map keyframe that were
localized, right or wrong; ``correct_availability``: localized within 2 m and 5 deg),
wrong fixes accepted (beyond 2 m or 5 deg), time per scan by mode, global
relocalizations, and with ``kidnap`` the scans until a correct fix after each jump. A
trajectory plot (ground truth and fixes coloured by mode) goes next to the JSON.
"""

from __future__ import annotations

import contextlib
import json
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from sgvloc.core.confidence import CORRECT_DEG, CORRECT_M  # a fix beyond either is wrong
from sgvloc.core.config import LocalizerConfig
from sgvloc.core.encoders import EncoderSpec
from sgvloc.core.errors import EmptyScanError, InputError
from sgvloc.core.files import write_text_whole
from sgvloc.core.sequence import KittiSequence
from sgvloc.core.tracking import Seed
from sgvloc.server.maps import KeyframeIn, MapManager
from sgvloc_client.tracking import MotionModel

from .build_map import insert_skipping_empty, select_frames
from .evaluation.metrics import rre, rte


@dataclass
class ScanRecord:
    index: int
    stamp: float
    mode: str
    localized: bool
    seeded: bool
    error_m: float | None
    error_deg: float | None
    ms: float
    in_coverage: bool
    estimate_xy: list[float] | None
    truth_xy: list[float]
    why: str = ""  # why a seeded fit was not trusted, or why nothing was localized


@dataclass
class TrackReport:
    data: str
    map_scans: int
    streamed: int
    in_coverage: int
    localized: int
    availability: float
    median_error_m: float | None
    p95_error_m: float | None
    p95_error_deg: float | None
    ate_m: float | None
    wrong_accepted: int
    worst_accepted_m: float | None
    relocalizations: int
    ms_median_by_mode: dict[str, float]
    scans_by_mode: dict[str, int]
    kidnaps: list[dict[str, Any]] = field(default_factory=list)
    scans: list[ScanRecord] = field(default_factory=list)
    map_scans_skipped: int = 0  # map scans the encoder found nothing to describe in
    #: share of the covered scans localized within 2 m and 5 deg (availability counts
    #: every accepted fix, wrong ones too)
    correct_availability: float = 0.0


@dataclass
class _NotLocalized:
    """The answer recorded for a streamed scan the service refused (a 422 ``empty_scan``:
    nothing for the map's encoder to describe), as the SDK's tracker would count it."""

    reason: str
    localized: bool = False
    mode: str = "empty_scan"
    T_map_sensor: None = None
    tracking: None = None


def _errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Position (m) and rotation (deg) error, as ``sgvloc eval`` measures them."""
    return float(rte(T_est, T_true)), float(rre(T_est, T_true))


def perturbed(T: np.ndarray, dxy: np.ndarray, dyaw_deg: float) -> np.ndarray:
    """``T`` moved by ``dxy`` (map x/y, m) and turned by ``dyaw_deg`` about the map's z."""
    c, s = np.cos(np.radians(dyaw_deg)), np.sin(np.radians(dyaw_deg))
    out = np.array(T, dtype=np.float64)
    out[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ out[:3, :3]
    out[:2, 3] += dxy
    return out


def stream_order(n: int, kidnaps: list[tuple[int, int]], first: int = 0) -> list[int]:
    """Scan indices in streaming order: ``first``, ``first + 1``, ... with each
    ``(at, to)`` jumping from scan ``at`` straight to scan ``to`` (then on from there)."""
    jumps = dict(kidnaps)
    order, i = [], first
    while 0 <= i < n:  # each jump is taken once, so the stream ends (a jump back revisits)
        order.append(i)
        i = jumps.pop(i, i + 1)
    return order


def eval_track(
    data: Path,
    out: Path,
    *,
    map_every: int = 5,
    map_until: float | None = None,
    encoder: EncoderSpec | None = None,
    kidnaps: list[tuple[int, int]] | None = None,
    max_scans: int | None = None,
    first_scan: int = 0,
    coverage_m: float = 5.0,
    motion: dict[str, Any] | None = None,
    tracking: dict[str, Any] | None = None,
    progress: Callable[[str], None] | None = None,
) -> TrackReport:
    """Build the map (``tracking``: its tracking settings, as in a map's
    ``localizer.tracking``), stream the sequence from ``first_scan`` on, write
    ``out/track.json`` and ``out/trajectory.png``; returns the report."""
    seq = KittiSequence(data)
    if seq.poses is None:  # the map's keyframes and every error are measured on them
        raise InputError(f"{data}: needs poses.txt (the ground truth)")
    n = len(seq) if max_scans is None else min(len(seq), max_scans)
    if not 0 <= first_scan < n:
        raise InputError(f"first_scan {first_scan} is outside the {n} scans streamed")
    order = stream_order(n, kidnaps or [], first_scan)
    steps = set(zip(order, order[1:], strict=False))
    for at, to in kidnaps or []:  # a jump the stream never takes measures nothing
        if not (0 <= at < n and 0 <= to < n and (at, to) in steps):
            raise InputError(
                f"kidnap {at}:{to}: the stream of scans {first_scan}..{n - 1} never takes "
                "this jump (both scans must be streamed, AT reached before the stream ends)"
            )
    # every scan of the first map_until seconds (as build-map --until), or every map_every-th
    every = 1 if map_until is not None else map_every
    times = None if seq.times is None else seq.times[:n]
    map_ids = select_frames(n, every, until=map_until, times=times)
    if not map_ids:
        raise InputError("the map would have no keyframe")
    say = progress or (lambda _msg: None)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="sgvloc-track-") as tmp:
        manager = MapManager(Path(tmp) / "maps")
        manager.load_all()
        try:
            manager.create("track", encoder, LocalizerConfig(tracking=tracking or {}))
            skipped: list[str] = []  # map scans the encoder found nothing to describe in
            for start in range(0, len(map_ids), 20):
                batch = [
                    KeyframeIn(seq[i].T_world_sensor, points=seq[i].scan().xyzi(), key=str(i))
                    for i in map_ids[start : start + 20]
                ]
                insert = partial(_inserted, manager)
                insert_skipping_empty(insert, batch, skipped)
                say(f"map: {min(start + 20, len(map_ids))}/{len(map_ids)} keyframes")
            map_ids = [i for i in map_ids if str(i) not in set(skipped)]
            report = _stream(seq, order, map_ids, manager, kidnaps or [], coverage_m, motion, say)
            report.map_scans_skipped = len(skipped)
        finally:
            manager.close()
    report.data = str(data)
    write_text_whole(out / "track.json", json.dumps(asdict(report), indent=1))
    plot_trajectory(report, seq, map_ids, out / "trajectory.png")
    return report


def _inserted(manager: MapManager, batch: list[KeyframeIn]) -> int:
    return len(manager.insert("track", batch).ids)


def _stream(
    seq: KittiSequence,
    order: list[int],
    map_ids: list[int],
    manager: MapManager,
    kidnaps: list[tuple[int, int]],
    coverage_m: float,
    motion: dict[str, Any] | None,
    say: Callable[[str], None],
) -> TrackReport:
    model = MotionModel(**(motion or {}))
    map_xy = np.array([seq[i].T_world_sensor[:3, 3] for i in map_ids])
    records: list[ScanRecord] = []
    relocalizations = 0
    times = [seq[i].time for i in range(len(seq))]
    steps = np.diff([t for t in times if t is not None])
    period = float(np.median(steps)) if len(steps) else 0.1  # the sensor's scan period
    # one untimed global localize first: libraries load and kernels compile once per process
    with contextlib.suppress(EmptyScanError):
        manager.localize("track", points=seq[order[0]].scan().xyzi())
    for k, i in enumerate(order):
        frame = seq[i]
        T_true = frame.T_world_sensor
        stamp = k * period  # the stream's clock: one period per scan, jumps included
        s = model.seed(stamp)
        seed = None if s is None else Seed(s.T_map_sensor, s.sigma_m, s.sigma_yaw_deg)
        if seed is None and model.pose is not None:
            relocalizations += 1
        t0 = time.perf_counter()
        try:
            result = manager.localize("track", points=frame.scan().xyzi(), seed=seed)
        except EmptyScanError as exc:  # nothing for the encoder: a scan not localized
            result = _NotLocalized(reason=f"empty_scan: {exc}")
        ms = (time.perf_counter() - t0) * 1e3
        model.observe(result, stamp)
        err = _errors(result.T_map_sensor, T_true) if result.localized else (None, None)
        covered = bool(np.min(np.linalg.norm(map_xy - T_true[:3, 3], axis=1)) <= coverage_m)
        est = None if result.T_map_sensor is None else result.T_map_sensor[:2, 3].tolist()
        records.append(
            ScanRecord(
                i,
                stamp,
                result.mode,
                bool(result.localized),
                seed is not None,
                err[0],
                err[1],
                ms,
                covered,
                est,
                T_true[:2, 3].tolist(),
                result.tracking["why"]
                if result.tracking and result.mode != "tracked"
                else ("" if result.localized else result.reason),
            )
        )
        if (k + 1) % 25 == 0 or k + 1 == len(order):
            say(f"streamed {k + 1}/{len(order)} scans")
    return summarize(records, len(map_ids), relocalizations, kidnaps, order)


def _pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def _correct(r: ScanRecord) -> bool:
    """A fix accepted within 2 m and 5 degrees of the truth."""
    return bool(
        r.localized
        and r.error_m is not None
        and r.error_m <= CORRECT_M
        and (r.error_deg or 0.0) <= CORRECT_DEG
    )


def summarize(
    records: list[ScanRecord],
    map_scans: int,
    relocalizations: int,
    kidnaps: list[tuple[int, int]],
    order: list[int],
) -> TrackReport:
    """The figures of a stream."""
    fixes = [r for r in records if r.localized]
    errs = [r.error_m for r in fixes if r.error_m is not None]
    rots = [r.error_deg for r in fixes if r.error_deg is not None]
    covered = [r for r in records if r.in_coverage]
    wrong = [r for r in fixes if (r.error_m or 0) > CORRECT_M or (r.error_deg or 0) > CORRECT_DEG]
    by_mode: dict[str, list[float]] = {}
    for r in records:
        by_mode.setdefault(r.mode, []).append(r.ms)
    kid = []
    for at, to in kidnaps:
        # the stream position just after the jump: the first ``to`` that follows an ``at``
        after = [k + 1 for k in range(len(order) - 1) if order[k] == at and order[k + 1] == to]
        if not after:
            continue
        start = after[0]
        until = None
        for j, r in enumerate(records[start:], 1):
            if _correct(r):
                until = j
                break
        kid.append({"from_scan": at, "to_scan": to, "scans_until_correct_fix": until})
    return TrackReport(
        data="",
        map_scans=map_scans,
        streamed=len(records),
        in_coverage=len(covered),
        localized=len(fixes),
        availability=sum(r.localized for r in covered) / len(covered) if covered else 0.0,
        correct_availability=sum(_correct(r) for r in covered) / len(covered) if covered else 0.0,
        median_error_m=_pct(errs, 50),
        p95_error_m=_pct(errs, 95),
        p95_error_deg=_pct(rots, 95),
        ate_m=float(np.sqrt(np.mean(np.square(errs)))) if errs else None,
        wrong_accepted=len(wrong),
        worst_accepted_m=max(errs) if errs else None,
        relocalizations=relocalizations,
        ms_median_by_mode={m: float(np.median(v)) for m, v in sorted(by_mode.items())},
        scans_by_mode={m: len(v) for m, v in sorted(by_mode.items())},
        kidnaps=kid,
        scans=records,
    )


def plot_trajectory(
    report: TrackReport, seq: KittiSequence, map_ids: list[int], path: Path
) -> None:
    """Ground truth (line), map keyframes (grey) and fixes coloured by mode (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    truth = np.array([seq[i].T_world_sensor[:2, 3] for i in range(len(seq))])
    fig, ax = plt.subplots(figsize=(7, 7), dpi=110)
    ax.plot(truth[:, 0], truth[:, 1], "-", color="0.6", lw=1, label="ground truth")
    kf = np.array([seq[i].T_world_sensor[:2, 3] for i in map_ids])
    ax.scatter(
        kf[:, 0],
        kf[:, 1],
        s=30,
        marker="s",
        facecolors="none",
        edgecolors="0.4",
        label="map keyframes",
    )
    colours = {"tracked": "tab:green", "relocalized": "tab:orange", "global": "tab:blue"}
    for mode, colour in colours.items():
        pts = np.array([r.estimate_xy for r in report.scans if r.localized and r.mode == mode])
        if len(pts):
            ax.scatter(pts[:, 0], pts[:, 1], s=9, color=colour, label=f"fix: {mode} ({len(pts)})")
    missed = np.array([r.truth_xy for r in report.scans if not r.localized])
    if len(missed):
        ax.scatter(
            missed[:, 0],
            missed[:, 1],
            s=25,
            marker="x",
            color="tab:red",
            label=f"not localized ({len(missed)})",
        )
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    med = report.median_error_m
    ax.set_title(
        f"tracking: availability {report.availability:.1%}, median error "
        f"{'-' if med is None else f'{med:.3f} m'}"
    )
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def report_lines(r: TrackReport) -> list[str]:
    """The figures as a few lines of text."""

    def f(v: float | None, unit: str, digits: int = 3) -> str:
        return "-" if v is None else f"{v:.{digits}f} {unit}"

    lines = [
        f"map: {r.map_scans} keyframes"
        + (
            f" ({r.map_scans_skipped} map scans left out: nothing to describe)"
            if r.map_scans_skipped
            else ""
        )
        + f"; streamed {r.streamed} scans, {r.in_coverage} within coverage; localized "
        f"{r.localized}",
        f"availability {r.availability:.1%} ({r.correct_availability:.1%} correct); position "
        f"error median {f(r.median_error_m, 'm')}, "
        f"p95 {f(r.p95_error_m, 'm')}, ATE {f(r.ate_m, 'm')}; rotation p95 "
        f"{f(r.p95_error_deg, 'deg', 2)}",
        f"wrong fixes accepted (> {CORRECT_M:g} m or {CORRECT_DEG:g} deg): {r.wrong_accepted}; "
        f"worst accepted {f(r.worst_accepted_m, 'm')}; global relocalizations "
        f"{r.relocalizations}",
        "time per scan (median): "
        + ", ".join(
            f"{m} {ms:.1f} ms ({r.scans_by_mode[m]} scans)" for m, ms in r.ms_median_by_mode.items()
        ),
    ]
    for k in r.kidnaps:
        lines.append(
            f"kidnap {k['from_scan']} -> {k['to_scan']}: correct fix after "
            f"{k['scans_until_correct_fix']} scan(s)"
        )
    return lines


# -- the tracking confidence model -------------------------------------------------------

#: seed perturbations (position sigma m, yaw sigma deg) drawn in turn: near seeds as a
#: tracker makes them, and far ones whose fits go wrong, so both labels are seen
PERTURBATIONS = ((0.3, 3.0), (1.5, 15.0), (4.0, 45.0))


def track_samples(
    data: Path,
    *,
    map_every: int = 5,
    encoder: EncoderSpec | None = None,
    max_scans: int | None = None,
    first_scan: int = 0,
    draws: int = 3,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> list[dict[str, float]]:
    """Seeded fits of the scans ``first_scan`` .. ``max_scans - 1`` of a sequence against
    a map of every Nth of them, from perturbed ground-truth seeds: ``{"fitness",
    "fitness_fine", "rmse_m", "seed_offset_m", ..., "error_m", "error_deg", "correct"}``
    each (the fit's evidence as the service reports it). The seeds are not gated (huge
    sigmas), so every fit is kept."""
    from sgvloc.core.config import LocalizerConfig, TrackingConfig
    from sgvloc.core.encoders import make_encoder
    from sgvloc.core.localizer import Localizer

    seq = KittiSequence(data)
    if seq.poses is None:
        raise InputError(f"{data}: needs poses.txt (the ground truth)")
    n = len(seq) if max_scans is None else min(len(seq), max_scans)
    config = LocalizerConfig(tracking=TrackingConfig(fallback="none"))
    loc = Localizer(make_encoder(encoder or EncoderSpec()), config)
    scans = range(first_scan, n)
    for i in scans[::map_every]:
        loc.add_keyframe(seq[i].T_world_sensor, scan=seq[i].scan().xyzi())
    rng = np.random.default_rng(seed)
    say = progress or (lambda _msg: None)
    out = []
    for i in scans:
        T_true = seq[i].T_world_sensor
        points = seq[i].scan().xyzi()
        for d in range(draws):
            sigma_t, sigma_yaw = PERTURBATIONS[(i * draws + d) % len(PERTURBATIONS)]
            dyaw = rng.normal(0.0, sigma_yaw)
            T = perturbed(T_true, rng.normal(0.0, sigma_t, size=2), dyaw)
            r = loc.localize(points, seed=Seed(T, 100.0, 180.0))
            if r.T_map_sensor_estimate is None or r.tracking is None:
                continue
            err_m, err_deg = _errors(r.T_map_sensor_estimate, T_true)
            correct = err_m <= CORRECT_M and err_deg <= CORRECT_DEG
            out.append({**r.tracking, "error_m": err_m, "error_deg": err_deg, "correct": correct})
        if (i + 1) % 50 == 0 or i + 1 == n:
            say(f"{data.name}: scan {i + 1} of {first_scan}..{n - 1}")
    return out


def _rows(samples: list[dict[str, Any]], features: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    from sgvloc.core.tracking import TrackConfidence

    X = np.stack([TrackConfidence.row(s, features) for s in samples])
    return X, np.array([float(s["correct"]) for s in samples])


def fit_track_confidence(
    samples: list[dict[str, Any]], fitted_on: dict[str, Any], features: Sequence[str] | None = None
) -> Any:  # TrackConfidence
    """The logistic model of :class:`~sgvloc.core.tracking.TrackConfidence` fitted to
    ``samples`` over ``features`` (default: all of them; L2 chosen by cross-validation,
    as ``sgvloc calibrate``)."""
    from sgvloc.core.tracking import TRACK_FEATURES, TrackConfidence

    from .calibrate import choose_l2, fit_weights

    features = tuple(features or TRACK_FEATURES)
    X, y = _rows(samples, features)
    l2 = choose_l2(X, y) if len(samples) >= 20 else 1e-2
    mean, scale, w, b = fit_weights(X, y, l2)
    return TrackConfidence(
        features,
        tuple(mean.tolist()),
        tuple(scale.tolist()),
        tuple(w.round(8).tolist()),
        b,
        {**fitted_on, "samples": len(samples), "correct": int(y.sum()), "l2": l2},
    )


def confidence_figures(
    samples: list[dict[str, float]], model: Any, threshold: float
) -> dict[str, float]:
    """How ``model`` does on ``samples``: ECE, and at ``threshold`` the share of correct
    fits accepted and of wrong fits accepted (false accepts)."""
    from .evaluation.metrics import expected_calibration_error

    y = np.array([float(s["correct"]) for s in samples])
    p = np.array([model.predict(s) for s in samples])
    accepted = p >= threshold
    wrong = y == 0
    return {
        "samples": len(samples),
        "correct": int(y.sum()),
        "ece": float(expected_calibration_error(p, y.astype(bool))),
        "correct_accepted": float(accepted[~wrong].mean()) if (~wrong).any() else 0.0,
        "wrong_accepted": float(accepted[wrong].mean()) if wrong.any() else 0.0,
        "accepted_that_are_wrong": float(wrong[accepted].mean()) if accepted.any() else 0.0,
    }
