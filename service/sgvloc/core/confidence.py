"""Confidence of a localization: the evidence behind it and a calibrated probability.

Every answer carries ``confidence``, meant as the probability that its pose is within
2 m and 5 degrees of the truth (the success criterion of docs/EVALUATION.md). It comes
from evidence the pipeline has already computed, fed to a small fitted model
(:class:`Calibration`):

- ``sgv``: the normalised SpectralGV score of the re-ranked top-1 (about its inlier
  ratio, comparable across queries with different keypoint counts);
- ``sgv_margin``: that score minus the best score of a candidate more than
  :data:`DISTINCT_RADIUS_M` from the top-1 (a distinct place): how much better the
  chosen place explains the scan than any other;
- ``similarity``: retrieval similarity (cosine) of the query and the top-1;
- ``inliers`` / ``inlier_ratio``: RANSAC inliers among the feature correspondences;
  for keypoints without height (BEV images, the ``planar`` profile) also the inliers
  divided by the share of the view the query and the keyframe have in common at the
  estimated offset (:func:`shared_view`, taken no lower than :data:`MIN_SHARED_VIEW`):
  the same inliers found in a smaller common area are stronger evidence;
- ``icp_fitness`` / ``icp_rmse``: share of query points within the ICP distance of the
  keyframe cloud after ICP, and their RMSE (metres); absent when ICP did not run;
- ``icp_constraint``: how well the ICP fit pins the position down in its weakest
  direction (:func:`sgvloc.core.pose.constraint`, 0 to 1/3; the pose step's own floor
  ``min_icp_constraint`` acts on it too);
- ``free_space``: after ICP, the share of the query's points that the nearest keyframes
  could judge and that lie in space those keyframes saw through
  (:mod:`sgvloc.core.freespace`; smaller is better); absent without ICP;
- ``agreement``: how many of the next :data:`AGREEMENT_CANDIDATES` re-ranked candidates
  imply the same query pose (within 2 m and 5 degrees) from their own SpectralGV inlier
  cluster (:func:`spectral_pose`), capped at :data:`AGREEMENT_CAP`;
- ``offset_m``: the estimated distance of the query from the matched keyframe (reported,
  and an input only through the common view above: whether a long offset is suspicious
  by itself depends on the map's spacing).

The model is a logistic regression per profile (``icp`` when ICP ran; without ICP,
``none`` for 3-D keypoints and ``planar`` for keypoints without height, from BEV images:
their evidence has other scales) whose weights are constrained to be non-negative on
features oriented so that "larger is better evidence": the confidence can only rise with
more inliers, a larger margin or a better ICP fit, whatever the data it was fitted on.
``sgvloc calibrate`` fits it (:mod:`sgvloc.tools.calibrate`); calibrations ship as
package data per encoder kind (``sgvloc/calibration/<kind>.json``) and a map stores the
one it uses.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sgvloc.about import PACKAGE_DIR

from .errors import InputError
from .files import write_text_whole
from .pose import rotation_angle_deg

#: candidates farther than this from the top-1 keyframe count as another place (margin)
DISTINCT_RADIUS_M = 5.0
#: re-ranked candidates after the top-1 whose implied poses are checked for agreement
AGREEMENT_CANDIDATES = 5
#: agreement counts at most this many candidates
AGREEMENT_CAP = 3
#: a pose this close to the truth is correct, what the confidence is the probability of
#: (the success thresholds of docs/EVALUATION.md)
CORRECT_M, CORRECT_DEG = 2.0, 5.0
#: implied poses agree within the same bounds
AGREEMENT_M, AGREEMENT_DEG = CORRECT_M, CORRECT_DEG
#: the view of a BEV image as a disc of this radius (the kitti-bev raster's half extent)
PLANAR_VIEW_RADIUS_M = 25.0
#: the common view that scales the inliers is taken no lower than this share: beyond
#: about 20 m of offset the inliers count at most twice (chosen by the cross-sequence
#: log-loss of the training runs, docs/VERDICT.md)
MIN_SHARED_VIEW = 0.5
#: model inputs: name -> how it is derived from the evidence (oriented: larger = better)
FEATURES: dict[str, Callable[[Evidence], float]] = {}

PROFILES = ("icp", "none", "planar")
#: per profile, the models that may answer it, best first (their inputs exist)
FALLBACK = {
    "icp": ("icp", "none", "planar"),
    "none": ("none", "planar"),
    "planar": ("planar", "none"),
}


@dataclass(frozen=True)
class SpectralCandidate:
    """What SpectralGV says about one candidate: its normalised score and the query pose
    relative to the keyframe fitted on its inlier cluster (None if too few inliers)."""

    normalised: float
    T_kf_query: np.ndarray | None


@dataclass
class Evidence:
    """The evidence behind one answer (see the module docstring)."""

    sgv: float = 0.0
    sgv_margin: float = 0.0
    similarity: float = 0.0
    inliers: int = 0
    inlier_ratio: float = 0.0
    icp_fitness: float | None = None
    icp_rmse: float | None = None
    icp_constraint: float | None = None
    free_space: float | None = None
    agreement: int = 0
    offset_m: float = 0.0
    planar: bool = False

    @property
    def profile(self) -> str:
        """``icp`` when ICP refined the pose, else ``planar`` for keypoints without
        height (BEV images), else ``none``."""
        if self.icp_fitness is not None:
            return "icp"
        return "planar" if self.planar else "none"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _feature(name: str):
    def register(fn: Callable[[Evidence], float]) -> Callable[[Evidence], float]:
        FEATURES[name] = fn
        return fn

    return register


_feature("sgv")(lambda e: e.sgv)
_feature("sgv_margin")(lambda e: e.sgv_margin)
_feature("similarity")(lambda e: e.similarity)
_feature("log_inliers")(lambda e: math.log1p(e.inliers))
_feature("inlier_ratio")(lambda e: e.inlier_ratio)
_feature("icp_fitness")(lambda e: e.icp_fitness or 0.0)
_feature("neg_icp_rmse")(lambda e: -(e.icp_rmse or 0.0))
_feature("neg_free_space")(lambda e: -(e.free_space or 0.0))
_feature("agreement")(lambda e: e.agreement / AGREEMENT_CAP)
_feature("log_inliers_shared")(
    lambda e: math.log1p(e.inliers / max(shared_view(e.offset_m), MIN_SHARED_VIEW))
)
_feature("icp_constraint")(lambda e: e.icp_constraint or 0.0)

#: the model inputs of each profile
PROFILE_FEATURES: dict[str, tuple[str, ...]] = {
    "none": (
        "sgv",
        "sgv_margin",
        "similarity",
        "log_inliers",
        "inlier_ratio",
        "agreement",
    ),
}
PROFILE_FEATURES["planar"] = PROFILE_FEATURES["none"] + ("log_inliers_shared",)
PROFILE_FEATURES["icp"] = PROFILE_FEATURES["none"] + (
    "icp_fitness",
    "neg_icp_rmse",
    "neg_free_space",
    "icp_constraint",
)


# -- evidence ---------------------------------------------------------------------------


def shared_view(offset_m: float, radius_m: float = PLANAR_VIEW_RADIUS_M) -> float:
    """Share of a disc of ``radius_m`` that a second one ``offset_m`` away covers: 1 at
    no offset, 0 from two radii apart."""
    d = abs(float(offset_m)) / (2.0 * radius_m)  # the offset over two radii: 0 to 1
    if not d < 1.0:
        return 0.0
    # the lens of two unit-radius discs at distance 2 d, over the disc's area pi
    return (2.0 * math.acos(d) - 2.0 * d * math.sqrt(1.0 - d * d)) / math.pi


def rigid_fit(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Weighted least-squares rigid transform ``T`` [4, 4] with ``dst ~ R src + t``."""
    w = np.ones(len(src)) if w is None else np.asarray(w, np.float64)
    w = w / w.sum()
    cs, cd = w @ src, w @ dst  # [3]
    H = (src - cs).T @ ((dst - cd) * w[:, None])  # [3, 3]
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, cd - R @ cs
    return T


def spectral_pose(
    query_kp: np.ndarray, cand_kp: np.ndarray, matches: np.ndarray, v: np.ndarray
) -> np.ndarray | None:
    """``T_cand_query`` from the SpectralGV inlier cluster of one candidate.

    ``matches`` ``[N]``: candidate keypoint per query keypoint (-1: none); ``v`` ``[N]``:
    the leading eigenvector. Correspondences with ``v`` at least half its maximum form the
    cluster; the fit is weighted by ``v``. None with fewer than three.
    """
    n = min(len(query_kp), len(matches), len(v))
    m, w = matches[:n], np.asarray(v[:n], np.float64)
    if n == 0 or not (w.max(initial=0.0) > 0):
        return None
    keep = (m >= 0) & (w >= 0.5 * w.max())
    if keep.sum() < 3:
        return None
    src = np.asarray(query_kp[:n][keep], np.float64)
    dst = np.asarray(cand_kp[m[keep]], np.float64)
    return rigid_fit(src, dst, w[keep])


def spectral_candidates(
    ids: Sequence[int],
    query_kp: np.ndarray,
    cand_kps: Sequence[np.ndarray],
    scores: Any,
    *,
    poses_for: set[int] | None = None,
) -> dict[int, SpectralCandidate]:
    """Per keyframe id, its :class:`SpectralCandidate` from an ``SGVScores`` of ``ids``
    (in that order, with ``matches``, as :func:`sgvloc.core.sgv.sgv_rerank_scores` gives).
    ``poses_for``: fit poses only for these ids (default: all)."""
    out = {}
    for i, kf in enumerate(ids):
        T = None
        if scores.matches is not None and (poses_for is None or int(kf) in poses_for):
            T = spectral_pose(query_kp, cand_kps[i], scores.matches[i], scores.v[i])
        out[int(kf)] = SpectralCandidate(float(scores.normalised[i]), T)
    return out


def poses_agree(
    T_a: np.ndarray, T_b: np.ndarray, max_m: float = AGREEMENT_M, max_deg: float = AGREEMENT_DEG
) -> bool:
    """Whether two 4x4 poses are within ``max_m`` metres and ``max_deg`` degrees."""
    if np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]) > max_m:
        return False
    return rotation_angle_deg(T_a[:3, :3].T @ T_b[:3, :3]) <= max_deg


def nearest_of_place(
    ranked: Sequence[int],
    spectral: Mapping[int, SpectralCandidate],
    T_map_kf: Callable[[int], np.ndarray],
    tolerance: float,
    gain_m: float,
) -> list[int]:
    """``ranked`` with its top-1 replaced by the nearest keyframe of the same place.

    SpectralGV scores neighbouring keyframes of one place almost alike, and which of them
    comes first is close to chance; the pose step does best against the one nearest the
    query (the most overlap). A candidate among the next :data:`AGREEMENT_CANDIDATES`
    takes the first place when its score is at least ``1 - tolerance`` times the top-1's,
    its SpectralGV pose puts the query where the top-1's does (within
    :data:`AGREEMENT_M` and :data:`AGREEMENT_DEG`) and it is at least ``gain_m`` nearer
    the query by that pose; of several, the nearest. The rest keep their order.
    ``tolerance`` 0 returns ``ranked`` unchanged."""
    ranked = [int(i) for i in ranked]
    top = spectral.get(ranked[0]) if ranked and tolerance > 0 else None
    if top is None or top.T_kf_query is None:
        return ranked
    T_map_query = T_map_kf(ranked[0]) @ top.T_kf_query
    best, best_m = ranked[0], float(np.linalg.norm(top.T_kf_query[:3, 3])) - gain_m
    for c in ranked[1 : 1 + AGREEMENT_CANDIDATES]:
        cand = spectral.get(c)
        if cand is None or cand.T_kf_query is None:
            continue
        if cand.normalised < (1.0 - tolerance) * top.normalised:
            continue
        offset = float(np.linalg.norm(cand.T_kf_query[:3, 3]))
        if offset <= best_m and poses_agree(T_map_kf(c) @ cand.T_kf_query, T_map_query):
            best, best_m = c, offset
    if best == ranked[0]:
        return ranked
    return [best, *(i for i in ranked if i != best)]


def gather_evidence(
    ranked: Sequence[int],
    spectral: Mapping[int, SpectralCandidate],
    T_map_kf: Callable[[int], np.ndarray],
    *,
    similarity: float,
    pose: Any | None,
    T_kf_query: np.ndarray | None,
    planar: bool = False,
    free_space: Callable[[np.ndarray], float | None] | None = None,
) -> Evidence:
    """The evidence of an answer whose pose ``T_kf_query`` was estimated against
    ``ranked[0]``.

    ``ranked``: keyframe ids after re-ranking, best first; ``spectral``: their
    :class:`SpectralCandidate`; ``T_map_kf``: a keyframe's pose in the map; ``pose``: the
    :class:`~sgvloc.core.pose.PoseResult` (None: no estimate, most fields stay 0);
    ``planar``: the query's keypoints have no height (a BEV image); ``free_space``:
    the free-space violation of a map pose of the query
    (:func:`sgvloc.core.freespace.violation`), asked only after ICP.
    """
    if not ranked:
        return Evidence(planar=bool(planar))
    top = int(ranked[0])
    T_top = T_map_kf(top)
    s_top = spectral[top].normalised if top in spectral else 0.0
    # the best score of a distinct place (farther than DISTINCT_RADIUS_M from the top-1)
    others = [
        spectral[c].normalised
        for c in ranked[1:]
        if c in spectral and np.linalg.norm(T_map_kf(c)[:3, 3] - T_top[:3, 3]) > DISTINCT_RADIUS_M
    ]
    ev = Evidence(
        sgv=float(s_top),
        sgv_margin=float(s_top - max(others, default=0.0)),
        similarity=float(similarity),
        planar=bool(planar),
    )
    if pose is None or T_kf_query is None:
        return ev
    ev.inliers, ev.inlier_ratio = int(pose.inliers), float(pose.fitness)
    T_map_query = T_top @ T_kf_query
    if getattr(pose, "refined", False) and pose.icp.get("used"):
        ev.icp_fitness = float(pose.icp["fitness"])
        ev.icp_rmse = float(pose.icp["inlier_rmse"])
        if pose.icp.get("constraint") is not None:
            ev.icp_constraint = float(pose.icp["constraint"])
        if free_space is not None:
            ev.free_space = free_space(T_map_query)
    ev.offset_m = float(np.linalg.norm(T_kf_query[:3, 3]))
    agree = 0
    for c in ranked[1 : 1 + AGREEMENT_CANDIDATES]:
        cand = spectral.get(int(c))
        if cand is not None and cand.T_kf_query is not None:
            agree += poses_agree(T_map_kf(int(c)) @ cand.T_kf_query, T_map_query)
    ev.agreement = min(agree, AGREEMENT_CAP)
    return ev


# -- the verdict ------------------------------------------------------------------------

#: reason codes of an answer, in the order they are checked
VERDICT_CODES = (
    "no_keyframes",  # the map (or the prior's radius) holds no keyframe
    "no_keyframe_in_prior",
    "no_estimate",  # too few correspondences for RANSAC
    "outside_prior",  # the estimate lies outside the prior region
    "pose_check",  # the pose step's own minimums (inliers, fitness, ICP fitness) failed
    "low_confidence",  # confidence < min_confidence
    "tracking_failed",  # a seeded fit failed its checks and no fallback was asked for
    "localized",
)


@dataclass(frozen=True)
class Verdict:
    """Whether to act on an answer: ``localized``, a reason ``code`` and a sentence."""

    localized: bool
    code: str
    reason: str


def decide(
    confidence: float,
    min_confidence: float,
    pose: Any | None,
    T_map_query: np.ndarray | None,
    prior: Any | None = None,
) -> Verdict:
    """The verdict on an estimate (``pose`` None or ``T_map_query`` None: no estimate).

    ``pose.localized`` carries the pose step's own minimums; ``prior`` a
    :class:`~sgvloc.core.prior.Prior` whose region the estimate must lie in.
    """
    if pose is None or T_map_query is None:
        why = pose.reason if pose is not None else "no pose estimate"
        return Verdict(False, "no_estimate", why)
    if prior is not None:
        why = prior.rejects(T_map_query)
        if why:
            return Verdict(False, "outside_prior", why)
    if not pose.localized:
        return Verdict(False, "pose_check", pose.reason)
    if not confidence >= min_confidence:  # a NaN confidence is not trusted either
        return Verdict(
            False,
            "low_confidence",
            f"confidence {confidence:.3f} < min_confidence {min_confidence:g} ({pose.reason})",
        )
    return Verdict(True, "localized", f"confidence {confidence:.3f}; {pose.reason}")


@dataclass(frozen=True)
class Assessment:
    """An answer's evidence, its calibrated confidence and the verdict on it."""

    evidence: Evidence
    confidence: float
    verdict: Verdict


def assess(
    calibration: Calibration,
    ranked: Sequence[int],
    spectral: Mapping[int, SpectralCandidate],
    T_map_kf: Callable[[int], np.ndarray],
    *,
    query_keypoints: np.ndarray,
    similarity: float,
    pose: Any,
    T_kf_query: np.ndarray | None,
    min_confidence: float,
    prior: Any | None = None,
    free_space: Callable[[np.ndarray], float | None] | None = None,
) -> Assessment:
    """Judge the answer whose pose ``T_kf_query`` (None: no estimate) was estimated
    against ``ranked[0]`` (non-empty) by ``pose``: the one path the localizer and
    ``sgvloc eval`` share, so that the evaluation measures what the service answers.
    Arguments as for :func:`gather_evidence` and :func:`decide`."""
    has_estimate = T_kf_query is not None
    ev = gather_evidence(
        ranked,
        spectral,
        T_map_kf,
        similarity=similarity,
        pose=pose if has_estimate else None,
        T_kf_query=T_kf_query,
        planar=not query_keypoints[:, 2].any(),
        free_space=free_space,
    )
    confidence = calibration.confidence(ev) if has_estimate else 0.0
    T_map_query = T_map_kf(int(ranked[0])) @ T_kf_query if has_estimate else None
    return Assessment(ev, confidence, decide(confidence, min_confidence, pose, T_map_query, prior))


# -- the calibrated model ---------------------------------------------------------------


def _finite_number(v: Any) -> bool:
    if not isinstance(v, int | float) or isinstance(v, bool):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:  # an integer beyond the float range
        return False


@dataclass
class LogisticModel:
    """``p = sigmoid(bias + sum_i weights[i] * (x_i - mean[i]) / scale[i])``, weights >= 0."""

    features: list[str]
    mean: list[float]
    scale: list[float]
    weights: list[float]
    bias: float

    def __post_init__(self) -> None:
        unknown = [f for f in self.features if f not in FEATURES]
        if unknown:
            raise InputError(f"calibration names unknown feature(s) {unknown}")
        n = len(self.features)
        if not (len(self.mean) == len(self.scale) == len(self.weights) == n):
            raise InputError("calibration: features, mean, scale and weights differ in length")
        for name, values in (
            ("mean", self.mean),
            ("scale", self.scale),
            ("weights", self.weights),
            ("bias", [self.bias]),
        ):
            if not all(_finite_number(v) for v in values):
                raise InputError(f"calibration: {name} must hold finite numbers")
        if any(not s > 0 for s in self.scale) or any(w < 0 for w in self.weights):
            raise InputError("calibration: scales must be positive and weights non-negative")

    def row(self, ev: Evidence) -> np.ndarray:
        """The model's input vector of one answer ``[F]`` (standardised)."""
        x = np.array([FEATURES[f](ev) for f in self.features], dtype=np.float64)
        return (x - np.asarray(self.mean)) / np.asarray(self.scale)

    def predict(self, ev: Evidence) -> float:
        z = self.bias + float(np.dot(self.weights, self.row(ev)))
        return float(1.0 / (1.0 + math.exp(-max(min(z, 50.0), -50.0))))


@dataclass
class Calibration:
    """Fitted confidence models, one per profile, for one encoder kind.

    ``fitted_on`` records what ``sgvloc calibrate`` used (data, counts, scores);
    ``fingerprint`` hashes the models, so a map can say which calibration answered.
    """

    name: str
    encoder_kind: str
    models: dict[str, LogisticModel]
    fitted_on: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        bad = [p for p in self.models if p not in PROFILES]
        if bad:
            raise InputError(f"calibration has unknown profile(s) {bad}; known: {PROFILES}")
        if not {"none", "planar"} & set(self.models):
            raise InputError(
                "calibration needs a model for answers without ICP (profile none or planar), "
                f"got only {sorted(self.models)}"
            )

    @property
    def fingerprint(self) -> str:
        blob = json.dumps(
            {p: asdict(m) for p, m in sorted(self.models.items())}, sort_keys=True
        ).encode()
        return hashlib.sha256(blob).hexdigest()[:16]

    def model_for(self, ev: Evidence) -> LogisticModel:
        """The model of the answer's profile, else the first of its :data:`FALLBACK`
        profiles the calibration has (there always is one: see the constructor)."""
        return next(self.models[p] for p in FALLBACK[ev.profile] if p in self.models)

    def confidence(self, ev: Evidence) -> float:
        """Probability that the answer behind ``ev`` is within 2 m and 5 degrees."""
        return self.model_for(ev).predict(ev)

    # -- files ----------------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": "sgvloc-calibration/1",
            "name": self.name,
            "encoder_kind": self.encoder_kind,
            "fingerprint": self.fingerprint,
            "models": {p: asdict(m) for p, m in self.models.items()},
            "fitted_on": self.fitted_on,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Calibration:
        if not isinstance(d, Mapping) or d.get("format") != "sgvloc-calibration/1":
            raise InputError("not an sgvloc calibration (format 'sgvloc-calibration/1' expected)")
        try:
            models = {}
            for p, m in dict(d["models"]).items():
                try:
                    models[p] = LogisticModel(**m)
                except InputError as exc:
                    why = str(exc).removeprefix("calibration: ")
                    raise InputError(f"models.{p}: {why}") from None
            return cls(str(d["name"]), str(d["encoder_kind"]), models, dict(d.get("fitted_on", {})))
        except InputError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"damaged calibration: {exc}") from None

    def save(self, path: str | Path) -> None:
        write_text_whole(path, json.dumps(self.to_dict(), indent=1) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        try:
            return cls.from_dict(json.loads(Path(path).read_text()))
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"cannot read calibration {path}: {exc}") from None


def shipped_calibration(encoder_kind: str) -> Calibration:
    """The calibration shipped for ``encoder_kind``, else the learned encoder's (the
    default encoder; its figures may not hold for another encoder: its ``encoder_kind``
    says what it was fitted for)."""
    pkg = PACKAGE_DIR / "calibration"
    for kind in (encoder_kind, "learned"):
        f = pkg / f"{kind}.json"
        if f.is_file():
            return Calibration.from_dict(json.loads(f.read_text()))
    raise InputError("no calibration is shipped with this installation")  # pragma: no cover
