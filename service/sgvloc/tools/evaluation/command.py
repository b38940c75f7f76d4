"""``sgvloc eval``: build the configuration from the command's options, run, report."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from sgvloc.core.config import LocalizerConfig
from sgvloc.core.encoders import EncoderSpec
from sgvloc.core.rerank import METHODS

from ..build_map import parse_encoder
from .report import (
    diagnostics_table,
    markdown_table,
    plot_sgv_scores,
    plot_sweep,
    plot_verdict,
    sweep_table,
    verdict_table,
    write_json,
)
from .runner import EvalConfig, run_evaluation


def evaluate(
    *,
    data: Path,
    db_until: float | None,
    min_gap: float | None,
    methods: str,
    db_range: tuple[int, int | None] | None = None,
    query_range: tuple[int, int | None] | None = None,
    fov: float | None = None,
    leave_out: float | None = None,
    topk: list[int],
    sweep: list[int],
    sweep_rir: list[int] | None,
    refine: str,
    max_queries: int | None,
    query_stride: int,
    encoder: str | None,
    localizer: LocalizerConfig | None,
    cache_dir: Path | None,
    frames: tuple[int, int | None] | None,
    negatives: bool,
    foreign: list[Path],
    planar_distance: bool,
    prior_noise: float | None,
    prior_radius: float,
    calibration: Path | None,
    out: Path,
    progress: bool,
    echo: Callable[[str], None],
) -> None:
    """Run the evaluation, print its tables and write OUT/eval.json and the plots.

    Raises ValueError (bad options, pydantic's ValidationError) or
    :class:`~sgvloc.core.errors.SgvlocError` (unreadable data).
    """
    cfg = EvalConfig(
        data=str(data),
        db_until=db_until,
        min_gap=min_gap,
        db_range=db_range,
        query_range=query_range,
        fov=fov,
        leave_out=leave_out,
        methods=[m.strip() for m in methods.split(",") if m.strip()] or list(METHODS),
        topk=topk,
        sweep=sweep,
        sweep_rir=sweep_rir,
        refine=refine,
        max_queries=max_queries,
        query_stride=query_stride,
        cache_dir=str(cache_dir) if cache_dir else None,
        frames=frames,
        negatives=negatives,
        foreign=[str(f) for f in foreign],
        planar_distance=planar_distance,
        prior_noise=prior_noise,
        prior_radius=prior_radius,
        calibration=str(calibration) if calibration else None,
        encoder=EncoderSpec.model_validate(parse_encoder(encoder) or {}),
        localizer=localizer or LocalizerConfig(),
    )
    result = run_evaluation(cfg, progress=progress)
    echo(markdown_table(result))
    echo("")
    echo(sweep_table(result))
    echo("")
    echo(verdict_table(result))
    echo("")
    echo(diagnostics_table(result))
    echo("")
    for note in result.notes:
        echo(f"- {note}")
    written = [
        write_json(result, out / "eval.json"),
        plot_sweep(result, out / "ntopk.png"),
        plot_sgv_scores(result, out / "sgv_scores.png"),
        plot_verdict(result, out / "verdict.png"),
    ]
    echo(f"wrote {', '.join(map(str, written))}")
