"""The status page (/ui) in a real headless browser (Debian's chromium) against a real
service with authentication on: it lists the maps, draws a map's keyframes and recent
localizations, refuses without a valid key, fetches nothing from elsewhere, and a
screenshot of it is saved as an artefact of the run.

The screenshot goes to ``$SGVLOC_ARTEFACTS/status-page.png`` when that variable is set
(``SGVLOC_ARTEFACTS=docs`` rewrites the one shown in README.md), else to the test's
temporary directory.
"""

from __future__ import annotations

import html
import json
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest
from browser import chromium, render
from conftest import Server
from svc_helpers import PRECOMPUTED, post_msgpack, random_features, rotation_z

from sgvloc.server.keys import hash_key

KEYS = {
    "viewer": "ui-viewer-key-0123456789abcdef",
    "admin": "ui-admin-key-0123456789abcdef",
    "vehicle": "ui-vehicle-key-0123456789abcdef",
    "mapper": "ui-mapper-key-0123456789abcdef",
}
MAP = "campus-loop"
KEYFRAMES = 1100  # more than one page of the keyframe listing (1000)
BATCH = 100


# -- a service with keys and a map ----------------------------------------------------------


@pytest.fixture(scope="module")
def ui_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    root = tmp_path_factory.mktemp("ui")
    keys = root / "keys.json"
    entries = [
        {"name": role, "role": role, "key": hash_key(key) if role == "viewer" else key}
        for role, key in KEYS.items()
    ]
    keys.write_text(json.dumps({"keys": entries}))
    srv = Server(
        data_dir=root / "data",
        log_path=root / "server.log",
        env={"SGVLOC_KEYS_FILE": str(keys), "SGVLOC_MAX_BATCH": str(BATCH)},
    )
    srv.start()
    try:
        yield srv
    finally:
        srv.stop()


def loop_poses(n: int) -> list[np.ndarray]:
    """``n`` sensor poses along a closed drive around a block (about 160 m x 90 m),
    heading along the path."""
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    x = 70 * np.cos(t) + 12 * np.cos(3 * t)
    y = 40 * np.sin(t) - 8 * np.sin(2 * t)
    poses = []
    for i in range(n):
        T = rotation_z(np.arctan2(y[(i + 1) % n] - y[i], x[(i + 1) % n] - x[i]))
        T[:3, 3] = [x[i], y[i], 0.0]
        poses.append(T)
    return poses


@dataclass
class UiMap:
    name: str
    keyframes: int
    localized: int  # answers with localized true
    answers: int  # localize answers in all


def _moved(feats: dict[str, np.ndarray], T_kf_query: np.ndarray) -> dict[str, np.ndarray]:
    """The keyframe's features as seen by a sensor at ``T_kf_query`` from it."""
    R, t = T_kf_query[:3, :3], T_kf_query[:3, 3]
    out = dict(feats)
    out["keypoints"] = ((feats["keypoints"] - t) @ R).astype(np.float32)
    return out


@pytest.fixture(scope="module")
def ui_map(ui_server: Server) -> UiMap:
    """Map ``campus-loop`` (precomputed features) with :data:`KEYFRAMES` keyframes and a
    few localizations: revisits of some keyframes and some scans from nowhere."""
    rng = np.random.default_rng(7)
    poses = loop_poses(KEYFRAMES)
    feats = [random_features(rng) for _ in poses]
    admin = {"Authorization": f"Bearer {KEYS['admin']}"}
    with httpx.Client(base_url=ui_server.url, timeout=120, headers=admin) as c:
        r = c.post("/v1/maps", json={"name": MAP, "encoder": PRECOMPUTED})
        assert r.status_code == 201, r.text
        for start in range(0, KEYFRAMES, BATCH):
            batch = [
                {"key": f"loop/{i:05d}", "T_map_sensor": poses[i], "features": feats[i]}
                for i in range(start, min(start + BATCH, KEYFRAMES))
            ]
            r = post_msgpack(c, f"/v1/maps/{MAP}/keyframes", {"keyframes": batch})
            assert r.status_code == 201, r.text
        localized = answers = 0
        offset = rotation_z(np.radians(4.0))
        offset[:3, 3] = [1.5, 0.3, 0.0]
        queries = [_moved(feats[i], offset) for i in range(40, KEYFRAMES, 120)]
        queries += [random_features(rng) for _ in range(3)]
        for q in queries:
            r = post_msgpack(c, f"/v1/maps/{MAP}/localize", {"features": q})
            assert r.status_code == 200, r.text
            answers += 1
            localized += r.json()["localized"]
    return UiMap(MAP, KEYFRAMES, localized, answers)


def _count(dom: str, pattern: str) -> int:
    return len(re.findall(pattern, dom))


# -- the page ---------------------------------------------------------------------------------


def test_page_and_assets_need_no_key_and_carry_a_strict_policy(ui_server: Server) -> None:
    for path, kind in (
        ("/ui", "text/html"),
        ("/ui/ui.js", "text/javascript"),
        ("/ui/ui.css", "text/css"),
    ):
        r = httpx.get(f"{ui_server.url}{path}")
        assert r.status_code == 200, (path, r.text)
        assert r.headers["content-type"].startswith(kind)
        csp = r.headers["content-security-policy"]
        assert "default-src 'self'" in csp and "script-src 'self'" in csp
        assert "unsafe-inline" not in csp and "unsafe-eval" not in csp
        assert r.headers["x-content-type-options"] == "nosniff"
    # the page at another address would load without its script and style
    r = httpx.get(f"{ui_server.url}/ui/index.html")
    assert r.status_code == 308 and r.headers["location"] == "/ui"
    assert httpx.get(f"{ui_server.url}/ui/keys.json").status_code == 404
    assert httpx.get(f"{ui_server.url}/ui/..%2Fsettings.py").status_code == 404
    # the data behind it is not open
    assert httpx.get(f"{ui_server.url}/v1/maps").status_code == 401


def test_page_references_nothing_outside_the_service(ui_server: Server) -> None:
    html = httpx.get(f"{ui_server.url}/ui").text
    js = httpx.get(f"{ui_server.url}/ui/ui.js").text
    css = httpx.get(f"{ui_server.url}/ui/ui.css").text
    svg_ns = "http://www.w3.org/2000/svg"  # a namespace name, never fetched
    for text in (html, js, css):
        assert not re.search(r"https?://", text.replace(svg_ns, "")), text[:300]
    assert not re.search(r"""(src|href|action)=["']?(https?:)?//""", html)
    for ref in re.findall(r"""(?:src|href)=["']([^"']+)""", html):
        assert ref.startswith("ui/"), ref  # relative to /ui: the service's own files
    assert not re.search(r"<script(?![^>]*\ssrc=)", html)  # no inline script
    assert not re.search(r"\son[a-z]+=", html)  # no inline event handlers
    assert "style=" not in html
    assert "url(" not in css and "@import" not in css
    # the key lives in sessionStorage only
    code = "\n".join(line.split("//")[0] for line in js.splitlines())  # without comments
    assert "sessionStorage." in code
    assert "localStorage" not in code and "cookie" not in code


def test_page_lists_the_map_and_draws_its_keyframes_and_localizations(
    ui_server: Server, ui_map: UiMap
) -> None:
    dom = render(f"{ui_server.url}/ui#key={KEYS['viewer']}")
    assert _count(dom, r'class="map-row[^"]*" data-map="campus-loop"') == 1, dom[:3000]
    assert _count(dom, r'class="map-row') == 1
    # the rows are reached with Tab and say which map is shown
    row = re.search(r'<tr class="map-row[^>]*>', dom).group(0)
    assert 'tabindex="0"' in row and 'aria-current="true"' in row, row
    # every keyframe drawn (two pages of the listing), and the recent answers on top
    assert _count(dom, r'<circle class="kf"') == ui_map.keyframes, dom[:3000]
    locs = _count(dom, r'<circle class="loc ')
    assert 1 <= locs <= ui_map.answers
    assert _count(dom, r'<circle class="loc localized"') == ui_map.localized >= 1
    assert _count(dom, r'class="loc-row"') == min(10, ui_map.answers)
    # live counters from /metrics, read with the viewer key
    localized = re.search(r'id="c-localized">([^<]*)<', dom).group(1)
    not_localized = re.search(r'id="c-not-localized">([^<]*)<', dom).group(1)
    assert int(localized.replace(",", "")) == ui_map.localized
    # the start-up's /readyz 503s ("still loading") are no service unavailable answers
    assert re.search(r'id="c-503">0<', dom), re.search(r'id="c-503">[^<]*<', dom)
    assert int(not_localized.replace(",", "")) == ui_map.answers - ui_map.localized
    assert re.search(r'id="version"[^>]*>version \S+<', dom)
    # the key form is hidden and the key is nowhere in the page
    assert re.search(r'<section id="auth" hidden', dom)
    assert KEYS["viewer"] not in dom


def test_page_with_a_mapper_key_shows_the_maps_without_counters(
    ui_server: Server, ui_map: UiMap
) -> None:
    dom = render(f"{ui_server.url}/ui#key={KEYS['mapper']}")
    assert _count(dom, r'class="map-row') == 1, dom[:3000]
    assert _count(dom, r'<circle class="kf"') == ui_map.keyframes
    # /metrics and /v1/config are for viewers and admins: no counters, no version
    assert re.search(r'id="c-localized">–<', dom)
    assert re.search(r'id="version"[^>]*><', dom)


def test_page_without_a_key_shows_the_key_form_and_no_data(
    ui_server: Server, ui_map: UiMap
) -> None:
    dom = render(f"{ui_server.url}/ui")
    assert '<section id="auth">' in dom and 'id="key-form"' in dom, dom[:3000]
    assert "Enter an API key" in dom
    assert "map-row" not in dom and '<circle class="kf"' not in dom
    assert ui_map.name not in dom


@pytest.mark.parametrize(
    ("key", "says"),
    [("not-a-configured-key-0123456789", "(401)"), (KEYS["vehicle"], "(403)")],
    ids=["unknown", "vehicle"],
)
def test_page_with_a_refused_key_says_so_and_shows_no_data(
    ui_server: Server, ui_map: UiMap, key: str, says: str
) -> None:
    dom = render(f"{ui_server.url}/ui#key={key}")
    message = re.search(r'<p id="auth-message"[^>]*>([^<]*)<', dom)
    assert message and says in message.group(1) and "refused" in dom, dom[:3000]
    assert '<section id="auth">' in dom
    assert "map-row" not in dom and '<circle class="kf"' not in dom
    assert ui_map.name not in dom


def test_screenshot_of_the_status_page(
    ui_server: Server, ui_map: UiMap, tmp_path_factory: pytest.TempPathFactory
) -> None:
    from PIL import Image

    folder = Path(os.environ.get("SGVLOC_ARTEFACTS") or tmp_path_factory.mktemp("artefacts"))
    folder.mkdir(parents=True, exist_ok=True)
    png = folder / "status-page.png"
    png.unlink(missing_ok=True)
    chromium(
        f"{ui_server.url}/ui#key={KEYS['viewer']}",
        f"--screenshot={png}",
        "--window-size=1280,800",
        "--hide-scrollbars",
    )
    assert png.is_file(), f"no screenshot at {png}"
    with Image.open(png) as image:
        assert image.size == (1280, 800)
        rgb = image.convert("RGB")
        colours = rgb.getcolors(maxcolors=1 << 20)
    assert colours is not None and len(colours) >= 32, f"{png}: a blank page?"
    most = max(n for n, _ in colours)
    assert most < 0.9 * 1280 * 800, f"{png}: one colour covers the page"
    # the keyframes are drawn: pixels near their blue (#3b5b92, blended on white)
    blue = sum(n for n, (r, g, b) in colours if b > r + 40 and b > g + 20 and r < 170)
    assert blue >= 500, f"{png}: no keyframes drawn?"


# -- many maps: one page of the table at a time -------------------------------------------

MANY = 120  # maps; the table shows 20 at a time
FEW_KEY = "ui-few-maps-key-0123456789abcdef"  # a viewer key for two of them


@pytest.fixture(scope="module")
def many_maps(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A service with :data:`MANY` empty maps ``m-000`` ... and three keyframes in the last."""
    root = tmp_path_factory.mktemp("ui-many")
    keys = root / "keys.json"
    keys.write_text(
        json.dumps(
            {
                "keys": [{"name": r, "role": r, "key": KEYS[r]} for r in ("viewer", "admin")]
                + [{"name": "few", "role": "viewer", "key": FEW_KEY, "maps": ["m-003", "m-004"]}]
            }
        )
    )
    srv = Server(
        data_dir=root / "data", log_path=root / "server.log", env={"SGVLOC_KEYS_FILE": str(keys)}
    )
    srv.start()
    try:
        admin = {"Authorization": f"Bearer {KEYS['admin']}"}
        with httpx.Client(base_url=srv.url, timeout=120, headers=admin) as c:
            for i in range(MANY):
                r = c.post("/v1/maps", json={"name": f"m-{i:03d}", "encoder": PRECOMPUTED})
                assert r.status_code == 201, r.text
            rng = np.random.default_rng(5)
            kfs = [{"T_map_sensor": T, "features": random_features(rng)} for T in loop_poses(3)]
            r = post_msgpack(c, f"/v1/maps/m-{MANY - 1:03d}/keyframes", {"keyframes": kfs})
            assert r.status_code == 201, r.text
        yield srv
    finally:
        srv.stop()


def _rows(dom: str) -> list[str]:
    return re.findall(r'class="map-row[^"]*" data-map="([^"]+)"', dom)


def test_many_maps_show_one_page_with_stats_for_its_rows_only(many_maps: Server) -> None:
    before = _stats_asked(many_maps)
    dom = render(f"{many_maps.url}/ui#key={KEYS['viewer']}")
    assert _rows(dom) == [f"m-{i:03d}" for i in range(20)], dom[:3000]
    assert re.search(r'<span id="maps-pager">', dom), "the pager is hidden"
    assert re.search(r'id="maps-range"[^>]*>1–20 of 120<', dom)
    assert re.search(r'<button type="button" id="maps-prev" disabled', dom)
    assert not re.search(r'<button type="button" id="maps-next" disabled', dom)
    assert re.search(r'id="map-title">m-000<', dom)
    # the page asks the statistics of the rows it shows, not of all 120 maps (once per
    # refresh of the table: at the start and maybe once more within the 20 s it ran)
    asked = _stats_asked(many_maps) - before
    assert asked in (20, 40), asked


def _stats_asked(srv: Server) -> int:
    """GET /v1/maps/{map}/stats requests the service answered so far (its metrics)."""
    text = httpx.get(
        f"{srv.url}/metrics", headers={"Authorization": f"Bearer {KEYS['admin']}"}
    ).text
    pattern = r'sgvloc_http_requests_total\{[^}]*route="/v1/maps/\{map\}/stats"[^}]*\} (\S+)'
    return int(sum(float(v) for v in re.findall(pattern, text)))


def test_many_maps_page_filter_and_selection_come_from_the_address(many_maps: Server) -> None:
    key = KEYS["viewer"]
    dom = render(f"{many_maps.url}/ui#key={key}&after=m-049")
    assert _rows(dom) == [f"m-{i:03d}" for i in range(50, 70)], dom[:3000]
    assert re.search(r'id="maps-range"[^>]*>maps after m-049 of 120<', dom)
    assert not re.search(r'<button type="button" id="maps-prev" disabled', dom)
    dom = render(f"{many_maps.url}/ui#key={key}&filter=m-11")
    assert _rows(dom) == [f"m-{i:03d}" for i in range(110, 120)], dom[:3000]
    assert re.search(r'<span id="maps-pager" hidden', dom)
    assert re.search(r'<input id="maps-filter"[^>]*>', dom)
    # a map off the page shown is still shown when the address names it
    dom = render(f"{many_maps.url}/ui#key={key}&map=m-119")
    assert _rows(dom)[:2] == ["m-000", "m-001"]
    assert re.search(r'id="map-title">m-119<', dom), dom[:3000]
    assert _count(dom, r'<circle class="kf"') == 3


def test_an_address_the_key_cannot_follow_falls_back_to_what_it_can_see(
    many_maps: Server,
) -> None:
    """A bookmark made with another key (a map this key may not use) or an edited address
    (a filter longer than any name) shows the first rows this key may see, not a refusal."""
    dom = render(f"{many_maps.url}/ui#key={FEW_KEY}&map=m-119")
    assert _rows(dom) == ["m-003", "m-004"], dom[:3000]
    assert re.search(r'id="map-title">m-003<', dom)
    assert re.search(r'<section id="auth" hidden', dom)
    dom = render(f"{many_maps.url}/ui#key={KEYS['viewer']}&filter={'m' * 65}")
    assert _rows(dom) == [f"m-{i:03d}" for i in range(20)], dom[:3000]


def _self_test_sentence(rep: dict, version: int, own: str) -> str:
    """What the status page should say of a self-test report (``own``: the map's encoder)."""
    f = rep["figures"]
    text = (
        f"Self-test of version {version}: R@1 {f['recall_at_1']:.1f} %, pose success "
        f"{f['pose_success']:.1f} %, {f['false_accepts']} false accepts over {f['queries']} "
        f"keyframes with a revisit and {f['negatives']} without."
    )
    mark = " (this map's)"
    parts = [
        f"{n}{mark if n == own else ''} {e['figures']['localized_correct']}"
        for n, e in rep["encoders"].items()
    ]
    text += f" Localized correctly by encoder: {', '.join(parts)}; best: {rep['chosen']}."
    if rep["chosen"] != own:
        text += f" {rep['chosen']} does better on this map's keyframes than its own encoder."
    if rep["warning"]:
        text += f" Warning: {rep['warning']}"
    return text


def _shown_self_test(url: str, name: str) -> str | None:
    dom = render(f"{url}/ui#key={KEYS['viewer']}&map={name}")
    if re.search(r'<p id="map-self-test"[^>]*hidden', dom):
        return None
    shown = re.search(r'<p id="map-self-test"[^>]*>([^<]*)<', dom)
    assert shown, dom[:3000]
    return html.unescape(shown.group(1))


def test_page_shows_the_selected_maps_self_test(ui_server: Server) -> None:
    """A map's latest self-test (``last_self_test``) is told in words above its drawing:
    the figures, the encoders compared and the best of them (the map's own wins ties),
    saying so when another does better; a map never tested shows no such line. Runs
    last: the map it makes is deleted."""
    from importlib.resources import files

    rng = np.random.default_rng(3)
    name = "sensor-check"
    places = [rng.uniform([-20, -20, 0], [20, 20, 3], (3000, 3)) for _ in range(12)]
    admin = {"Authorization": f"Bearer {KEYS['admin']}"}
    with httpx.Client(base_url=ui_server.url, timeout=120, headers=admin) as c:
        r = c.post("/v1/maps", json={"name": name, "encoder": {"kind": "bev"}})
        assert r.status_code == 201, r.text
        assert _shown_self_test(ui_server.url, name) is None
        batch = []
        for lap in range(2):  # the same places twice, 20 s apart: every keyframe a revisit
            for i, pts in enumerate(places):
                T = np.eye(4)
                T[:3, 3] = [8.0 * i, 0.0, 0.0]
                seen = pts + rng.normal(0.0, 0.02, pts.shape)
                stamp = 20.0 * lap + i
                batch.append({"T_map_sensor": T, "points": seen.astype(np.float32),
                              "metadata": {"timestamp": stamp}})  # fmt: skip
        r = post_msgpack(c, f"/v1/maps/{name}/keyframes", {"keyframes": batch})
        assert r.status_code == 201, r.text
        body = {"queries": 6, "gap_s": 10, "encoders": ["handcrafted", "bev"]}
        r = c.post(f"/v1/maps/{name}/self-test", json=body)
        assert r.status_code == 200, r.text
        tie = r.json()
        version = c.get(f"/v1/maps/{name}").json()["version"]
        shown = _shown_self_test(ui_server.url, name)
        assert shown == _self_test_sentence(tie, version, "bev")
        # both find and pose every place: the map's own is named, nothing more is said
        assert tie["figures"]["recall_at_1"] == 100.0 and tie["chosen"] == "bev"
        assert "does better" not in shown
        # a calibration that trusts nothing: the map accepts no answer, handcrafted (with
        # its own shipped calibration) does better
        cal = json.loads((files("sgvloc") / "calibration" / "bev.json").read_text())
        for model in cal["models"].values():
            model["bias"] = -30.0
        r = c.patch(f"/v1/maps/{name}", json={"calibration": cal})
        assert r.status_code == 200, r.text
        body["encoders"] = ["handcrafted"]
        r = c.post(f"/v1/maps/{name}/self-test", json=body)
        assert r.status_code == 200, r.text
        worse = r.json()
        assert worse["encoders"]["bev"]["figures"]["localized_correct"] == 0
        assert worse["chosen"] == "handcrafted"
        shown = _shown_self_test(ui_server.url, name)
        assert shown == _self_test_sentence(worse, version, "bev")
        assert shown.endswith(
            "handcrafted does better on this map's keyframes than its own encoder."
        )
        assert c.delete(f"/v1/maps/{name}").status_code == 204
