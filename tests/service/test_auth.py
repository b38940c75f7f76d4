"""Access control: every role x every route (allowed, 401 or 403), keys restricted to
maps, the probes' settings, keys never logged, and no start without keys.

A server of its own runs with a keys file (plain and ``sha256:`` entries); the role
table below is written out here on purpose, independently of the service's own table.
"""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from conftest import Server
from svc_helpers import PRECOMPUTED, error_of, post_msgpack, random_features

import sgvloc_client
from sgvloc.server.api.auth import ROUTE_ROLES, KeyRing, KeysError, parse_keys
from sgvloc.server.keys import hash_key
from sgvloc.server.settings import Settings

ROLES = ("vehicle", "mapper", "viewer", "admin")
KEYS = {role: f"test-{role}-key-0123456789abcdef" for role in ROLES}
KEYS["vehicle-a"] = "test-vehicle-a-key-0123456789abcdef"  # localize in map auth-a only
KEYS["mapper-a"] = "test-mapper-a-key-0123456789abcdef"  # mapper of auth-a only
KEYS["viewer-a"] = "test-viewer-a-key-0123456789abcdef"  # viewer of auth-a only

#: who may call what (the issue's roles; mappers also read the maps they build)
ALLOWED: dict[str, set[str]] = {
    "create_map": {"mapper", "admin"},
    "list_maps": {"mapper", "viewer", "admin"},
    "get_map": {"mapper", "viewer", "admin"},
    "update_map": {"mapper", "admin"},
    "self_test_map": {"mapper", "admin"},
    "delete_map": {"admin"},
    "reload_map": {"admin"},
    "reload_keys": {"admin"},
    "insert_keyframes": {"mapper", "admin"},
    "get_keyframe": {"mapper", "viewer", "admin"},
    "delete_keyframe": {"mapper", "admin"},
    "list_keyframes": {"mapper", "viewer", "admin"},
    "delete_keyframes": {"mapper", "admin"},
    "map_stats": {"mapper", "viewer", "admin"},
    "export_map": {"mapper", "admin"},
    "import_map": {"mapper", "admin"},
    "localize": {"vehicle", "mapper", "admin"},
    "recent_localizations": {"mapper", "viewer", "admin"},
    "get_config": {"viewer", "admin"},
    "metrics": {"viewer", "admin"},  # metrics_auth=viewer, the default
    "healthz": {"anyone"},
    "readyz": {"anyone"},  # readyz_auth=open, the default
}
EYE = np.eye(4)


def _write_keys(path: Path) -> Path:
    entries = []
    for label, key in KEYS.items():
        role = label.split("-")[0]
        # half the keys as SHA-256 digests, half as plain keys: both are accepted
        entry = {"name": label, "role": role, "key": hash_key(key) if len(label) % 2 else key}
        if label.endswith("-a"):
            entry["maps"] = ["auth-a"]
        entries.append(entry)
    lines = []
    for e in entries:
        lines.append("[[keys]]")
        lines += [f"{k} = {json.dumps(v)}" for k, v in e.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def auth_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    root = tmp_path_factory.mktemp("auth")
    keys = _write_keys(root / "keys.toml")
    srv = Server(
        data_dir=root / "data",
        log_path=root / "server.log",
        env={"SGVLOC_KEYS_FILE": str(keys), "SGVLOC_LOG_LEVEL": "debug"},
    )
    srv.start()
    try:
        yield srv
    finally:
        srv.stop()


def _h(who: str | None) -> dict[str, str]:
    if who is None:
        return {}
    if who == "wrong":
        return {"Authorization": "Bearer not-a-configured-key-0123456789"}
    return {"Authorization": f"Bearer {KEYS[who]}"}


@pytest.fixture(scope="module")
def admin(auth_server: Server) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=auth_server.url, timeout=60, headers=_h("admin")) as c:
        yield c


@pytest.fixture(scope="module")
def maps(admin: httpx.Client) -> dict[str, int]:
    """Maps auth-a and auth-b (precomputed features), one keyframe each: name -> its id."""
    out = {}
    for name in ("auth-a", "auth-b"):
        r = admin.post("/v1/maps", json={"name": name, "encoder": PRECOMPUTED})
        assert r.status_code == 201, r.text
        feats = random_features(np.random.default_rng(1))
        r = post_msgpack(
            admin,
            f"/v1/maps/{name}/keyframes",
            {"keyframes": [{"T_map_sensor": EYE, "features": feats}]},
        )
        assert r.status_code == 201, r.text
        out[name] = r.json()["ids"][0]
    return out


_counter = itertools.count()


def _request(op: str, c: httpx.Client, admin: httpx.Client, ids: dict[str, int]) -> httpx.Response:
    """Call operation ``op`` as ``c``, on map auth-a (throwaway objects made by admin)."""
    feats = random_features(np.random.default_rng(2))
    n = next(_counter)
    if op == "create_map":
        return c.post("/v1/maps", json={"name": f"auth-new-{n}", "encoder": PRECOMPUTED})
    if op == "list_maps":
        return c.get("/v1/maps")
    if op == "get_map":
        return c.get("/v1/maps/auth-a")
    if op == "update_map":
        return c.patch("/v1/maps/auth-a", json={"localizer": {"top_k": 20}})
    if op == "self_test_map":  # auth-a's keyframes never revisit a place: 422 from the handler
        return c.post("/v1/maps/auth-a/self-test", json={"queries": 2})
    if op == "delete_map":
        name = f"auth-del-{n}"
        assert (
            admin.post("/v1/maps", json={"name": name, "encoder": PRECOMPUTED}).status_code == 201
        )
        return c.delete(f"/v1/maps/{name}")
    if op == "reload_map":  # auth-a is loaded: an allowed caller gets 409 from the handler
        return c.post("/v1/maps/auth-a/reload")
    if op == "reload_keys":  # the file is unchanged: the same keys again
        return c.post("/v1/keys/reload")
    if op == "insert_keyframes":
        body = {"keyframes": [{"T_map_sensor": EYE, "features": feats}]}
        return post_msgpack(c, "/v1/maps/auth-a/keyframes", body)
    if op == "get_keyframe":
        return c.get(f"/v1/maps/auth-a/keyframes/{ids['auth-a']}")
    if op == "delete_keyframe":
        body = {"keyframes": [{"T_map_sensor": EYE, "features": feats}]}
        r = post_msgpack(admin, "/v1/maps/auth-a/keyframes", body)
        assert r.status_code == 201, r.text
        return c.delete(f"/v1/maps/auth-a/keyframes/{r.json()['ids'][0]}")
    if op == "list_keyframes":
        return c.get("/v1/maps/auth-a/keyframes", params={"limit": 5})
    if op == "delete_keyframes":  # a key nothing has: deletes nothing
        return c.delete("/v1/maps/auth-a/keyframes", params={"key_prefix": "no-such-key"})
    if op == "map_stats":
        return c.get("/v1/maps/auth-a/stats")
    if op == "export_map":
        return c.get("/v1/maps/auth-a/export")
    if op == "import_map":  # into a map the -a keys may use, freed again by admin
        archive = admin.get("/v1/maps/auth-a/export")
        assert archive.status_code == 200, archive.text
        admin.delete("/v1/maps/auth-imported")
        return c.post(
            "/v1/map-archives",
            params={"name": "auth-imported"},
            content=archive.content,
            headers={"Content-Type": "application/x-tar"},
        )
    if op == "localize":
        return post_msgpack(c, "/v1/maps/auth-a/localize", {"features": feats, "rerank": "none"})
    if op == "recent_localizations":
        return c.get("/v1/maps/auth-a/localizations")
    if op == "get_config":
        return c.get("/v1/config")
    if op == "healthz":
        return c.get("/healthz")
    if op == "readyz":
        return c.get("/readyz")
    if op == "metrics":
        return c.get("/metrics")
    raise AssertionError(f"no request for {op}")


def test_the_matrix_covers_every_route(auth_server: Server) -> None:
    doc = httpx.get(f"{auth_server.url}/openapi.json").json()
    ops = {o["operationId"] for p in doc["paths"].values() for o in p.values()}
    assert ops == set(ALLOWED) == set(ROUTE_ROLES)


@pytest.mark.parametrize("op", sorted(ALLOWED))
@pytest.mark.parametrize("who", [*ROLES, None, "wrong"])
def test_role_matrix(
    auth_server: Server, admin: httpx.Client, maps: dict[str, int], op: str, who: str | None
) -> None:
    with httpx.Client(base_url=auth_server.url, timeout=60, headers=_h(who)) as c:
        r = _request(op, c, admin, maps)
    if "anyone" in ALLOWED[op] or who in ALLOWED[op]:
        expected = {"reload_map": 409, "self_test_map": 422}.get(op)  # see _request
        assert (r.status_code == expected) if expected else r.status_code < 300, (op, who, r.text)
    elif who in (None, "wrong"):
        assert r.status_code == 401, (op, who, r.text)
        assert r.headers["www-authenticate"] == "Bearer"
        assert error_of(r)["code"] == "unauthorized"
    else:
        assert r.status_code == 403, (op, who, r.text)
        err = error_of(r)
        assert err["code"] == "forbidden" and who in err["message"]


@pytest.mark.parametrize(
    "header", ["Basic dGVzdDp0ZXN0", "Bearer", "Bearer  x", KEYS["admin"], f"Token {KEYS['admin']}"]
)
def test_malformed_authorization(auth_server: Server, maps: dict, header: str) -> None:
    r = httpx.get(f"{auth_server.url}/v1/maps", headers={"Authorization": header})
    assert r.status_code == 401 and error_of(r)["code"] == "unauthorized"


def test_bearer_scheme_is_case_insensitive(auth_server: Server, maps: dict) -> None:
    r = httpx.get(
        f"{auth_server.url}/v1/maps", headers={"Authorization": f"bearer {KEYS['viewer']}"}
    )
    assert r.status_code == 200


def test_key_restricted_to_maps(auth_server: Server, admin: httpx.Client, maps: dict) -> None:
    feats = random_features(np.random.default_rng(3))
    body = {"features": feats, "rerank": "none"}
    with httpx.Client(base_url=auth_server.url, timeout=60, headers=_h("vehicle-a")) as c:
        assert post_msgpack(c, "/v1/maps/auth-a/localize", body).status_code == 200
        r = post_msgpack(c, "/v1/maps/auth-b/localize", body)
        assert r.status_code == 403 and "auth-b" in error_of(r)["message"]
        # an unknown map is a 403 too: a restricted key learns nothing about other maps
        assert post_msgpack(c, "/v1/maps/nowhere/localize", body).status_code == 403
    with httpx.Client(base_url=auth_server.url, timeout=60, headers=_h("mapper-a")) as c:
        assert [m["name"] for m in c.get("/v1/maps").json()["maps"]] == ["auth-a"]
        # paging counts only the maps the key may use: no cursor past a hidden map
        one = c.get("/v1/maps", params={"limit": 1, "prefix": "auth-"}).json()
        assert [m["name"] for m in one["maps"]] == ["auth-a"] and one["next_cursor"] is None
        assert one["total"] == 1
        assert c.get("/v1/maps/auth-b").status_code == 403
        kf = {"keyframes": [{"T_map_sensor": EYE, "features": feats}]}
        assert post_msgpack(c, "/v1/maps/auth-a/keyframes", kf).status_code == 201
        assert post_msgpack(c, "/v1/maps/auth-b/keyframes", kf).status_code == 403
        r = c.post("/v1/maps", json={"name": "auth-c", "encoder": PRECOMPUTED})
        assert r.status_code == 403 and error_of(r)["field"] == "name"
    assert admin.get("/v1/maps/auth-c").status_code == 404
    # the metrics name every map and key: not for a key limited to some maps
    with httpx.Client(base_url=auth_server.url, timeout=60, headers=_h("viewer-a")) as c:
        assert c.get("/v1/maps/auth-a").status_code == 200
        r = c.get("/metrics")
        assert r.status_code == 403 and "limited to some maps" in error_of(r)["message"]
        # the configuration's limits, not how many keys there are or where the store is
        cfg = c.get("/v1/config").json()
        assert cfg["limits"]["max_top_k"] > 0
        assert cfg["auth"]["keys"] is None and cfg["store"]["location"] is None
    with httpx.Client(base_url=auth_server.url, timeout=60, headers=_h("viewer")) as c:
        assert c.get("/metrics").status_code == 200
        cfg = c.get("/v1/config").json()
        assert cfg["auth"]["keys"] == len(KEYS) and cfg["store"]["location"]


def test_sdk_sends_the_key(auth_server: Server, maps: dict) -> None:
    feats = random_features(np.random.default_rng(4))
    with sgvloc_client.Client(auth_server.url, api_key=KEYS["vehicle"]) as c:
        loc = c.localize("auth-a", features=feats, rerank="none")
        assert loc.map == "auth-a"
    with sgvloc_client.Client(auth_server.url, api_key="wrong-key-0123456789abcdef") as c:
        with pytest.raises(sgvloc_client.APIError) as info:
            c.localize("auth-a", features=feats)
    assert info.value.status == 401


def test_the_cli_says_how_to_give_a_key(auth_server: Server, maps: dict) -> None:
    """A 401 to the CLI names its option and variable, not only the header."""
    env = {k: v for k, v in os.environ.items() if k != "SGVLOC_API_KEY"}
    run = subprocess.run(
        [sys.executable, "-m", "sgvloc.cli", "map", "list", "--url", auth_server.url],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert run.returncode == 1, run.stderr
    assert "--api-key or SGVLOC_API_KEY" in run.stderr, run.stderr
    run = subprocess.run(
        [sys.executable, "-m", "sgvloc.cli", "map", "list", "--url", auth_server.url],
        capture_output=True,
        text=True,
        env={**env, "SGVLOC_API_KEY": KEYS["viewer"]},
        timeout=120,
    )
    assert run.returncode == 0 and "auth-a" in run.stdout, run.stderr


def test_keys_never_logged(auth_server: Server, maps: dict) -> None:
    # every key was used above (some refused); the debug log names keys, never their value
    log = auth_server.log()
    assert "authentication on: 7 key(s)" in log
    for key in KEYS.values():
        assert key not in log
        assert hash_key(key)[7:] not in log


# -- in process: settings of the probes, start-up refusal --------------------------------


def _call(app, *requests: tuple[str, str, dict]) -> list[httpx.Response]:
    import asyncio

    async def go() -> list[httpx.Response]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            return [await c.request(m, p, headers=h) for m, p, h in requests]

    return asyncio.run(go())


@pytest.fixture
def keys_file(tmp_path: Path) -> Path:
    return _write_keys(tmp_path / "keys.toml")


@pytest.mark.parametrize(
    ("setting", "path"), [("metrics_auth", "/metrics"), ("readyz_auth", "/readyz")]
)
def test_probe_auth_settings(tmp_path: Path, keys_file: Path, setting: str, path: str) -> None:
    from sgvloc.server.api import create_app

    for mode in ("open", "viewer"):
        app = create_app(Settings(data_dir=tmp_path, keys_file=keys_file, **{setting: mode}))
        anon, vehicle, viewer = _call(
            app, ("GET", path, {}), ("GET", path, _h("vehicle")), ("GET", path, _h("viewer"))
        )
        ok = (200, 503)  # /readyz: 503 while loading (no lifespan here)
        if mode == "open":
            assert anon.status_code in ok and vehicle.status_code in ok
        else:
            assert anon.status_code == 401 and vehicle.status_code == 403
        assert viewer.status_code in ok
    health = _call(app, ("GET", "/healthz", {}))[0]
    assert health.status_code == 200


def test_keys_file_formats(tmp_path: Path) -> None:
    good = {"keys": [{"name": "a", "role": "viewer", "key": hash_key("x" * 20)}]}
    (tmp_path / "k.json").write_text(json.dumps(good))
    ring = KeyRing.from_settings(Settings(keys_file=tmp_path / "k.json"))
    assert ring.identify("x" * 20).role == "viewer"
    assert ring.identify("x" * 19) is None
    bad: list[tuple[object, str]] = [
        ({"keys": [{"role": "boss", "key": "x" * 20}]}, "role must be one of"),
        ({"keys": [{"role": "admin", "key": "short"}]}, "at least 16"),
        ({"keys": [{"role": "admin", "key": "sha256:abc"}]}, "64 hex digits"),
        ({"keys": [{"role": "admin", "key": "x" * 20, "extra": 1}]}, "unknown field"),
        (
            {
                "keys": [
                    {"name": "ops", "role": "admin", "key": "x" * 20},
                    {"name": "bot", "role": "viewer", "key": hash_key("x" * 20)},
                ]
            },
            r"the same key appears twice \('ops' and 'bot'\)",
        ),
        (
            {
                "keys": [
                    {"name": "ops", "role": "admin", "key": "x" * 20},
                    {"name": "ops", "role": "viewer", "key": "y" * 20},
                ]
            },
            "unique; twice: ops",
        ),
        ({"keys": [{"role": "admin", "key": "x" * 20, "maps": "campus"}]}, "list of map names"),
        ({"users": []}, "under 'keys'"),
    ]
    for data, fragment in bad:
        with pytest.raises(KeysError, match=fragment):
            parse_keys(data)
    (tmp_path / "broken.toml").write_text("[[keys]\n")
    with pytest.raises(KeysError, match="not valid"):
        KeyRing.from_settings(Settings(keys_file=tmp_path / "broken.toml"))
    with pytest.raises(KeysError, match="cannot read"):
        KeyRing.from_settings(Settings(keys_file=tmp_path / "missing.toml"))
    (tmp_path / "empty.toml").write_text("keys = []\n")
    with pytest.raises(KeysError, match="development mode"):
        KeyRing.from_settings(Settings(keys_file=tmp_path / "empty.toml"))
    assert not KeyRing.from_settings(Settings(dev=True)).enabled


def _serve(tmp_path: Path, *args: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("SGVLOC_")}
    return subprocess.run(
        [sys.executable, "-m", "sgvloc.cli", "serve", "--data-dir", str(tmp_path), *args],
        capture_output=True,
        text=True,
        timeout=120,
        env={**clean, **env},
    )


def test_refuses_to_start_without_keys(tmp_path: Path, keys_file: Path) -> None:
    out = _serve(tmp_path, "--port", "1", env={})
    assert out.returncode == 2, out.stderr
    assert "no API keys configured" in out.stderr and "--dev" in out.stderr
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"keys": [{"role": "root", "key": "x" * 20}]}))
    out = _serve(tmp_path, "--keys-file", str(bad), env={})
    assert out.returncode == 2 and "role must be one of" in out.stderr


def test_keys_change_without_a_restart(tmp_path: Path) -> None:
    """SIGHUP and POST /v1/keys/reload re-read the keys file: an added key works, a
    revoked one stops at once, and a broken file keeps the previous keys."""
    import signal
    import time

    admin, viewer, added = ("key-admin-0123456789abcdef", "key-viewer-0123456789abcdef",
                            "key-added-0123456789abcdef")  # fmt: skip

    def entry(name: str, role: str, key: str) -> str:
        return f'[[keys]]\nname = "{name}"\nrole = "{role}"\nkey = "{hash_key(key)}"\n'

    keys = tmp_path / "keys.toml"
    keys.write_text(entry("ops", "admin", admin) + entry("dash", "viewer", viewer))
    srv = Server(tmp_path / "data", tmp_path / "server.log", env={"SGVLOC_KEYS_FILE": str(keys)})
    srv.start()

    def status(key: str) -> int:
        h = {"Authorization": f"Bearer {key}"}
        return httpx.get(f"{srv.url}/v1/config", headers=h, timeout=30).status_code

    def reload() -> httpx.Response:
        h = {"Authorization": f"Bearer {admin}"}
        return httpx.post(f"{srv.url}/v1/keys/reload", headers=h, timeout=30)

    try:
        assert status(viewer) == 200 and status(added) == 401
        keys.write_text(keys.read_text() + entry("new", "viewer", added))
        srv.proc.send_signal(signal.SIGHUP)
        deadline = time.monotonic() + 30
        while status(added) != 200:
            assert time.monotonic() < deadline, "SIGHUP did not load the added key"
            time.sleep(0.1)
        keys.write_text(entry("ops", "admin", admin) + entry("new", "viewer", added))
        r = reload()
        assert r.status_code == 200 and r.json() == {
            "keys": 2,
            "by_role": {"admin": 1, "viewer": 1},
        }
        assert status(viewer) == 401  # revoked: at once
        keys.write_text("[[keys]\nbroken = ")
        r = reload()
        assert r.status_code == 422 and "previous keys stay" in r.text
        srv.proc.send_signal(signal.SIGHUP)
        time.sleep(0.5)
        assert status(admin) == 200 and status(added) == 200 and status(viewer) == 401
        assert srv.proc.poll() is None  # SIGHUP does not stop the service
    finally:
        srv.stop()
    assert "keys file not reloaded" in srv.log()


def test_an_open_readyz_names_failed_maps_only_to_key_holders(tmp_path: Path) -> None:
    """/readyz is open by default (load balancers call it without a key): a map folder
    that fails to load makes it 503 degraded with a count for anyone, and its name and
    reason only for a caller with a key that may use that map."""
    keys = _write_keys(tmp_path / "keys.toml")
    maps = tmp_path / "data" / "maps"
    for name in ("auth-a", "other"):  # neither can be loaded
        (maps / name).mkdir(parents=True)
        (maps / name / "map.sqlite").write_bytes(b"not a database")
    srv = Server(tmp_path / "data", tmp_path / "server.log", env={"SGVLOC_KEYS_FILE": str(keys)})
    srv.start()
    try:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            seen = {}
            for who in (None, "wrong", "vehicle", "viewer-a", "admin"):
                r = c.get("/readyz", headers=_h(who))
                assert r.status_code == 503 and r.json()["status"] == "degraded", (who, r.text)
                assert r.json()["failed_maps"] == 2, r.text
                seen[who] = r.json()["failed"]
    finally:
        srv.stop()
    assert seen[None] == {} and seen["wrong"] == {}
    assert set(seen["vehicle"]) == set(seen["admin"]) == {"auth-a", "other"}
    assert "not a database" in seen["admin"]["other"], seen
    assert set(seen["viewer-a"]) == {"auth-a"}
