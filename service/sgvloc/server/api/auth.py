"""Access control: API keys with roles, optionally restricted to named maps.

Keys come from the operator's keys file (``SGVLOC_KEYS_FILE``, TOML or JSON)::

    [[keys]]
    name = "truck-17"                 # a label for logs; the key itself is never logged
    key = "sha256:9f86d08188..."      # SHA-256 of the key (hex), or the plain key
    role = "vehicle"                  # vehicle | mapper | viewer | admin
    maps = ["campus"]                 # optional: only these maps (default: every map)

Clients send ``Authorization: Bearer <key>``. A missing or unknown key is a 401 (with
``WWW-Authenticate: Bearer``); a known key whose role or maps do not allow the route is a
403. The presented key is hashed with SHA-256 and compared with every configured hash by
:func:`hmac.compare_digest`, so the time taken does not depend on how much of a key is
right, nor on which key matched.

Who may do what is the one table :data:`ROUTE_ROLES`, by route ``operation_id``; each
router carries the :func:`authorize` dependency, which looks its route up there (a route
missing from the table is refused: fail closed). In development mode (``--dev``,
``SGVLOC_DEV=1``) there is no check at all; outside it the service does not start
without keys.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import re
from dataclasses import dataclass
from typing import Any

from fastapi import Request

from ..keys import ROLES, SHA_PREFIX, KeysError, Role, read_keys_file
from ..settings import Settings
from .errors import ApiError

log = logging.getLogger(__name__)


#: operation_id -> the roles allowed to call it. The one place that says who may do what.
#: ``None`` marks a route open to anyone (no key needed); ``"probe:<setting>"`` routes are
#: open or viewer/admin as that setting says.
ROUTE_ROLES: dict[str, frozenset[Role] | None | str] = {
    # maps
    "create_map": frozenset({"mapper", "admin"}),
    "list_maps": frozenset({"mapper", "viewer", "admin"}),
    "get_map": frozenset({"mapper", "viewer", "admin"}),
    "map_stats": frozenset({"mapper", "viewer", "admin"}),
    "update_map": frozenset({"mapper", "admin"}),
    "self_test_map": frozenset({"mapper", "admin"}),
    "delete_map": frozenset({"admin"}),
    "reload_keys": frozenset({"admin"}),
    "reload_map": frozenset({"admin"}),
    "export_map": frozenset({"mapper", "admin"}),
    "import_map": frozenset({"mapper", "admin"}),
    # keyframes
    "insert_keyframes": frozenset({"mapper", "admin"}),
    "get_keyframe": frozenset({"mapper", "viewer", "admin"}),
    "delete_keyframe": frozenset({"mapper", "admin"}),
    "list_keyframes": frozenset({"mapper", "viewer", "admin"}),
    "delete_keyframes": frozenset({"mapper", "admin"}),
    # localize
    "localize": frozenset({"vehicle", "mapper", "admin"}),
    "recent_localizations": frozenset({"mapper", "viewer", "admin"}),
    # service
    "get_config": frozenset({"viewer", "admin"}),
    "healthz": None,
    "readyz": "probe:readyz_auth",
    "metrics": "probe:metrics_auth",
}
_PROBE_ROLES: frozenset[Role] = frozenset({"viewer", "admin"})

_HEX64 = re.compile(r"^[0-9a-f]{64}$")


@dataclass(frozen=True)
class Principal:
    """Who is calling: the key's label, role and allowed maps (None = every map)."""

    name: str
    role: Role
    maps: frozenset[str] | None = None

    def may_use_map(self, name: str) -> bool:
        return self.maps is None or name in self.maps


DEV_PRINCIPAL = Principal("development", "admin")
#: the caller of a route open to all (no key asked for)
ANONYMOUS = Principal("anonymous", "viewer", frozenset())


@dataclass(frozen=True)
class ApiKey:
    """One configured key: the SHA-256 digest of the secret, never the secret."""

    digest: bytes  # 32 bytes
    principal: Principal


def _entry(raw: Any, i: int, source: str) -> ApiKey:
    where = f"{source}: keys[{i}]"
    if not isinstance(raw, dict):
        raise KeysError(f"{where} must be a table with key and role")
    unknown = set(raw) - {"name", "key", "role", "maps"}
    if unknown:
        raise KeysError(f"{where} has unknown field(s) {sorted(unknown)}")
    name = raw.get("name", f"key#{i}")
    secret, role, maps = raw.get("key"), raw.get("role"), raw.get("maps")
    if not isinstance(name, str) or not name:
        raise KeysError(f"{where}.name must be a non-empty string")
    if role not in ROLES:
        raise KeysError(f"{where} ({name}): role must be one of {', '.join(ROLES)}, got {role!r}")
    if not isinstance(secret, str) or not secret:
        raise KeysError(f"{where} ({name}): key must be a non-empty string")
    if secret.startswith(SHA_PREFIX):
        hexdigest = secret[len(SHA_PREFIX) :].lower()
        if not _HEX64.match(hexdigest):
            raise KeysError(f"{where} ({name}): a sha256: key needs 64 hex digits")
        digest = bytes.fromhex(hexdigest)
    else:
        if len(secret) < 16:
            raise KeysError(f"{where} ({name}): a plain key needs at least 16 characters")
        digest = hashlib.sha256(secret.encode()).digest()
    if maps is not None:
        if not isinstance(maps, list) or not all(isinstance(m, str) and m for m in maps):
            raise KeysError(f"{where} ({name}): maps must be a list of map names")
        maps = frozenset(maps)
    return ApiKey(digest, Principal(name, role, maps))


def parse_keys(data: Any, source: str = "keys") -> list[ApiKey]:
    """Keys from a parsed keys file: ``{"keys": [{"key", "role", "name"?, "maps"?}]}``."""
    if not isinstance(data, dict) or not isinstance(data.get("keys"), list):
        raise KeysError(f"{source}: expected a list of keys under 'keys'")
    keys = [_entry(raw, i, source) for i, raw in enumerate(data["keys"])]
    first: dict[bytes, str] = {}
    for k in keys:
        if k.digest in first:
            raise KeysError(
                f"{source}: the same key appears twice ({first[k.digest]!r} and "
                f"{k.principal.name!r})"
            )
        first[k.digest] = k.principal.name
    names = [k.principal.name for k in keys]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise KeysError(f"{source}: key names must be unique; twice: {', '.join(twice)}")
    return keys


class KeyRing:
    """The configured keys; :meth:`identify` finds a presented key's principal."""

    def __init__(self, keys: list[ApiKey], *, enabled: bool = True) -> None:
        self.keys = keys
        self.enabled = enabled

    @classmethod
    def from_settings(cls, settings: Settings) -> KeyRing:
        """The keys of ``settings``; raises :class:`KeysError` when there are none outside
        development mode (the service must not run open by accident)."""
        if settings.dev:  # the keys file is not even read: it may be absent
            if settings.keys_file is not None:
                log.warning("development mode: the keys file %s is ignored", settings.keys_file)
            log.warning("development mode: authentication is OFF; do not expose this service")
            return cls([], enabled=False)
        keys: list[ApiKey] = []
        if settings.keys_file is not None:
            keys = parse_keys(read_keys_file(settings.keys_file), str(settings.keys_file))
        if not keys:
            where = f"the keys file {settings.keys_file}" if settings.keys_file else "no keys file"
            raise KeysError(
                f"no API keys configured ({where}): set SGVLOC_KEYS_FILE (or --keys-file) to a "
                "TOML/JSON file of keys with roles, or run in development mode (--dev or "
                "SGVLOC_DEV=1) to switch authentication off"
            )
        by_role = {r: sum(k.principal.role == r for k in keys) for r in ROLES}
        log.info(
            "authentication on: %d key(s) (%s)",
            len(keys),
            ", ".join(f"{n} {r}" for r, n in by_role.items() if n),
        )
        return cls(keys, enabled=True)

    def identify(self, presented: str) -> Principal | None:
        """The principal of ``presented``, or None. Constant time in the key's content:
        every configured digest is compared, whatever matched before."""
        digest = hashlib.sha256(presented.encode()).digest()
        found: Principal | None = None
        for key in self.keys:
            if hmac.compare_digest(digest, key.digest):
                found = key.principal
        return found


def _bearer(request: Request) -> str | None:
    header = request.headers.get("authorization")
    if not header:
        return None
    scheme, _, token = header.partition(" ")
    token = token.strip()
    if scheme.lower() != "bearer" or not token:
        return None
    return token


def _unauthorized(message: str) -> ApiError:
    return ApiError(401, "unauthorized", message, headers={"WWW-Authenticate": "Bearer"})


def _allowed_roles(operation: str, settings: Settings) -> frozenset[Role] | None:
    """The roles that may call ``operation`` (None: open). Unknown operations: nobody."""
    if operation not in ROUTE_ROLES:
        log.error("route %r has no entry in the role table: refused", operation)
        return frozenset()
    rule = ROUTE_ROLES[operation]
    if isinstance(rule, str):  # "probe:<setting>"
        return None if getattr(settings, rule.split(":", 1)[1]) == "open" else _PROBE_ROLES
    return rule


async def authorize(request: Request) -> Principal:
    """The router dependency: 401/403 unless the caller may use this route (and map).

    The principal is left in ``request.state.principal`` for the route (e.g. to filter
    the map list of a key restricted to some maps).
    """
    settings: Settings = request.app.state.settings
    ring: KeyRing = request.app.state.keyring
    route = request.scope.get("route")
    operation = getattr(route, "operation_id", None) or ""
    allowed = _allowed_roles(operation, settings)
    if not ring.enabled:
        principal = DEV_PRINCIPAL
    elif allowed is None:
        principal = ANONYMOUS
    else:
        token = _bearer(request)
        if token is None:
            raise _unauthorized("this route needs an API key: send 'Authorization: Bearer <key>'")
        found = ring.identify(token)
        if found is None:
            raise _unauthorized("the API key is not valid")
        principal = found
        request.state.principal = principal  # a refusal's access line names the key too
        if principal.role not in allowed:
            log.info("key %r (%s) refused for %s", principal.name, principal.role, operation)
            raise ApiError(
                403,
                "forbidden",
                f"role {principal.role!r} may not {operation.replace('_', ' ')} (allowed: "
                f"{', '.join(sorted(allowed))})",
            )
        map_name = request.path_params.get("map")
        if map_name is not None and not principal.may_use_map(map_name):
            log.info("key %r refused for map %r", principal.name, map_name)
            raise ApiError(403, "forbidden", f"this key may not use map {map_name!r}")
    request.state.principal = principal
    return principal


def reload_keys(app: Any) -> KeyRing:
    """Read the keys file again and swap the app's keys in one step (requests in flight
    finish with the keys they were checked with; the next ones use the new set). A file
    that cannot be used keeps the old keys: :class:`KeysError` says why (and is logged).
    Revoked keys stop working at once."""
    settings: Settings = app.state.settings
    try:
        ring = KeyRing.from_settings(settings)
    except KeysError as exc:
        log.error("keys file not reloaded, the previous keys stay in force: %s", exc)
        raise
    app.state.keyring = ring
    log.info("keys reloaded: %d key(s)", len(ring.keys))
    return ring


def key_holder(request: Request) -> Principal | None:
    """On an open route, the caller its valid key names (if it sent one), or None."""
    token = _bearer(request)
    ring: KeyRing = request.app.state.keyring
    return ring.identify(token) if token is not None and ring.enabled else None


def principal_of(request: Request) -> Principal:
    """The caller, as :func:`authorize` found it."""
    return getattr(request.state, "principal", DEV_PRINCIPAL)
