"""API keys as the keys file holds them: roles, the SHA-256 entry of a key, new keys.

Free of the web stack, so that ``sgvloc new-key`` runs with the client-only install;
the service's access control (:mod:`sgvloc.server.api.auth`) reads these files.
"""

from __future__ import annotations

import hashlib
import json
import os
import secrets
from pathlib import Path
from typing import Any, Literal

Role = Literal["vehicle", "mapper", "viewer", "admin"]
ROLES: tuple[Role, ...] = ("vehicle", "mapper", "viewer", "admin")
SHA_PREFIX = "sha256:"


class KeysError(ValueError):
    """The keys file is missing, unreadable or malformed, or no keys are configured."""


def read_keys_file(path: Path) -> Any:
    """The parsed keys file (TOML, or JSON by its suffix); KeysError if it cannot be read."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise KeysError(f"cannot read the keys file {path}: {exc.strerror or exc}") from None
    if is_json(path):
        parse = json.loads
    else:
        try:
            import tomllib
        except ModuleNotFoundError:  # Python 3.10: the tomli dependency
            import tomli as tomllib  # type: ignore[no-redef]
        parse = tomllib.loads
    try:
        return parse(text)
    except ValueError as exc:  # JSONDecodeError and TOMLDecodeError are ValueErrors
        kind = "JSON" if is_json(path) else "TOML"
        raise KeysError(f"{path} is not valid {kind}: {exc}") from None


def is_json(path: Path) -> bool:
    """A keys file is JSON by its suffix, else TOML."""
    return path.suffix.lower() == ".json"


def key_names(path: Path) -> list[str]:
    """The names of the keys in a keys file (KeysError if it cannot be read)."""
    data = read_keys_file(path)
    keys = data.get("keys", []) if isinstance(data, dict) else None
    if not isinstance(keys, list):
        raise KeysError(f'{path} must hold a "keys" list of tables (TOML) or objects (JSON)')
    return [k["name"] for k in keys if isinstance(k, dict) and "name" in k]


def hash_key(key: str) -> str:
    """The ``sha256:<hex>`` entry for a keys file, from a plain key."""
    return SHA_PREFIX + hashlib.sha256(key.encode()).hexdigest()


def new_key() -> str:
    """A random key: 32 bytes from the OS's generator, URL-safe base64 (43 characters)."""
    return secrets.token_urlsafe(32)


def keys_entry(name: str, role: str, key: str, maps: list[str] | None = None) -> dict[str, Any]:
    """The keys-file entry of ``key`` (stored as its SHA-256 only)."""
    if role not in ROLES:
        raise ValueError(f"role must be one of {', '.join(ROLES)}, got {role!r}")
    entry: dict[str, Any] = {"name": name, "role": role, "key": hash_key(key)}
    if maps:
        entry["maps"] = list(maps)
    return entry


def toml_entry(entry: dict[str, Any]) -> str:
    """``entry`` as a TOML ``[[keys]]`` table (JSON strings and arrays of strings are
    valid TOML values)."""
    return "[[keys]]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in entry.items())


def append_entry(keys_file: Path, entry: dict[str, Any]) -> None:
    """Add ``entry`` to ``keys_file`` (created if missing): a TOML table appended, or for
    a ``.json`` file the whole document written again with the entry at the end of its
    ``keys`` list. The file is written in place, not replaced, so that a service reading
    it through a single-file bind mount (docker-compose.yml) sees the change. The file
    holds hashes only, so a new one is made readable by all: the container's service
    user reads it. KeysError when an existing JSON file cannot take the entry."""
    existed = keys_file.exists()
    if is_json(keys_file):
        data = read_keys_file(keys_file) if existed else {"keys": []}
        keys = data.setdefault("keys", []) if isinstance(data, dict) else None
        if not isinstance(keys, list):
            raise KeysError(f'{keys_file} must hold a "keys" list of objects')
        keys.append(entry)
        with keys_file.open("w") as f:
            f.write(json.dumps(data, indent=2) + "\n")
    else:
        text = keys_file.read_text() if existed else ""
        prefix = "" if not text else ("\n" if text.endswith("\n") else "\n\n")
        with keys_file.open("a") as f:
            f.write(prefix + toml_entry(entry))
    if not existed:
        keys_file.chmod(0o644)


def write_key(path: Path, key: str) -> None:
    """Write a plain key (nothing else: it is a bearer token file) to a new file readable
    by its owner only; refuses to overwrite an existing file (``FileExistsError``)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key)
