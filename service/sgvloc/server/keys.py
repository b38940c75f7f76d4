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
    try:
        if path.suffix.lower() == ".json":
            return json.loads(text)
        try:
            import tomllib
        except ModuleNotFoundError:  # Python 3.10
            try:
                import tomli as tomllib  # type: ignore[no-redef]
            except ModuleNotFoundError:
                raise KeysError(
                    f"{path}: reading TOML needs Python 3.11+ (or tomli); use a .json file"
                ) from None
        return tomllib.loads(text)
    except ValueError as exc:  # JSONDecodeError and TOMLDecodeError are ValueErrors
        raise KeysError(f"{path} is not valid {path.suffix.lstrip('.') or 'TOML'}: {exc}") from None


def key_names(path: Path) -> list[str]:
    """The names of the keys in a keys file (KeysError if it cannot be read)."""
    data = read_keys_file(path)
    keys = data.get("keys") if isinstance(data, dict) else None
    return [k["name"] for k in keys or [] if isinstance(k, dict) and "name" in k]


def hash_key(key: str) -> str:
    """The ``sha256:<hex>`` entry for a keys file, from a plain key."""
    return SHA_PREFIX + hashlib.sha256(key.encode()).hexdigest()


def new_key() -> str:
    """A random key: 32 bytes from the OS's generator, URL-safe base64 (43 characters)."""
    return secrets.token_urlsafe(32)


def keys_entry(name: str, role: str, key: str, maps: list[str] | None = None) -> str:
    """The TOML ``[[keys]]`` table of ``key`` (stored as its SHA-256 only)."""
    if role not in ROLES:
        raise ValueError(f"role must be one of {', '.join(ROLES)}, got {role!r}")
    # JSON strings are valid TOML basic strings
    entry = f'[[keys]]\nname = {json.dumps(name)}\nrole = "{role}"\nkey = "{hash_key(key)}"\n'
    if maps:
        entry += f"maps = {json.dumps(maps)}\n"
    return entry


def append_entry(keys_file: Path, entry: str) -> None:
    """Append ``entry`` to ``keys_file`` (created if missing). The file holds hashes
    only, so a new one is made readable by all: the container's service user reads it."""
    existed = keys_file.exists()
    text = keys_file.read_text() if existed else ""
    prefix = "" if not text else ("\n" if text.endswith("\n") else "\n\n")
    with keys_file.open("a") as f:
        f.write(prefix + entry)
    if not existed:
        keys_file.chmod(0o644)


def write_key(path: Path, key: str) -> None:
    """Write a plain key (nothing else: it is a bearer token file) to a new file readable
    by its owner only; refuses to overwrite an existing file (``FileExistsError``)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key)
