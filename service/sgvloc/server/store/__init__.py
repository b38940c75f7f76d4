"""Map persistence: the interface the map manager uses (:mod:`.base`) and its backends
(:mod:`.sqlite`, the embedded default; :mod:`.postgres`, the store replicas share, imported
only when asked for since it needs psycopg)."""

from .base import (
    INDEX_NAME,
    Change,
    DuplicateKeyError,
    KeyframeFilter,
    KeyframeRow,
    KeyframeSummary,
    MapRecord,
    MapStore,
    SharedBackend,
    StoreBackend,
    StoreClosedError,
    StoreError,
    StoreUnavailableError,
    raise_if_full,
    storage_full,
    utc_now,
)
from .sqlite import DB_NAME, SqliteBackend, SqliteMapStore


def open_backend(url: str | None, *, pool_size: int = 8) -> StoreBackend | SharedBackend:
    """The backend a store URL names: None -> one SQLite database per map folder;
    ``postgresql://...`` (or ``postgres://``) -> the shared PostgreSQL store."""
    if url is None or url == "":
        return SqliteBackend()
    if url.startswith(("postgresql://", "postgres://")):
        try:
            from .postgres import PgBackend
        except ImportError as exc:
            raise StoreError(
                f"a PostgreSQL store needs psycopg: pip install 'sgvloc[service]' ({exc})"
            ) from None
        return PgBackend(url, pool_size=pool_size)
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
    "StoreClosedError",
    "StoreError",
    "raise_if_full",
    "storage_full",
    "utc_now",
]
