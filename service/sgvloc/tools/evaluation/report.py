"""Reports of an evaluation run: Markdown tables, a JSON file, the n_topk plot and the
SGV score histogram."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

from sgvloc.core.files import write_text_whole

from .runner import EvalResult


def _fmt(v: Any, digits: int = 1) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def split_label(s: dict[str, Any]) -> str:
    """The split as the options that make it (``--db-until 44``, ``--min-gap 30``, ...)."""
    if s["mode"] == "time":
        return f"--db-until {s['db_until_s']:g}"
    if s["mode"] == "loop":
        return f"--min-gap {s['min_gap_s']:g}"
    if s["mode"] == "leave-out":
        return f"--leave-out {s['leave_out_s']:g}"
    (a, b), (c, d) = s["db_range"], s["query_range"]
    return f"--db-range {a}:{b} --query-range {c}:{d}"


def markdown_table(result: EvalResult) -> str:
    """The table of every (method, top-k): recall, MRR, pose success, errors and time."""
    thr = result.config["thresholds"]
    s = result.split
    split = split_label(s)
    head = ["method", "top-k", "candidates", f"ceiling {thr[0]:g}m"]
    for t in thr:
        head += [f"R@1 {t:g}m", f"R@5 {t:g}m", f"MRR {t:g}m"]
    head += ["S %", f"S % top-1 < {thr[0]:g}m", "RTE m", "RRE deg", "rerank ms"]
    lines = [
        f"{result.config['data']} ({split}): {s['queries']} queries in coverage, "
        f"{s['dropped_queries']} out of coverage (no database scan within "
        f"{s['drop_threshold_m']:g} m; {s.get('negative_queries', 0)} kept as negatives for "
        f"the verdict), {s['database_scans']} database scans",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "|".join("---" if i < 2 else "---:" for i in range(len(head))) + "|",
    ]
    for r in result.rows:
        cells = [
            r["method"],
            str(r["k"]),
            _fmt(r.get("candidates_mean")),
            _fmt(r.get(f"ceiling_{thr[0]:g}m")),
        ]
        for t in thr:
            cells += [_fmt(r[f"R@1_{t:g}m"]), _fmt(r[f"R@5_{t:g}m"]), _fmt(r[f"MRR_{t:g}m"])]
        cells += [
            _fmt(r.get("success_pct")),
            _fmt(r.get("success_true_top1_pct")),
            _fmt(r.get("mean_rte_m"), 2),
            _fmt(r.get("mean_rre_deg"), 2),
            _fmt(r["rerank_median_ms"], 1),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def verdict_table(result: EvalResult) -> str:
    """What the verdict did: acceptance, false accepts (in and out of coverage) and the
    calibration error of the confidence, per (method, top-k)."""
    rows = [r for r in result.rows if "false_accepts" in r]
    if not rows:
        return ""
    r0 = rows[0]
    lines = [
        f"Verdict over all {r0['all_queries']} queries ({r0['all_queries'] - r0['out_of_coverage']}"
        f" in coverage, {r0['out_of_coverage']} out of coverage); correct = RTE <= 2 m and "
        "RRE <= 5 deg:",
        "",
        "| method | top-k | accepted % (in coverage) | accepted % of correct | false accepts "
        "| of them out of coverage | false accepts % | ECE |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        cells = [
            r["method"],
            str(r["k"]),
            _fmt(r["accepted_in_coverage_pct"]),
            _fmt(r["accepted_of_correct_pct"]),
            str(r["false_accepts"]),
            str(r["false_accepts_out_of_coverage"]),
            _fmt(r["false_accept_pct"], 2),
            _fmt(r["ece"], 3),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def diagnostics_table(result: EvalResult) -> str:
    """Encoder diagnostics: local matches on true pairs and SGV scores of true/false."""
    m, sc = result.matches, result.sgv_scores
    if not m or not sc:
        return ""
    enc = result.config.get("encoder", {}).get("kind", "?")
    where = "x/y" if m["planar"] else "3-D"
    lines = [
        f"Local matches on true pairs (query vs nearest database scan; correct: within "
        f"{m['radius_m']:g} m after the ground-truth pose, {where}):",
        "",
        "| encoder | pairs | kp query | kp db | NN correct mean | NN correct median "
        "| mutual-NN correct mean | mutual matches | repeatability | chance |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        "| "
        + " | ".join(
            [
                enc,
                str(m["pairs"]),
                _fmt(m["query_keypoints_mean"], 0),
                _fmt(m["db_keypoints_mean"], 0),
                _fmt(m["nn_ratio_mean"], 3),
                _fmt(m["nn_ratio_median"], 3),
                _fmt(m["mutual_ratio_mean"], 3),
                _fmt(m["mutual_matches_mean"], 1),
                _fmt(m["repeatability_mean"], 3),
                _fmt(m["chance_ratio_mean"], 3),
            ]
        )
        + " |",
        "",
        f"SGV scores of the candidates re-ranked at top-k {sc['k']} (true: within "
        f"{sc['threshold_m']:g} m):",
        "",
        "| candidates | count | mean | p10 | p50 | p90 |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name in ("true", "false"):
        d = sc[name]
        cells = [name, str(d["count"])] + [_fmt(d[k], 4) for k in ("mean", "p10", "p50", "p90")]
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        f"SGV score ROC AUC (true vs false): {_fmt(sc['auc'], 3)} pooled; "
        f"{_fmt(sc['auc_per_query_mean'], 3)} mean per query over {sc['auc_queries']} queries "
        "with both",
    ]
    return "\n".join(lines)


def _nan_to_none(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _nan_to_none(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_nan_to_none(v) for v in x]
    return x


def report_dict(result: EvalResult) -> dict[str, Any]:
    """The report as written to eval.json: plain JSON types, NaN as None."""
    return json.loads(json.dumps(_nan_to_none(result.to_dict()), default=str))


def write_json(result: EvalResult, path: str | os.PathLike) -> Path:
    """Every figure and the exact configuration as JSON (NaN written as null), atomically."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    return write_text_whole(p, json.dumps(report_dict(result), indent=1))


def _save(fig, path: str | Path) -> Path:
    """Write a figure (creating its folder) and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p


def _ceiling_sweep(result: EvalResult) -> list[dict[str, Any]]:
    """The sweep of a method that re-ranks the retrieved candidates as they are (sgv or
    none; query expansion searches again), whose ceiling is retrieval's."""
    for m in ("sgv", "none"):
        if result.sweep.get(m):
            return result.sweep[m]
    return []


def sweep_table(result: EvalResult) -> str:
    """Per k of the sweep: the candidates re-ranking starts from (mean), the recall
    ceiling (a true match among them) and R@1 of each fully swept method."""
    base = _ceiling_sweep(result)
    if not base:
        return ""
    thr = result.config["thresholds"][0]
    methods = [m for m, pts in result.sweep.items() if len(pts) == len(base)]
    by_k = {m: {p["k"]: p for p in result.sweep[m]} for m in methods}
    head = ["k", "candidates", f"ceiling {thr:g}m"] + [f"R@1 {m}" for m in methods]
    lines = [
        f"Recall ceiling and R@1 at {thr:g} m over the n_topk sweep (in-coverage queries):",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "|".join("---:" for _ in head) + "|",
    ]
    for p in base:
        cells = [str(p["k"]), _fmt(p.get("candidates_mean")), _fmt(p[f"ceiling_{thr:g}m"])]
        cells += [_fmt(by_k[m].get(p["k"], {}).get(f"R@1_{thr:g}m")) for m in methods]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot_sweep(result: EvalResult, path: str | os.PathLike) -> Path:
    """PNG of R@1 (first threshold) and median re-ranking time against n_topk per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    thr = result.config["thresholds"][0]
    fig, (ax_r, ax_t) = plt.subplots(1, 2, figsize=(11, 4.2))
    for method, pts in result.sweep.items():
        ks = [p["k"] for p in pts]
        style = "o-" if len(ks) > 3 else "s--"
        ax_r.plot(ks, [p[f"R@1_{thr:g}m"] for p in pts], style, ms=3, label=method)
        ax_t.plot(ks, [max(p["rerank_median_ms"], 1e-3) for p in pts], style, ms=3, label=method)
    ax_r.set(xlabel="n_topk", ylabel=f"Recall@1 at {thr:g} m (%)", title="Recall@1 vs n_topk")
    ax_t.set(
        xlabel="n_topk",
        ylabel="re-ranking time per query, median (ms)",
        yscale="log",
        title="Re-ranking time vs n_topk",
    )
    for ax in (ax_r, ax_t):
        ax.grid(True, alpha=0.3)
    base = _ceiling_sweep(result)
    if base:
        ax_r.plot(
            [p["k"] for p in base],
            [p[f"ceiling_{thr:g}m"] for p in base],
            "k:",
            lw=1.2,
            label="ceiling (a true match among the candidates)",
        )
    ax_r.legend(fontsize=8)
    s = result.split
    name = Path(result.config["data"]).name
    fig.suptitle(f"{name}: {s['queries']} queries, {split_label(s)}", fontsize=10)
    return _save(fig, path)


def plot_sgv_scores(result: EvalResult, path: str | os.PathLike) -> Path:
    """PNG histogram of SGV scores of true vs false candidates (density per group)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    sc = result.sgv_scores
    per_q = sc.get("per_query", [])
    groups = {
        name: np.asarray(
            [s for q in per_q for s, t in zip(q["scores"], q["true"], strict=True) if t == want],
            dtype=np.float64,
        )
        for name, want in (("true", True), ("false", False))
    }
    every = np.concatenate(list(groups.values()))
    lo, hi = (float(every.min()), float(every.max())) if every.size else (0.0, 1.0)
    bins = np.linspace(lo, hi if hi > lo else lo + 1.0, 41)
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for (name, xs), colour in zip(groups.items(), ("tab:green", "tab:red"), strict=True):
        if xs.size:
            ax.hist(
                xs, bins=bins, density=True, alpha=0.55, color=colour, label=f"{name} (n={xs.size})"
            )
    per_n = result.config.get("localizer", {}).get("sgv", {}).get("normalise", "n") == "n"
    ax.set(
        xlabel="SGV score (v^T M v / n)" if per_n else "SGV score (v^T M v)",
        ylabel="density",
        title=f"SGV scores, top-{sc.get('k', '?')} candidates: ROC AUC {_fmt(sc.get('auc'), 3)}",
    )
    ax.grid(True, alpha=0.3)
    if every.size:
        ax.legend(fontsize=8)
    name = Path(result.config["data"]).name
    fig.suptitle(f"{name}: true = within {sc.get('threshold_m', 0):g} m of the query", fontsize=9)
    return _save(fig, path)


def plot_verdict(result: EvalResult, path: str | os.PathLike) -> Path:
    """PNG per method at the largest table top-k: precision and recall of the verdict and
    the false-accept rate over confidence thresholds, and a reliability diagram."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from .metrics import verdict_curve

    k = max(result.config["topk"])
    thresholds = np.linspace(0.0, 1.0, 101)
    fig, (ax_c, ax_r) = plt.subplots(1, 2, figsize=(11, 4.2))
    for key, recs in result.per_query.items():
        method, kk = key.rsplit("@", 1)
        if int(kk) != k or not recs or "confidence" not in recs[0]:
            continue
        conf = np.array([r["confidence"] for r in recs], dtype=np.float64)
        ok = np.array([r["correct"] for r in recs], dtype=bool)
        c = verdict_curve(conf, ok, thresholds)
        (line,) = ax_c.plot(c["threshold"], c["precision"], "-", label=f"{method} precision")
        ax_c.plot(
            c["threshold"], c["recall"], "--", color=line.get_color(), label=f"{method} recall"
        )
        ax_c.plot(
            c["threshold"],
            c["false_accept"],
            ":",
            color=line.get_color(),
            label=f"{method} false accepts",
        )
        which = np.minimum((conf * 10).astype(int), 9)
        xs = [conf[which == b].mean() for b in range(10) if (which == b).any()]
        ys = [ok[which == b].mean() for b in range(10) if (which == b).any()]
        ax_r.plot(xs, ys, "o-", color=line.get_color(), label=method)
    mc = result.config.get("localizer", {}).get("verdict", {}).get("min_confidence")
    if mc is not None:
        ax_c.axvline(mc, color="grey", lw=0.8)
    ax_c.set(
        xlabel="min_confidence", ylabel="%", title=f"Verdict at top-{k} (precision, recall, FA)"
    )
    ax_r.plot([0, 1], [0, 1], color="grey", lw=0.8)
    ax_r.set(
        xlabel="confidence (bin mean)",
        ylabel="share correct",
        xlim=(0, 1),
        ylim=(0, 1),
        title="Reliability",
    )
    for ax in (ax_c, ax_r):
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    name = Path(result.config["data"]).name
    out = next((r["out_of_coverage"] for r in result.rows if "out_of_coverage" in r), 0)
    fig.suptitle(
        f"{name}: {result.split['queries']} in coverage, {out} out of coverage", fontsize=9
    )
    return _save(fig, path)
