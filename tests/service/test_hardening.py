"""Hardening against a real server: bounded settings and keypoints, finite metadata,
model files confined to a models directory, and a bad map folder that blocks nothing
and leaks no server path."""

from __future__ import annotations

import re
import shutil
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import msgpack
import numpy as np
import pytest
from conftest import Server
from svc_helpers import PRECOMPUTED, answer_head, error_of, post_msgpack, random_features

import sgvloc_client
from sgvloc.core.encoders.learned import shipped_weights_path
from sgvloc_client import wire

_JSON = {"Content-Type": "application/json"}
_MSGPACK = {"Content-Type": wire.MSGPACK}

EYE = np.eye(4).tolist()


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"localizer": {"pose": {"max_iterations": 10**12}}}, "max_iterations"),
        ({"retrieval": {"index": "hnsw", "hnsw_m": 10**6}}, "hnsw_m"),
        ({"retrieval": {"index": "ivf", "nlist": 10**9}}, "nlist"),
        ({"encoder": {"kind": "bev", "bev": {"raster": {"extent": 1e6}}}}, "extent"),
        ({"encoder": {"kind": "handcrafted", "handcrafted": {"rings": 10**6}}}, "rings"),
        ({"encoder": {"kind": "handcrafted", "handcrafted": {"sectors": 10**6}}}, "sectors"),
        ({"localizer": {"pose": {"seed": -1}}}, "seed"),
        ({"encoder": {**PRECOMPUTED, "global_dim": 10**9}}, "global_dim"),
    ],
)
def test_map_settings_have_upper_bounds(client: httpx.Client, body: dict, field: str) -> None:
    r = client.post("/v1/maps", json={"name": "bounded", **body})
    assert r.status_code == 422, r.text
    err = error_of(r)
    assert err["code"] == "invalid_input" and field in (err["field"] or ""), err
    assert client.get("/v1/maps/bounded").status_code == 404


def test_config_reports_every_limit_and_timeout(client: httpx.Client) -> None:
    """OPERATIONS.md: every limit is reported by GET /v1/config (each max_* and *_timeout_s
    setting, under limits or at the top)."""
    from sgvloc.server.settings import Settings

    cfg = client.get("/v1/config").json()
    shown = set(cfg) | set(cfg["limits"])
    wanted = {f for f in Settings.model_fields if f.startswith("max_") or f.endswith("_timeout_s")}
    assert wanted - shown == set(), wanted - shown


def test_keypoints_per_feature_set_are_limited(client: httpx.Client) -> None:
    """Precomputed features beyond max_keypoints (4096 by default) are refused before
    any work; a new map's encoder may not make more either."""
    assert client.get("/v1/config").json()["limits"]["max_keypoints"] == 4096
    assert client.post("/v1/maps", json={"name": "kp", "encoder": PRECOMPUTED}).status_code == 201
    rng = np.random.default_rng(0)
    n = 5000
    feats = {
        "global_descriptor": rng.normal(size=16).astype(np.float32),
        "keypoints": rng.normal(size=(n, 3)).astype(np.float32),
        "local_features": rng.normal(size=(n, 8)).astype(np.float32),
    }
    r = post_msgpack(client, "/v1/maps/kp/localize", {"features": feats})
    assert r.status_code == 422 and "max_keypoints" in error_of(r)["message"], r.text
    assert error_of(r)["field"].startswith("features.")
    r = post_msgpack(client, "/v1/maps/kp/keyframes", {"keyframes": [
        {"T_map_sensor": np.eye(4), "features": feats}]})  # fmt: skip
    assert r.status_code == 422, r.text
    assert client.get("/v1/maps/kp").json()["keyframes"] == 0
    spec = {"kind": "handcrafted", "handcrafted": {"num_keypoints": 10_000}}
    r = client.post("/v1/maps", json={"name": "kp2", "encoder": spec})
    assert r.status_code == 422, r.text
    assert error_of(r)["field"] == "encoder.handcrafted.num_keypoints"
    client.delete("/v1/maps/kp")


@pytest.mark.parametrize("value", ["NaN", "Infinity", "-Infinity"])
def test_metadata_timestamps_are_finite(client: httpx.Client, value: str) -> None:
    assert client.post("/v1/maps", json={"name": "ts", "encoder": PRECOMPUTED}).status_code in (
        201,
        409,
    )
    feats = ('{"global_descriptor": [1,0,0,0,0,0,0,0,0,0,0,0,0,0,0,0], "keypoints": [[0,0,0]],'
             ' "local_features": [[1,0,0,0,0,0,0,0]]}')  # fmt: skip
    body = (
        f'{{"keyframes": [{{"T_map_sensor": {EYE}, "features": {feats}, '
        f'"metadata": {{"timestamp": {value}}}}}]}}'
    )
    r = client.post(
        "/v1/maps/ts/keyframes", content=body, headers={"Content-Type": "application/json"}
    )
    assert r.status_code == 422, r.text
    assert error_of(r)["field"] == "keyframes[0].metadata.timestamp"


def test_model_files_only_from_the_models_directory(tmp_path: Path) -> None:
    """Without SGVLOC_MODELS_DIR no path is accepted; with it, only files inside it, and
    every refusal reads the same (no probing the server's files)."""
    models = tmp_path / "models"
    models.mkdir()
    shutil.copy(shipped_weights_path(), models / "bevnet.pt")
    srv = Server(tmp_path / "data", tmp_path / "server.log", env={})
    srv.start()
    try:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            spec = {"kind": "learned", "model_path": "/etc/passwd"}
            r = c.post("/v1/maps", json={"name": "m", "encoder": spec})
            assert r.status_code == 422 and error_of(r)["field"] == "encoder.model_path"
    finally:
        srv.stop()
    srv = Server(tmp_path / "data", tmp_path / "server.log", env={"SGVLOC_MODELS_DIR": str(models)})
    srv.start()
    try:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            messages = set()
            for path in ("/etc/passwd", "/etc/nonexistent", "../../etc/passwd", "nope.pt",
                         str(tmp_path / "server.log")):  # fmt: skip
                spec = {"kind": "torchscript", "model_path": path}
                r = c.post("/v1/maps", json={"name": "m", "encoder": spec})
                assert r.status_code == 422, r.text
                assert error_of(r)["field"] == "encoder.model_path"
                messages.add(error_of(r)["message"])
            assert len(messages) == 1 and "/etc" not in messages.pop()
            (models / "broken.pt").write_bytes(b"not a model")
            spec = {"kind": "torchscript", "model_path": "broken.pt"}
            r = c.post("/v1/maps", json={"name": "m", "encoder": spec})
            assert r.status_code == 422 and "broken.pt" in r.text, r.text
            assert str(models) not in r.text, r.text  # its name, not the server's path
            spec = {"kind": "learned", "model_path": "bevnet.pt"}
            r = c.post("/v1/maps", json={"name": "m", "encoder": spec})
            assert r.status_code == 201, r.text
            assert c.get("/v1/maps").json()["maps"][0]["name"] == "m"
    finally:
        srv.stop()


def test_a_bad_map_folder_blocks_no_other_map_and_leaks_no_path(tmp_path: Path) -> None:
    """Folders that fail to load block no other map, leak no server path, make /readyz
    503 "degraded", answer 503 map_unavailable, and come back with POST .../reload once
    the cause is gone (no restart)."""
    srv = Server(tmp_path / "data", tmp_path / "server.log")
    srv.start()
    try:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            for name in ("good", "moved"):
                made = c.post("/v1/maps", json={"name": name, "encoder": PRECOMPUTED})
                assert made.status_code == 201
    finally:
        srv.stop()
    maps = tmp_path / "data" / "maps"
    (maps / "moved" / "map.sqlite").rename(tmp_path / "away.sqlite")  # a lost mount, say
    for name, content in (("broken", b"not a database"), ("empty", None)):
        (maps / name).mkdir()
        if content is not None:
            (maps / name / "map.sqlite").write_bytes(content)
    srv.start()
    try:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            assert c.get("/v1/maps/good").status_code == 200
            r = c.get("/readyz")
            assert r.status_code == 503 and r.json()["status"] == "degraded", r.text
            assert set(r.json()["failed"]) == {"broken", "empty", "moved"}, r.text
            gone = c.get("/v1/maps/moved")
            assert gone.status_code == 503 and error_of(gone)["code"] == "map_unavailable"
            kept = c.delete("/v1/maps/broken")  # not deleted, and not said to be missing
            assert kept.status_code == 503 and error_of(kept)["code"] == "map_unavailable"
            assert "?force=true" in error_of(kept)["message"]
            assert (maps / "broken" / "map.sqlite").exists()
            text = r.text + gone.text + c.post("/v1/maps", json={"name": "broken"}).text
            assert str(tmp_path) not in text, text
            # still broken: 503 with the reason; then the cause is fixed: 200
            again = c.post("/v1/maps/moved/reload")
            assert again.status_code == 503 and "still cannot be loaded" in again.text
            (tmp_path / "away.sqlite").rename(maps / "moved" / "map.sqlite")
            back = c.post("/v1/maps/moved/reload")
            assert back.status_code == 200 and back.json()["name"] == "moved", back.text
            assert c.get("/v1/maps/moved").status_code == 200
            assert c.post("/v1/maps/good/reload").status_code == 409
            # removed by the operator, or deleted unread through the API
            shutil.rmtree(maps / "empty")
            assert c.post("/v1/maps/empty/reload").status_code == 404
            assert c.delete("/v1/maps/broken", params={"force": "true"}).status_code == 204
            assert not (maps / "broken").exists()
            assert c.post("/v1/maps/broken/reload").status_code == 404
            with sgvloc_client.Client(srv.url) as sdk:  # the SDK's force (a loaded map too)
                sdk.delete_map("good", force=True)
            assert c.get("/v1/maps/good").status_code == 404
            ready = c.get("/readyz")
            assert ready.status_code == 200 and ready.json()["status"] == "ready", ready.text
    finally:
        srv.stop()


def make_map(c: httpx.Client, name: str, count: int, keypoints: int, rng) -> None:  # noqa: ANN001
    """A precomputed-feature map of ``count`` random keyframes, inserted 10 at a time."""
    assert c.post("/v1/maps", json={"name": name, "encoder": PRECOMPUTED}).status_code == 201
    for start in range(0, count, 10):
        kfs = [{"T_map_sensor": np.eye(4), "features": random_features(rng, keypoints)}
               for _ in range(min(10, count - start))]  # fmt: skip
        r = post_msgpack(c, f"/v1/maps/{name}/keyframes", {"keyframes": kfs})
        assert r.status_code == 201, r.text


@pytest.fixture(scope="module")
def strict_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A server with one localize slot, a 1 s compute deadline, a 2 s body deadline,
    a 1.5 s header deadline and JSON bodies of at most 1 MiB, holding map ``heavy`` (30
    keyframes of 2000 keypoints) and map ``light``."""
    root = tmp_path_factory.mktemp("strict")
    env = {
        "SGVLOC_MAX_INFLIGHT_LOCALIZE": "1",
        "SGVLOC_REQUEST_TIMEOUT_S": "1.0",
        "SGVLOC_BODY_TIMEOUT_S": "2.0",
        "SGVLOC_HEADER_TIMEOUT_S": "1.5",
        "SGVLOC_MAX_TOP_K": "100",
        "SGVLOC_MAX_JSON_BODY_BYTES": str(1 << 20),
    }
    srv = Server(root / "data", root / "server.log", env=env)
    srv.start()
    rng = np.random.default_rng(5)
    with httpx.Client(base_url=srv.url, timeout=120) as c:
        make_map(c, "heavy", 80, 2000, rng)
        make_map(c, "light", 5, 32, rng)
    try:
        yield srv
    finally:
        srv.stop()


def test_a_localize_past_its_deadline_stops_and_says_so(strict_server: Server) -> None:
    """RANSAC-RIR over 30 candidates of 2000 keypoints takes seconds; with
    request_timeout_s = 1 the work stops at its next step: 503 deadline_exceeded, and
    the message names the step (a candidate before the last: the rest never ran)."""
    rng = np.random.default_rng(6)
    body = {"features": random_features(rng, 2000), "top_k": 80, "rerank": "ransac-rir"}
    with httpx.Client(base_url=strict_server.url, timeout=120) as c:
        r = post_msgpack(c, "/v1/maps/heavy/localize", body)
        assert r.status_code == 503, r.text
        err = error_of(r)
        assert err["code"] == "deadline_exceeded" and r.headers["Retry-After"] == "1"
        assert "stopped at" in err["message"], err
        if "candidate" in err["message"]:
            k = int(err["message"].split("candidate ")[1].split(" of")[0])
            assert k < 80, err
        # the service is free again at once: a light request is answered
        light = {"features": random_features(rng, 32), "rerank": "none", "refine": "none"}
        assert post_msgpack(c, "/v1/maps/light/localize", light).status_code == 200


def test_a_slow_upload_holds_no_localize_slot(strict_server: Server) -> None:
    """With one localize slot, an upload trickling its body does not keep a normal
    localize out (it used to take the slot before its body was read); the slow one gets
    408 with Connection: close once body_timeout_s has passed."""
    rng = np.random.default_rng(7)
    slow = socket.create_connection(("127.0.0.1", strict_server.port))
    try:
        slow.sendall(
            b"POST /v1/maps/light/localize HTTP/1.1\r\nHost: x\r\n"
            b'Content-Type: application/json\r\nContent-Length: 100000\r\n\r\n{"points": ['
        )
        time.sleep(0.3)  # the server has the headers and waits for the body
        body = {"features": random_features(rng, 32), "rerank": "none", "refine": "none"}
        with httpx.Client(base_url=strict_server.url, timeout=60) as c:
            for _ in range(3):
                r = post_msgpack(c, "/v1/maps/light/localize", body)
                assert r.status_code == 200, r.text
        head = answer_head(slow)
    finally:
        slow.close()
    assert head.startswith("http/1.1 408"), head
    assert "connection: close" in head


def test_sigterm_stops_in_flight_work_and_exits(tmp_path: Path) -> None:
    """SIGTERM while a long localize runs (request_timeout_s 300 s: no deadline cuts it):
    the work stops at its next step, its client gets 503, and the process exits (it
    used to wait for the whole computation)."""
    import signal
    import threading

    env = {
        "SGVLOC_REQUEST_TIMEOUT_S": "300",
        "SGVLOC_SHUTDOWN_TIMEOUT_S": "5",
        "SGVLOC_MAX_TOP_K": "100",
    }
    srv = Server(tmp_path / "data", tmp_path / "server.log", env=env)
    srv.start()
    rng = np.random.default_rng(8)
    answer: dict[str, httpx.Response] = {}
    try:
        with httpx.Client(base_url=srv.url, timeout=120) as c:
            make_map(c, "h", 80, 2000, rng)
        body = {"features": random_features(rng, 2000), "top_k": 80, "rerank": "ransac-rir"}

        def heavy() -> None:
            with httpx.Client(base_url=srv.url, timeout=120) as c:
                answer["r"] = post_msgpack(c, "/v1/maps/h/localize", body)

        client = threading.Thread(target=heavy)
        client.start()
        time.sleep(0.7)  # the localize is computing now (for seconds)
        srv.proc.send_signal(signal.SIGTERM)
        code = srv.proc.wait(timeout=60)
        client.join(60)
    finally:
        srv.kill()
    assert code in (0, -signal.SIGTERM), srv.log()[-2000:]  # uvicorn re-raises the signal
    r = answer["r"]
    assert r.status_code == 503 and "shutting down" in error_of(r)["message"], r.text


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A real 16 MiB tmpfs (needs root and mount rights: skipped where it cannot mount)."""
    import subprocess

    disk = tmp_path / "disk"
    disk.mkdir()
    run = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=16m", "tmpfs", str(disk)],
        capture_output=True,
        text=True,
    )
    if run.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {run.stderr.strip()}")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def test_a_full_disk_is_507_and_changes_nothing(tmp_path: Path, small_disk: Path) -> None:
    srv = Server(small_disk / "data", tmp_path / "server.log")
    srv.start()
    rng = np.random.default_rng(9)
    ballast = small_disk / "ballast"
    try:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            assert c.post("/v1/maps", json={"name": "d", "encoder": PRECOMPUTED}).status_code == 201
            kfs = [{"T_map_sensor": np.eye(4), "features": random_features(rng, 64)}]
            assert post_msgpack(c, "/v1/maps/d/keyframes", {"keyframes": kfs}).status_code == 201
            before = c.get("/v1/maps/d").json()
            with ballast.open("wb") as f:  # fill the disk to the last byte
                try:
                    while True:
                        f.write(b"\0" * 65536)
                        f.flush()
                except OSError:
                    pass
            kfs = [{"T_map_sensor": np.eye(4), "features": random_features(rng, 2000)}
                   for _ in range(10)]  # fmt: skip
            r = post_msgpack(c, "/v1/maps/d/keyframes", {"keyframes": kfs})
            assert r.status_code == 507, r.text
            assert error_of(r)["code"] == "insufficient_storage"
            after = c.get("/v1/maps/d").json()
            assert (after["keyframes"], after["version"]) == (
                before["keyframes"],
                before["version"],
            )
            made = c.post("/v1/maps", json={"name": "e", "encoder": PRECOMPUTED})
            assert made.status_code == 507, made.text
            assert not (small_disk / "data" / "maps" / "e").exists()
            ballast.unlink()  # space again: the same insert is stored
            assert post_msgpack(c, "/v1/maps/d/keyframes", {"keyframes": kfs}).status_code == 201
            assert c.get("/v1/maps/d").json()["keyframes"] == before["keyframes"] + 10
    finally:
        srv.stop()


@pytest.mark.parametrize("shape", [[2**62, 4], [2**64 - 1], [2**32, 2**32, 3]])
def test_msgpack_shapes_beyond_the_data_say_so(client: httpx.Client, shape: list[int]) -> None:
    import msgpack

    assert client.post("/v1/maps", json={"name": "shapes", "encoder": PRECOMPUTED}).status_code in (
        201,
        409,
    )
    arr = {"__nd__": True, "dtype": "<f4", "shape": shape, "data": b"\0" * 48}
    body = msgpack.packb({"points": arr}, use_bin_type=True)
    r = client.post(
        "/v1/maps/shapes/localize", content=body, headers={"Content-Type": "application/msgpack"}
    )
    assert r.status_code == 400, r.text
    message = error_of(r)["message"]
    assert "data has 48 bytes" in message and "needs" in message and "-" not in message, message


def test_huge_but_finite_descriptors_are_normalised(client: httpx.Client) -> None:
    """A global descriptor of 1e38 values (finite float32) is a direction like any other."""
    assert client.post("/v1/maps", json={"name": "huge", "encoder": PRECOMPUTED}).status_code in (
        201,
        409,
    )
    feats = random_features(np.random.default_rng(10))
    feats["global_descriptor"] = np.full(16, 1e38, np.float32)
    r = post_msgpack(client, "/v1/maps/huge/keyframes", {"keyframes": [
        {"T_map_sensor": np.eye(4), "features": feats}]})  # fmt: skip
    assert r.status_code == 201, r.text


def test_trickled_headers_are_cut_off(strict_server: Server) -> None:
    """Headers sent a line every 0.3 s never complete: the connection is closed after
    header_timeout_s (1.5 s here), and a keep-alive connection gets the same limit for
    its next request."""
    for first in (b"", b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n"):
        sock = socket.create_connection(("127.0.0.1", strict_server.port))
        try:
            sock.settimeout(0.05)
            if first:
                sock.sendall(first)
            sock.sendall(b"POST /v1/maps HTTP/1.1\r\nHost: x\r\n")
            closed, received = False, b""
            t0 = time.monotonic()
            while time.monotonic() - t0 < 20:
                try:
                    sock.sendall(b"X-Slow: 1\r\n")
                except OSError:
                    closed = True
                    break
                try:
                    chunk = sock.recv(4096)
                    if not chunk:
                        closed = True
                        break
                    received += chunk
                except TimeoutError:
                    pass
                time.sleep(0.3)
        finally:
            sock.close()
        assert closed, "a connection trickling its headers was never closed"
        if first:
            assert received.startswith(b"HTTP/1.1 200"), received[:100]
    with httpx.Client(base_url=strict_server.url) as c:  # normal requests are unaffected
        assert c.get("/v1/maps").status_code == 200
        cut = re.search(
            r'sgvloc_connections_cut_total\{reason="header_timeout"\} (\S+)', c.get("/metrics").text
        )
    assert cut and float(cut.group(1)) >= 2, "the cuts are counted"


def test_large_bodies_go_as_msgpack_and_no_list_is_longer_than_a_field(
    strict_server: Server,
) -> None:
    """Parsing JSON holds the interpreter for the whole body: a JSON body is bounded by
    max_json_body_bytes (1 MiB here), while the same points as MessagePack pass. A
    MessagePack list longer than any field could be is refused before it is walked."""
    import json

    pts = np.random.default_rng(0).uniform(-20, 20, (50_000, 3)).round(3)
    with httpx.Client(base_url=strict_server.url, timeout=60) as c:
        text = json.dumps({"points": pts.tolist()})
        assert len(text) > 1 << 20
        r = c.post("/v1/maps/light/localize", content=text, headers=_JSON)
        assert r.status_code == 413 and "MessagePack" in error_of(r)["message"], r.text
        r = post_msgpack(c, "/v1/maps/light/localize", {"points": pts.astype(np.float32)})
        assert r.status_code != 413, r.text
        flat = msgpack.packb({"points": [0] * 600_000})  # past max_points (500 000)
        r = c.post("/v1/maps/light/localize", content=flat, headers=_MSGPACK)
        assert r.status_code == 400 and "longer than any field" in error_of(r)["message"]


def test_an_answer_before_the_body_ends_the_connection_in_time(strict_server: Server) -> None:
    """A request answered before its body was read (here 405) must not hold its
    connection while the client trickles the body: it is closed within header_timeout_s
    of the answer."""
    sock = socket.create_connection(("127.0.0.1", strict_server.port))
    try:
        sock.sendall(
            b"POST /healthz HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            b"Content-Length: 100000\r\n\r\n"
        )
        sock.settimeout(5)
        assert sock.recv(4096).startswith(b"HTTP/1.1 405")
        sock.settimeout(0.05)
        closed, t0 = False, time.monotonic()
        while time.monotonic() - t0 < 20 and not closed:
            try:
                sock.sendall(b"x")
                closed = sock.recv(100) == b""
            except TimeoutError:
                pass
            except OSError:
                closed = True
            time.sleep(0.3)
        assert closed, "a connection trickling an unread body was never closed"
    finally:
        sock.close()


def test_a_client_that_goes_away_mid_body_is_not_a_server_error(strict_server: Server) -> None:
    """Half a body and a closed socket: nobody to answer, no 500 counted or logged."""
    for _ in range(2):
        sock = socket.create_connection(("127.0.0.1", strict_server.port))
        sock.sendall(
            b"POST /v1/maps/light/localize HTTP/1.1\r\nHost: x\r\n"
            b"Content-Type: application/msgpack\r\nContent-Length: 100000\r\n\r\n" + b"\x00" * 500
        )
        time.sleep(0.3)
        sock.close()
    time.sleep(0.5)
    with httpx.Client(base_url=strict_server.url) as c:
        metrics = c.get("/metrics").text
    assert 'route="/v1/maps/{map}/localize",status="500"' not in metrics


@pytest.fixture(scope="module")
def patient_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """One worker, a generous compute deadline (120 s) and map ``heavy`` (80 keyframes of
    2000 keypoints: RANSAC-RIR over all of them takes seconds)."""
    root = tmp_path_factory.mktemp("patient")
    env = {"SGVLOC_REQUEST_TIMEOUT_S": "120", "SGVLOC_MAX_TOP_K": "100"}
    srv = Server(root / "data", root / "server.log", env=env, workers=1)
    srv.start()
    with httpx.Client(base_url=srv.url, timeout=120) as c:
        make_map(c, "heavy", 80, 2000, np.random.default_rng(8))
    try:
        yield srv
    finally:
        srv.stop()


def _localize_counts(srv: Server) -> tuple[float, float, dict[str, float]]:
    """(localizations answered in map heavy, caller_gone errors, localize requests by
    status) from the service's metrics."""
    text = httpx.get(f"{srv.url}/metrics").text

    def total(pattern: str) -> float:
        return sum(float(v) for v in re.findall(pattern, text))

    done = total(r'sgvloc_localize_total\{map="heavy",verdict="[a-z_]+"\} (\S+)')
    gone = total(r'sgvloc_errors_total\{code="caller_gone",route="[^"]*localize"\} (\S+)')
    by_status = {
        s: float(v)
        for s, v in re.findall(
            r'sgvloc_http_requests_total\{method="POST",route="/v1/maps/\{map\}/localize",'
            r'status="(\d+)"\} (\S+)',
            text,
        )
    }
    return done, gone, by_status


def _wait_for_answers(srv: Server, status_total: float) -> dict[str, float]:
    """Poll until the service has answered ``status_total`` localize requests in all."""
    end = time.monotonic() + 120
    while time.monotonic() < end:
        by_status = _localize_counts(srv)[2]
        if sum(by_status.values()) >= status_total:
            return by_status
        time.sleep(0.2)
    raise AssertionError(f"the service answered {by_status}, not {status_total} requests")


def test_a_client_that_goes_away_stops_its_localization(patient_server: Server) -> None:
    """A client that gives up (its read timeout) stops the localization it sent at the
    next step, whether it was running or waiting for the one worker: the service records
    a 499 caller_gone and no localization for it, and serves the others as usual."""
    rng = np.random.default_rng(9)
    heavy = {"features": random_features(rng, 2000), "top_k": 80, "rerank": "ransac-rir"}
    done0, gone0, by0 = _localize_counts(patient_server)
    answered0 = sum(by0.values())
    # running: the only request, given up after 0.5 s
    with httpx.Client(base_url=patient_server.url, timeout=0.5) as c:
        with pytest.raises(httpx.ReadTimeout):
            post_msgpack(c, "/v1/maps/heavy/localize", heavy)
    by_status = _wait_for_answers(patient_server, answered0 + 1)
    done, gone, _ = _localize_counts(patient_server)
    assert (done, gone) == (done0, gone0 + 1), by_status
    assert by_status.get("499", 0) == by0.get("499", 0) + 1, by_status
    # waiting: a second request queued behind one that holds the worker, given up
    first: list[httpx.Response] = []

    def send_first() -> None:
        with httpx.Client(base_url=patient_server.url, timeout=300) as c:
            first.append(post_msgpack(c, "/v1/maps/heavy/localize", heavy))

    runner = threading.Thread(target=send_first)
    runner.start()
    time.sleep(0.3)  # the first holds the worker (or soon will)
    with httpx.Client(base_url=patient_server.url, timeout=0.5) as c:
        with pytest.raises(httpx.ReadTimeout):
            post_msgpack(c, "/v1/maps/heavy/localize", heavy)
    runner.join(timeout=300)
    assert first and first[0].status_code == 200, first
    _wait_for_answers(patient_server, answered0 + 3)
    done, gone, by_status = _localize_counts(patient_server)
    assert (done, gone) == (done0 + 1, gone0 + 2), by_status
