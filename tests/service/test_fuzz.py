"""Property-based fuzzing of the HTTP API from its own OpenAPI document (schemathesis),
in a short form: a bounded number of generated requests per operation, JSON and
MessagePack bodies, against a real server of its own with authentication on, every call
made with an admin key (so requests reach the handlers of every route). Every answer must
be a documented status with a body matching the schema; never a 5xx.

Malformed binary payloads (random bytes, truncated MessagePack, arrays whose declared
shape lies about their length) must get a 4xx too.
"""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import msgpack
import numpy as np
import pytest
import schemathesis
import schemathesis_hooks  # noqa: F401 - registers the MessagePack serializer
from conftest import Server
from hypothesis import HealthCheck, Phase, settings
from schemathesis.specs.openapi.checks import positive_data_acceptance
from svc_helpers import PRECOMPUTED, post_msgpack, random_features

from sgvloc_client import wire

MAX_EXAMPLES = 25
ADMIN_KEY = "fuzz-admin-key-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {ADMIN_KEY}"}


@pytest.fixture(scope="module")
def fuzz_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    root = tmp_path_factory.mktemp("fuzz")
    keys = root / "keys.toml"
    keys.write_text(f'[[keys]]\nname = "fuzz"\nrole = "admin"\nkey = "{ADMIN_KEY}"\n')
    srv = Server(
        data_dir=root / "data", log_path=root / "server.log", env={"SGVLOC_KEYS_FILE": str(keys)}
    )
    srv.start()
    try:
        with httpx.Client(base_url=srv.url, timeout=60, headers=AUTH) as c:
            r = c.post("/v1/maps", json={"name": "fuzz", "encoder": PRECOMPUTED})
            assert r.status_code == 201
            kf = {"T_map_sensor": np.eye(4), "features": random_features(np.random.default_rng(0))}
            assert (
                post_msgpack(c, "/v1/maps/fuzz/keyframes", {"keyframes": [kf]}).status_code == 201
            )
        yield srv
    finally:
        srv.stop()


@pytest.fixture(scope="module")
def api_schema(fuzz_server: Server):
    return schemathesis.openapi.from_url(f"{fuzz_server.url}/openapi.json")


schema = schemathesis.pytest.from_fixture("api_schema")


@schema.parametrize()
@settings(
    max_examples=MAX_EXAMPLES,
    deadline=None,
    phases=[Phase.explicit, Phase.generate],
    suppress_health_check=list(HealthCheck),
    derandomize=True,
)
def test_api_conforms_to_its_schema(case) -> None:  # noqa: ANN001
    # "schema-valid request accepted" does not hold: the service checks more than the
    # schema can say (map names, encoder specs, array shapes) and answers those with 4xx
    case.call_and_validate(timeout=60, headers=AUTH, excluded_checks=[positive_data_acceptance])


# -- malformed binary payloads ---------------------------------------------------------------


def _post(srv: Server, path: str, data: bytes) -> httpx.Response:
    return httpx.post(
        f"{srv.url}{path}", content=data, headers={"Content-Type": wire.MSGPACK, **AUTH}, timeout=60
    )


@pytest.mark.parametrize("path", ["/v1/maps/fuzz/localize", "/v1/maps/fuzz/keyframes", "/v1/maps"])
def test_random_and_lying_msgpack_is_4xx(fuzz_server: Server, path: str) -> None:
    rng = np.random.default_rng(7)
    feats = random_features(rng)
    good = wire.packb({"features": feats, "keyframes": [{"T_map_sensor": np.eye(4)}]})
    bodies = [rng.bytes(n) for n in (1, 7, 64, 1000)]
    bodies += [good[:cut] for cut in (1, 5, len(good) // 3, len(good) - 1)]
    # arrays whose header lies: more/less data than the shape, odd dtypes, huge shapes
    raw = wire._to_wire({"features": feats})
    for change in (
        {"shape": [64, 3000]},
        {"shape": [-1, 3]},
        {"shape": [2**40, 2**40]},
        {"dtype": "<c16"},
        {"dtype": "|O"},
        {"dtype": "nonsense"},
        {"data": b"\x00" * 7},
        {"data": "not bytes"},
    ):
        bad = {"features": {**raw["features"]}}
        bad["features"]["keypoints"] = {**raw["features"]["keypoints"], **change}
        bodies.append(msgpack.packb(bad, use_bin_type=True))
    bodies.append(msgpack.packb({"__nd__": True}, use_bin_type=True))
    bodies.append(b"\xc1" * 16)  # a never-used MessagePack type byte
    bodies.append(b"\xdd\xff\xff\xff\xff")  # an array header claiming 4 billion items
    bodies.append(b"\x91" * 5000)  # deeply nested arrays
    for body in bodies:
        r = _post(fuzz_server, path, body)
        assert 400 <= r.status_code < 500, (body[:40], r.status_code, r.text)
        assert set(r.json()) == {"error"}


def test_server_survived(fuzz_server: Server) -> None:
    assert httpx.get(f"{fuzz_server.url}/readyz").status_code == 200
    assert "Traceback" not in fuzz_server.log()


def test_schema_lists_every_error_body(fuzz_server: Server) -> None:
    doc = httpx.get(f"{fuzz_server.url}/openapi.json").json()
    for path, ops in doc["paths"].items():
        for op in ops.values():
            if op["operationId"] != "healthz":
                assert {"401", "403"} <= set(op["responses"]), path
