"""Map persistence: the interface the map manager uses (:mod:`.base`) and its backends
(:mod:`.sqlite`, the embedded default; :mod:`.postgres`, the store replicas share, imported
only when asked for since it needs psycopg)."""

from pathlib import Path

from .base import (
    INDEX_NAME,
    Change,
    DuplicateKeyError,
    KeyframeFilter,
    KeyframeRow,
    KeyframeSummary,
    MapRecord,
    MapStore,
    SettingsChangedError,
    SharedBackend,
    StoreBackend,
    StoreClosedError,
    StoreError,
    StoreUnavailableError,
    no_nul,
    plain_json,
    raise_if_full,
    storage_full,
    utc_now,
)
from .sqlite import DB_NAME, SqliteBackend, SqliteMapStore


def open_backend(
    url: str | None, *, pool_size: int = 8, password_file: Path | None = None
) -> StoreBackend | SharedBackend:
    """The backend a store URL names: None -> one SQLite database per map folder;
    ``postgresql://...`` (or ``postgres://``) -> the shared PostgreSQL store, with the
    password of ``password_file`` when given."""
    if url is None or url == "":
        return SqliteBackend()
    if url.startswith(("postgresql://", "postgres://")):
        try:
            from .postgres import PgBackend
        except ImportError as exc:
            raise StoreError(
                f"a PostgreSQL store needs psycopg: pip install 'sgvloc[service]' ({exc})"
            ) from None
        password = None
        if password_file is not None:
            try:
                password = Path(password_file).read_text().strip()
            except OSError as exc:
                raise StoreError(f"cannot read the store password file: {exc}") from None
        return PgBackend(url, pool_size=pool_size, password=password)
    raise StoreError("store URL must start with postgresql:// (or be empty for SQLite)")


__all__ = [
    "DB_NAME",
    "INDEX_NAME",
    "Change",
    "DuplicateKeyError",
    "SharedBackend",
    "StoreUnavailableError",
    "open_backend",
    "KeyframeFilter",
    "KeyframeRow",
    "KeyframeSummary",
    "MapRecord",
    "MapStore",
    "SqliteBackend",
    "SqliteMapStore",
    "StoreBackend",
    "SettingsChangedError",
    "StoreClosedError",
    "StoreError",
    "no_nul",
    "plain_json",
    "raise_if_full",
    "storage_full",
    "utc_now",
]
