"""The load test in its short form (4 clients, 5 s) against the shared test server;
the long form (16 clients, 60 s) is ``sgvloc loadtest``, run by hand."""

from __future__ import annotations

import pytest

from sgvloc.tools.loadtest import check_loopback, run_loadtest


def test_short_load_has_no_errors(server) -> None:
    result = run_loadtest(server.url, clients=4, duration_s=5.0, seed_keyframes=50)
    assert result.errors == 0, result.summary()
    loc, ins = result.kinds["localize"], result.kinds["insert"]
    assert loc.ok > 0 and ins.ok > 0, result.summary()
    assert 0 < loc.p50_ms <= loc.p99_ms
    assert result.as_dict()["requests"] == result.requests


@pytest.mark.parametrize("url", ["http://10.0.0.1:8470", "https://example.org"])
def test_only_this_machine(url: str) -> None:
    with pytest.raises(ValueError, match="this machine"):
        check_loopback(url)


def test_slow_uploads_hold_up_no_one(tmp_path) -> None:
    """8 slow uploads (as many as the localize slots) against a service that closes them
    after body_timeout_s = 1 s: every normal request is still served, none refused."""
    from conftest import Server

    env = {"SGVLOC_BODY_TIMEOUT_S": "1", "SGVLOC_MAX_INFLIGHT_LOCALIZE": "8"}
    srv = Server(tmp_path / "data", tmp_path / "server.log", env=env)
    srv.start()
    try:
        result = run_loadtest(srv.url, clients=2, duration_s=4.0, seed_keyframes=20, slow_clients=8)
    finally:
        srv.stop()
    loc = result.kinds["localize"]
    assert result.errors == 0 and loc.refused == 0 and loc.ok > 0, result.summary()
    slow = result.slow
    assert slow.connections >= 8 and slow.timed_out >= 8, result.summary()
    assert "slow uploads: 8 clients" in result.summary()


def test_a_run_that_fails_leaves_no_map_behind(tmp_path) -> None:
    """The map is deleted however the run ends: here its seeding fails (a service that
    takes 5 keyframes per insert, the run sends 10)."""
    import httpx
    from conftest import Server

    srv = Server(tmp_path / "data", tmp_path / "server.log", env={"SGVLOC_MAX_BATCH": "5"})
    srv.start()
    try:
        with pytest.raises(RuntimeError, match="cannot seed map"):
            run_loadtest(srv.url, clients=1, duration_s=1.0, seed_keyframes=10, map_name="lt")
        assert httpx.get(f"{srv.url}/v1/maps/lt").status_code == 404
    finally:
        srv.stop()
