"""The ``sgvloc`` command line: options parsed here, the work done in :mod:`sgvloc.server`
(``serve``) and :mod:`sgvloc.tools` (every other command). Modules are imported inside
each command, so the client-only install can list the commands."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer

T = TypeVar("T")

app = typer.Typer(
    help="sgvloc: LiDAR localization service and tools.",
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode="markdown",
)


def _print_version(value: bool) -> None:
    if value:
        from .about import __version__

        typer.echo(f"sgvloc {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool,
        typer.Option("--version", callback=_print_version, is_eager=True, help="print the version"),
    ] = False,
) -> None:
    """sgvloc: LiDAR localization service and tools."""


#: top-level modules of the service extra (pyproject.toml); a command that needs one of
#: them says so in one line when the client-only install lacks it
SERVICE_MODULES = frozenset(
    "torch faiss open3d scipy numba fastapi fastapi_offline starlette uvicorn "
    "pydantic_settings prometheus_client matplotlib cv2 pypcd4 plyfile".split()
)


#: every command but serve: threads of each numeric library
ThreadsOpt = Annotated[
    int | None,
    typer.Option(
        min=1,
        envvar="SGVLOC_THREADS",
        help="threads of each numeric library (env SGVLOC_THREADS; default: see below)",
    ),
]


def _threads_epilog(default: str) -> str:
    return (
        "Threads: each numeric library (OpenMP in Open3D and FAISS, BLAS, numba, torch) "
        f"gets --threads threads, default {default}, set before any of them loads; "
        "OMP_NUM_THREADS and the like, when set, win over the default (not over --threads). "
        "See docs/OPERATIONS.md, 'Threads'."
    )


ONE_THREAD = _threads_epilog("1 (measured fastest: several small calls per scan)")


def _above_zero(value: float | None) -> float | None:
    """An option's callback: a number that must be above 0 (None: not given)."""
    if value is not None and not value > 0:
        raise typer.BadParameter(f"must be above 0, got {value:g}")
    return value


def _exit_on_sigterm() -> None:
    """SIGTERM ends the command through its ``finally`` blocks (what it started is removed):
    :func:`sgvloc.tools.service_process.exit_on_sigterm`."""
    from .tools.service_process import exit_on_sigterm

    exit_on_sigterm()


def _output_file(path: Path | None, option: str) -> None:
    """Before any work: a usage error for an output file the command could not write at
    its end (its path is a folder, or its folder cannot be made or written)."""
    if path is None:
        return
    if path.is_dir():
        raise typer.BadParameter(f"{path} is a folder; name a file", param_hint=option)
    _writable_folder(path.parent, option)


def _output_folder(path: Path, option: str) -> None:
    """Before any work: a usage error for an output folder that is a file or cannot be
    made or written."""
    if path.exists() and not path.is_dir():
        raise typer.BadParameter(f"{path} is a file; name a folder", param_hint=option)
    _writable_folder(path, option)


def _writable_folder(folder: Path, option: str) -> None:
    import os

    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        above = next((p for p in (folder, *folder.parents) if p.exists()), None)
        if above is not None and not above.is_dir():
            raise typer.BadParameter(
                f"{above} is a file, not a folder", param_hint=option
            ) from None
        raise typer.BadParameter(
            f"cannot make {folder}: {exc.strerror}", param_hint=option
        ) from None
    if not os.access(folder, os.W_OK | os.X_OK):
        raise typer.BadParameter(f"{folder} is not writable", param_hint=option)


def _cap_threads(threads: int | None, default: int = 1) -> None:
    """Apply the thread policy (sgvloc.server.threads) before numpy & co. are imported."""
    from .server.threads import limit_library_threads

    limit_library_threads(threads or default, force=threads is not None)


def _configure_logging(level: str, fmt: str = "text") -> None:
    # the standard library only: the numeric libraries are not loaded yet
    from .server.logs import configure_logging

    configure_logging(level, "json" if fmt == "json" else "text")


#: the serve options of settings, as an error names them
SERVE_OPTIONS = {
    "host": "--host",
    "port": "--port",
    "data_dir": "--data-dir",
    "store_url": "--store",
    "workers": "--workers",
    "threads_per_worker": "--threads",
    "log_level": "--log-level",
    "log_format": "--log-format",
    "keys_file": "--keys-file",
    "dev": "--dev",
}


@app.command(
    epilog="Threads: each numeric library (OpenMP in Open3D and FAISS, BLAS, numba, torch) "
    "gets --threads threads per worker (env SGVLOC_THREADS_PER_WORKER), default usable "
    "cores // workers, set before any of them loads; OMP_NUM_THREADS and the like, when "
    "set, win over the default (not over --threads). See docs/OPERATIONS.md, 'Threads'."
)
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
    store: Annotated[
        str | None,
        typer.Option(
            help="postgresql://user@host:port/db: keep the maps in PostgreSQL, shared by "
            "every replica started with the same URL (env SGVLOC_STORE_URL; default: SQLite "
            "under --data-dir). Give the password in a file (env SGVLOC_STORE_PASSWORD_FILE) "
            "or PGPASSFILE, not in the URL: a command line is visible to every user of the "
            "machine (ps). See docs/SCALING.md"
        ),
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(
            help="threads for CPU work (encode, search, re-rank, pose) "
            "(env SGVLOC_WORKERS, default 2)"
        ),
    ] = None,
    threads: Annotated[
        int | None,
        typer.Option(min=1, help="threads of each numeric library per worker (see below)"),
    ] = None,
    log_level: Annotated[
        str | None, typer.Option(help="critical|error|warning|info|debug (env SGVLOC_LOG_LEVEL)")
    ] = None,
    log_format: Annotated[
        str | None,
        typer.Option(
            help="text | json: JSON lines with request ids and an access line per request "
            "(env SGVLOC_LOG_FORMAT, default text)"
        ),
    ] = None,
    keys_file: Annotated[
        Path | None,
        typer.Option(
            help="TOML/JSON file of API keys with roles (env SGVLOC_KEYS_FILE); "
            "see docs/OPERATIONS.md"
        ),
    ] = None,
    dev: Annotated[
        bool,
        typer.Option(
            "--dev",
            help="development mode: authentication OFF, no keys needed (env SGVLOC_DEV=1); "
            "never on a shared network",
        ),
    ] = False,
) -> None:
    """Run the HTTP service in ONE process.

    Authentication is on: the service refuses to start without API keys (--keys-file)
    unless --dev says it is a development setup.

    CPU work runs in a pool of --workers threads inside this process (FAISS, Open3D and
    torch release the GIL); each library gets threads_per_worker threads of its own
    (env SGVLOC_THREADS_PER_WORKER, default: cores // workers), unless OMP_NUM_THREADS and
    the like are already set; a request running alone takes the idle cores where that
    keeps its answer the same (env SGVLOC_SPARE_CORES, default true). There is
    deliberately no option for several worker processes, --preload or fork: FAISS/OpenMP
    can hang in forked children, each process would hold its own copy of every map, and
    Prometheus metrics would split across processes. Scale out with more replicas sharing
    one PostgreSQL store (--store): each loads the maps and follows the others' writes.
    """
    # nothing that loads numpy, FAISS, Open3D or torch before run_service caps their threads
    import logging
    import os

    from pydantic import ValidationError

    from .server.run import StartupError
    from .server.run import serve as run_service
    from .server.settings import Settings, env_name, unknown_env

    overrides = {
        "host": host,
        "port": port,
        "data_dir": data_dir,
        "store_url": store,
        "workers": workers,
        "threads_per_worker": threads,
        "log_level": log_level.lower() if log_level else None,
        "log_format": log_format.lower() if log_format else None,
        "keys_file": keys_file,
        "dev": True if dev else None,
    }
    given = {k: v for k, v in overrides.items() if v is not None}
    try:
        settings = Settings(**given)
    except ValidationError as exc:  # named as given: an option, else its variable
        options = {k: SERVE_OPTIONS[k] for k in given}
        raise typer.BadParameter(_why(exc, options, unnamed=env_name)) from None
    _configure_logging(settings.log_level, settings.log_format)
    for line in unknown_env(os.environ):
        logging.getLogger("sgvloc.cli").warning("%s", line)
    try:
        run_service(settings)
    except StartupError as exc:
        typer.echo(f"sgvloc serve: {exc}", err=True)
        raise typer.Exit(2) from None


@app.command("new-key")
def new_key_command(
    role: Annotated[str, typer.Option(help="vehicle | mapper | viewer | admin")],
    name: Annotated[str, typer.Option(help="a label for the key (shown in logs)")],
    maps: Annotated[
        str, typer.Option(help="comma-separated maps the key may use (default: every map)")
    ] = "",
    keys_file: Annotated[
        Path | None,
        typer.Option(
            help="append the entry to this keys file (created if missing, readable by all: "
            "it holds the key's SHA-256 only) instead of printing it",
            dir_okay=False,
        ),
    ] = None,
    key_file: Annotated[
        Path | None,
        typer.Option(
            help="write the key itself to this new file (owner-only) instead of stderr",
            dir_okay=False,
        ),
    ] = None,
) -> None:
    """Make a random API key: the key goes to the client (stderr, or --key-file; it is
    not stored), the keys-file entry holds only its SHA-256 (stdout, or --keys-file).
    Works with the client-only install.

    The keys of docker-compose.yml: `sgvloc new-key --role admin --name operator
    --keys-file sgvloc-keys.toml --key-file sgvloc-admin.key`, then the same with
    `--role viewer --name prometheus --key-file sgvloc-metrics.key`.
    """
    from .server.keys import (
        ROLES,
        KeysError,
        append_entry,
        is_json,
        key_names,
        keys_entry,
        new_key,
        toml_entry,
        write_key,
    )

    if role not in ROLES:
        raise typer.BadParameter(f"role must be one of {', '.join(ROLES)}", param_hint="--role")
    if keys_file is not None and keys_file.exists():  # a second entry of a name: no start
        try:
            taken = name in key_names(keys_file)
        except KeysError as exc:
            raise typer.BadParameter(str(exc), param_hint="--keys-file") from None
        if taken:
            raise typer.BadParameter(
                f"{keys_file} has a key named {name!r} already: names must be unique",
                param_hint="--name",
            )
    key = new_key()
    entry = keys_entry(name, role, key, [m.strip() for m in maps.split(",") if m.strip()])
    if keys_file is not None and not keys_file.parent.is_dir():  # before a key is written
        raise typer.BadParameter(f"{keys_file.parent} is not a folder", param_hint="--keys-file")
    if key_file is not None:
        try:
            write_key(key_file, key)
        except FileExistsError:
            raise typer.BadParameter(
                f"{key_file} exists: a key file is never overwritten", param_hint="--key-file"
            ) from None
        except OSError as exc:
            why = f"{key_file}: {exc.strerror}"
            raise typer.BadParameter(why, param_hint="--key-file") from None
        typer.echo(f"wrote the {role} key {name!r} to {key_file}", err=True)
    else:
        typer.echo(f"key: {key}", err=True)
    if keys_file is not None:
        try:
            append_entry(keys_file, entry)
        except (OSError, KeysError) as exc:
            why = exc.strerror if isinstance(exc, OSError) else str(exc)
            typer.echo(f"new-key: {keys_file}: {why}; the entry was not added", err=True)
            typer.echo(json.dumps(entry) if is_json(keys_file) else toml_entry(entry))
            raise typer.Exit(1) from None
        typer.echo(f"added {name!r} ({role}) to {keys_file}", err=True)
    else:
        typer.echo(toml_entry(entry))


# -- loadtest (sgvloc.tools.loadtest) -----------------------------------------------------


@app.command("loadtest", epilog=ONE_THREAD)
def loadtest_command(
    url: Annotated[
        str | None,
        typer.Option(help="a service on this machine; default: start one (--dev, temp data)"),
    ] = None,
    clients: Annotated[int, typer.Option(min=1, max=256, help="concurrent clients")] = 16,
    duration: Annotated[float, typer.Option(min=0.5, max=3600, help="seconds of load")] = 60.0,
    insert_fraction: Annotated[
        float, typer.Option(min=0.0, max=1.0, help="share of requests that are bulk inserts")
    ] = 0.2,
    workers: Annotated[int, typer.Option(min=1, help="--workers of a started service")] = 2,
    api_key: Annotated[
        str | None,
        typer.Option(
            help="bearer token: admin (a mapper key runs the test but cannot delete its map)",
            envvar="SGVLOC_API_KEY",
        ),
    ] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the figures here")] = None,
    slow_clients: Annotated[
        int,
        typer.Option(
            min=0,
            max=64,
            help="extra connections that trickle a localize body 1 byte / 0.5 s meanwhile",
        ),
    ] = 0,
    threads: ThreadsOpt = None,
) -> None:
    """Load a local service with N clients for D seconds (localize + bulk inserts); report
    errors, p50/p99 latency and throughput. Exits 1 if any request failed (429/503 with
    Retry-After are counted apart, as deliberate refusals). --slow-clients shows whether
    slow uploads hold up the others."""
    _cap_threads(threads)
    _exit_on_sigterm()  # the service it starts and its map are cleaned up
    _output_file(json_out, "--json")
    import httpx

    from .tools.loadtest import run_loadtest, run_loadtest_local

    _configure_logging("warning")
    options = dict(
        clients=clients,
        duration_s=duration,
        insert_fraction=insert_fraction,
        api_key=api_key,
        slow_clients=slow_clients,
    )
    try:
        if url is None:
            result = run_loadtest_local(workers=workers, **options)
        else:
            result = run_loadtest(url, **options)
    except (ValueError, RuntimeError, httpx.HTTPError) as exc:
        typer.echo(f"loadtest: {exc}", err=True)
        raise typer.Exit(2) from None
    typer.echo(result.summary())
    if json_out is not None:
        from .core.files import write_text_whole

        write_text_whole(json_out, json.dumps(result.as_dict(), indent=2))
    if result.errors:
        raise typer.Exit(1)


# -- build-map (sgvloc.tools.build_map) ---------------------------------------------------


@app.command("build-map", epilog=ONE_THREAD)
def build_map_command(
    ctx: typer.Context,
    source: Annotated[
        Path | None,
        typer.Argument(
            help="the same as --data (kept for earlier scripts)",
            exists=True,
            file_okay=False,
            show_default=False,
        ),
    ] = None,
    map_name: Annotated[str, typer.Option("--map", "-m", help="the map to fill")] = "",
    data: Annotated[
        Path | None,
        typer.Option(
            help="KITTI-layout folder: velodyne/*.bin and poses.txt (times.txt optional)",
            exists=True,
            file_okay=False,
        ),
    ] = None,
    url: Annotated[
        str,
        typer.Option(
            help="base URL of the running service (not with --data-dir)", envvar="SGVLOC_URL"
        ),
    ] = "http://127.0.0.1:8470",
    data_dir: Annotated[
        Path | None,
        typer.Option(
            help="write into this service data directory instead of a service (not with "
            "--url); no service may run on it meanwhile: stop it first",
            file_okay=False,
        ),
    ] = None,
    create: Annotated[bool, typer.Option(help="create the map if it does not exist")] = True,
    encoder: Annotated[
        str | None,
        typer.Option(
            help="encoder of a new map: a kind (learned, handcrafted, bev), learned-fpfh "
            "(the self-test's name for the learned encoder with FPFH keypoints) or a JSON "
            "EncoderSpec (default: learned)"
        ),
    ] = None,
    batch_size: Annotated[
        int, typer.Option(min=1, help="keyframes per request (or store transaction)")
    ] = 16,
    every: Annotated[int, typer.Option(min=1, help="insert every n-th scan only")] = 1,
    limit: Annotated[int | None, typer.Option(min=1, help="insert at most this many scans")] = None,
    until: Annotated[
        float | None,
        typer.Option(
            min=0.0,
            help="insert only the scans of the first SECONDS (times.txt; the database of "
            "sgvloc eval --db-until)",
        ),
    ] = None,
    timeout: Annotated[
        float, typer.Option(min=0.001, help="seconds to wait for one request")
    ] = 300.0,
    api_key: Annotated[
        str | None, typer.Option(help="bearer token for the service", envvar="SGVLOC_API_KEY")
    ] = None,
    choose_encoder: Annotated[
        bool,
        typer.Option(
            help="first run the encoder self-test (learned, handcrafted, bev and "
            "learned-fpfh, the learned encoder with FPFH keypoints: each localizes "
            "a sample of the scans against the others, its own stretch of the drive left "
            "out) and build the map with the encoder that does best; recorded with the map. "
            "It looks at every scan up to where --until/--limit stop the build (--every "
            "does not thin it)"
        ),
    ] = False,
    dry_run: Annotated[
        bool, typer.Option(help="with --choose-encoder: report the self-test, build nothing")
    ] = False,
    self_test_queries: Annotated[
        int, typer.Option(min=1, help="self-test: scans with a revisit to localize (at most)")
    ] = 50,
    self_test_gap: Annotated[
        float,
        typer.Option(
            min=0.0,
            help="self-test: scans closer in time than SECONDS to a query are left out of "
            "its database",
        ),
    ] = 30.0,
    self_test_out: Annotated[
        Path | None, typer.Option(help="self-test: also write the report (JSON) here")
    ] = None,
    key_prefix: Annotated[
        str | None,
        typer.Option(
            help="first part of each keyframe's key, PREFIX/SCAN (default: the folder's "
            "name); give the earlier name to resume a build from a renamed or moved folder "
            "(without one, a build that would add the same scans again is refused)"
        ),
    ] = None,
    progress: Annotated[bool, typer.Option(help="show a progress bar")] = True,
    threads: ThreadsOpt = None,
) -> None:
    """Insert a KITTI-layout sequence into a map of a running service or a data directory.

    Each keyframe's key is FOLDER/SCAN (e.g. 00/000042; --key-prefix replaces FOLDER), so
    running the same command again resumes an interrupted build and stores nothing twice.

    With --data-dir the keyframes go straight into the map stores of that directory (needs
    the service extra) and the index snapshot is saved at the end, so a service started on
    it later loads the map at once. A service already running on that directory would not
    see them: stop it first, or use --url.
    """
    _cap_threads(threads)
    _exit_on_sigterm()  # as Ctrl-C: a data directory's index snapshot is saved on the way out
    _output_file(self_test_out, "--self-test-out")
    import sgvloc_client

    from .core.errors import SgvlocError
    from .tools.build_map import build_map, key_prefix_for

    if (source is None) == (data is None):
        raise typer.BadParameter(
            "give the sequence folder once: --data FOLDER", ctx=ctx, param_hint="'--data'"
        )
    source = source or data
    try:
        key_prefix_for(source, key_prefix)
    except SgvlocError as exc:
        raise typer.BadParameter(str(exc), ctx=ctx, param_hint="'--key-prefix'") from None
    if not map_name:
        raise typer.BadParameter("name the map to fill", ctx=ctx, param_hint="'--map'")
    # SGVLOC_URL in the environment is no conflict; --url on the command line is
    url_source = ctx.get_parameter_source("url")
    if data_dir is not None and getattr(url_source, "name", None) == "COMMANDLINE":
        raise typer.BadParameter(
            "give either --url (a running service) or --data-dir (a data directory), not both",
            ctx=ctx,
            param_hint="'--url' / '--data-dir'",
        )
    if data_dir is not None:
        _output_folder(data_dir, "--data-dir")
    if choose_encoder and encoder is not None:
        raise typer.BadParameter(
            "--choose-encoder picks the encoder: leave out --encoder",
            ctx=ctx,
            param_hint="'--encoder'",
        )
    if dry_run and not choose_encoder:
        raise typer.BadParameter(
            "--dry-run reports the encoder self-test: give --choose-encoder",
            ctx=ctx,
            param_hint="'--dry-run'",
        )
    _encoder_spec(encoder)  # a usage error now, naming the option
    _configure_logging("warning")

    report = None
    if choose_encoder:
        report = _encoder_self_test(
            source, every, limit, until, self_test_queries, self_test_gap, progress
        )
        if self_test_out is not None:
            from .core.files import write_text_whole

            write_text_whole(self_test_out, json.dumps(report, indent=1))
        if dry_run:
            return
        encoder = report["chosen"]  # a candidate's name: parse_encoder gives its spec
    options = dict(create=create, encoder=encoder, batch_size=batch_size, every=every)
    options.update(limit=limit, until=until, progress=progress, self_test=report)
    options.update(key_prefix=key_prefix)
    try:
        if data_dir is not None:
            result = build_map(source, data_dir, map_name, **options)
        else:
            with _sdk(url, api_key, timeout) as client:
                result = build_map(source, client, map_name, **options)
    except (SgvlocError, sgvloc_client.SgvlocError) as exc:
        typer.echo(f"build-map: {_sdk_error(exc)}", err=True)
        raise typer.Exit(1) from None
    typer.echo(
        f"map {result.map}: {result.scans} scans sent, {result.created} new keyframes, "
        f"{result.existing} already present; {result.keyframes} keyframes, "
        f"version {result.map_version}"
    )
    if result.skipped:
        shown = ", ".join(result.skipped[:5]) + (", ..." if len(result.skipped) > 5 else "")
        typer.echo(
            f"{len(result.skipped)} scans skipped: the map's encoder found nothing to "
            f"describe in them (too sparse for it; try another encoder): {shown}"
        )


def _encoder_self_test(
    source: Path,
    every: int,
    limit: int | None,
    until: float | None,
    queries: int,
    gap: float,
    progress: bool,
) -> dict[str, Any]:
    """Run and print build-map's encoder self-test over the scans the build would insert
    (their whole index range: --every does not thin the self-test)."""
    from .core.errors import SgvlocError
    from .core.sequence import KittiSequence
    from .tools.build_map import select_frames
    from .tools.self_test import report_table, self_test

    try:
        seq = KittiSequence(source)
        picked = select_frames(len(seq), every, limit, until=until, times=seq.times)
        if not len(picked):
            raise typer.BadParameter("no scan selected for the self-test")
        report = self_test(
            source,
            queries=queries,
            gap_s=gap,
            frames=(0, int(max(picked)) + 1),
            progress=progress,
        )
    except (SgvlocError, ValueError) as exc:
        typer.echo(f"build-map: encoder self-test: {exc}", err=True)
        raise typer.Exit(1) from None
    typer.echo(report_table(report))
    return report


# -- eval and synth (sgvloc.tools.evaluation, sgvloc.tools.synth) -------------------------


#: options that eval and calibrate share
DbUntilOpt = Annotated[
    float | None, typer.Option(help="time split: database = scans of the first SECONDS")
]
MinGapOpt = Annotated[
    float | None,
    typer.Option(help="loop split: database = scans >= SECONDS older than the query"),
]
EncoderOpt = Annotated[
    str | None, typer.Option(help="encoder: a kind or a JSON EncoderSpec (default: learned)")
]
CacheDirOpt = Annotated[
    Path | None, typer.Option(help="feature cache (default ~/.cache/sgvloc/features)")
]
ProgressOpt = Annotated[bool, typer.Option(help="show progress bars")]


def _localizer_config(ctx: typer.Context, text: str | None) -> Any:
    """``--config``: a LocalizerConfig from a JSON file or from JSON text (``{...}``);
    a usage error naming the option when it is neither or does not validate."""
    from pydantic import ValidationError

    from .core.config import LocalizerConfig

    if text is None:
        return LocalizerConfig()
    if text.lstrip().startswith("{"):
        source, raw = "the JSON given", text
    else:
        path = Path(text)
        if not path.is_file():
            raise typer.BadParameter(
                f"{text!r} is neither a JSON file nor JSON text ({{...}})",
                ctx=ctx,
                param_hint="'--config'",
            )
        try:
            source, raw = str(path), path.read_text()
        except (OSError, UnicodeDecodeError) as exc:
            raise typer.BadParameter(
                f"cannot read {path}: {exc}", ctx=ctx, param_hint="'--config'"
            ) from None
    try:
        return LocalizerConfig.model_validate_json(raw)
    except ValidationError as exc:
        why = "; ".join(
            f"{'.'.join(map(str, e['loc'])) or 'the JSON'}: {e['msg']}" for e in exc.errors()
        )
        raise typer.BadParameter(f"{source}: {why}", ctx=ctx, param_hint="'--config'") from None


def _why(
    exc: BaseException,
    names: dict[str, str] | None = None,
    json_option: bool = False,
    unnamed: Callable[[str], str] = lambda field: "--" + field.replace("_", "-"),
) -> str:
    """An error as one line for stderr. pydantic's ValidationError is said per error as
    ``OPTION: message (got VALUE)``, OPTION naming the field that failed as the user gave
    it (``names``, else ``unnamed(field)``: ``--field-name``), or for a JSON option's value
    (``json_option``) as ``field.path: message``; not pydantic's multi-line dump."""
    from pydantic import ValidationError

    if not isinstance(exc, ValidationError):
        return str(exc)
    parts = []
    for e in exc.errors(include_url=False):
        loc = [str(x) for x in e["loc"]]
        msg = str(e["msg"]).removeprefix("Value error, ")
        if not loc:
            parts.append(msg)
        elif json_option:
            parts.append(f"{'.'.join(loc)}: {msg}")
        else:
            head = (names or {}).get(loc[0]) or unnamed(loc[0])
            got = e.get("input")
            secret = loc[0].endswith("_url") or "password" in loc[0]  # never echoed
            value = f" (got {got!r})" if isinstance(got, str | int | float) and not secret else ""
            parts.append(f"{head}{''.join(f'.{x}' for x in loc[1:])}: {msg}{value}")
    return "; ".join(parts)


def _encoder_spec(value: str | None) -> Any:
    """``--encoder``: an EncoderSpec (None without one); a usage error naming the option."""
    from .core.encoders import EncoderSpec
    from .core.errors import InputError
    from .tools.build_map import parse_encoder

    try:
        spec = parse_encoder(value)
        return None if spec is None else EncoderSpec.model_validate(spec)
    except (InputError, ValueError) as exc:
        why = _why(exc, json_option=True).removeprefix("encoder: ")
        raise typer.BadParameter(why, param_hint="'--encoder'") from None


def _frames(text: str | None, option: str = "--frames") -> tuple[int, int | None] | None:
    """``START:STOP`` (STOP optional) as a pair of frame indices."""
    if text is None:
        return None
    start, sep, stop = text.partition(":")
    try:
        if not sep:
            raise ValueError
        return int(start or 0), int(stop) if stop.strip() else None
    except ValueError:
        raise typer.BadParameter(
            f"expected START:STOP frame indices, got {text!r}", param_hint=f"'{option}'"
        ) from None


def _scan_span(spec: str, option: str) -> tuple[Path, int, int | None]:
    """``DIR``, ``DIR@N`` (its first N scans) or ``DIR@A:B`` (scans A..B-1) as
    ``(DIR, A, B or None)``; a usage error naming ``option`` otherwise."""
    path, at, span = spec.partition("@")
    a, _, b = span.rpartition(":")
    try:
        first, end = int(a or 0), (int(b) if b else None)
    except ValueError:
        first, end = -1, None
    if not path or (at and not b) or first < 0 or (end is not None and end <= first):
        raise typer.BadParameter(
            f"{spec!r}: give DIR, DIR@N or DIR@A:B with scan numbers 0 <= A < B",
            param_hint=option,
        )
    from .core.errors import SgvlocError
    from .core.sequence import KittiSequence

    try:
        scans = len(KittiSequence(Path(path)))
    except SgvlocError as exc:
        raise typer.BadParameter(f"{spec!r}: {exc}", param_hint=option) from None
    if first >= scans or (end is not None and end > scans):
        raise typer.BadParameter(
            f"{spec!r}: {path} has {scans} scans (0..{scans - 1})", param_hint=option
        )
    return Path(path), first, end


def _int_list(text: str, option: str | None = None, *, positive: bool = False) -> list[int]:
    """Comma-separated integers; ``positive``: one or more, each at least 1 (a usage error
    naming ``option`` otherwise)."""
    try:
        values = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise typer.BadParameter(
            f"expected comma-separated integers, got {text!r}", param_hint=option
        ) from None
    if positive and (not values or min(values) < 1):
        raise typer.BadParameter(
            f"expected one or more integers of at least 1, got {text!r}", param_hint=option
        )
    return values


@app.command("eval", epilog=ONE_THREAD)
def eval_command(
    ctx: typer.Context,
    data: Annotated[
        Path,
        typer.Option(
            help="KITTI-layout sequence (velodyne/, poses.txt, times.txt) or kitti-bev "
            "folder (imgs/*.png, pose.txt; needs an image encoder, e.g. bev)"
        ),
    ],
    db_until: DbUntilOpt = None,
    min_gap: MinGapOpt = None,
    db_range: Annotated[
        str | None,
        typer.Option(
            help="range split: database = frames START:STOP (by index, STOP exclusive), "
            "e.g. 0:3000; instead of --db-until / --min-gap"
        ),
    ] = None,
    query_range: Annotated[
        str | None,
        typer.Option(
            help="range split: queries from frames START:STOP (STOP optional), e.g. 3200: "
            "(default: every frame after --db-range)"
        ),
    ] = None,
    methods: Annotated[
        str, typer.Option(help="comma-separated re-ranking methods (default: all)")
    ] = "",
    leave_out: Annotated[
        float | None,
        typer.Option(
            help="self-test split: every scan is a query, its database every other scan at "
            "least SECONDS away in time (before or after); instead of --db-until / --min-gap"
        ),
    ] = None,
    fov: Annotated[
        float | None,
        typer.Option(
            max=360.0,
            callback=_above_zero,
            help="crop every scan to this horizontal field of view (deg) about the "
            "sensor's forward axis before encoding: a forward-looking sensor on 360-degree data",
        ),
    ] = None,
    topk: Annotated[str, typer.Option(help="comma-separated top-k values of the table")] = "2,20",
    sweep: Annotated[
        str, typer.Option(help="n_topk values of the plot (none, QE, sgv)")
    ] = "1,2,3,4,5,7,10,15,20,25,30,40,50",
    sweep_rir: Annotated[
        str, typer.Option(help="n_topk values of the plot for *-rir methods (default: --topk)")
    ] = "",
    refine: Annotated[str, typer.Option(help="pose refinement after RANSAC: icp | none")] = "icp",
    max_queries: Annotated[
        int | None,
        typer.Option(
            min=1,
            help="evaluate at most N in-coverage queries and at most N out-of-coverage "
            "ones (every --foreign scan is kept)",
        ),
    ] = None,
    query_stride: Annotated[int, typer.Option(min=1, help="evaluate every n-th query")] = 1,
    encoder: EncoderOpt = None,
    config: Annotated[
        str | None,
        typer.Option(
            help="LocalizerConfig (retrieval, sgv, pose settings): a JSON file, or the JSON "
            """itself ('{"pose": {"min_icp_constraint": 0}}')""",
        ),
    ] = None,
    cache_dir: CacheDirOpt = None,
    frames: Annotated[
        str | None,
        typer.Option(help="use only frames START:STOP of the sequence (by index; STOP optional)"),
    ] = None,
    negatives: Annotated[
        bool,
        typer.Option(
            help="keep the out-of-coverage queries (no database scan within 5 m) as "
            "negatives for the verdict (recall never counts them)"
        ),
    ] = True,
    foreign: Annotated[
        list[Path] | None,
        typer.Option(
            help="a sequence of another place: each of its scans is queried against the "
            "database and any accepted answer counts as a false accept (repeatable)"
        ),
    ] = None,
    planar_distance: Annotated[
        bool,
        typer.Option(
            help="measure the 5 m and 20 m revisit distances in the plane, ignoring height "
            "(for ground truth whose heights disagree between passes)"
        ),
    ] = False,
    prior_noise: Annotated[
        float | None,
        typer.Option(
            min=0.0,
            help="simulate a GNSS prior: per query the true x/y plus Gaussian noise of "
            "SIGMA m per axis; retrieval searches only inside --prior-radius",
        ),
    ] = None,
    prior_radius: Annotated[
        float, typer.Option(callback=_above_zero, help="radius of the simulated prior (m)")
    ] = 20.0,
    calibration: Annotated[
        Path | None,
        typer.Option(help="calibration file from sgvloc calibrate (default: the shipped one)"),
    ] = None,
    out: Annotated[
        Path,
        typer.Option(help="folder for eval.json, ntopk.png, sgv_scores.png and verdict.png"),
    ] = Path("eval-out"),
    progress: ProgressOpt = True,
    threads: ThreadsOpt = None,
) -> None:
    """Evaluate every re-ranking method x top-k on a sequence (docs/EVALUATION.md).

    Prints a Markdown table (recall over the in-coverage queries, the recall ceiling of
    the top-k, pose success), a verdict table over every query, in and out of coverage
    (acceptance, false accepts, the confidence's expected calibration error), then the
    encoder's diagnostics; writes OUT/eval.json (every figure, per query its confidence
    and evidence, the exact configuration), OUT/ntopk.png, OUT/sgv_scores.png and
    OUT/verdict.png (precision and recall of the verdict over confidence thresholds, and
    a reliability diagram).
    """
    _cap_threads(threads)
    from .core.errors import SgvlocError
    from .tools.evaluation.command import evaluate

    if sum(x is not None for x in (db_until, min_gap, db_range, leave_out)) != 1:
        raise typer.BadParameter(
            "give exactly one split: --db-until (time), --min-gap (loops), --db-range "
            "(frame ranges) or --leave-out (self-test)",
            ctx=ctx,
            param_hint="'--db-until' / '--min-gap' / '--db-range' / '--leave-out'",
        )
    localizer = _localizer_config(ctx, config)
    _encoder_spec(encoder)  # a usage error now, naming the option
    _output_folder(out, "--out")

    _configure_logging("warning")
    try:
        evaluate(
            data=data,
            db_until=db_until,
            min_gap=min_gap,
            db_range=_frames(db_range, "--db-range"),
            query_range=_frames(query_range, "--query-range"),
            fov=fov,
            leave_out=leave_out,
            methods=methods,
            topk=_int_list(topk, "--topk", positive=True),
            sweep=_int_list(sweep, "--sweep", positive=True),
            sweep_rir=_int_list(sweep_rir, "--sweep-rir") or None,
            refine=refine,
            max_queries=max_queries,
            query_stride=query_stride,
            encoder=encoder,
            localizer=localizer,
            cache_dir=cache_dir,
            frames=_frames(frames),
            negatives=negatives,
            foreign=foreign or [],
            planar_distance=planar_distance,
            prior_noise=prior_noise,
            prior_radius=prior_radius,
            calibration=calibration,
            out=out,
            progress=progress,
            echo=typer.echo,
        )
    except ValueError as exc:  # pydantic's ValidationError and InputError
        typer.echo(f"eval: {_why(exc)}", err=True)
        raise typer.Exit(2) from None
    except SgvlocError as exc:
        typer.echo(f"eval: {exc}", err=True)
        raise typer.Exit(1) from None


def _kidnap(text: str) -> tuple[int, int]:
    try:
        at, to = (int(v) for v in text.split(":"))
    except ValueError:
        raise typer.BadParameter(
            f"{text!r}: give AT:TO scan indices", param_hint="'--kidnap'"
        ) from None
    return at, to


@app.command("eval-track", epilog=ONE_THREAD)
def eval_track_command(
    data: Annotated[
        Path,
        typer.Option(
            help="KITTI-layout sequence with poses (velodyne/, poses.txt)",
            exists=True,
            file_okay=False,
        ),
    ],
    out: Annotated[Path, typer.Option(help="folder for track.json and trajectory.png")] = Path(
        "eval-track"
    ),
    map_every: Annotated[int, typer.Option(min=1, help="map = every Nth scan")] = 5,
    map_until: Annotated[
        float | None, typer.Option(help="map = the scans of the first SECONDS instead")
    ] = None,
    encoder: EncoderOpt = None,
    kidnap: Annotated[
        list[str] | None,
        typer.Option(help="AT:TO: after scan AT the stream jumps to scan TO (repeatable)"),
    ] = None,
    max_scans: Annotated[int | None, typer.Option(min=1, help="use the first N scans")] = None,
    first_scan: Annotated[
        int, typer.Option(min=0, help="stream from this scan on (the map still spans all)")
    ] = 0,
    tracking: Annotated[
        str | None,
        typer.Option(help="the map's tracking settings as JSON, e.g. '{\"scan_voxel_m\": 0.7}'"),
    ] = None,
    coverage: Annotated[
        float, typer.Option(help="scans within this of a map keyframe count for availability (m)")
    ] = 5.0,
    progress: Annotated[bool, typer.Option(help="print progress lines")] = True,
    threads: ThreadsOpt = None,
) -> None:
    """Evaluate tracking: build a map from part of a sequence, stream every scan through
    the service's seeded localize with the SDK's motion model, compare with the ground
    truth (errors, availability, wrong fixes, time per mode, kidnap recovery)."""
    _cap_threads(threads)
    _exit_on_sigterm()  # the map folder it builds is removed
    _output_folder(out, "--out")
    from .core.errors import SgvlocError
    from .tools.eval_track import eval_track, report_lines

    _configure_logging("warning")
    jumps = [_kidnap(k) for k in kidnap or []]
    enc = _encoder_spec(encoder)
    settings = _tracking_settings(tracking)
    try:
        report = eval_track(
            data,
            out,
            map_every=map_every,
            map_until=map_until,
            encoder=enc,
            kidnaps=jumps,
            max_scans=max_scans,
            first_scan=first_scan,
            coverage_m=coverage,
            tracking=settings,
            progress=(lambda m: typer.echo(m, err=True)) if progress else None,
        )
    except (ValueError, SgvlocError) as exc:
        typer.echo(f"eval-track: {exc}", err=True)
        raise typer.Exit(1) from None
    for line in report_lines(report):
        typer.echo(line)
    typer.echo(f"wrote {out / 'track.json'} and {out / 'trajectory.png'}")


def _tracking_settings(text: str | None) -> dict[str, Any] | None:
    """``--tracking``: the map's tracking settings as JSON, checked; a usage error naming
    the option."""
    from pydantic import ValidationError

    from .core.config import TrackingConfig

    if text is None:
        return None
    try:
        settings = json.loads(text)
        TrackingConfig.model_validate(settings)
    except json.JSONDecodeError as exc:
        raise typer.BadParameter(f"not valid JSON: {exc}", param_hint="'--tracking'") from None
    except ValidationError as exc:
        raise typer.BadParameter(_why(exc, json_option=True), param_hint="'--tracking'") from None
    return settings


def _tracking_registration() -> dict[str, object]:
    """The default tracking settings a fitted confidence depends on (recorded with it)."""
    from .core.config import TrackingConfig

    t = TrackingConfig()
    keys = (
        "registration",
        "scan_voxel_m",
        "scan_neighbors",
        "vgicp_voxel_m",
        "vgicp_coarse_voxel_m",
        "stop_m",
        "stop_deg",
    )
    # the registration's code as well: its Hessian gives two of the features
    return {**{k: getattr(t, k) for k in keys}, "implementation": "sgvloc.core.gicp_numba"}


def _saved_samples(
    path: Path, data: list[str], check: list[str]
) -> tuple[list[dict], dict[str, list[dict]], list[str]]:
    """``--samples`` read back: (training fits, held-out fits per sequence, the training
    sequences they came from); a usage error naming the option when the file is not one
    this command wrote. A file of other sequences than --data/--check is used as it is,
    with a warning: the samples are what the fit sees."""
    try:
        saved = json.loads(path.read_text())
        train, held, came = saved["train"], saved["check"], saved.get("data", data)
        if not (isinstance(train, list) and isinstance(held, dict) and isinstance(came, list)):
            raise TypeError("train, check or data of another type")
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
        why = f"{path} is not a samples file of calibrate-track ({exc}); remove it to sample"
        raise typer.BadParameter(why, param_hint="'--samples'") from None
    if sorted(came) != sorted(data) or sorted(held) != sorted(check):
        typer.echo(
            f"calibrate-track: {path} holds the samples of --data {', '.join(came)} and "
            f"--check {', '.join(held) or '(none)'}; fitting those, not the sequences "
            "given (remove the file to sample them)",
            err=True,
        )
    return train, held, came


@app.command("calibrate-track", epilog=ONE_THREAD)
def calibrate_track_command(
    data: Annotated[
        list[str],
        typer.Option(
            help="training sequence with poses, DIR@N for its first N scans or DIR@A:B for "
            "scans A..B-1 (repeatable)"
        ),
    ],
    out: Annotated[Path, typer.Option(help="model file to write (JSON)")],
    check: Annotated[
        list[str] | None,
        typer.Option(help="held-out sequence to report on (DIR, DIR@N, DIR@A:B; repeatable)"),
    ] = None,
    map_every: Annotated[int, typer.Option(min=1, help="map = every Nth scan")] = 5,
    max_scans: Annotated[int | None, typer.Option(min=1, help="first N scans of each")] = None,
    draws: Annotated[int, typer.Option(min=1, help="perturbed seeds per scan")] = 3,
    encoder: EncoderOpt = None,
    threshold: Annotated[
        float | None,
        typer.Option(help="report acceptance at this confidence (default: the map default)"),
    ] = None,
    samples_file: Annotated[
        Path | None,
        typer.Option(
            "--samples",
            help="JSON of the fits: written after sampling, or read instead of sampling when "
            "it exists (to refit without re-running the registrations)",
        ),
    ] = None,
    progress: Annotated[bool, typer.Option(help="print progress lines")] = True,
    threads: ThreadsOpt = None,
) -> None:
    """Fit the confidence of tracked answers (P(fit within 2 m and 5 deg) from its
    fitness and RMSE) on sequences with ground truth, from seeds perturbed near and far;
    report it on held-out sequences. Ship the result as sgvloc/calibration/tracking.json."""
    _cap_threads(threads)
    _output_file(out, "--out")
    _output_file(samples_file, "--samples")
    from .core.config import VerdictConfig
    from .core.errors import SgvlocError
    from .core.files import write_text_whole
    from .tools.eval_track import confidence_figures, fit_track_confidence, track_samples

    _configure_logging("warning")
    say = (lambda m: typer.echo(m, err=True)) if progress else None
    cut = VerdictConfig().min_confidence if threshold is None else threshold
    options = dict(map_every=map_every, encoder=_encoder_spec(encoder), draws=draws)
    try:
        spans = {d: _scan_span(d, "--data") for d in data}
        spans.update({d: _scan_span(d, "--check") for d in check or []})

        def samples(spec: str, seed: int) -> list[dict[str, float]]:
            path, first, end = spans[spec]
            return track_samples(
                path,
                first_scan=first,
                max_scans=end or max_scans,
                seed=seed,
                progress=say,
                **options,
            )

        trained_on = list(data)
        fresh = samples_file is None or not samples_file.is_file()
        if not fresh:
            train, held, trained_on = _saved_samples(samples_file, data, check or [])
        else:
            train = [s for d in data for s in samples(d, 0)]
            held = {d: samples(d, 1) for d in check or []}
        model = fit_track_confidence(
            train,
            {
                "data": trained_on,
                "map_every": map_every,
                "draws": draws,
                "tracking": _tracking_registration(),
            },
        )
        if fresh and samples_file is not None:  # only the samples of a fit that worked
            saved = {"data": trained_on, "train": train, "check": held}
            write_text_whole(samples_file, json.dumps(saved))
        write_text_whole(out, json.dumps(model.to_dict(), indent=1) + "\n")
        typer.echo(f"training: {confidence_figures(train, model, cut)}")
        for d, fits in held.items():
            typer.echo(f"held out ({d}): {confidence_figures(fits, model, cut)}")
    except (ValueError, SgvlocError) as exc:
        typer.echo(f"calibrate-track: {exc}", err=True)
        raise typer.Exit(1) from None
    typer.echo(f"wrote {out} (acceptance figures at confidence >= {cut:g})")


@app.command("calibrate", epilog=ONE_THREAD)
def calibrate_command(
    ctx: typer.Context,
    out: Annotated[Path, typer.Option(help="calibration file to write (JSON)")],
    data: Annotated[
        list[Path] | None,
        typer.Option(help="sequence with ground truth (repeat for several); as for eval"),
    ] = None,
    from_: Annotated[
        list[Path] | None,
        typer.Option(
            "--from",
            help="an eval.json of sgvloc eval run with --methods sgv at the map's top_k "
            "(repeat for several; each with its own split)",
        ),
    ] = None,
    db_until: DbUntilOpt = None,
    min_gap: MinGapOpt = None,
    refine: Annotated[
        str, typer.Option(help="comma-separated: icp, none (3-D sequences run each)")
    ] = "icp,none",
    name: Annotated[str, typer.Option(help="name recorded in the calibration")] = "calibration",
    base: Annotated[
        str | None,
        typer.Option(
            help="a calibration file, or 'shipped' for the one shipped for the encoder's "
            "kind: profiles the answers do not cover are kept from it"
        ),
    ] = None,
    max_queries: Annotated[
        int | None,
        typer.Option(
            min=1, help="per sequence, at most N in-coverage and N out-of-coverage queries"
        ),
    ] = None,
    query_stride: Annotated[int, typer.Option(min=1, help="every n-th query")] = 1,
    encoder: EncoderOpt = None,
    config: Annotated[
        str | None,
        typer.Option(
            help="LocalizerConfig (top_k, sgv, pose settings): a JSON file, or the JSON itself"
        ),
    ] = None,
    cache_dir: CacheDirOpt = None,
    progress: ProgressOpt = True,
    threads: ThreadsOpt = None,
) -> None:
    """Fit the confidence model on sequences with ground truth.

    Takes the answers of `sgvloc eval` reports (--from) and/or runs each --data sequence
    the same way (SGV at the map's top_k, out-of-coverage queries kept); every answer's
    evidence and whether its pose is within 2 m and 5 deg train one logistic model per
    profile (with ICP, without). Give the file to a map (`calibration` in POST /v1/maps
    or PATCH /v1/maps/{map}) or to `sgvloc eval --calibration`. Calibrate on data you do
    not report on.
    """
    _cap_threads(threads)
    if data and (db_until is None) == (min_gap is None):
        raise typer.BadParameter(
            "--data sequences need one split: --db-until (time) or --min-gap (loops)",
            ctx=ctx,
            param_hint="'--db-until' / '--min-gap'",
        )
    localizer = _localizer_config(ctx, config)
    _output_file(out, "--out")
    from .core.confidence import Calibration, shipped_calibration
    from .core.encoders import EncoderSpec
    from .core.errors import SgvlocError
    from .tools.calibrate import calibrate

    _configure_logging("warning")
    modes = [m.strip() for m in refine.split(",") if m.strip()]
    if not modes or set(modes) - {"icp", "none"}:
        raise typer.BadParameter(
            f"expected icp and/or none, got {refine!r}", param_hint="'--refine'"
        )
    if "none" not in modes and base is None and not from_:  # no answers without ICP
        raise typer.BadParameter(
            "a calibration needs its answers without ICP too: add none (--refine icp,none), "
            "or keep that profile from --base (shipped or a file)",
            param_hint="'--refine'",
        )
    spec = _encoder_spec(encoder) or EncoderSpec()
    try:
        base_cal = None
        if base == "shipped":
            base_cal = shipped_calibration(spec.kind)
        elif base:
            base_cal = Calibration.load(base)
        cal = calibrate(
            data or [],
            reports=from_ or [],
            db_until=db_until,
            min_gap=min_gap,
            refine=modes,
            encoder=spec,
            localizer=localizer,
            max_queries=max_queries,
            query_stride=query_stride,
            cache_dir=cache_dir,
            name=name,
            base=base_cal,
            progress=progress,
            echo=typer.echo,
        )
    except ValueError as exc:
        typer.echo(f"calibrate: {_why(exc)}", err=True)
        raise typer.Exit(2) from None
    except SgvlocError as exc:
        typer.echo(f"calibrate: {exc}", err=True)
        raise typer.Exit(1) from None
    out.parent.mkdir(parents=True, exist_ok=True)
    cal.save(out)
    typer.echo(f"wrote {out} (calibration {cal.name}, fingerprint {cal.fingerprint})")


@app.command("synth", epilog=ONE_THREAD)
def synth_command(
    out: Annotated[Path, typer.Argument(help="output folder (KITTI layout)")],
    scans: Annotated[int, typer.Option(min=1, help="number of scans")] = 400,
    seed: Annotated[int, typer.Option(help="random seed (same seed, same files)")] = 0,
    beams: Annotated[int, typer.Option(min=8, max=128, help="LiDAR beams")] = 32,
    fov: Annotated[
        float,
        typer.Option(
            max=360.0,
            callback=_above_zero,
            help="horizontal field of view (deg) about the forward axis",
        ),
    ] = 360.0,
    pattern: Annotated[
        str,
        typer.Option(help="spinning (rings) or rosette (non-repetitive, solid-state)"),
    ] = "spinning",
    fov_up: Annotated[float, typer.Option(help="upper edge of the vertical spread (deg)")] = 15.0,
    fov_down: Annotated[
        float, typer.Option(help="lower edge of the vertical spread (deg)")
    ] = -25.0,
    max_range: Annotated[float, typer.Option(min=1.0, help="LiDAR range (m)")] = 80.0,
    step: Annotated[float, typer.Option(min=0.01, help="distance between scans (m)")] = 1.0,
    overwrite: Annotated[bool, typer.Option(help="replace an existing sequence")] = False,
    progress: Annotated[bool, typer.Option(help="show a progress bar")] = True,
    threads: ThreadsOpt = None,
) -> None:
    """Generate a synthetic town with repeated blocks and a revisiting LiDAR drive.

    The sensor: --beams rings over --fov-down..--fov-up, a 360-degree spinning LiDAR by
    default; --fov 70 narrows it to a forward-looking window, --pattern rosette scans it
    with a non-repetitive petal pattern (solid-state sensors), --max-range and --step set
    its range and the spacing of the scans (keyframes).
    """
    _cap_threads(threads)
    _exit_on_sigterm()  # the staging folder is removed
    _output_folder(out, "OUT")
    from pydantic import ValidationError

    from .core.errors import SgvlocError
    from .tools.synth import SynthConfig, generate

    _configure_logging("warning")
    try:
        cfg = SynthConfig(
            scans=scans,
            seed=seed,
            beams=beams,
            fov_h_deg=fov,
            pattern=pattern,
            fov_up_deg=fov_up,
            fov_down_deg=fov_down,
            max_range_m=max_range,
            step_m=step,
        )
        info = generate(
            out,
            cfg,
            overwrite=overwrite,
            progress=progress,
        )
    except ValidationError as exc:  # a setting out of range: a usage error
        names = {"fov_h_deg": "--fov", "fov_up_deg": "--fov-up", "fov_down_deg": "--fov-down"}
        names.update(max_range_m="--max-range", step_m="--step")
        typer.echo(f"synth: {_why(exc, names)}", err=True)
        raise typer.Exit(2) from None
    except (ValueError, SgvlocError) as exc:
        typer.echo(f"synth: {exc}", err=True)
        raise typer.Exit(1) from None
    typer.echo(
        f"wrote {info['scans']} scans to {out} "
        f"({info['route_m']:.0f} m route, {info['blocks']} blocks)"
    )


# -- bench and train (sgvloc.tools.bench, sgvloc.tools.train) -----------------------------


@app.command("bev-images", epilog=ONE_THREAD)
def bev_images_command(
    src: Annotated[Path, typer.Argument(help="KITTI-layout scan sequence (velodyne/, poses.txt)")],
    out: Annotated[Path, typer.Argument(help="output folder (kitti-bev layout)")],
    overwrite: Annotated[bool, typer.Option(help="replace existing images")] = False,
    progress: Annotated[bool, typer.Option(help="show a progress bar")] = True,
    threads: ThreadsOpt = None,
) -> None:
    """Write a scan sequence as kitti-bev images (imgs/*.png, pose.txt, times.txt)."""
    _cap_threads(threads)
    _exit_on_sigterm()  # the staging folder is removed
    _output_folder(out, "OUT")
    from .core.errors import SgvlocError
    from .tools.bev_images import export_bev_images

    try:
        n = export_bev_images(src, out, overwrite=overwrite, progress=progress)
    except SgvlocError as exc:
        typer.echo(f"bev-images: {exc}", err=True)
        raise typer.Exit(1) from None
    typer.echo(f"wrote {n} images to {out}")


@app.command("bench", epilog=ONE_THREAD)
def bench_command(
    ctx: typer.Context,
    only: Annotated[
        str,
        typer.Option(
            help="comma-separated sections: rerank, retrieval, encoding, pipeline, http, "
            "scaling, prior, tracking, cluster (PostgreSQL: not in the default list)"
        ),
    ] = "rerank,retrieval,encoding,pipeline,http,scaling,prior,tracking",
    compare: Annotated[
        bool,
        typer.Option(
            help="pipeline, http: also run the earlier path (network in torch, Open3D ICP) "
            "in the same run, interleaved, and report ratios"
        ),
    ] = False,
    out: Annotated[Path, typer.Option(help="JSON file with every figure")] = Path("bench.json"),
    ks: Annotated[str, typer.Option(help="rerank: candidates per query")] = "2,5,10,20,50",
    ns: Annotated[str, typer.Option(help="rerank: keypoints (correspondences)")] = "128,256,1000",
    large_ns: Annotated[str, typer.Option(help="rerank: SGV alone, k=1")] = "5000,15000",
    repeats: Annotated[int, typer.Option(min=1, help="rerank: timed runs per point")] = 7,
    rir: Annotated[bool, typer.Option(help="rerank: run RANSAC-RIR and FGR-RIR")] = True,
    rir_max_k: Annotated[int, typer.Option(help="rerank: RIR only up to this k")] = 20,
    sizes: Annotated[str, typer.Option(help="retrieval: database sizes")] = "10000,100000,1000000",
    dim: Annotated[int, typer.Option(help="retrieval: descriptor dimension")] = 620,
    large_dim: Annotated[
        int, typer.Option(help="retrieval: dimension from 500k descriptors on")
    ] = 256,
    hnsw_max: Annotated[int, typer.Option(help="retrieval: HNSW up to this size")] = 100000,
    scan_sizes: Annotated[str, typer.Option(help="encoding: points per scan")] = "25000,120000",
    http_keyframes: Annotated[int, typer.Option(min=1, help="http: keyframes in the map")] = 10000,
    http_clients: Annotated[str, typer.Option(help="http: concurrent clients")] = "1,4,16",
    http_duration: Annotated[
        float, typer.Option(min=0.1, help="http: seconds of localize per client count")
    ] = 8.0,
    http_batch: Annotated[int, typer.Option(min=1, help="http: keyframes per insert")] = 250,
    raw_scans: Annotated[int, typer.Option(min=0, help="http: raw scans to insert")] = 24,
    raw_batch: Annotated[int, typer.Option(min=1, help="http: raw scans per insert")] = 8,
    batch_wait_ms: Annotated[
        float,
        typer.Option(
            min=0.0,
            help="http: also load a second service with dynamic batching on (this wait, ms) "
            "at every client count; 0 = not measured",
        ),
    ] = 0.0,
    scale_sizes: Annotated[
        str, typer.Option(help="scaling: map sizes (keyframes)")
    ] = "1000,3000,10000,30000,100000",
    scale_clients: Annotated[str, typer.Option(help="scaling: concurrent clients")] = "1,4",
    scale_duration: Annotated[
        float, typer.Option(min=0.1, help="scaling: seconds of localize per client count")
    ] = 3.0,
    scale_batch: Annotated[int, typer.Option(min=1, help="scaling: keyframes per insert")] = 1000,
    scale_keypoints: Annotated[
        int, typer.Option(min=1, help="scaling: keypoints per keyframe (map encoder)")
    ] = 64,
    scale_reload: Annotated[
        bool, typer.Option(help="scaling: restart on the largest map, time until ready")
    ] = True,
    plot: Annotated[
        Path | None, typer.Option(help="scaling: PNG of the curves (default: next to --out)")
    ] = None,
    service_workers: Annotated[
        int, typer.Option(min=1, help="http, scaling: --workers of the started service")
    ] = 2,
    prior_sizes: Annotated[str, typer.Option(help="prior: map sizes (keyframes)")] = "10000,100000",
    prior_radius: Annotated[float, typer.Option(min=0.1, help="prior: radius (m)")] = 20.0,
    prior_noise: Annotated[
        float, typer.Option(min=0.0, help="prior: position noise per axis (m)")
    ] = 5.0,
    pipeline_data: Annotated[
        Path | None,
        typer.Option(
            help="pipeline: KITTI-layout sequence (default: the shipped fixture)",
            exists=True,
            file_okay=False,
        ),
    ] = None,
    pipeline_map_every: Annotated[
        int, typer.Option(min=2, help="pipeline: the map is every Nth scan, queries the rest")
    ] = 2,
    pipeline_rounds: Annotated[
        int, typer.Option(min=1, help="pipeline: timed rounds over the queries")
    ] = 3,
    track_data: Annotated[
        Path | None,
        typer.Option(
            help="tracking: KITTI-layout sequence (default: the shipped fixture)",
            exists=True,
            file_okay=False,
        ),
    ] = None,
    track_map_every: Annotated[
        int, typer.Option(min=1, help="tracking: the map is every Nth scan")
    ] = 2,
    cluster_store: Annotated[
        str | None,
        typer.Option(
            help="cluster: postgresql:// URL of a database to fill (default: a throwaway "
            "cluster from the system's postgresql package)"
        ),
    ] = None,
    cluster_sizes: Annotated[
        str, typer.Option(help="cluster: catch-up map sizes (keyframes)")
    ] = "10000,100000",
    cluster_visible: Annotated[
        int, typer.Option(min=1, help="cluster: inserts timed until the other replica has them")
    ] = 50,
    cluster_keypoints: Annotated[
        int, typer.Option(min=1, help="cluster: keypoints per synthetic keyframe")
    ] = 64,
    cluster_clients: Annotated[
        int, typer.Option(min=1, help="cluster: SDK clients for one vs two replicas")
    ] = 4,
    cluster_duration: Annotated[
        float, typer.Option(min=0.1, help="cluster: seconds of localize per replica count")
    ] = 8.0,
    threads: ThreadsOpt = None,
) -> None:
    """Measure re-ranking, retrieval, encoding, one localization by stage (pipeline), the
    service end to end (http, scaling), localize with a prior (prior), tracked against
    global localize (tracking) and replicas over PostgreSQL (cluster: insert-to-visible,
    catch-up, features fetched per query, one vs two replicas); print tables and write
    --out (JSON).

    Medians after warm-up, every comparison in one process on the same inputs. The
    defaults take a few minutes on 2 cores; CUDA timings of SGV are added when a GPU is
    present. http and scaling start the service on 127.0.0.1 (--dev, temporary data)
    and load it from a second process (see sgvloc.tools.bench.http).
    """
    _cap_threads(threads)
    _exit_on_sigterm()  # the services, clusters and folders it starts are cleaned up
    _output_file(out, "--out")
    from .core.errors import SgvlocError
    from .tools.bench import check_sections, run_bench

    _configure_logging("warning")
    options = {k: v for k, v in ctx.params.items() if k not in ("only", "out", "threads")}
    for key in ("ks", "ns", "large_ns", "sizes", "scan_sizes", "http_clients",
                "scale_sizes", "scale_clients", "prior_sizes", "cluster_sizes"):  # fmt: skip
        options[key] = _int_list(options[key], "--" + key.replace("_", "-"), positive=True)
    try:
        sections = check_sections([x.strip() for x in only.split(",") if x.strip()])
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--only") from None
    try:
        run_bench(sections, options, out, typer.echo)
    except (ValueError, SgvlocError) as exc:  # data or values a section cannot use
        typer.echo(f"bench: {exc}", err=True)
        raise typer.Exit(2) from None


@app.command("train", epilog=_threads_epilog("every usable core (one large torch job)"))
def train_command(
    data: Annotated[
        list[Path],
        typer.Option(
            help="training sequence: kitti-bev folder (imgs/, pose.txt) or KITTI-layout scans "
            "(velodyne/, poses.txt, times.txt; levelled and rasterised to BEV images); repeat"
        ),
    ],
    out: Annotated[Path, typer.Option(help="folder for checkpoint.pt, curves.png, log.json")],
    val: Annotated[
        list[Path] | None, typer.Option(help="held-out sequence for validation curves; repeat")
    ] = None,
    steps: Annotated[int, typer.Option(min=1, help="optimiser steps in all")] = 3000,
    batch: Annotated[
        int,
        typer.Option(
            min=1,
            max=64,
            help="scan pairs per step (each holds about 40 MB while a step runs on CPU)",
        ),
    ] = 8,
    seed: Annotated[int, typer.Option(help="random seed")] = 0,
    device: Annotated[str, typer.Option(help="cpu | cuda | auto")] = "cpu",
    resume: Annotated[bool, typer.Option(help="continue from OUT/checkpoint.pt")] = True,
    lr: Annotated[float, typer.Option(min=0.0, help="learning rate (AdamW)")] = 1e-3,
    init: Annotated[
        Path | None,
        typer.Option(help="start from these weights (sgvloc export-weights): fine-tune"),
    ] = None,
    fov_crop: Annotated[
        float,
        typer.Option(
            min=0.0,
            max=1.0,
            help="share of training images cropped to a 60-120 deg field of view ahead "
            "(forward-looking sensors)",
        ),
    ] = 0.0,
    threads: ThreadsOpt = None,
) -> None:
    """Train the learned BEV encoder (a small CNN) on BEV image sequences with poses."""
    if device not in ("cpu", "cuda", "auto"):
        raise typer.BadParameter(f"{device!r} is not cpu, cuda or auto", param_hint="'--device'")
    from .server.threads import usable_cpus

    _cap_threads(threads, usable_cpus())
    _output_folder(out, "--out")
    _exit_on_sigterm()  # the steps since the last checkpoint are saved
    from .core.errors import SgvlocError
    from .tools.train import Sequence, TrainConfig, train

    _configure_logging("info")
    try:
        cfg = TrainConfig(
            steps=steps,
            batch=batch,
            seed=seed,
            device=device,
            lr=lr,
            init=None if init is None else str(init),
            fov_crop=fov_crop,
        )
        seqs = [Sequence.load(p) for p in data]
        vals = [Sequence.load(p) for p in val or []]
        ckpt = train(seqs, out, cfg, vals, resume=resume)
    except SgvlocError as exc:
        typer.echo(f"sgvloc train: {exc}", err=True)
        raise typer.Exit(2) from None
    typer.echo(f"wrote {ckpt}")


@app.command("export-weights", epilog=ONE_THREAD)
def export_weights_command(
    checkpoint: Annotated[Path, typer.Argument(help="checkpoint.pt written by 'sgvloc train'")],
    out: Annotated[Path, typer.Argument(help="weights file to write (use as model_path)")],
    note: Annotated[str, typer.Option(help="free text stored in the file")] = "",
    threads: ThreadsOpt = None,
) -> None:
    """Export a training checkpoint as weights for the 'learned' encoder kind.

    A map uses them with the encoder spec {"kind": "learned", "model_path": OUT}.
    """
    _cap_threads(threads)
    _output_file(out, "OUT")
    from .core.errors import SgvlocError
    from .tools.train import export_weights

    try:
        path = export_weights(checkpoint, out, note)
    except SgvlocError as exc:
        typer.echo(f"sgvloc export-weights: {exc}", err=True)
        raise typer.Exit(2) from None
    typer.echo(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB)")
    typer.echo(f"for ONNX Runtime on CPU: sgvloc export-onnx {path}")


@app.command("export-onnx", epilog=ONE_THREAD)
def export_onnx_command(
    weights: Annotated[
        Path | None,
        typer.Argument(help="weights file of the 'learned' encoder (default: the shipped one)"),
    ] = None,
    out: Annotated[
        Path | None, typer.Option(help="ONNX file to write (default: WEIGHTS with suffix .onnx)")
    ] = None,
    threads: ThreadsOpt = None,
) -> None:
    """Export the network of a weights file to ONNX, beside it, for ONNX Runtime.

    The 'learned' encoder runs the network in ONNX Runtime on CPU when onnxruntime is
    installed and WEIGHTS.onnx was exported from these weights (runtime 'auto'); the
    package ships one for its own weights. Needs the onnx and onnxscript packages
    (the dev extra).
    """
    _cap_threads(threads)
    _output_file(out, "--out")
    from .core.encoders.learned import shipped_weights_path
    from .core.errors import SgvlocError
    from .tools.train import export_onnx

    try:
        path = export_onnx(weights or shipped_weights_path(), out)
    except SgvlocError as exc:
        typer.echo(f"sgvloc export-onnx: {exc}", err=True)
        raise typer.Exit(2) from None
    typer.echo(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB)")


# -- map management on a running service (the SDK only: works with the client install) --

map_app = typer.Typer(
    help="Manage the maps of a running service: list, statistics, keyframes, bulk "
    "delete, export and import archives.",
    no_args_is_help=True,
)
app.add_typer(map_app, name="map")

UrlOpt = Annotated[str, typer.Option(help="base URL of the service", envvar="SGVLOC_URL")]
KeyOpt = Annotated[
    str | None,
    typer.Option(
        "--api-key",
        help="bearer token (viewer reads; mapper/admin writes)",
        envvar="SGVLOC_API_KEY",
    ),
]
TimeoutOpt = Annotated[float, typer.Option(min=0.001, help="seconds to wait for the service")]
KeyPrefixOpt = Annotated[str | None, typer.Option(help="keyframes whose key starts with this")]
BboxOpt = Annotated[
    str | None, typer.Option(help="x_min,y_min,x_max,y_max: positions inside this box")
]
TimeMinOpt = Annotated[float | None, typer.Option(help="metadata timestamp >= this")]
TimeMaxOpt = Annotated[float | None, typer.Option(help="metadata timestamp <= this")]
SequenceOpt = Annotated[str | None, typer.Option(help="metadata sequence equal to this")]
DEFAULT_URL = "http://127.0.0.1:8470"


def _filters(
    key_prefix: str | None,
    bbox: str | None,
    time_min: float | None,
    time_max: float | None,
    sequence: str | None,
) -> dict[str, Any]:
    box = None
    if bbox is not None:
        try:
            box = [float(v) for v in bbox.split(",")]
        except ValueError:
            box = []
        if len(box) != 4:
            raise typer.BadParameter("four numbers: x_min,y_min,x_max,y_max", param_hint="'--bbox'")
    return dict(
        key_prefix=key_prefix, bbox=box, time_min=time_min, time_max=time_max, sequence=sequence
    )


def _sdk_call(command: str, fn: Callable[[], T]) -> T:
    """Run ``fn`` and turn the SDK's errors into one line on stderr (exit 1)."""
    import sgvloc_client

    try:
        return fn()
    except BrokenPipeError:  # the reader went away (| head): click exits 1 quietly
        raise
    except (sgvloc_client.SgvlocError, OSError) as exc:
        typer.echo(f"sgvloc map {command}: {_sdk_error(exc)}", err=True)
        raise typer.Exit(1) from None


def _sdk_error(exc: Exception) -> str:
    """An SDK error as the CLI says it: a missing or unknown key (401) names the option
    that gives one."""
    import sgvloc_client

    if isinstance(exc, sgvloc_client.Unauthorized):
        return f"{exc} (the CLI sends the key given by --api-key or SGVLOC_API_KEY)"
    return str(exc)


def _sdk(url: str, api_key: str | None, timeout: float) -> Any:
    """A :class:`sgvloc_client.Client` (imported here: the CLI starts without httpx); a
    URL it cannot use is a usage error naming ``--url``."""
    import httpx

    import sgvloc_client

    try:
        return sgvloc_client.Client(url, timeout=timeout, api_key=api_key)
    except (httpx.InvalidURL, ValueError) as exc:
        raise typer.BadParameter(f"{url!r}: {exc}", param_hint="'--url'") from None


@map_app.command("list")
def map_list_command(
    url: UrlOpt = DEFAULT_URL,
    api_key: KeyOpt = None,
    timeout: TimeoutOpt = 30.0,
    prefix: Annotated[
        str | None, typer.Option(help="only the maps whose name starts with this")
    ] = None,
) -> None:
    """The maps with keyframes, version and encoder, one per line, by name."""
    with _sdk(url, api_key, timeout) as c:
        maps = _sdk_call("list", lambda: c.list_maps(prefix=prefix))
    for m in maps:
        typer.echo(f"{m.name}\t{m.keyframes} keyframes\tversion {m.version}\t{m.encoder.kind}")


@map_app.command("stats")
def map_stats_command(
    map_name: Annotated[str, typer.Argument(metavar="MAP")],
    url: UrlOpt = DEFAULT_URL,
    api_key: KeyOpt = None,
    timeout: TimeoutOpt = 30.0,
) -> None:
    """A map's statistics as JSON: keyframes, extent, disk and memory use, index kind,
    last write."""
    with _sdk(url, api_key, timeout) as c:
        s = _sdk_call("stats", lambda: c.map_stats(map_name))
    typer.echo(json.dumps(_stats_dict(s), indent=1))


def _stats_dict(s: Any) -> dict[str, Any]:
    return {
        "map": s.map,
        "version": s.version,
        "keyframes": s.keyframes,
        "extent": None
        if s.extent is None
        else {"min": s.extent[0].tolist(), "max": s.extent[1].tolist()},
        "disk_bytes": s.disk_bytes,
        "memory_bytes": s.memory_bytes,
        "index_kind": s.index_kind,
        "created_at": s.created_at,
        "last_write": s.last_write,
    }


@map_app.command("self-test")
def map_self_test_command(
    map_name: Annotated[str, typer.Argument(metavar="MAP")],
    queries: Annotated[
        int, typer.Option(min=1, max=200, help="at most this many queries with a revisit")
    ] = 50,
    gap_s: Annotated[
        float, typer.Option(help="leave out each query's keyframes closer in time (seconds)")
    ] = 30.0,
    gap_keyframes: Annotated[
        int, typer.Option(min=1, help="the same in insertion order, without timestamps")
    ] = 30,
    radius_m: Annotated[float, typer.Option(help="a keyframe this close is a revisit")] = 5.0,
    encoders: Annotated[
        str | None,
        typer.Option(
            help="also measure these encoders (comma-separated: learned, handcrafted, "
            "bev, learned-fpfh; or all) on the same queries, from the keyframes' stored "
            "clouds, and name the best"
        ),
    ] = None,
    as_json: Annotated[
        bool, typer.Option("--json", help="print the whole report (with per-query records)")
    ] = False,
    url: UrlOpt = DEFAULT_URL,
    api_key: KeyOpt = None,
    timeout: TimeoutOpt = 600.0,
) -> None:
    """Localize a sample of a served map's own keyframes against the others, each one's
    own stretch of the drive left out (POST /v1/maps/{map}/self-test): Recall@1, pose
    success, correct answers accepted and false accepts; recorded with the map. With
    --encoders, other encoders are measured alike and the best is named."""
    from .core import leave_out

    names = None
    if encoders is not None:
        names = [e.strip() for e in encoders.split(",") if e.strip()]
        names = list(leave_out.CANDIDATES) if names == ["all"] else names
        if not names:
            raise typer.BadParameter("name at least one encoder", param_hint="--encoders")
        typer.echo(
            f"self-test of {map_name!r} with {len(names)} encoder(s): each encodes the "
            "map's keyframes again (0.03-0.15 s per keyframe and encoder on 2 cores); "
            f"waiting up to {timeout:g} s (--timeout)",
            err=True,
        )
    with _sdk(url, api_key, timeout) as c:
        rep = _sdk_call(
            "self-test",
            lambda: c.self_test_map(
                map_name,
                queries=queries,
                gap_s=gap_s,
                gap_keyframes=gap_keyframes,
                radius_m=radius_m,
                encoders=names,
                timeout=timeout,
            ),
        )
    if as_json:
        typer.echo(json.dumps(rep, indent=1))
        return
    f = rep["figures"]

    def pct(v: float | None) -> str:
        return "-" if v is None else f"{v:.1f}"

    typer.echo(
        f"map {map_name!r} (version {rep['map_version']}, {rep['encoder']} encoder), "
        f"gap by {rep['basis']}, {rep['seconds']:.1f} s"
    )
    typer.echo(
        "| queries | negatives | R@1 % | pose success % | correct accepted % | "
        "false accepts | median ms |"
    )
    typer.echo("|---:|---:|---:|---:|---:|---:|---:|")
    typer.echo(
        f"| {f['queries']} | {f['negatives']} | {pct(f['recall_at_1'])} | "
        f"{pct(f['pose_success'])} | {pct(f['accepted_of_correct'])} | "
        f"{f['false_accepts']} | {pct(f['median_ms'])} |"
    )
    if not rep.get("encoders"):
        return
    typer.echo("")
    typer.echo(
        "| encoder | R@1 % | pose success % | localized correctly | false accepts | "
        "not encoded | seconds |"
    )
    typer.echo("|---|---:|---:|---:|---:|---:|---:|")
    for name, e in rep["encoders"].items():
        g = e["figures"]
        mark = " (chosen)" if name == rep["chosen"] else ""
        typer.echo(
            f"| {name}{mark} | {pct(g['recall_at_1'])} | {pct(g['pose_success'])} | "
            f"{g['localized_correct']} of {g['queries']} | {g['false_accepts']} | "
            f"{e['unencoded']} | {e['seconds']:.1f} |"
        )
    typer.echo(f"chosen: {rep['chosen']} ({rep['rule']})")
    if rep.get("warning"):
        typer.echo(f"warning: {rep['warning']}")


@map_app.command("keyframes")
def map_keyframes_command(
    map_name: Annotated[str, typer.Argument(metavar="MAP")],
    key_prefix: KeyPrefixOpt = None,
    bbox: BboxOpt = None,
    time_min: TimeMinOpt = None,
    time_max: TimeMaxOpt = None,
    sequence: SequenceOpt = None,
    url: UrlOpt = DEFAULT_URL,
    api_key: KeyOpt = None,
    timeout: TimeoutOpt = 30.0,
) -> None:
    """The keyframes matching the filters, one JSON object per line (id, key, position,
    metadata, created_at), every page."""
    where = _filters(key_prefix, bbox, time_min, time_max, sequence)
    with _sdk(url, api_key, timeout) as c:

        def run() -> None:
            for kf in c.iter_keyframes(map_name, **where):
                line = {
                    "id": kf.id,
                    "key": kf.key,
                    "position": kf.position.tolist(),
                    "metadata": kf.metadata,
                    "created_at": kf.created_at,
                }
                typer.echo(json.dumps(line))

        _sdk_call("keyframes", run)


@map_app.command("delete-keyframes")
def map_delete_keyframes_command(
    map_name: Annotated[str, typer.Argument(metavar="MAP")],
    key_prefix: KeyPrefixOpt = None,
    bbox: BboxOpt = None,
    time_min: TimeMinOpt = None,
    time_max: TimeMaxOpt = None,
    sequence: SequenceOpt = None,
    all_keyframes: Annotated[
        bool, typer.Option("--all", help="delete every keyframe (when no filter is given)")
    ] = False,
    url: UrlOpt = DEFAULT_URL,
    api_key: KeyOpt = None,
    timeout: TimeoutOpt = 30.0,
) -> None:
    """Delete the keyframes matching the filters in one transaction (mapper/admin)."""
    where = _filters(key_prefix, bbox, time_min, time_max, sequence)
    if all(v is None for v in where.values()) and not all_keyframes:
        raise typer.BadParameter("give a filter, or --all to delete every keyframe")
    with _sdk(url, api_key, timeout) as c:
        r = _sdk_call(
            "delete-keyframes", lambda: c.delete_keyframes(map_name, all=all_keyframes, **where)
        )
    typer.echo(f"map {map_name}: {r.deleted} keyframes deleted, version {r.map_version}")


@map_app.command("export")
def map_export_command(
    map_name: Annotated[str, typer.Argument(metavar="MAP")],
    file: Annotated[Path, typer.Argument(help="the archive to write", dir_okay=False)],
    force: Annotated[bool, typer.Option(help="overwrite FILE if it exists")] = False,
    url: UrlOpt = DEFAULT_URL,
    api_key: KeyOpt = None,
    timeout: TimeoutOpt = 600.0,
) -> None:
    """Download MAP as one archive file (mapper/admin): settings, encoder identity,
    calibration, version, every keyframe with features and cloud, checksums. Streamed;
    written aside and renamed when complete, so FILE is never half an archive."""
    import time

    if file.exists() and not force:
        raise typer.BadParameter(f"{file} exists (--force to overwrite)", param_hint="'FILE'")
    part = file.with_name(file.name + ".part")
    t0 = time.perf_counter()
    with _sdk(url, api_key, timeout) as c:
        try:
            size = _sdk_call("export", lambda: c.export_map(map_name, part, timeout=timeout))
        except BaseException:
            part.unlink(missing_ok=True)
            raise
    part.replace(file)
    typer.echo(
        f"map {map_name}: {size / 1e6:.1f} MB written to {file} in {time.perf_counter() - t0:.1f} s"
    )


@map_app.command("import")
def map_import_command(
    file: Annotated[
        Path,
        typer.Argument(help="an archive from `sgvloc map export`", exists=True, dir_okay=False),
    ],
    name: Annotated[
        str | None, typer.Option(help="the new map's name (default: the archived name)")
    ] = None,
    url: UrlOpt = DEFAULT_URL,
    api_key: KeyOpt = None,
    timeout: TimeoutOpt = 600.0,
) -> None:
    """Create a map from an archive (mapper/admin), streamed to the service: the same
    keyframes, ids, version and settings, so the same answers. A damaged or foreign
    archive is refused and leaves nothing behind."""
    import time

    t0 = time.perf_counter()
    with _sdk(url, api_key, timeout) as c:
        info = _sdk_call("import", lambda: c.import_map(file, name, timeout=timeout))
    typer.echo(
        f"map {info.name}: {info.keyframes} keyframes, version {info.version}, imported in "
        f"{time.perf_counter() - t0:.1f} s"
    )


def interruption_exit_code(exc: BaseException) -> int | None:
    """The exit code of a Ctrl-C (130) or SIGTERM (its ``SystemExit``) that reached a
    compiled kernel's call back into Python and came out as a ``SystemError`` with the
    interruption as its cause; None for any other error."""
    seen: BaseException | None = exc
    for _ in range(16):
        seen = seen.__cause__ or seen.__context__
        if seen is None:
            return None
        if isinstance(seen, KeyboardInterrupt):
            return 130
        if isinstance(seen, SystemExit):
            return seen.code if isinstance(seen.code, int) else 1
    return None


def main() -> None:
    """Entry point of the ``sgvloc`` console script."""
    try:
        app()
    except SystemError as exc:  # an interruption inside numba: exit as one, quietly
        code = interruption_exit_code(exc)
        if code is None:
            raise
        import sys

        typer.echo("interrupted", err=True)
        sys.exit(code)
    except ModuleNotFoundError as exc:
        if (exc.name or "").split(".")[0] not in SERVICE_MODULES:
            raise
        import sys

        command = next((a for a in sys.argv[1:] if not a.startswith("-")), "")
        typer.echo(
            f"sgvloc {command}: needs the service extra (module {exc.name!r} is missing): "
            "pip install -e '.[service]' after the CPU build of torch (README, Install)",
            err=True,
        )
        sys.exit(2)


if __name__ == "__main__":
    main()
