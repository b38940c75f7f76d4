"""Which encoder suits a sensor: a leave-out self-test on the map's own scans.

``sgvloc build-map --choose-encoder`` runs it before building a map: each candidate
encoder localizes a sample of the sequence's scans against the others, leaving out each
query's own stretch of the drive (every scan closer than ``gap_s`` seconds to it, before
or after: a revisit must be found, not the neighbour recorded a moment earlier). This is
``sgvloc eval --leave-out GAP`` with SGV re-ranking of the top 20 and RANSAC + ICP, the
service's default pipeline (:mod:`sgvloc.tools.evaluation`), run once per encoder on the
same queries.

The encoder chosen is the one whose answers a vehicle can act on most often: the most
in-coverage queries localized correctly (accepted by the verdict and within 2 m and
5 deg), then the fewest false accepts over every sampled query (in and out of
coverage), then the most correct poses in coverage (pose success, whatever the
verdict), then the highest Recall@1 at 5 m, then the order the candidates were given
in: the same data always gives the same choice. The candidates and the rule are
:mod:`sgvloc.core.leave_out`'s, which a served map's self-test uses alike.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from sgvloc.core import leave_out
from sgvloc.core.encoders import EncoderSpec
from sgvloc.core.errors import InputError
from sgvloc.core.leave_out import CANDIDATES, RULE, SPECS, spec_of, warning

#: format tag of a self-test report
FORMAT = "sgvloc-self-test/1"


def self_test(
    data: str | Path,
    *,
    encoders: tuple[str, ...] = CANDIDATES,
    queries: int = 50,
    gap_s: float = 30.0,
    frames: tuple[int, int | None] | None = None,
    cache_dir: str | Path | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Run the leave-out self-test of ``encoders`` on a KITTI-layout sequence.

    ``queries``: at most this many in-coverage queries (evenly spaced over the sequence;
    out-of-coverage scans are sampled alike as negatives for the false-accept count).
    Returns a JSON-able report: per encoder its figures, the encoder ``chosen`` and the
    ``rule`` that chose it. Raises :class:`InputError` when no scan has a revisit (a scan
    more than ``gap_s`` seconds away within 5 m), since nothing can then be measured.
    """
    from .evaluation.runner import EvalConfig, run_evaluation

    if not encoders:
        raise InputError("self-test: no encoder to compare")
    t_all = time.perf_counter()
    figures: dict[str, dict[str, Any]] = {}
    split: dict[str, Any] = {}
    for kind in encoders:
        t0 = time.perf_counter()
        cfg = EvalConfig(
            data=str(data),
            frames=frames,
            leave_out=gap_s,
            methods=["sgv"],
            topk=[20],
            sweep=[20],
            max_queries=queries,
            cache_dir=str(cache_dir) if cache_dir else None,
            encoder=EncoderSpec(**spec_of(kind)),
        )
        try:
            result = run_evaluation(cfg, progress=progress)
        except InputError as exc:
            raise InputError(f"self-test: {exc}") from None
        row = result.rows[0]
        split = result.split
        if not row["queries"]:
            raise InputError(
                f"self-test: no scan of {data} has a revisit (another scan within 5 m and "
                f"at least {gap_s:g} s away); the encoders cannot be compared on it"
            )
        recs = result.per_query[f"sgv@{row['k']}"]
        inside = [q for q in recs if q["in_coverage"]]
        correct = sum(q["correct"] for q in inside)
        localized_correct = sum(q["correct"] and q["accepted"] for q in inside)
        figures[kind] = {
            "queries": row["queries"],
            "negatives": row["out_of_coverage"],
            "recall_at_1_pct": row["R@1_5m"],
            "ceiling_pct": row["ceiling_5m"],
            "pose_success_pct": row["success_pct"],
            "correct_poses": correct,
            "localized_correct": localized_correct,
            "localized_correct_pct": 100.0 * localized_correct / len(inside),
            "false_accepts": row["false_accepts"],
            "accepted_in_coverage_pct": row["accepted_in_coverage_pct"],
            "encoder": spec_of(kind),
            "encoder_fingerprint": result.config["encoder_fingerprint"],
            "seconds": round(time.perf_counter() - t0, 1),
        }
    chosen = choose(figures, encoders)
    return {
        "format": FORMAT,
        "data": str(Path(data).resolve()),
        "leave_out_s": gap_s,
        "scans": split.get("scans"),
        "queries": split.get("queries"),
        "negatives": split.get("negative_queries"),
        "pipeline": "SGV top-20, RANSAC + ICP, the shipped calibration's verdict",
        "encoders": figures,
        "chosen": chosen,
        "rule": RULE,
        "warning": warning(figures, chosen),
        "seconds": round(time.perf_counter() - t_all, 1),
    }


def choose(figures: dict[str, dict[str, Any]], order: tuple[str, ...]) -> str:
    """The encoder :data:`RULE` picks from the report's per-encoder ``figures``."""
    named = {k: f | {"recall_at_1": f["recall_at_1_pct"]} for k, f in figures.items()}
    return leave_out.choose(named, order)


def report_table(report: dict[str, Any]) -> str:
    """The self-test as a Markdown table, the chosen encoder marked."""
    lines = [
        f"Encoder self-test on {report['data']}: {report['queries']} scans with a revisit and "
        f"{report['negatives']} without, each localized against the scans at least "
        f"{report['leave_out_s']:g} s away ({report['pipeline']}; {report['seconds']:g} s)",
        "",
        "| encoder | R@1 5 m % | ceiling % | pose success % | localized correctly % "
        "| false accepts | seconds |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for kind, f in report["encoders"].items():
        mark = " (chosen)" if kind == report["chosen"] else ""
        lines.append(
            f"| {kind}{mark} | {f['recall_at_1_pct']:.1f} | {f['ceiling_pct']:.1f} | "
            f"{f['pose_success_pct']:.1f} | {f['localized_correct_pct']:.1f} | "
            f"{f['false_accepts']} | {f['seconds']:g} |"
        )
    lines += ["", f"chosen: {report['chosen']} ({report['rule']})"]
    if report.get("warning"):
        lines.append(f"warning: {report['warning']}")
    return "\n".join(lines)


__all__ = [
    "CANDIDATES",
    "FORMAT",
    "SPECS",
    "choose",
    "report_table",
    "self_test",
    "spec_of",
    "warning",
]
