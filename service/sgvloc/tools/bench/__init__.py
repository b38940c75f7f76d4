"""``sgvloc bench``: the engine's stages (:mod:`.engine`: rerank, retrieval, encoding, prior),
one localization's cost by stage (:mod:`.pipeline`), the service end to end (:mod:`.http`:
http, scaling), tracking against global localization (:mod:`.tracking`), replicas over one
PostgreSQL store (:mod:`.cluster`), one JSON file of every figure."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sgvloc.core.files import write_text_whole

SECTIONS = (
    "rerank",
    "retrieval",
    "encoding",
    "pipeline",
    "http",
    "scaling",
    "prior",
    "tracking",
    "cluster",
)


def check_sections(sections: list[str]) -> list[str]:
    """``sections`` if every one is known; raises ValueError naming the unknown ones."""
    unknown = sorted(set(sections) - set(SECTIONS))
    if unknown:
        raise ValueError(f"unknown sections {unknown}; choose from {list(SECTIONS)}")
    return sections


def run_bench(
    sections: list[str], options: dict[str, Any], out: Path, echo: Callable[[str], None]
) -> dict:
    """Run ``sections`` in order with the command's ``options``; print each section's table
    and write ``out`` after every section (partial results survive an interruption).

    ``sections`` are checked with :func:`check_sections` first.
    """
    from . import cluster, engine, http, pipeline, tracking

    check_sections(sections)
    o = options
    runners: dict[str, Callable[[], dict]] = {
        "rerank": lambda: engine.bench_rerank(
            o["ks"], o["ns"], repeats=o["repeats"], rir=o["rir"], rir_max_k=o["rir_max_k"],
            large_ns=o["large_ns"], echo=echo,
        ),
        "retrieval": lambda: engine.bench_retrieval(
            o["sizes"], dim=o["dim"], large_dim=o["large_dim"], hnsw_max=o["hnsw_max"], echo=echo
        ),
        "encoding": lambda: engine.bench_encoding(o["scan_sizes"], echo=echo),
        "pipeline": lambda: pipeline.bench_pipeline(
            data=o["pipeline_data"], map_every=o["pipeline_map_every"],
            rounds=o["pipeline_rounds"], compare=o["compare"], echo=echo,
        ),
        "prior": lambda: engine.bench_prior(
            o["prior_sizes"], radius_m=o["prior_radius"], noise_m=o["prior_noise"], echo=echo
        ),
        "http": lambda: http.bench_http(
            keyframes=o["http_keyframes"], clients=o["http_clients"],
            duration_s=o["http_duration"], batch=o["http_batch"], raw_scans=o["raw_scans"],
            raw_batch=o["raw_batch"], workers=o["service_workers"], compare=o["compare"],
            batch_wait_ms=o["batch_wait_ms"], echo=echo,
        ),
        "scaling": lambda: http.bench_scaling(
            sizes=o["scale_sizes"], clients=o["scale_clients"], duration_s=o["scale_duration"],
            batch=o["scale_batch"], keypoints=o["scale_keypoints"], reload=o["scale_reload"],
            workers=o["service_workers"],
            plot=o["plot"] or out.with_name(f"{out.stem}-scaling.png"), echo=echo,
        ),
        "tracking": lambda: tracking.bench_tracking(
            data=o["track_data"], map_every=o["track_map_every"], workers=o["service_workers"],
            echo=echo,
        ),
        "cluster": lambda: cluster.bench_cluster(
            store=o["cluster_store"], sizes=o["cluster_sizes"], visible=o["cluster_visible"],
            keypoints=o["cluster_keypoints"], clients=o["cluster_clients"],
            duration_s=o["cluster_duration"], rounds=o["pipeline_rounds"],
            data=o["pipeline_data"], echo=echo,
        ),
    }  # fmt: skip
    formatters = {
        **engine.FORMATTERS, **pipeline.FORMATTERS, **http.FORMATTERS, **tracking.FORMATTERS,
        **cluster.FORMATTERS,
    }  # fmt: skip
    result: dict = {"machine": engine.machine_info(), "command": " ".join(sys.argv)}
    for section in sections:
        echo(f"## {section}")
        res = runners[section]()
        result[section] = res
        echo(formatters[section](res))
        for note in res.get("notes", []):
            echo(f"- {note}")
        if section == "rerank":
            cuda = engine.bench_sgv_cuda(o["ks"], o["ns"], large_ns=o["large_ns"])
            if "skipped" not in cuda:
                result["cuda"] = cuda
                echo(f"## SGV on CUDA ({cuda['device']})")
                echo(engine.format_cuda(cuda))
        write_text_whole(out, json.dumps(result, indent=1))
    echo(f"wrote {out}")
    return result
