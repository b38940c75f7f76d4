"""SDK behaviour that needs no service: error mapping, headers, retries, imports, scans.

Requests go through ``httpx.MockTransport`` or to a closed port.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import httpx
import msgpack
import numpy as np
import pytest

from sgvloc_client import (
    APIError,
    AsyncClient,
    BadRequest,
    Client,
    Conflict,
    EncoderMismatch,
    Forbidden,
    KeyframeIn,
    MapUnavailable,
    NotFound,
    Overloaded,
    PayloadTooLarge,
    ScanFileError,
    ServerError,
    SgvlocError,
    TransportError,
    Unauthorized,
    wire,
)
from sgvloc_client.scans import read_kitti_bin, read_scan


def _packed(status: int, body: object) -> httpx.Response:
    return httpx.Response(status, content=wire.packb(body), headers={"Content-Type": wire.MSGPACK})


def _error_response(status: int, code: str, message: str = "m", field=None) -> httpx.Response:
    return httpx.Response(
        status, json={"error": {"code": code, "message": message, "field": field}}
    )


@pytest.mark.parametrize(
    ("status", "code", "cls"),
    [
        (400, "bad_body", BadRequest),
        (415, "unsupported_media_type", BadRequest),
        (422, "invalid_input", BadRequest),
        (404, "not_found", NotFound),
        (409, "conflict", Conflict),
        (409, "encoder_mismatch", EncoderMismatch),
        (413, "payload_too_large", PayloadTooLarge),
        (429, "overloaded", Overloaded),
        (503, "not_ready", Overloaded),
        (500, "internal", ServerError),
        (502, "http_502", ServerError),
        (401, "unauthorized", Unauthorized),
        (403, "forbidden", Forbidden),
        (405, "method_not_allowed", APIError),
    ],
)
def test_error_status_maps_to_exception(status: int, code: str, cls: type) -> None:
    transport = httpx.MockTransport(
        lambda request: _error_response(status, code, "what is wrong", "keyframes[3].points")
    )
    with Client(transport=transport, retries=0) as c, pytest.raises(cls) as info:
        c.get_map("campus")
    err = info.value
    assert type(err) is cls
    assert isinstance(err, APIError) and isinstance(err, SgvlocError)
    assert (err.status, err.code, err.message) == (status, code, "what is wrong")
    assert err.field == "keyframes[3].points"
    assert "keyframes[3].points" in str(err)


def test_error_body_in_msgpack_and_foreign_shapes() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/a"):
            err = {"code": "not_found", "message": "no map", "field": None}
            return _packed(404, {"error": err})
        if request.url.path.endswith("/b"):  # framework default body
            return httpx.Response(405, json={"detail": "Method Not Allowed"})
        return httpx.Response(500, text="<html>internal error</html>")  # a proxy's page

    with Client(transport=httpx.MockTransport(handler), retries=0) as c:
        with pytest.raises(NotFound, match="no map"):
            c.get_map("a")
        with pytest.raises(APIError) as info:
            c.get_map("b")
        assert (info.value.status, info.value.code) == (405, "http_405")
        assert "Method Not Allowed" in info.value.message
        with pytest.raises(ServerError) as info:
            c.get_map("c")
        assert info.value.code == "http_500"


def test_requests_are_msgpack_with_auth_header() -> None:
    seen: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        body = {"ids": [7], "created": [True], "map_version": 3}
        return _packed(201, body)

    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    pts = np.arange(12, dtype=np.float64).reshape(3, 4)
    with Client(transport=httpx.MockTransport(handler), api_key="s3cret") as c:
        res = c.insert_keyframe("campus", T, points=pts, key="seq/000001", metadata={"tags": {}})
    assert (res.ids, res.created, res.map_version, res.num_created) == ([7], [True], 3, 1)

    (req,) = seen
    assert req.method == "POST" and req.url.path == "/v1/maps/campus/keyframes"
    assert req.headers["content-type"] == wire.MSGPACK
    assert req.headers["accept"] == wire.MSGPACK
    assert req.headers["authorization"] == "Bearer s3cret"
    raw = msgpack.unpackb(req.content, raw=False)  # arrays travel as raw bytes
    kf = raw["keyframes"][0]
    assert kf["points"]["__nd__"] is True and kf["points"]["dtype"] == "<f4"
    assert kf["T_map_sensor"]["dtype"] == "<f8"
    decoded = wire.unpackb(req.content)["keyframes"][0]
    np.testing.assert_array_equal(decoded["T_map_sensor"], T)
    np.testing.assert_array_equal(decoded["points"], pts.astype(np.float32))
    assert decoded["key"] == "seq/000001"


def test_json_wire_format_and_no_auth_by_default() -> None:
    seen: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return httpx.Response(200, json={"status": "ok"})

    with Client(transport=httpx.MockTransport(handler), wire_format="json") as c:
        assert c.health() == {"status": "ok"}
        with pytest.raises(ValueError, match="exactly one"):
            c.localize("m")
    assert seen[0].headers["accept"] == wire.JSON
    assert "authorization" not in seen[0].headers


def test_localize_body_and_typed_result() -> None:
    T = np.eye(4)
    T[:3, 3] = [4.0, 5.0, 6.0]
    answer = {
        "map": "campus",
        "map_version": 9,
        "localized": True,
        "reason": "ok",
        "keyframe_id": 3,
        "T_map_sensor": T,
        "T_keyframe_sensor": np.eye(4),
        "translation": np.array([4.0, 5.0, 6.0]),
        "quaternion_xyzw": np.array([0.0, 0.0, 0.0, 1.0]),
        "pose": {
            "inliers": 40,
            "num_correspondences": 100,
            "fitness": 0.4,
            "inlier_rmse": 0.1,
            "refined": False,
        },
        "retrieved": [{"keyframe_id": 3, "similarity": 0.9, "retrieval_rank": 0, "score": 0.8}],
        "reranked": [{"keyframe_id": 3, "similarity": 0.9, "retrieval_rank": 0, "score": 0.8}],
        "top1_changed": False,
        "rerank_method": "sgv",
        "timings_ms": {"encode": 1.0, "total": 2.0},
    }
    seen: list[dict] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(wire.unpackb(request.content))
        return _packed(200, answer)

    with Client(transport=httpx.MockTransport(handler)) as c:
        loc = c.localize("campus", points=np.zeros((5, 3)), top_k=5, rerank="sgv")
    assert seen[0]["top_k"] == 5 and seen[0]["rerank"] == "sgv" and "refine" not in seen[0]
    assert seen[0]["points"].dtype == np.float32
    assert loc.localized and loc.keyframe_id == 3 and loc.map_version == 9
    assert loc.T_map_sensor.shape == (4, 4) and loc.T_map_sensor.dtype == np.float64
    np.testing.assert_array_equal(loc.T_map_sensor, T)
    loc.T_map_sensor[0, 0] = 2.0  # results own writable copies
    assert loc.pose.inliers == 40 and loc.retrieved[0].score == 0.8
    assert loc.quaternion_xyzw.tolist() == [0.0, 0.0, 0.0, 1.0]


class CountingTransport(httpx.HTTPTransport):
    """A real transport that counts the requests it tries to send."""

    def __init__(self) -> None:
        super().__init__()
        self.sent = 0

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        self.sent += 1
        return super().handle_request(request)


def test_retries_on_closed_port_only_for_idempotent_calls(closed_url: str) -> None:
    url = closed_url
    kf = {"T_map_sensor": np.eye(4), "points": np.zeros((4, 3))}

    def attempts(call) -> int:
        transport = CountingTransport()
        with Client(url, retries=2, backoff=0.01, transport=transport) as c:
            with pytest.raises(TransportError) as info:
                call(c)
        assert info.value.attempts == transport.sent
        assert isinstance(info.value.__cause__, httpx.ConnectError)
        return transport.sent

    assert attempts(lambda c: c.get_map("m")) == 3
    assert attempts(lambda c: c.localize("m", points=np.zeros((4, 3)))) == 3
    assert attempts(lambda c: c.insert_keyframes("m", [{**kf, "key": "a"}])) == 3
    # Not safe to resend: a keyless insert could store twice, a create could 409, a
    # delete whose answer was lost would answer 404 (or delete what was added since),
    # a self-test that timed out may still run and each try would start another.
    assert attempts(lambda c: c.insert_keyframes("m", [{**kf, "key": "a"}, kf])) == 1
    assert attempts(lambda c: c.create_map("m")) == 1
    assert attempts(lambda c: c.delete_map("m")) == 1
    assert attempts(lambda c: c.delete_keyframe("m", 1)) == 1
    assert attempts(lambda c: c.delete_keyframes("m", key_prefix="k")) == 1
    assert attempts(lambda c: c.self_test_map("m")) == 1

    with Client(url, retries=0) as c, pytest.raises(TransportError, match="1 attempt"):
        c.health()


def test_each_resend_is_logged(closed_url: str, caplog) -> None:
    """A call that keeps failing says so as it resends (a stuck build was silent for
    its whole timeout times its tries)."""
    with Client(closed_url, retries=2, backoff=0.01) as c, caplog.at_level("WARNING"):
        with pytest.raises(TransportError):
            c.get_map("m")
    lines = [r.getMessage() for r in caplog.records if r.name == "sgvloc_client"]
    assert len(lines) == 2, lines
    assert "GET " in lines[0] and "/v1/maps/m failed (ConnectError)" in lines[0], lines
    assert lines[0].endswith("(try 2 of 3)") and lines[1].endswith("(try 3 of 3)"), lines


def test_async_client_retries_and_errors(closed_url: str) -> None:
    url = closed_url

    async def main() -> None:
        async with AsyncClient(url, retries=1, backoff=0.01) as c:
            with pytest.raises(TransportError) as info:
                await c.list_maps()
            assert info.value.attempts == 2
        transport = httpx.MockTransport(lambda r: _error_response(409, "conflict"))
        async with AsyncClient(transport=transport) as c:
            with pytest.raises(Conflict):
                await c.create_map("campus")

    asyncio.run(main())


def test_a_failed_export_keeps_the_file_and_archive_calls_raise_the_sdks_errors(
    closed_url: str, tmp_path: Path
) -> None:
    """export_map writes beside the destination and replaces it only once the archive
    arrived whole; a connection that fails is the SDK's TransportError, sync and async."""
    dest = tmp_path / "campus.sgvmap.tar"
    dest.write_bytes(b"an earlier archive")
    transport = httpx.MockTransport(lambda r: _error_response(404, "not_found"))
    with Client(transport=transport) as c, pytest.raises(NotFound):
        c.export_map("nope", dest)
    assert dest.read_bytes() == b"an earlier archive" and sorted(tmp_path.iterdir()) == [dest]
    ok = httpx.MockTransport(lambda r: httpx.Response(200, content=b"tar" * 1000))
    with Client(transport=ok) as c:
        assert c.export_map("campus", dest) == 3000 and dest.read_bytes() == b"tar" * 1000
    with Client(closed_url) as c:
        with pytest.raises(TransportError):
            c.export_map("campus", tmp_path / "x.tar")
        with pytest.raises(TransportError):
            c.import_map(dest)

    async def main() -> None:
        async with AsyncClient(closed_url) as c:
            with pytest.raises(TransportError):
                await c.export_map("campus", tmp_path / "y.tar")
            with pytest.raises(TransportError):
                await c.import_map(dest)

    asyncio.run(main())
    assert sorted(tmp_path.iterdir()) == [dest]


def test_wait_until_ready_ends_when_it_said_against_a_silent_service() -> None:
    """A service that never answers: each poll is sent once, with no more time than the
    wait has left, not retried at the client's timeout (here 10 s each)."""
    timeouts = []

    def silent(request: httpx.Request) -> httpx.Response:
        timeouts.append(request.extensions["timeout"]["read"])
        raise httpx.ReadTimeout("no answer", request=request)

    with Client(transport=httpx.MockTransport(silent), timeout=10.0, retries=3) as c:
        with pytest.raises(TransportError, match="not ready after 0.5 s"):
            c.wait_until_ready(timeout=0.5)
    assert timeouts and all(t <= 0.5 for t in timeouts), timeouts


def test_a_self_test_without_a_timeout_waits_as_long_as_it_takes() -> None:
    seen = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request.extensions["timeout"])
        return _packed(200, {"figures": {}})

    with Client(transport=httpx.MockTransport(handler), timeout=0.5) as c:
        c.self_test_map("m", timeout=None)
        c.self_test_map("m", timeout=60.0)
    assert seen[0]["read"] is None and seen[1]["read"] == 60.0


def test_arrays_keep_their_values_on_the_wire() -> None:
    for a in (
        np.array([3_000_000_000], np.uint32),
        np.array([-3], np.int8),
        np.array([2**40], np.uint64),
        np.zeros((0, 3), np.float32),
    ):
        back = wire.unpackb(wire.packb({"a": a}))["a"]
        assert back.tolist() == a.tolist() and back.shape == a.shape
    with pytest.raises(ValueError, match="beyond int64"):
        wire.packb(np.array([2**63], np.uint64))
    with pytest.raises(ValueError, match="numbers only"):
        wire.packb(np.array(["text"]))


def test_timeout_is_an_httpx_timeout_value() -> None:
    with Client(timeout=2.5) as c:
        assert c.timeout == httpx.Timeout(2.5)
    custom = httpx.Timeout(10.0, connect=1.0)
    with Client(timeout=custom) as c:
        assert c.timeout is custom


def test_keyframe_in_coercion() -> None:
    kf = KeyframeIn.coerce({"T_map_sensor": np.eye(4), "points": [[1, 2, 3]], "key": "k"})
    body = kf.to_body()
    assert body["points"].dtype == np.float32 and body["T_map_sensor"].dtype == np.float64
    assert "features" not in body and "metadata" not in body
    with pytest.raises(TypeError, match="unknown keyframe field"):
        KeyframeIn.coerce({"T_map_sensor": np.eye(4), "pose": np.eye(4)})
    with Client() as c, pytest.raises(TypeError, match="must be a list"):
        c.insert_keyframes("m", kf)


def test_client_imports_without_heavy_dependencies() -> None:
    code = textwrap.dedent(
        """
        import sys
        from importlib.abc import MetaPathFinder

        BLOCKED = ("torch", "open3d", "faiss", "scipy", "fastapi", "sgvloc.core.encoders")

        class Block(MetaPathFinder):
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in BLOCKED or name in BLOCKED:
                    raise ImportError(f"{name} is blocked")
                return None

        sys.meta_path.insert(0, Block())
        import numpy as np
        import sgvloc_client
        from sgvloc_client import Client, AsyncClient, KeyframeIn
        from sgvloc_client.scans import read_scan
        pts = read_scan(sys.argv[1])
        assert pts.shape[1] == 4
        print("ok", len(sgvloc_client.__all__))
        """
    )
    scan = "tests/fixtures/balm_mini/velodyne/000000.bin"
    npy_code = code.replace("read_scan(sys.argv[1])", "read_scan(sys.argv[2])")
    with tempfile.TemporaryDirectory() as d:
        npy = Path(d) / "scan.npy"
        np.save(npy, np.zeros((5, 3), dtype=np.float32))
        for src in (code, npy_code):
            out = subprocess.run(
                [sys.executable, "-c", src, scan, str(npy)],
                capture_output=True,
                text=True,
                timeout=60,
                cwd=Path(__file__).resolve().parents[2],
            )
            assert out.returncode == 0, out.stderr
            assert out.stdout.startswith("ok")


def test_a_scan_format_whose_package_is_missing_says_which(tmp_path, monkeypatch) -> None:
    """The client-only install reads .bin/.npy/.npz; a .pcd without pypcd4 (or a .ply
    without plyfile) is a ScanFileError naming the package, not a ModuleNotFoundError."""
    from sgvloc.core.io import write_pcd, write_ply

    pts = np.random.default_rng(0).normal(size=(20, 4)).astype(np.float32)
    for name, package, write in (("s.pcd", "pypcd4", write_pcd), ("s.ply", "plyfile", write_ply)):
        write(tmp_path / name, pts)
        with monkeypatch.context() as m:
            for mod in [k for k in sys.modules if k.split(".")[0] == package]:
                m.delitem(sys.modules, mod)
            m.setitem(sys.modules, package, None)  # as if not installed
            with pytest.raises(ScanFileError, match=f"needs the {package} package"):
                read_scan(tmp_path / name)


def test_read_scan_formats_and_errors(tmp_path, balm_mini_dir) -> None:
    pts = read_kitti_bin(balm_mini_dir / "velodyne" / "000000.bin")
    assert pts.dtype == np.float32 and pts.shape == (9120, 4)
    np.save(tmp_path / "a.npy", pts[:, :3].astype(np.float64))
    a = read_scan(tmp_path / "a.npy")
    assert a.shape == (9120, 4) and a.dtype == np.float32
    np.testing.assert_array_equal(a[:, :3], pts[:, :3])
    assert (a[:, 3] == 0).all()

    (tmp_path / "bad.bin").write_bytes(b"\0" * 10)
    with pytest.raises(ScanFileError, match="multiple of 16"):
        read_scan(tmp_path / "bad.bin")
    with pytest.raises(ScanFileError, match="not found|cannot read"):
        read_scan(tmp_path / "missing.bin")
    with pytest.raises(ScanFileError, match="extension"):
        read_scan(tmp_path / "scan.xyz")
    (tmp_path / "bad.pcd").write_text("VERSION 0.7\nFIELDS a b\n")
    with pytest.raises(ScanFileError, match="bad.pcd"):
        read_scan(tmp_path / "bad.pcd")
    assert issubclass(ScanFileError, ValueError)


def test_json_bodies_roundtrip_through_models() -> None:
    info = {
        "name": "campus",
        "version": 2,
        "keyframes": 5,
        "encoder": {"kind": "handcrafted", "name": "h", "fingerprint": "ab", "spec": {}},
        "retrieval": {"index": "flat"},
        "index_kind": "flat",
        "created_at": "2024-01-01T00:00:00Z",
    }
    transport = httpx.MockTransport(
        lambda r: httpx.Response(
            200,
            content=json.dumps({"maps": [info]}).encode(),
            headers={"Content-Type": "application/json"},
        )
    )
    with Client(transport=transport) as c:
        (m,) = c.list_maps()
    assert (m.name, m.version, m.keyframes, m.encoder.kind, m.index_kind) == (
        "campus",
        2,
        5,
        "handcrafted",
        "flat",
    )


def _overloaded_then_ok(statuses: list[int], retry_after: str | None = "0"):
    """A transport answering each status of ``statuses`` in turn (429/503 with
    ``Retry-After``), then 200 with a map; records every request."""
    seen: list[httpx.Request] = []
    body = {"name": "campus", "version": 1, "keyframes": 0, "encoder": {}, "retrieval": {}}

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        if len(seen) <= len(statuses):
            headers = {} if retry_after is None else {"Retry-After": retry_after}
            status = statuses[len(seen) - 1]
            return httpx.Response(
                status, json={"error": {"code": "overloaded", "message": "busy"}}, headers=headers
            )
        return httpx.Response(200, json=body)

    return handler, seen


def test_list_maps_follows_pages_and_refuses_a_stuck_cursor() -> None:
    """list_maps reads every page; a service without paging (no next_cursor) is one
    page; a cursor that does not move on is an error rather than a loop."""

    def info(name: str) -> dict:
        return {"name": name, "version": 0, "keyframes": 0, "encoder": {}, "retrieval": {}}

    names = ["m-a", "m-b", "m-c", "m-d", "m-e"]
    seen: list[httpx.URL] = []

    def paged(request: httpx.Request) -> httpx.Response:
        seen.append(request.url)
        cursor = request.url.params.get("cursor")
        rest = [n for n in names if cursor is None or n > cursor]
        page = rest[:2]  # a service whose pages are smaller than asked
        nxt = page[-1] if len(rest) > 2 else None
        return httpx.Response(200, json={"maps": [info(n) for n in page], "next_cursor": nxt})

    with Client(transport=httpx.MockTransport(paged)) as c:
        assert [m.name for m in c.list_maps(prefix="m-")] == names
    assert [u.params.get("cursor") for u in seen] == [None, "m-b", "m-d"]
    assert all(u.params["prefix"] == "m-" and u.params["limit"] == "1000" for u in seen)

    def unpaged(request: httpx.Request) -> httpx.Response:
        return httpx.Response(200, json={"maps": [info(n) for n in names]})

    with Client(transport=httpx.MockTransport(unpaged)) as c:
        assert [m.name for m in c.list_maps()] == names
        assert [m.name for m in c.list_maps(prefix="m-c")] == ["m-c"]  # it ignores prefix
        assert c.list_maps_page(prefix="m-c").total == 1
        assert c.list_maps_page().total is None  # it does not count

    def stuck(request: httpx.Request) -> httpx.Response:
        return httpx.Response(200, json={"maps": [info("m-a")], "next_cursor": "m-a"})

    with Client(transport=httpx.MockTransport(stuck)) as c:
        with pytest.raises(SgvlocError, match="did not move on"):
            c.list_maps()
        with pytest.raises(ValueError, match="limit"):
            c.list_maps_page(limit=0)


def test_overloaded_answers_are_retried_only_when_asked() -> None:
    handler, seen = _overloaded_then_ok([429, 503])
    transport = httpx.MockTransport(handler)
    # off by default: the first 429 is the answer
    with Client(transport=transport) as c, pytest.raises(Overloaded):
        c.get_map("campus")
    assert len(seen) == 1
    seen.clear()
    with Client(transport=transport, retry_overloaded=True, retries=3) as c:
        assert c.get_map("campus").name == "campus"
    assert len(seen) == 3
    # the retries are counted: 2 overloaded answers with retries=1 raise
    seen.clear()
    with Client(transport=transport, retry_overloaded=True, retries=1) as c:
        with pytest.raises(Overloaded):
            c.get_map("campus")
    assert len(seen) == 2


def test_overload_retry_waits_retry_after_and_skips_unsafe_calls(monkeypatch) -> None:
    import sgvloc_client._client as sync_client

    waits: list[float] = []  # what the client sleeps, recorded instead of slept
    monkeypatch.setattr(sync_client.time, "sleep", waits.append)
    handler, seen = _overloaded_then_ok([503], retry_after="0.3")
    with Client(transport=httpx.MockTransport(handler), retry_overloaded=True) as c:
        c.get_map("campus")
        assert waits == [0.3] and len(seen) == 2
    # a Retry-After longer than max_retry_after is not waited for
    handler, seen = _overloaded_then_ok([503], retry_after="120")
    with Client(transport=httpx.MockTransport(handler), retry_overloaded=True) as c:
        with pytest.raises(Overloaded):
            c.get_map("campus")
    assert len(seen) == 1
    # create_map is not safe to resend: never retried
    handler, seen = _overloaded_then_ok([429])
    with Client(transport=httpx.MockTransport(handler), retry_overloaded=True) as c:
        with pytest.raises(Overloaded):
            c.create_map("campus")
    assert len(seen) == 1


def _six_overloads_then_ok(**options) -> int:
    """get_map against six 503s without Retry-After and then the map, resending after
    each (backoff 0.2 s, at most 1 s); returns how many requests were sent."""
    handler, seen = _overloaded_then_ok([503] * 6, retry_after=None)
    with Client(
        transport=httpx.MockTransport(handler),
        retry_overloaded=True,
        retries=6,
        backoff=0.2,
        max_backoff=1.0,
        **options,
    ) as c:
        c.get_map("campus")
    return len(seen)


def test_backoff_jitter_spreads_waits_within_the_backoff(monkeypatch) -> None:
    """By default each wait is a random draw from half the backoff to all of it, and two
    clients that fail together wait differently; a connection error's resend waits the
    same way."""
    import sgvloc_client._client as sync_client

    waits: list[float] = []
    monkeypatch.setattr(sync_client.time, "sleep", waits.append)
    for _ in range(2):
        assert _six_overloads_then_ok() == 7
    caps = [0.2, 0.4, 0.8, 1.0, 1.0, 1.0] * 2
    assert all(cap / 2 <= w <= cap for w, cap in zip(waits, caps, strict=True)), waits
    assert waits[:6] != waits[6:]  # two clients, two draws
    waits.clear()

    def refuse(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("refused", request=request)

    with Client(transport=httpx.MockTransport(refuse), retries=3, backoff=0.4) as c:
        with pytest.raises(TransportError):
            c.get_map("campus")
    assert len(waits) == 3
    assert all(cap / 2 <= w <= cap for w, cap in zip(waits, [0.4, 0.8, 1.6], strict=True))


def test_overload_waits_are_bounded_and_read_http_dates(monkeypatch) -> None:
    """Without Retry-After the wait is the backoff, within max_backoff; a Retry-After
    date is read as the time until it (a date past max_retry_after is not waited for)."""
    import email.utils

    import sgvloc_client._client as sync_client

    waits: list[float] = []
    monkeypatch.setattr(sync_client.time, "sleep", waits.append)
    assert _six_overloads_then_ok(jitter=False) == 7
    assert waits == pytest.approx([0.2, 0.4, 0.8, 1.0, 1.0, 1.0])
    waits.clear()
    soon = email.utils.formatdate(time.time() + 10, usegmt=True)
    handler, seen = _overloaded_then_ok([503], retry_after=soon)
    with Client(transport=httpx.MockTransport(handler), retry_overloaded=True) as c:
        c.get_map("campus")
    assert len(waits) == 1 and 8.0 <= waits[0] <= 10.0, waits
    far = email.utils.formatdate(time.time() + 3600, usegmt=True)
    handler, seen = _overloaded_then_ok([503], retry_after=far)
    with Client(transport=httpx.MockTransport(handler), retry_overloaded=True) as c:
        with pytest.raises(Overloaded):
            c.get_map("campus")
    assert len(seen) == 1
    with pytest.raises(ValueError, match="backoff"):
        Client(backoff=-1)


def test_async_client_retries_overloaded_answers() -> None:
    handler, seen = _overloaded_then_ok([429, 429], retry_after=None)

    async def main() -> str:
        transport = httpx.MockTransport(handler)
        async with AsyncClient(transport=transport, retry_overloaded=True, backoff=0.01) as c:
            return (await c.get_map("campus")).name

    assert asyncio.run(main()) == "campus" and len(seen) == 3


@pytest.mark.parametrize(
    ("failure", "sent"),
    [(httpx.ReadTimeout, 1), (httpx.ConnectError, 3), (httpx.RemoteProtocolError, 3)],
)
def test_a_keyed_insert_is_not_resent_after_a_read_timeout(failure, sent: int) -> None:
    """A keyed insert is safe to resend, but after a read timeout the service may still
    be encoding the batch: a resend would encode it again on another worker."""
    calls = []

    def failing(request: httpx.Request) -> httpx.Response:
        calls.append(request.method)
        raise failure("no answer", request=request)

    kf = {"T_map_sensor": np.eye(4), "points": np.zeros((10, 3), np.float32), "key": "k1"}
    with Client(transport=httpx.MockTransport(failing), retries=2, backoff=0.0) as c:
        with pytest.raises(TransportError):
            c.insert_keyframes("m", [kf])
    assert calls == ["POST"] * sent

    async def main() -> None:
        calls.clear()
        transport = httpx.MockTransport(failing)
        async with AsyncClient(transport=transport, retries=2, backoff=0.0) as c:
            with pytest.raises(TransportError):
                await c.insert_keyframes("m", [kf])
        assert calls == ["POST"] * sent

    asyncio.run(main())


def test_a_tracker_that_lost_the_track_for_long_asks_for_a_global_search() -> None:
    """Each miss widens the seed; once it would pass what the service takes
    (seed.sigma_m <= 1e4) the tracker gives no seed: a global localization."""
    from sgvloc_client.tracking import MAX_SEED_SIGMA_M, MotionModel

    t = MotionModel(max_misses=100)
    t.pose, t.stamp = np.eye(4), 0.0
    seeds = []
    for k in range(1, 40):
        t.misses = k
        seeds.append(t.seed(0.1))
    sigmas = [s.sigma_m for s in seeds if s is not None]
    assert sigmas and max(sigmas) <= MAX_SEED_SIGMA_M
    assert seeds[-1] is None


def test_a_scan_stamped_before_the_last_fix_gets_no_seed() -> None:
    """A clock reset or a bag played again: what the track knows is of another time."""
    from sgvloc_client.tracking import MotionModel

    m = MotionModel()
    m.pose, m.stamp = np.eye(4), 100.0
    assert m.seed(100.1) is not None
    assert m.seed(0.0) is None and m.seed(-5000.0) is None


def test_a_refused_replica_is_left_whatever_retries_says(closed_url: str) -> None:
    """With retries=0 a refused connection (nothing sent) still moves to the next
    replica and marks the dead one down: every call succeeds, not every second one."""
    body = {"name": "m", "version": 1, "keyframes": 0, "encoder": {}, "retrieval": {}}
    live = httpx.MockTransport(lambda r: httpx.Response(200, json=body))

    class Mixed(httpx.BaseTransport):
        def handle_request(self, request: httpx.Request) -> httpx.Response:
            if request.url.port == httpx.URL(closed_url).port:
                raise httpx.ConnectError("refused", request=request)
            return live.handle_request(request)

    with Client([closed_url, "http://127.0.0.1:9"], retries=0, transport=Mixed()) as c:
        assert [c.get_map("m").name for _ in range(4)] == ["m"] * 4


def test_an_answer_that_is_not_the_services_is_a_transport_error() -> None:
    """A captive portal's page or another service's JSON under 200 is an SgvlocError
    (TransportError), not an AttributeError or KeyError out of the parser."""
    for content, ctype in (
        (b"<html>login</html>", "text/html"),
        (b'{"map": "m"}', "application/json"),
    ):
        transport = httpx.MockTransport(
            lambda r, c=content, t=ctype: httpx.Response(
                200, content=c, headers={"Content-Type": t}
            )
        )
        with Client(transport=transport) as c:
            with pytest.raises(TransportError, match="is not the service's"):
                c.localize("m", points=np.zeros((10, 3)))


def test_total_timeout_counts_the_tries_it_sent(closed_url: str) -> None:
    with Client(closed_url, retries=5, backoff=0.3, total_timeout=0.5) as c:
        with pytest.raises(TransportError, match="total_timeout") as info:
            c.get_map("m")
    assert info.value.attempts >= 2 and "ConnectError" in str(info.value)


def test_map_unavailable_is_its_own_error_and_not_resent() -> None:
    seen = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        error = {"code": "map_unavailable", "message": "could not be loaded"}
        return httpx.Response(503, json={"error": error})

    with Client(transport=httpx.MockTransport(handler), retry_overloaded=True) as c:
        with pytest.raises(MapUnavailable):
            c.get_map("broken")
    assert len(seen) == 1  # waits on an operator, not on time
    assert issubclass(MapUnavailable, Overloaded)


def test_wait_until_ready_takes_a_degraded_service() -> None:
    """A service with one map that failed to load serves the others: ready to use."""
    answers = iter(["loading", "degraded", "degraded"])
    transport = httpx.MockTransport(
        lambda r: httpx.Response(503, json={"status": next(answers), "maps": 1})
    )
    with Client(transport=transport) as c:
        c.wait_until_ready(timeout=5, interval=0.01)
        assert c.ready() is False  # the probe itself still says not all is well


def test_sdk_argument_checks() -> None:
    from sgvloc_client import Tracker

    with Client("http://127.0.0.1:9") as c:
        with pytest.raises(ValueError, match="may not set seed"):
            Tracker(c, "m", localize_options={"seed": None})
        with pytest.raises(ValueError, match="an integer"):
            c.localize("m", points=np.zeros((10, 3)), min_map_version=0.9)


def test_error_classes_by_code() -> None:
    from sgvloc_client import EmptyScan
    from sgvloc_client._errors import error_class

    assert error_class(422, "empty_scan") is EmptyScan and issubclass(EmptyScan, BadRequest)
    assert error_class(503, "map_unavailable") is MapUnavailable
    assert error_class(503, "overloaded") is Overloaded
    assert error_class(422, "invalid_input") is BadRequest


def test_tracker_and_prior_arguments_are_checked() -> None:
    from sgvloc_client import Prior
    from sgvloc_client.tracking import MotionModel

    with pytest.raises(ValueError, match="nanoseconds"):
        MotionModel().seed(1.7e18, None)  # a ROS stamp in ns
    with pytest.raises(TypeError, match=r"\[x, y\]"):
        Prior(3.0, 5).to_body()


def test_a_gateway_error_is_no_answer_and_moves_to_the_next_replica() -> None:
    """A load balancer's 502/504 page means no replica answered: a TransportError, and
    with several URLs the call moves on (a ServerError before, never resent)."""
    body = {"name": "m", "version": 1, "keyframes": 0, "encoder": {}, "retrieval": {}}

    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.port == 1:
            return httpx.Response(502, text="<html>502 Bad Gateway</html>")
        return httpx.Response(200, json=body)

    transport = httpx.MockTransport(handler)
    with Client("http://127.0.0.1:1", transport=transport, retries=0) as c:
        with pytest.raises(TransportError, match="load balancer answered 502"):
            c.get_map("m")
    with Client(["http://127.0.0.1:1", "http://127.0.0.1:2"], transport=transport) as c:
        assert [c.get_map("m").name for _ in range(3)] == ["m"] * 3


def test_a_busy_replica_hands_the_call_to_the_next() -> None:
    """A 429 (that replica is full) moves a call safe to resend to another replica at
    once, as a 503 does; with one URL it stays an Overloaded answer."""
    body = {"name": "m", "version": 1, "keyframes": 0, "encoder": {}, "retrieval": {}}

    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.port == 1:
            error = {"code": "overloaded", "message": "too many localizations"}
            return httpx.Response(429, json={"error": error}, headers={"Retry-After": "1"})
        return httpx.Response(200, json=body)

    transport = httpx.MockTransport(handler)
    with Client(["http://127.0.0.1:1", "http://127.0.0.1:2"], transport=transport) as c:
        assert [c.get_map("m").name for _ in range(3)] == ["m"] * 3
    with Client("http://127.0.0.1:1", transport=transport) as c:
        with pytest.raises(Overloaded):
            c.get_map("m")
