"""Map persistence: the interface the map manager uses (:mod:`.base`) and its backends
(:mod:`.sqlite`, the embedded default)."""

from .base import (
    INDEX_NAME,
    KeyframeFilter,
    KeyframeRow,
    KeyframeSummary,
    MapRecord,
    MapStore,
    StoreBackend,
    StoreClosedError,
    StoreError,
    raise_if_full,
    storage_full,
    utc_now,
)
from .sqlite import DB_NAME, SqliteBackend, SqliteMapStore

__all__ = [
    "DB_NAME",
    "INDEX_NAME",
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
