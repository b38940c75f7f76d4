"""``sgvloc calibrate``: fit the confidence model on sequences with ground truth.

The examples are answers of the map's pipeline (SGV at ``top_k``) with their evidence
(:class:`~sgvloc.core.confidence.Evidence`) and whether their pose is within 2 m and 5
degrees, out-of-coverage queries included, so that the data hold both kinds of answers a
service gives: right places and wrong ones. They come from ``sgvloc eval`` reports
(``--from OUT/eval.json``, each run with its own split) or from sequences given with
``--data``, which run through the same evaluation here (3-D sequences with ICP and
without: the ``icp`` and ``none`` profiles; BEV images have no cloud and no height:
``planar``).

Per profile, a logistic regression with non-negative weights on the oriented,
standardised features (:data:`~sgvloc.core.confidence.PROFILE_FEATURES`) is fitted by
L-BFGS-B; its L2 penalty is chosen from a small grid by 5-fold cross-validated log-loss
on the same examples. The result records what it was fitted on and how it fits there.
With a ``base`` calibration, the profiles these answers do not cover are kept from it
(and recorded as kept), so that one profile can be refitted without re-running the data
of the others.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sgvloc.core.confidence import FEATURES, PROFILE_FEATURES, Calibration, Evidence, LogisticModel
from sgvloc.core.config import LocalizerConfig
from sgvloc.core.encoders import EncoderSpec
from sgvloc.core.errors import InputError

from .evaluation.diagnostics import roc_auc
from .evaluation.metrics import expected_calibration_error

log = logging.getLogger(__name__)

#: L2 penalties (on standardised weights, per example) tried by cross-validation
L2_GRID = (1e-3, 1e-2, 3e-2, 1e-1, 3e-1)
FOLDS = 5


@dataclass
class Examples:
    """Evidence and labels of one profile."""

    evidence: list[Evidence] = field(default_factory=list)
    correct: list[bool] = field(default_factory=list)

    def extend(self, other: Examples) -> None:
        self.evidence += other.evidence
        self.correct += other.correct


def fit_weights(
    X: np.ndarray, y: np.ndarray, l2: float = 1e-2
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Logistic regression ``[n, F] -> p`` with weights >= 0 on standardised inputs:
    ``(mean, scale, weights, bias)``."""
    from scipy.optimize import minimize

    X = np.asarray(X, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if X.ndim != 2 or X.shape[0] != len(y):
        raise InputError("fit_logistic: X must be [n, F] with one label per row")
    if y.min(initial=1) == y.max(initial=0):
        raise InputError(
            "calibration needs both correct and wrong answers; these data have only "
            + ("correct" if len(y) and y[0] else "wrong")
            + " ones"
        )
    mean = X.mean(axis=0)
    scale = X.std(axis=0)
    scale[scale < 1e-9] = 1.0
    Z = (X - mean) / scale  # [n, F]
    n, F = Z.shape

    def loss(theta: np.ndarray) -> tuple[float, np.ndarray]:
        w, b = theta[:F], theta[F]
        z = Z @ w + b
        nll = np.logaddexp(0.0, z) - y * z  # log(1 + e^z) - y z, stably
        g = 1.0 / (1.0 + np.exp(-z)) - y
        value = nll.mean() + 0.5 * l2 * float(w @ w)
        grad = np.concatenate([Z.T @ g / n + l2 * w, [g.mean()]])
        return value, grad

    bounds = [(0.0, None)] * F + [(None, None)]
    res = minimize(loss, np.zeros(F + 1), jac=True, method="L-BFGS-B", bounds=bounds)
    if not res.success:
        log.warning("calibration fit: %s", res.message)
    return mean, scale, np.maximum(res.x[:F], 0.0), float(res.x[F])


def fit_logistic(
    X: np.ndarray, y: np.ndarray, features: list[str], l2: float = 1e-2
) -> LogisticModel:
    """:func:`fit_weights` as the confidence model of ``features``."""
    if np.asarray(X).ndim != 2 or np.asarray(X).shape[1] != len(features):
        raise InputError("fit_logistic: X must be [n, F] with one label per row")
    mean, scale, w, b = fit_weights(X, y, l2)
    return LogisticModel(list(features), mean.tolist(), scale.tolist(), w.round(8).tolist(), b)


def choose_l2(X: np.ndarray, y: np.ndarray, seed: int = 0) -> float:
    """The L2 penalty of :data:`L2_GRID` with the lowest 5-fold cross-validated log-loss
    (folds stratified by label, seeded)."""
    rng = np.random.default_rng(seed)
    fold = np.empty(len(y), dtype=np.int64)
    for label in (False, True):
        idx = np.flatnonzero(y == label)
        fold[rng.permutation(idx)] = np.arange(len(idx)) % FOLDS
    per_fold = [np.bincount(fold[y == label], minlength=FOLDS).min() for label in (False, True)]
    if min(per_fold) == 0:
        return L2_GRID[1]  # too few of one label to cross-validate
    losses = []
    for l2 in L2_GRID:
        total = 0.0
        for f in range(FOLDS):
            tr, te = fold != f, fold == f
            mean, scale, w, b = fit_weights(X[tr], y[tr], l2)
            z = b + ((X[te] - mean) / scale) @ w
            total += float((np.logaddexp(0.0, z) - y[te] * z).sum())
        losses.append(total / len(y))
    return L2_GRID[int(np.argmin(losses))]


#: fewer correct or wrong answers than this per profile: the fit is reported as weak
MIN_PER_LABEL = 20


def evidence_matrix(evidence: list[Evidence], features: Iterable[str]) -> np.ndarray:
    """The model inputs (unstandardised) of many answers ``[n, F]``."""
    return np.array([[FEATURES[f](e) for f in features] for e in evidence], dtype=np.float64)


def _name(path: str | Path) -> str:
    """A sequence's folder and its parent's name (no absolute path in a shipped file)."""
    return "/".join(Path(path).resolve().parts[-2:])


def examples_from_report(report: dict[str, Any], top_k: int) -> dict[str, Examples]:
    """Per profile, the answers of ``sgv`` at ``top_k`` in an eval report (as a dict)."""
    key = f"sgv@{top_k}"
    if key not in report.get("per_query", {}):
        raise InputError(
            f"the eval report has no answers of sgv at top-k {top_k}: run sgvloc eval with "
            f"--methods sgv --topk {top_k} (it has {sorted(report.get('per_query', {}))})"
        )
    out: dict[str, Examples] = {}
    for r in report["per_query"][key]:
        if not r.get("evidence") or not r.get("has_estimate"):
            continue  # no estimate: the confidence is 0 whatever the model
        ev = Evidence(**r["evidence"])
        ex = out.setdefault(ev.profile, Examples())
        ex.evidence.append(ev)
        ex.correct.append(bool(r["correct"]))
    return out


def _summary(report: dict[str, Any], ex: dict[str, Examples]) -> dict[str, Any]:
    cfg = report["config"]
    return {
        "data": _name(cfg["data"]),
        "frames": cfg.get("frames"),
        "refine": cfg["refine_effective"],
        "split": {k: v for k, v in report["split"].items() if not k.endswith("_indices")},
        "answers": {p: len(e.correct) for p, e in ex.items()},
        "correct": {p: int(sum(e.correct)) for p, e in ex.items()},
    }


def calibrate(
    data: list[Path] = (),
    *,
    reports: list[Path] = (),
    db_until: float | None = None,
    min_gap: float | None = None,
    refine: list[str] = ("icp", "none"),
    encoder: EncoderSpec | None = None,
    localizer: LocalizerConfig | None = None,
    max_queries: int | None = None,
    query_stride: int = 1,
    cache_dir: Path | None = None,
    name: str = "calibration",
    base: Calibration | None = None,
    progress: bool = True,
    echo: Callable[[str], None] = lambda s: None,
) -> Calibration:
    """Fit a :class:`Calibration` on sequences and/or eval reports (module docstring);
    profiles without answers come from ``base`` when given."""
    from .evaluation.data import open_sequence
    from .evaluation.report import report_dict
    from .evaluation.runner import EvalConfig, run_evaluation

    if not data and not reports:
        raise InputError("give sequences (--data) or eval reports (--from)")
    localizer = localizer or LocalizerConfig()
    kinds: set[str] = set()
    pooled: dict[str, Examples] = {}
    runs = []

    def add(report: dict[str, Any]) -> None:
        ex = examples_from_report(report, localizer.top_k)
        kinds.add(report["config"]["encoder"]["kind"])
        runs.append(_summary(report, ex))
        for p, e in ex.items():
            pooled.setdefault(p, Examples()).extend(e)

    for path in reports:
        echo(f"calibrate: answers from {path}")
        try:
            add(json.loads(Path(path).read_text()))
        except (OSError, json.JSONDecodeError, KeyError) as exc:
            raise InputError(f"{path}: not a readable sgvloc eval report ({exc})") from None
    for d in data:
        images = open_sequence(d).kind == "bev-images"
        for mode in refine:
            if mode == "icp" and images:
                continue  # images have no cloud: their run without ICP covers them
            echo(f"calibrate: {d} (refine {mode})")
            cfg = EvalConfig(
                data=str(d),
                db_until=db_until,
                min_gap=min_gap,
                methods=["sgv"],
                topk=[localizer.top_k],
                sweep=[localizer.top_k],
                refine=mode,
                max_queries=max_queries,
                query_stride=query_stride,
                negatives=True,
                cache_dir=str(cache_dir) if cache_dir else None,
                encoder=encoder or EncoderSpec(),
                localizer=localizer,
            )
            add(report_dict(run_evaluation(cfg, progress=progress)))
    if base is not None:
        kinds.add(base.encoder_kind)
    if len(kinds) > 1:
        raise InputError(f"the answers come from different encoder kinds {sorted(kinds)}")

    models, fit = {}, {}
    for profile, ex in sorted(pooled.items()):
        feats = list(PROFILE_FEATURES[profile])
        X = evidence_matrix(ex.evidence, feats)
        y = np.asarray(ex.correct, dtype=bool)
        if y.all() or not y.any():
            raise InputError(
                f"profile {profile}: the {len(y)} answers are all "
                f"{'correct' if y.any() else 'wrong'}; calibration needs both"
            )
        l2 = choose_l2(X, y)
        model = fit_logistic(X, y, feats, l2)
        p = np.array([model.predict(e) for e in ex.evidence])
        models[profile] = model
        fit[profile] = {
            "answers": len(y),
            "correct": int(y.sum()),
            "l2": l2,
            "ece": round(expected_calibration_error(p, y), 4),
            "auc": round(roc_auc(p[y], p[~y]), 4),
        }
        echo(
            f"calibrate: profile {profile}: {len(y)} answers ({int(y.sum())} correct), "
            f"L2 {l2:g}, fitted ECE {fit[profile]['ece']:.3f}, AUC {fit[profile]['auc']:.3f}"
        )
        fewest = min(int(y.sum()), int((~y).sum()))
        if fewest < MIN_PER_LABEL:
            echo(
                f"calibrate: warning: profile {profile} has only {fewest} "
                f"{'correct' if fewest == int(y.sum()) else 'wrong'} answers (fewer than "
                f"{MIN_PER_LABEL}): its figures on these answers say little; add sequences "
                "and check the calibration on held-out data (sgvloc eval --calibration)"
            )
    if not models:
        raise InputError("no answers with a pose estimate: nothing to calibrate on")
    fitted_on: dict[str, Any] = {"runs": runs, "fit": fit, "top_k": localizer.top_k}
    if base is not None:
        kept = sorted(set(base.models) - set(models))
        for profile in kept:
            models[profile] = base.models[profile]
            echo(f"calibrate: profile {profile}: kept from {base.name} ({base.fingerprint})")
        fitted_on["kept"] = {
            p: {"from": base.name, "fingerprint": base.fingerprint, **_kept_record(base, p)}
            for p in kept
        }
    return Calibration(name, kinds.pop(), models, fitted_on)


def _kept_record(base: Calibration, profile: str) -> dict[str, Any]:
    """What ``base`` says it fitted ``profile`` on: its fit figures and the runs that
    gave it answers of that profile; for a profile ``base`` kept from one before it, that
    one's record (``fitted_by`` names the calibration that fitted it)."""
    fitted = base.fitted_on
    earlier = fitted.get("kept", {}).get(profile)
    if isinstance(earlier, dict):
        return {
            "fitted_by": earlier.get("fitted_by", earlier.get("from")),
            "fit": earlier.get("fit"),
            "runs": earlier.get("runs", []),
        }
    runs = [r for r in fitted.get("runs", []) if profile in r.get("answers", {})]
    return {"fit": fitted.get("fit", {}).get(profile), "runs": runs}
