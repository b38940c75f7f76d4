"""The ``sgvloc`` command line. One function per command; add commands to ``app``."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer(
    help="sgvloc: LiDAR localization service and tools.",
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode="markdown",
)


@app.callback()
def _root() -> None:
    """sgvloc: LiDAR localization service and tools."""


def _configure_logging(level: str) -> None:
    logging.basicConfig(
        level=level.upper(),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )


@app.command()
def serve(
    host: Annotated[
        str | None, typer.Option(help="interface to bind (env SGVLOC_HOST, default 127.0.0.1)")
    ] = None,
    port: Annotated[
        int | None, typer.Option(help="TCP port (env SGVLOC_PORT, default 8470)")
    ] = None,
    data_dir: Annotated[
        Path | None,
        typer.Option(help="where maps are stored (env SGVLOC_DATA_DIR, default ./data)"),
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(
            help="threads for CPU work (encode, search, re-rank, pose) "
            "(env SGVLOC_WORKERS, default 2)"
        ),
    ] = None,
    log_level: Annotated[
        str | None, typer.Option(help="critical|error|warning|info|debug (env SGVLOC_LOG_LEVEL)")
    ] = None,
) -> None:
    """Run the HTTP service in ONE process.

    CPU work runs in a pool of --workers threads inside this process (FAISS, Open3D and
    torch release the GIL). There is deliberately no option for several worker
    processes, --preload or fork: FAISS/OpenMP can hang in forked children, each process
    would hold its own copy of every map, and Prometheus metrics would split across
    processes. Scale out with more containers, each loading the maps.
    """
    import uvicorn

    from .api import create_app
    from .settings import Settings

    overrides = {
        "host": host,
        "port": port,
        "data_dir": data_dir,
        "workers": workers,
        "log_level": log_level.lower() if log_level else None,
    }
    try:
        settings = Settings(**{k: v for k, v in overrides.items() if v is not None})
    except ValueError as exc:  # pydantic's ValidationError
        raise typer.BadParameter(str(exc)) from None
    _configure_logging(settings.log_level)
    uvicorn.run(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        workers=None,  # one process: an app object cannot be forked into workers anyway
        access_log=settings.log_level == "debug",
    )


# -- build-map (sgvloc.build_map) ---------------------------------------------------------


@app.command("build-map")
def build_map_command(
    source: Annotated[
        Path,
        typer.Argument(
            help="KITTI-layout folder: velodyne/*.bin and poses.txt (times.txt optional)",
            exists=True,
            file_okay=False,
        ),
    ],
    map_name: Annotated[str, typer.Option("--map", "-m", help="the map to fill")],
    url: Annotated[
        str, typer.Option(help="base URL of the running service", envvar="SGVLOC_URL")
    ] = "http://127.0.0.1:8470",
    create: Annotated[bool, typer.Option(help="create the map if it does not exist")] = True,
    encoder: Annotated[
        str | None,
        typer.Option(help="encoder of a new map: a kind (handcrafted) or a JSON EncoderSpec"),
    ] = None,
    batch_size: Annotated[int, typer.Option(min=1, help="keyframes per request")] = 16,
    every: Annotated[int, typer.Option(min=1, help="insert every n-th scan only")] = 1,
    limit: Annotated[int | None, typer.Option(min=0, help="insert at most this many scans")] = None,
    timeout: Annotated[float, typer.Option(help="seconds to wait for one request")] = 300.0,
    api_key: Annotated[
        str | None, typer.Option(help="bearer token for the service", envvar="SGVLOC_API_KEY")
    ] = None,
    progress: Annotated[bool, typer.Option(help="show a progress bar")] = True,
) -> None:
    """Insert a KITTI-layout sequence into a map of a running service.

    Each keyframe's key is FOLDER/SCAN (e.g. 00/000042), so running the same command
    again resumes an interrupted build and stores nothing twice.
    """
    import sgvloc_client

    from .build_map import build_map
    from .core.errors import SgvlocError

    _configure_logging("warning")
    try:
        with sgvloc_client.Client(url, timeout=timeout, api_key=api_key) as client:
            result = build_map(
                source,
                client,
                map_name,
                create=create,
                encoder=encoder,
                batch_size=batch_size,
                every=every,
                limit=limit,
                progress=progress,
            )
    except (SgvlocError, sgvloc_client.SgvlocError) as exc:
        typer.echo(f"build-map: {exc}", err=True)
        raise typer.Exit(1) from None
    typer.echo(
        f"map {result.map}: {result.scans} scans sent, {result.created} new keyframes, "
        f"{result.existing} already present; {result.keyframes} keyframes, "
        f"version {result.map_version}"
    )


def main() -> None:
    """Entry point of the ``sgvloc`` console script."""
    app()


if __name__ == "__main__":
    main()
