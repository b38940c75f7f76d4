"""Service settings, read once from the environment (prefix ``SGVLOC_``).

Every field can be set as ``SGVLOC_<FIELD>`` (e.g. ``SGVLOC_DATA_DIR=/srv/maps``) or
overridden by the ``sgvloc serve`` options.
"""

from __future__ import annotations

import difflib
from collections.abc import Mapping
from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from .threads import usable_cpus

LogLevel = Literal["critical", "error", "warning", "info", "debug"]
ProbeAuth = Literal["open", "viewer"]


class Settings(BaseSettings):
    """Configuration of one service process."""

    model_config = SettingsConfigDict(env_prefix="SGVLOC_", extra="forbid")

    host: str = Field("127.0.0.1", description="interface to bind (0.0.0.0 in containers)")
    port: int = Field(8470, ge=1, le=65535)
    data_dir: Path = Field(Path("./data"), description="maps live in <data_dir>/maps/<name>/")
    store_url: str | None = Field(
        None,
        description="postgresql://user:password@host:port/db: keep every map in PostgreSQL, "
        "shared by any number of replicas (each follows the others' writes); unset: one "
        "SQLite database per map under data_dir",
    )
    store_password_file: Path | None = Field(
        None,
        description="a file holding the PostgreSQL password (a container secret), so "
        "that store_url need not carry it",
    )
    store_pool_size: int = Field(
        8, ge=2, le=200, description="connections each replica keeps to a PostgreSQL store"
    )
    follow_poll_s: float = Field(
        1.0,
        gt=0,
        le=60,
        description="PostgreSQL store: longest time between two catch-ups with the other "
        "replicas' writes (announced writes are applied at once)",
    )
    local_features: Literal["memory", "store"] = Field(
        "memory",
        description="store: keep only keyframe poses and global descriptors in memory and "
        "fetch the retrieved candidates' local features and clouds from the store per "
        "localization (one read), through an LRU cache of feature_cache keyframes per map",
    )
    feature_cache: int = Field(
        4096, ge=1, description="local_features=store: keyframes cached per map"
    )
    catch_up_wait_s: float = Field(
        2.0,
        ge=0,
        le=30,
        description="longest a localize with min_map_version waits for this replica to "
        "catch up; beyond it 503 stale with Retry-After",
    )
    workers: int = Field(
        2, ge=1, le=256, description="threads running CPU work (encode, search, re-rank, pose)"
    )
    write_workers: int | None = Field(
        None,
        ge=1,
        le=256,
        description="of the workers, how many may run map changes and long jobs at once "
        "(keyframe inserts and deletes, map creation, reload, deletion and import, "
        "self-tests), so that localizations always find workers - write_workers of them "
        "free of such work. Default: workers - 1 (at least 1); at most workers",
    )
    threads_per_worker: int | None = Field(
        None,
        ge=1,
        le=256,
        description="threads that the numeric libraries (OpenMP in Open3D and FAISS, BLAS, "
        "numba, torch) may use inside one request. Default: usable cores // workers, at "
        "least 1, so that the worker threads do not oversubscribe the cores",
    )
    spare_cores: bool = Field(
        True,
        description="let a request use the cores no other request is using: the network "
        "forward (ONNX Runtime) and ICP with its fitness pass take usable cores // busy workers "
        "threads, so that one request alone on an idle service answers sooner; the answers "
        "are the same at any thread count. false: threads_per_worker always",
    )
    batch_wait_ms: float | None = Field(
        None,
        ge=0.0,
        le=100.0,
        description="dynamic batching: how long the first of concurrent localizations waits "
        "for others to share one network forward and one SGV kernel call (0 = off). "
        "Default: 2 ms when CUDA is present, else off (on CPU a batch is no cheaper per "
        "scan; sgvloc bench --only http --batch-wait-ms measures it)",
    )
    batch_max: int = Field(16, ge=1, le=256, description="dynamic batching: largest batch")
    max_body_bytes: int = Field(64 * 1024 * 1024, ge=1024, description="413 above this")
    max_body_memory_bytes: int | None = Field(
        None,
        ge=1024,
        description="request bodies held in memory at once, over all requests (received or "
        "being handled); a body that would pass it is answered 503 overloaded with "
        "Retry-After. Default 4 x max_body_bytes; at least max_body_bytes",
    )
    max_json_body_bytes: int = Field(
        8 * 1024 * 1024,
        ge=1024,
        description="413 above this for a JSON body (parsing JSON holds the interpreter for "
        "the whole body; large bodies go as MessagePack, whose arrays are bytes)",
    )
    max_batch: int = Field(1000, ge=1, description="keyframes per insert request")
    max_import_bytes: int = Field(
        64 * 1024**3,
        ge=1024,
        le=2**50,
        description="largest map archive POST /v1/map-archives takes (streamed to the data "
        "directory, never held in memory); 413 above this",
    )
    max_points: int = Field(500_000, ge=1, le=10_000_000, description="points per scan")
    max_keypoints: int = Field(
        4096,
        ge=1,
        le=100_000,
        description="keypoints per feature set: precomputed features in a request, and a new "
        "map's encoder num_keypoints (the encoders make at most 512 by default). Re-ranking "
        "costs grow with its square",
    )
    max_self_test_keyframes: int = Field(
        1000,
        ge=1,
        description="a self-test compares encoders (encoders) only on maps of at most "
        "this many keyframes: each candidate holds its own copy of them",
    )
    max_top_k: int = Field(100, ge=1, description="largest top_k a localize request may ask")
    snapshot_every: int = Field(
        1000,
        ge=1,
        description="save a map's FAISS snapshot after this many keyframe changes (or half "
        "the map's keyframes, when that is more)",
    )
    snapshot_delay_s: float = Field(
        30.0, gt=0, description="save a changed map's snapshot at most this long after a write"
    )
    log_level: LogLevel = "info"
    log_format: Literal["text", "json"] = Field(
        "text",
        description="text lines, or JSON lines with request ids and one access line per "
        "request (docs/OPERATIONS.md, 'Monitoring')",
    )

    # -- access control (docs/OPERATIONS.md) --
    dev: bool = Field(
        False,
        description="development mode: authentication is OFF (never on a shared network)",
    )
    models_dir: Path | None = Field(
        None,
        description="the only folder whose files a map's encoder.model_path may name (a "
        "name relative to it, or a path inside it); unset: maps created over HTTP cannot "
        "name model files",
    )
    keys_file: Path | None = Field(
        None, description="TOML or JSON file of API keys with roles (see docs/OPERATIONS.md)"
    )
    api_docs: Literal["open", "off"] = Field(
        "open",
        description="/openapi.json, /docs and /redoc: served to anyone (they describe the API, "
        "never data or keys), or not at all (404)",
    )
    metrics_auth: ProbeAuth = Field(
        "viewer", description="/metrics: open to anyone, or a viewer (or admin) key"
    )
    readyz_auth: ProbeAuth = Field(
        "open", description="/readyz: open to anyone, or a viewer (or admin) key"
    )

    # -- admission and timeouts --
    max_inflight_localize: int | None = Field(
        None,
        ge=1,
        description="localize requests admitted at once (running or waiting for a worker); "
        "beyond it 429 with Retry-After. Default 4 x workers",
    )
    request_timeout_s: float = Field(
        30.0,
        gt=0,
        description="longest a request waits for a worker thread; beyond it 503 with Retry-After",
    )
    retry_after_s: int = Field(1, ge=1, description="Retry-After of 429/503 answers (seconds)")
    shutdown_timeout_s: float = Field(
        10.0,
        gt=0,
        le=600,
        description="on SIGTERM, longest wait for open requests and for map loading before "
        "the process exits (in-flight localize work is stopped at once)",
    )
    header_timeout_s: float = Field(
        10.0,
        gt=0,
        le=600,
        description="longest a request's headers may take to arrive (from the connection or "
        "the previous answer); beyond it the connection is closed",
    )
    send_timeout_s: float = Field(
        60.0,
        gt=0,
        le=3600,
        description="longest the send buffer of an answer (a map export, a large answer) may "
        "stay full, or a finished answer's tail wait in it, because the client does not read "
        "(or reads under about 1 KiB/s); beyond it the connection is reset and the answer's "
        "resources (an export's snapshot of the store) are let go",
    )
    body_timeout_s: float = Field(
        30.0,
        gt=0,
        le=3600,
        description="longest a request body may take to arrive; beyond it 408 and the "
        "connection is closed (a slow upload holds no localize slot meanwhile)",
    )

    @model_validator(mode="after")
    def _default_inflight(self) -> Settings:
        if self.max_inflight_localize is None:
            self.max_inflight_localize = 4 * self.workers
        return self

    @model_validator(mode="after")
    def _write_workers_within_workers(self) -> Settings:
        if self.write_workers is not None and self.write_workers > self.workers:
            raise ValueError(
                f"write_workers ({self.write_workers}) may not exceed workers ({self.workers})"
            )
        return self

    @model_validator(mode="after")
    def _body_memory_holds_a_body(self) -> Settings:
        if self.max_body_memory_bytes is not None and (
            self.max_body_memory_bytes < self.max_body_bytes
        ):
            raise ValueError(
                f"max_body_memory_bytes ({self.max_body_memory_bytes}) may not be less than "
                f"max_body_bytes ({self.max_body_bytes})"
            )
        return self

    @property
    def body_memory_limit(self) -> int:
        """The effective ``max_body_memory_bytes``."""
        return self.max_body_memory_bytes or 4 * self.max_body_bytes

    @property
    def write_limit(self) -> int:
        """The effective ``write_workers``."""
        return self.write_workers or max(1, self.workers - 1)

    @property
    def inflight_limit(self) -> int:
        """The effective ``max_inflight_localize``."""
        return self.max_inflight_localize or 4 * self.workers

    @property
    def library_threads(self) -> int:
        """The effective ``threads_per_worker``."""
        if self.threads_per_worker:
            return self.threads_per_worker
        return max(1, usable_cpus() // self.workers)

    @property
    def maps_dir(self) -> Path:
        """``<data_dir>/maps``: one folder per map."""
        return self.data_dir / "maps"


#: ``SGVLOC_`` variables that are not service settings: the CLI's client options
#: (``--url``, ``--api-key``, ``--threads``) and the test suite's
OTHER_ENV = frozenset({"SGVLOC_URL", "SGVLOC_API_KEY", "SGVLOC_THREADS", "SGVLOC_ARTEFACTS"})
OTHER_ENV_PREFIX = "SGVLOC_TEST_", "SGVLOC_REQUIRE_"


def env_name(field: str) -> str:
    """The environment variable of a setting."""
    return "SGVLOC_" + field.upper()


def unknown_env(environ: Mapping[str, str]) -> list[str]:
    """One line per ``SGVLOC_`` variable that is no setting (a typo is ignored otherwise),
    with the nearest setting's name when one is close."""
    known = {env_name(f) for f in Settings.model_fields}
    lines = []
    for var in sorted(environ):
        name = var.upper()  # the settings read variables whatever their case
        if not name.startswith("SGVLOC_") or name in known or name in OTHER_ENV:
            continue
        if name.startswith(OTHER_ENV_PREFIX):
            continue
        near = difflib.get_close_matches(name, sorted(known), n=1)
        lines.append(f"{var} is not a setting (ignored)" + (f"; {near[0]}?" if near else ""))
    return lines
