"""Map archives end to end, as an operator moves a map: ``sgvloc map export`` from one
real server, ``sgvloc map import`` into a map of another name, the same answers; damaged
and foreign uploads refused over HTTP; the SDK's listing, bulk delete and statistics."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from svc_helpers import PRECOMPUTED, BalmMap, error_of, post_msgpack, random_features

import sgvloc_client

TAR = {"Content-Type": "application/x-tar"}


def _sgvloc(*args: str, url: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "SGVLOC_URL": url}
    return subprocess.run(
        [sys.executable, "-m", "sgvloc.cli", *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )


def test_cli_export_import_gives_the_same_answers(
    server, client: httpx.Client, balm_map: BalmMap, tmp_path: Path
) -> None:
    archive = tmp_path / "balm.sgvmap.tar"
    run = _sgvloc("map", "export", "balm", str(archive), url=server.url)
    assert run.returncode == 0, run.stderr
    assert "written to" in run.stdout and archive.stat().st_size > 0
    assert not archive.with_name(archive.name + ".part").exists()
    run = _sgvloc("map", "export", "balm", str(archive), url=server.url)  # never overwritten
    assert run.returncode == 2 and "--force" in run.stderr

    run = _sgvloc("map", "import", str(archive), "--name", "balm-copy", url=server.url)
    assert run.returncode == 0, run.stderr
    assert "map balm-copy:" in run.stdout
    a, b = client.get("/v1/maps/balm").json(), client.get("/v1/maps/balm-copy").json()
    for field in ("version", "keyframes", "encoder", "localizer", "calibration", "keep_clouds"):
        assert a[field] == b[field], field
    for i in balm_map.queries[:3]:  # raw scans through the whole pipeline, ICP included
        body = {"points": balm_map.seq[i].scan().xyzi(), "top_k": 5}
        ra = post_msgpack(client, "/v1/maps/balm/localize", body).json()
        rb = post_msgpack(client, "/v1/maps/balm-copy/localize", body).json()
        for field in ("localized", "keyframe_id", "verdict", "retrieved", "reranked"):
            assert ra[field] == rb[field], field
        assert ra["confidence"] == pytest.approx(rb["confidence"], abs=1e-9)
        if ra["T_map_sensor"] is not None:
            np.testing.assert_allclose(ra["T_map_sensor"], rb["T_map_sensor"], atol=1e-9)
    page = client.get("/v1/maps/balm-copy/keyframes", params={"limit": 1000}).json()
    orig = client.get("/v1/maps/balm/keyframes", params={"limit": 1000}).json()
    assert page == orig  # ids, keys, poses, metadata, creation times
    run = _sgvloc("map", "import", str(archive), "--name", "balm-copy", url=server.url)
    assert run.returncode == 1 and "exists already; import it under another name" in run.stderr
    assert client.delete("/v1/maps/balm-copy").status_code == 204


def test_export_streams_and_bad_uploads_are_refused(client: httpx.Client) -> None:
    assert (
        client.post("/v1/maps", json={"name": "arc-h", "encoder": PRECOMPUTED}).status_code == 201
    )
    rng = np.random.default_rng(2)
    kfs = [{"T_map_sensor": np.eye(4), "features": random_features(rng)} for _ in range(3)]
    assert post_msgpack(client, "/v1/maps/arc-h/keyframes", {"keyframes": kfs}).status_code == 201
    r = client.get("/v1/maps/arc-h/export")
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-tar"
    assert "content-length" not in r.headers  # streamed
    assert 'filename="arc-h.sgvmap.tar"' in r.headers["content-disposition"]
    data = r.content
    assert client.get("/v1/maps/nope/export").status_code == 404

    def upload(content: bytes, name: str = "arc-new", headers=TAR) -> httpx.Response:
        return client.post(
            "/v1/map-archives", params={"name": name}, content=content, headers=headers
        )

    damaged = bytearray(data)
    damaged[len(data) // 2] ^= 0xFF
    for bad, words in [
        (bytes(damaged), "damaged"),
        (data[: len(data) // 2], "truncated"),
        (b"just some text", "not an sgvloc map archive"),
    ]:
        r = upload(bad)
        assert r.status_code == 422, r.text
        assert words in error_of(r)["message"]
        assert client.get("/v1/maps/arc-new").status_code == 404  # nothing left behind
    r = upload(data, headers={"Content-Type": "application/json"})
    assert r.status_code == 415
    r = upload(data, name="bad name!")
    assert r.status_code == 422 and error_of(r)["field"] == "name"
    r = upload(data, name="arc-h")
    assert r.status_code == 409
    r = upload(data)
    assert r.status_code == 201 and r.json()["keyframes"] == 3
    assert client.delete("/v1/maps/arc-new").status_code == 204


def test_sdk_map_management(server, client: httpx.Client) -> None:
    assert (
        client.post("/v1/maps", json={"name": "arc-sdk", "encoder": PRECOMPUTED}).status_code == 201
    )
    rng = np.random.default_rng(3)
    with sgvloc_client.Client(server.url) as c:
        for i in range(12):
            T = np.eye(4)
            T[:3, 3] = [i, 0, 0]
            c.insert_keyframe(
                "arc-sdk",
                T,
                features=random_features(rng),
                key=f"k{i:02d}",
                metadata={"timestamp": float(i), "sequence": "a" if i < 6 else "b"},
            )
        page = c.list_keyframes("arc-sdk", limit=5)
        assert len(page.keyframes) == 5 and page.next_cursor is not None
        assert page.keyframes[0].key == "k00" and page.keyframes[0].position.tolist() == [0, 0, 0]
        all_b = [kf.key for kf in c.iter_keyframes("arc-sdk", page_size=2, sequence="b")]
        assert all_b == [f"k{i:02d}" for i in range(6, 12)]
        assert [kf.key for kf in c.iter_keyframes("arc-sdk", bbox=(2.5, -1, 4.5, 1))] == [
            "k03",
            "k04",
        ]
        with pytest.raises(ValueError, match="all=True"):
            c.delete_keyframes("arc-sdk")
        gone = c.delete_keyframes("arc-sdk", time_min=10)
        assert gone.deleted == 2
        stats = c.map_stats("arc-sdk")
        assert stats.keyframes == 10 and stats.version == gone.map_version
        assert stats.extent[1].tolist() == [9.0, 0.0, 0.0]
        archive = Path(server.data_dir).parent / "arc-sdk.tar"
        size = c.export_map("arc-sdk", archive)
        assert size == archive.stat().st_size > 0
        info = c.import_map(archive, "arc-sdk-2")
        assert info.keyframes == 10 and info.version == stats.version
        with pytest.raises(sgvloc_client.Conflict):
            c.import_map(archive, "arc-sdk-2")
        with pytest.raises(sgvloc_client.NotFound):
            c.export_map("nope", archive)
    import asyncio

    async def main() -> None:
        async with sgvloc_client.AsyncClient(server.url) as ac:
            keys = [kf.key async for kf in ac.iter_keyframes("arc-sdk-2", page_size=3)]
            assert len(keys) == 10
            assert (await ac.map_stats("arc-sdk-2")).keyframes == 10
            assert await ac.export_map("arc-sdk-2", archive) > 0
            info = await ac.import_map(archive, "arc-sdk-3")
            assert info.keyframes == 10
            assert (await ac.delete_keyframes("arc-sdk-3", all=True)).deleted == 10

    asyncio.run(main())


def test_cli_lists_filters_and_deletes(server, client: httpx.Client) -> None:
    import json

    assert (
        client.post("/v1/maps", json={"name": "arc-cli", "encoder": PRECOMPUTED}).status_code == 201
    )
    rng = np.random.default_rng(4)
    kfs = []
    for i in range(6):
        T = np.eye(4)
        T[:3, 3] = [i, 2 * i, 0]
        kfs.append({"key": f"d{i % 2}/{i}", "T_map_sensor": T, "features": random_features(rng)})
    assert post_msgpack(client, "/v1/maps/arc-cli/keyframes", {"keyframes": kfs}).status_code == 201

    run = _sgvloc("map", "list", url=server.url)
    assert run.returncode == 0 and any(
        ln.startswith("arc-cli\t6 keyframes") for ln in run.stdout.splitlines()
    )
    run = _sgvloc("map", "list", "--prefix", "arc-c", url=server.url)
    assert [ln.split("\t")[0] for ln in run.stdout.splitlines()] == ["arc-cli"], run.stderr
    run = _sgvloc("map", "stats", "arc-cli", url=server.url)
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout)["extent"] == {"min": [0.0, 0.0, 0.0], "max": [5.0, 10.0, 0.0]}
    run = _sgvloc("map", "keyframes", "arc-cli", "--bbox", "0.5,0,3.5,100", url=server.url)
    assert [json.loads(ln)["key"] for ln in run.stdout.splitlines()] == ["d1/1", "d0/2", "d1/3"]
    run = _sgvloc("map", "delete-keyframes", "arc-cli", url=server.url)
    assert run.returncode == 2 and "--all" in run.stderr
    run = _sgvloc("map", "delete-keyframes", "arc-cli", "--key-prefix", "d1/", url=server.url)
    assert run.returncode == 0 and "3 keyframes deleted" in run.stdout, run.stderr
    run = _sgvloc("map", "stats", "nope", url=server.url)
    assert run.returncode == 1 and "does not exist" in run.stderr
    run = _sgvloc("map", "keyframes", "arc-cli", "--bbox", "1,2", url=server.url)
    assert run.returncode == 2 and "--bbox" in run.stderr
    # a reader that stops early (| head): a quiet exit (it printed "[Errno 32] Broken pipe")
    proc = subprocess.Popen(
        [sys.executable, "-m", "sgvloc.cli", "map", "keyframes", "arc-cli"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env={**os.environ, "SGVLOC_URL": server.url},
    )
    proc.stdout.close()  # before the command (seconds of imports) writes a line
    _, err = proc.communicate(timeout=300)
    assert (proc.returncode, err.decode()) == (1, ""), err.decode()


@pytest.mark.parametrize(
    ("spec", "localizer", "field"),
    [
        (
            {"kind": "precomputed", "name": "egonn", "global_dim": 16, "local_dim": 8},
            {"top_k": 1000},
            "localizer.top_k",
        ),
        (
            {"kind": "handcrafted", "handcrafted": {"num_keypoints": 20000}},
            {},
            "encoder.handcrafted.num_keypoints",
        ),
    ],
)
def test_an_archive_past_this_servers_limits_is_refused(
    client: httpx.Client, tmp_path: Path, spec: dict, localizer: dict, field: str
) -> None:
    """An archive made where the limits are wider (or by the library, which has none)
    meets this server's max_top_k and max_keypoints, as a new map would."""
    from sgvloc.core.config import LocalizerConfig
    from sgvloc.core.encoders import EncoderSpec
    from sgvloc.server.maps import MapManager
    from sgvloc.server.store import open_backend

    manager = MapManager(tmp_path / "maps", backend=open_backend(None))
    manager.load_all()
    try:
        manager.create("wide", EncoderSpec.model_validate(spec), LocalizerConfig(**localizer))
        with manager.export_archive("wide") as stream:
            data = b"".join(stream)
    finally:
        manager.close()
    r = client.post("/v1/map-archives", params={"name": "arc-wide"}, content=data, headers=TAR)
    assert r.status_code == 422, r.text
    assert error_of(r)["field"] == field
    assert client.get("/v1/maps/arc-wide").status_code == 404


def _stalled_get(port: int, path: str) -> tuple[socket.socket, bytes]:
    """A GET whose client reads the first 4 KiB of the answer and then nothing (a receive
    window of 4 KiB): the socket and what it read."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", port))
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
    sock.settimeout(30)
    return sock, sock.recv(4096)


def test_a_stalled_download_is_cut_and_lets_its_snapshot_go(tmp_path: Path) -> None:
    """A client that stops reading an export (its receive window closed) loses the
    connection send_timeout_s after the server's buffer filled (a reset): what it reads
    ends without the archive's last chunk, the log says why, and the server serves on."""
    from conftest import Server

    srv = Server(tmp_path / "data", tmp_path / "server.log", env={"SGVLOC_SEND_TIMEOUT_S": "1.5"})
    srv.start()
    sock = None
    try:
        rng = np.random.default_rng(3)
        with httpx.Client(base_url=srv.url, timeout=120) as c:
            assert c.post("/v1/maps", json={"name": "big", "encoder": PRECOMPUTED}).is_success
            for _ in range(8):  # 80 keyframes of 4000 keypoints: an archive of about 14 MB
                kfs = [{"T_map_sensor": np.eye(4), "features": random_features(rng, 4000)}
                       for _ in range(10)]  # fmt: skip
                assert post_msgpack(c, "/v1/maps/big/keyframes", {"keyframes": kfs}).is_success
        sock, got = _stalled_get(srv.port, "/v1/maps/big/export")
        assert got.startswith(b"HTTP/1.1 200"), got[:200]
        time.sleep(5)  # reads nothing: the server's buffer fills and it waits
        sock.settimeout(10)
        try:
            while chunk := sock.recv(1 << 16):
                got += chunk
            closed = True
        except ConnectionResetError:  # reset: the unsent rest is dropped
            closed = True
        except TimeoutError:
            closed = False
        assert closed, f"the connection stayed open ({len(got)} bytes read)"
        assert len(got) < 10_000_000 and not got.endswith(b"0\r\n\r\n"), len(got)
        assert "took none of its answer for 1.5 s" in srv.log_path.read_text()
        with httpx.Client(base_url=srv.url, timeout=120) as c:
            whole = c.get("/v1/maps/big/export")
            assert whole.status_code == 200 and len(whole.content) > 10_000_000
            metrics = c.get("/metrics").text
            assert 'status="500"' not in metrics
            assert 'sgvloc_connections_cut_total{reason="send_timeout"} 1.0' in metrics
    finally:
        if sock is not None:
            sock.close()
        srv.stop()


def test_a_stalled_answer_is_cut_also_once_its_connection_is_closing(tmp_path: Path) -> None:
    """A large answer sent whole (a 5 MB keyframe listing) that the client never reads:
    uvicorn closes the idle keep-alive connection after 5 s, and a close waits for the
    buffer; send_timeout_s (7 s here) still resets it, and the cut is counted."""
    from conftest import Server

    srv = Server(tmp_path / "data", tmp_path / "server.log", env={"SGVLOC_SEND_TIMEOUT_S": "7"})
    srv.start()
    sock = None
    try:
        rng = np.random.default_rng(4)
        tags = {f"t{i}": "x" * 1000 for i in range(64)}
        with httpx.Client(base_url=srv.url, timeout=120) as c:
            assert c.post("/v1/maps", json={"name": "meta", "encoder": PRECOMPUTED}).is_success
            for _ in range(8):
                kfs = [{"T_map_sensor": np.eye(4), "features": random_features(rng, 20),
                        "metadata": {"tags": tags}} for _ in range(10)]  # fmt: skip
                assert post_msgpack(c, "/v1/maps/meta/keyframes", {"keyframes": kfs}).is_success
        sock, first = _stalled_get(srv.port, "/v1/maps/meta/keyframes?limit=1000")
        assert first.startswith(b"HTTP/1.1 200")
        time.sleep(12)  # reads nothing: keep-alive closes at 5 s, the deadline cuts at 7 s
        got, cut = 0, False
        try:
            while chunk := sock.recv(1 << 16):
                got += len(chunk)
        except ConnectionResetError:
            cut = True
        assert cut or got < 5_000_000, got  # reset: the rest of the answer never came
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            metrics = c.get("/metrics").text
        assert 'sgvloc_connections_cut_total{reason="send_timeout"} 1.0' in metrics
        assert "took none of its answer for 7 s" in srv.log_path.read_text()
    finally:
        if sock is not None:
            sock.close()
        srv.stop()
