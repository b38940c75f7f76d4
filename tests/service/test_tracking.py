"""Tracking end to end on a real server: seeded localize (tracked, relocalized, bad
seeds), the SDK Tracker following the real fixture against a map of its own subset, a
kidnap recovered, and ``sgvloc eval-track`` on the fixture."""

from __future__ import annotations

from pathlib import Path

import httpx
import numpy as np
import pytest
from svc_helpers import error_of, pose_error, post_msgpack, random_features, rotation_z

import sgvloc_client
from sgvloc.core.sequence import KittiSequence


@pytest.fixture(scope="module")
def track_map(server, balm_mini_dir: Path) -> KittiSequence:
    """Map ``track`` (learned encoder, the default) of the fixture's even-numbered scans."""
    seq = KittiSequence(balm_mini_dir)
    with httpx.Client(base_url=server.url, timeout=300.0) as c:
        assert c.post("/v1/maps", json={"name": "track"}).status_code == 201
        kfs = [
            {"key": str(i), "T_map_sensor": seq[i].T_world_sensor, "points": seq[i].scan().xyzi()}
            for i in range(0, len(seq), 2)
        ]
        r = post_msgpack(c, "/v1/maps/track/keyframes", {"keyframes": kfs})
        assert r.status_code == 201, r.text
    return seq


def _seed(T: np.ndarray, dx: float, dyaw_deg: float, sigma_m=1.0, sigma_yaw=5.0) -> dict:
    S = T.copy()
    S[:3, :3] = rotation_z(np.radians(dyaw_deg))[:3, :3] @ S[:3, :3]
    S[0, 3] += dx
    return {"T_map_sensor": S, "sigma_m": sigma_m, "sigma_yaw_deg": sigma_yaw}


@pytest.mark.parametrize("i", [1, 7, 13])  # scans that are not in the map
def test_a_seed_off_by_1m_and_5deg_is_tracked(client, track_map, i: int) -> None:
    T = track_map[i].T_world_sensor
    body = {"points": track_map[i].scan().xyzi(), "seed": _seed(T, 1.0, 5.0)}
    r = post_msgpack(client, "/v1/maps/track/localize", body)
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["mode"] == "tracked" and out["localized"], out["tracking"]
    err_m, err_deg = pose_error(np.array(out["T_map_sensor"]), T)
    assert err_m < 0.15 and err_deg < 1.0, (err_m, err_deg)
    t = out["tracking"]
    assert t["fitness"] >= 0.5 and t["submap_keyframes"] >= 1 and t["why"]
    assert 0.5 <= out["confidence"] <= 1.0
    assert out["retrieved"] == [] and out["timings_ms"]["track"] > 0
    # the answer names a map keyframe and places the scan relative to it
    kf = client.get(f"/v1/maps/track/keyframes/{out['keyframe_id']}").json()
    np.testing.assert_allclose(
        np.array(kf["T_map_sensor"]) @ np.array(out["T_keyframe_sensor"]),
        np.array(out["T_map_sensor"]),
        atol=1e-9,
    )


def test_a_seed_30m_off_falls_back_to_the_global_path(client, track_map) -> None:
    i = 7
    T = track_map[i].T_world_sensor
    body = {"points": track_map[i].scan().xyzi(), "seed": _seed(T, 30.0, 0.0)}
    out = post_msgpack(client, "/v1/maps/track/localize", body).json()
    assert out["mode"] == "relocalized", out
    assert out["tracking"]["why"] != "the scan fits the map around the seed"
    assert out["prior"] is not None  # the global path ran with the seed as a prior
    # a wide seed lets the global path find the scan
    body["seed"] = _seed(T, 30.0, 0.0, sigma_m=20.0)
    out = post_msgpack(client, "/v1/maps/track/localize", body).json()
    assert out["mode"] in ("tracked", "relocalized") and out["localized"], out["reason"]
    assert pose_error(np.array(out["T_map_sensor"]), T)[0] < 0.3


def test_a_failed_fit_of_a_scan_the_encoder_cannot_describe_is_answered(client, track_map) -> None:
    """Flat ground alone: the fit from a seed 30 m off fails and the global fallback has
    nothing to describe, so the answer is the failed fit (200, not localized, saying
    why), not a 422 for a request tracking could have answered; without a seed the same
    scan is a 422 ``empty_scan``."""
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-10, 10, (300, 2)), np.full(300, -1.5), np.ones(300)]
    T = track_map[7].T_world_sensor
    body = {"points": ground, "seed": _seed(T, 30.0, 0.0)}
    r = post_msgpack(client, "/v1/maps/track/localize", body)
    assert r.status_code == 200, r.text
    out = r.json()
    assert not out["localized"] and out["verdict"] == "tracking_failed", out
    assert "no global fallback" in out["reason"] and "nothing to describe" in out["reason"]
    r = post_msgpack(client, "/v1/maps/track/localize", {"points": ground})
    assert r.status_code == 422 and error_of(r)["code"] == "empty_scan", r.text


@pytest.mark.parametrize(
    ("seed", "field"),
    [
        (
            {"T_map_sensor": np.diag([2.0, 1, 1, 1]), "sigma_m": 1, "sigma_yaw_deg": 5},
            "seed.T_map_sensor",
        ),
        (
            {"T_map_sensor": np.full((4, 4), np.nan), "sigma_m": 1, "sigma_yaw_deg": 5},
            "seed.T_map_sensor",
        ),
        ({"T_map_sensor": np.eye(3), "sigma_m": 1, "sigma_yaw_deg": 5}, "seed.T_map_sensor"),
        ({"T_map_sensor": np.eye(4), "sigma_m": -1, "sigma_yaw_deg": 5}, "seed.sigma_m"),
        ({"T_map_sensor": np.eye(4), "sigma_m": float("nan"), "sigma_yaw_deg": 5}, "seed.sigma_m"),
        ({"T_map_sensor": np.eye(4), "sigma_m": 1, "sigma_yaw_deg": 0}, "seed.sigma_yaw_deg"),
        ({"T_map_sensor": np.eye(4), "sigma_m": 1}, "seed.sigma_yaw_deg"),
    ],
)
def test_bad_seeds_are_422_naming_the_field(client, track_map, seed, field) -> None:
    body = {"points": track_map[1].scan().xyzi(), "seed": seed}
    r = post_msgpack(client, "/v1/maps/track/localize", body)
    assert r.status_code == 422, r.text
    assert error_of(r)["field"] == field


def test_a_seed_needs_a_scan(client, track_map) -> None:
    r = post_msgpack(
        client,
        "/v1/maps/track/localize",
        {
            "features": random_features(np.random.default_rng(0), g=620, d=64),
            "seed": _seed(np.eye(4), 0, 0),
        },
    )
    assert r.status_code in (409, 422), r.text


def test_the_sdk_tracker_follows_the_fixture_and_recovers_a_kidnap(server, track_map) -> None:
    seq = track_map
    with sgvloc_client.Client(server.url, timeout=120) as c:
        tracker = sgvloc_client.Tracker(c, "track")
        fixes = []
        for i in range(len(seq)):
            fix = tracker.update(seq[i].scan().xyzi(), seq[i].time)
            if fix.localized:
                fixes.append((i, fix.mode, pose_error(fix.T_map_sensor, seq[i].T_world_sensor)[0]))
        assert len(fixes) >= len(seq) - 1, fixes
        assert all(err < 0.3 for _, _, err in fixes), fixes
        assert any(mode == "tracked" for _, mode, _ in fixes)
        assert tracker.pose is not None and not tracker.lost

        # kidnapped: from the last scan's place to the first's, one period later
        stamp = seq[len(seq) - 1].time + 0.5
        recovered = None
        for k, i in enumerate([0, 1, 2], 1):
            fix = tracker.update(seq[i].scan().xyzi(), stamp + 0.5 * k)
            if fix.localized and pose_error(fix.T_map_sensor, seq[i].T_world_sensor)[0] < 0.3:
                recovered = k
                break
        assert recovered is not None and recovered <= 2


def test_the_async_tracker(server, track_map) -> None:
    import asyncio

    seq = track_map

    async def main() -> list[tuple[str, float]]:
        async with sgvloc_client.AsyncClient(server.url, timeout=120) as c:
            tracker = sgvloc_client.AsyncTracker(c, "track", localize_options={"top_k": 5})
            out = []
            for i in (8, 9, 10):  # 3.0 s and 3.5 s apart
                fix = await tracker.update(seq[i].scan().xyzi(), seq[i].time)
                err = pose_error(fix.T_map_sensor, seq[i].T_world_sensor)[0]
                out.append((fix.mode, err))
            return out

    fixes = asyncio.run(main())
    assert fixes[0][0] == "global" and all(err < 0.3 for _, err in fixes), fixes
    assert fixes[2][0] in ("tracked", "relocalized"), fixes


def test_eval_track_on_the_fixture(balm_mini_dir: Path, tmp_path: Path) -> None:
    from sgvloc.tools.eval_track import eval_track, report_lines

    r = eval_track(balm_mini_dir, tmp_path, map_every=2, kidnaps=[(6, 12)])
    assert r.map_scans == 8 and r.streamed == 10  # 0..6, then 12..14
    assert r.wrong_accepted == 0 and r.localized >= 8
    assert r.median_error_m is not None and r.median_error_m < 0.1
    assert r.kidnaps[0]["scans_until_correct_fix"] is not None
    assert r.kidnaps[0]["scans_until_correct_fix"] <= 2
    assert (tmp_path / "track.json").is_file()
    png = (tmp_path / "trajectory.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert any("availability" in line for line in report_lines(r))


def test_a_kidnap_back_revisits_and_bad_stream_options_are_clear(
    balm_mini_dir: Path, tmp_path: Path
) -> None:
    """A jump back in the sequence streams the scans again (it ended the stream and
    measured the recovery from the first visit); frame options that select nothing
    are errors that say so."""
    from sgvloc.core.errors import InputError
    from sgvloc.tools.eval_track import ScanRecord, eval_track, stream_order, summarize

    assert stream_order(20, [(12, 4)]) == [*range(13), *range(4, 20)]
    assert stream_order(10, [(3, 7), (8, 1)]) == [0, 1, 2, 3, 7, 8, 1, 2, 3, 4, 5, 6, 7, 8, 9]
    order = stream_order(8, [(5, 2)])  # 0..5, then 2..7: scan 2's second visit is the jump's
    recs = [
        ScanRecord(i, k * 0.1, "tracked", k >= 7, True, 0.1, 0.1, 5.0, True, None, [0.0, 0.0])
        for k, i in enumerate(order)
    ]
    kid = summarize(recs, 4, 0, [(5, 2)], order).kidnaps[0]
    assert kid["scans_until_correct_fix"] == 2  # from stream position 6 on; position 7 fixes
    for kwargs, match in [
        ({"first_scan": 99}, "outside the 15 scans"),
        ({"map_until": -1.0}, "until must be a finite number of seconds >= 0"),
        ({"map_every": 0}, "every must be >= 1"),
    ]:
        with pytest.raises(InputError, match=match):
            eval_track(balm_mini_dir, tmp_path, **kwargs)
    import shutil

    bare = tmp_path / "bare"
    shutil.copytree(balm_mini_dir, bare)
    (bare / "poses.txt").unlink()
    with pytest.raises(InputError, match="needs poses.txt"):
        eval_track(bare, tmp_path / "out")


def test_eval_track_counts_scans_the_encoder_cannot_describe(
    balm_mini_dir: Path, tmp_path: Path
) -> None:
    """A map scan with nothing for the encoder (flat ground only) is left out of the map,
    a streamed one is a scan not localized; the run goes on."""
    import shutil

    from sgvloc.tools.eval_track import eval_track, report_lines

    data = tmp_path / "seq"
    shutil.copytree(balm_mini_dir, data)
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-10, 10, (300, 2)), np.full(300, -1.5), np.ones(300)]
    for i in (2, 0):  # a map scan, and the first streamed scan (a global localize)
        ground.astype(np.float32).tofile(data / "velodyne" / f"{i:06d}.bin")
    r = eval_track(data, tmp_path / "out", map_every=2, max_scans=8)
    assert r.map_scans == 2 and r.map_scans_skipped == 2  # 4 and 6 stay; 0 and 2 left out
    first = r.scans[0]
    assert first.index == 0 and first.mode == "empty_scan" and not first.localized
    assert first.why.startswith("empty_scan: ") and r.streamed == 8
    assert "2 map scans left out" in report_lines(r)[0]


def test_the_readme_tracking_example_runs(server) -> None:
    import re
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    section = (root / "README.md").read_text().split("## Tracking", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    code = code.replace("http://127.0.0.1:8470", server.url).replace('"walk"', '"readme-walk"')
    run = subprocess.run(
        [sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert len(lines) == 15 and all("localized=True" in line for line in lines[1:]), lines
    assert any(" tracked " in line for line in lines), lines  # scans 3-8 s apart: few


@pytest.mark.parametrize("kidnap", [(5, 100), (30, 5), (-1, 5)])
def test_eval_track_refuses_a_kidnap_the_stream_never_takes(
    balm_mini_dir, tmp_path, kidnap
) -> None:
    from sgvloc.core.errors import InputError
    from sgvloc.tools.eval_track import eval_track

    with pytest.raises(InputError, match="never takes this jump"):
        eval_track(balm_mini_dir, tmp_path, map_every=2, kidnaps=[kidnap], max_scans=20)
    assert not (tmp_path / "track.json").exists()


def test_availability_and_correct_availability() -> None:
    """Availability counts every accepted fix of a covered scan, wrong ones too; correct
    availability only those within 2 m and 5 degrees."""
    from sgvloc.tools.eval_track import ScanRecord, summarize

    def rec(i: int, err: float | None) -> ScanRecord:
        return ScanRecord(i, 0.1 * i, "tracked", err is not None, True, err, 0.5, 1.0, True,
                          [0.0, 0.0], [0.0, 0.0])  # fmt: skip

    records = [rec(i, 0.1) for i in range(5)] + [rec(5 + i, 180.0) for i in range(5)]
    records.append(rec(10, None))  # not localized
    r = summarize(records, 4, 0, [], list(range(11)))
    assert r.availability == pytest.approx(10 / 11)
    assert r.correct_availability == pytest.approx(5 / 11) and r.wrong_accepted == 5
