// The sgvloc status page. Plain JavaScript, no dependencies, no external requests.
//
// The page holds no data of its own: it asks for an API key, keeps it in
// sessionStorage (this tab only; never localStorage or a cookie) and reads the JSON API
// with "Authorization: Bearer <key>":
//   GET v1/maps (paged), v1/maps/{map}, v1/maps/{map}/stats (the rows shown),
//   v1/maps/{map}/keyframes (paged),
//   v1/maps/{map}/localizations, v1/config (version) and metrics (Prometheus text).
// A key given in the address fragment (/ui#key=...) is moved into sessionStorage and
// removed from the address at once. Every URL is relative, so the page also works
// behind a reverse proxy that serves the service under a path prefix.
"use strict";

(() => {
  const KEY_ITEM = "sgvloc.apiKey";
  const MAX_KEYFRAMES = 50000; // drawn at most
  const PAGE = 1000; // keyframes per listing request
  const MAPS_PAGE = 20; // map rows per page of the maps table
  const RECENT = 200; // localizations drawn
  const EVERY_MS = { localizations: 3000, metrics: 5000, maps: 15000, loading: 2000, retry: 5000 };
  const SVG_NS = "http://www.w3.org/2000/svg";
  const KF_RADIUS_PX = 2.5;
  const LOC_RADIUS_PX = 7;

  const state = {
    maps: [], // the page of maps shown
    stats: {},
    mapsAfter: null, // cursor of the page shown (null: the first page)
    mapsBefore: [], // cursors of the pages before it, for "Previous" (null: not known)
    mapsSeq: 0, // bumped by every listing: an older listing's late answer is dropped
    mapsNext: null, // next_cursor of the page shown
    mapsTotal: null, // maps matching the filter on every page
    selected: null,
    selectedInfo: null, // MapInfo of the selected map, on the page shown or not
    keyframes: [], // {id, key, x, y}
    keyframeById: new Map(),
    keyframesVersion: null, // map version the keyframes were read at
    localizations: [],
    view: null, // {s, tx, ty}: screen = (tx + s * x, ty - s * y)
    timers: [],
    generation: 0, // bumped when polling stops: late answers of old requests are dropped
    failing: new Map(), // what -> message, while that poll fails: shown until it succeeds
    updated: null, // time of the last successful refresh of the selected map (HH:MM:SS)
  };

  const $ = (id) => document.getElementById(id);

  // -- errors ---------------------------------------------------------------------------

  class Refused extends Error {} // no key, or the key was refused (401/403)
  class Loading extends Error {} // 503: maps are loading, or the service is busy
  class HttpError extends Error {
    constructor(status, message) {
      super(message);
      this.status = status;
    }
  }

  async function errorMessage(response) {
    try {
      const body = await response.json();
      if (body && body.error && body.error.message) return body.error.message;
    } catch (_) {
      // not the service's error body
    }
    return `${response.status} ${response.statusText}`;
  }

  // -- the key --------------------------------------------------------------------------

  function keyFromFragment() {
    const params = new URLSearchParams(location.hash.slice(1));
    if (!params.has("key")) return;
    const key = params.get("key");
    params.delete("key");
    if (key) sessionStorage.setItem(KEY_ITEM, key);
    const rest = params.toString();
    history.replaceState(null, "", location.pathname + location.search + (rest ? `#${rest}` : ""));
  }

  function storedKey() {
    return sessionStorage.getItem(KEY_ITEM);
  }

  // -- the API --------------------------------------------------------------------------

  // ``one``: a request about one map, whose 403 only says this key may not use that map
  // (an HttpError, not a refusal of the key)
  async function api(path, { text = false, one = false } = {}) {
    const key = storedKey();
    if (!key) throw new Refused("Enter an API key to see the service's status.");
    let response;
    try {
      response = await fetch(path, {
        headers: { Authorization: `Bearer ${key}`, Accept: text ? "text/plain" : "application/json" },
        cache: "no-store",
        credentials: "omit",
        referrerPolicy: "no-referrer",
      });
    } catch (exc) {
      throw new HttpError(0, `cannot reach the service (${exc.message})`);
    }
    if (response.status === 401) {
      throw new Refused(`The service refused this key (401): ${await errorMessage(response)}`);
    }
    if (response.status === 403 && one) throw new HttpError(403, await errorMessage(response));
    if (response.status === 403) {
      throw new Refused(
        `This key may not read the status (403): ${await errorMessage(response)}. ` +
          "The status page needs a viewer or admin key.",
      );
    }
    if (response.status === 503) throw new Loading(await errorMessage(response));
    if (!response.ok) throw new HttpError(response.status, await errorMessage(response));
    return text ? response.text() : response.json();
  }

  const mapPath = (name) => `v1/maps/${encodeURIComponent(name)}`;

  // -- page states ----------------------------------------------------------------------

  function setStatus(message, warn = false) {
    const el = $("status");
    el.textContent = message;
    el.classList.toggle("warn", warn);
  }

  // a failing poll's message stays until that poll succeeds again, and the data on the
  // page is greyed meanwhile: it may be out of date
  function showProgress() {
    const stale = state.failing.size > 0;
    $("content").classList.toggle("stale", stale);
    if (stale) {
      const since = state.updated ? ` (data as of ${state.updated} UTC)` : "";
      setStatus(`${[...state.failing.values()].join("; ")}${since}`, true);
    } else if (state.updated) {
      setStatus(`updated ${state.updated} UTC`);
    }
  }

  function succeeded(what) {
    if (state.failing.delete(what)) showProgress();
  }

  function stopPolling() {
    state.timers.forEach(clearInterval);
    state.timers = [];
    state.generation += 1;
    state.metricsRefused = false;
    state.failing.clear();
    state.updated = null;
    $("content").classList.remove("stale");
  }

  function clearData() {
    state.maps = [];
    state.stats = {};
    state.mapsNext = null;
    state.selected = null;
    state.selectedInfo = null;
    state.keyframes = [];
    state.keyframeById = new Map();
    state.keyframesVersion = null;
    state.localizations = [];
    $("maps").tBodies[0].replaceChildren();
    $("recent").tBodies[0].replaceChildren();
    $("kf-layer").replaceChildren();
    $("loc-layer").replaceChildren();
    $("map-section").hidden = true;
    $("content").hidden = true;
    $("version").textContent = "";
    for (const id of ["c-localized", "c-not-localized", "c-429", "c-503"]) $(id).textContent = "–";
  }

  function showKeyForm(message, refused) {
    stopPolling();
    clearData();
    if (refused) sessionStorage.removeItem(KEY_ITEM);
    const msg = $("auth-message");
    msg.textContent = message;
    msg.classList.toggle("refused", refused);
    $("auth").hidden = false;
    $("forget").hidden = true;
    setStatus("");
    $("key-input").focus();
  }

  // ``key``: the poll that failed, whose next success clears the message
  function handle(exc, what, key = what) {
    if (exc instanceof Refused) {
      showKeyForm(exc.message, Boolean(storedKey()));
      return;
    }
    if (exc instanceof Loading) {
      state.failing.set(key, `${what}: the service is not ready (${exc.message}); retrying…`);
    } else {
      state.failing.set(key, `${what}: ${exc.message}`);
    }
    showProgress();
  }

  // -- counters -------------------------------------------------------------------------

  // Prometheus text -> [{name, labels, value}]
  function parseMetrics(text) {
    const samples = [];
    const line = /^([A-Za-z_:][A-Za-z0-9_:]*)(?:\{(.*)\})?\s+(\S+)/;
    const label = /([A-Za-z_][A-Za-z0-9_]*)="((?:[^"\\]|\\.)*)"/g;
    for (const raw of text.split("\n")) {
      if (!raw || raw.startsWith("#")) continue;
      const m = line.exec(raw);
      if (!m) continue;
      const labels = {};
      for (const l of (m[2] || "").matchAll(label)) labels[l[1]] = l[2];
      samples.push({ name: m[1], labels, value: Number(m[3]) });
    }
    return samples;
  }

  // Sums of one counter family: the shortest name that starts with `prefix`, ends with
  // "_total" and carries label `by` (tolerant of renamed or relabelled series), over the
  // samples whose labels `keep` accepts.
  function family(samples, prefix, by, keep = () => true) {
    const names = [...new Set(samples.map((s) => s.name))]
      .filter((n) => n.startsWith(prefix) && n.endsWith("_total"))
      .filter((n) => samples.some((s) => s.name === n && by in s.labels))
      .sort((a, b) => a.length - b.length);
    if (!names.length) return null;
    const sums = {};
    for (const s of samples) {
      if (s.name !== names[0] || !(by in s.labels) || !Number.isFinite(s.value)) continue;
      if (!keep(s.labels)) continue;
      sums[s.labels[by]] = (sums[s.labels[by]] || 0) + s.value;
    }
    return sums;
  }

  const count = (v) => (v === undefined || v === null ? "–" : Math.round(v).toLocaleString("en"));

  async function refreshMetrics() {
    if (state.metricsRefused) return;
    const generation = state.generation;
    let text;
    try {
      text = await api("metrics", { text: true });
    } catch (exc) {
      if (exc instanceof Refused && generation === state.generation) {
        // a key that reads the maps but not the metrics (e.g. a mapper): no counters, and
        // no more asking (a new key starts polling again)
        $("counters").title = "The counters need a viewer or admin key (this key may not read /metrics).";
        state.metricsRefused = true;
        return;
      }
      throw exc;
    }
    if (generation !== state.generation) return;
    const samples = parseMetrics(text);
    // by key, not by map: a deleted map's series go, these counters since the start stay
    const verdicts = family(samples, "sgvloc_localize_by_key", "verdict") || {};
    let localized = 0;
    let other = 0;
    for (const [verdict, n] of Object.entries(verdicts)) {
      if (verdict === "localized") localized += n;
      else other += n;
    }
    // a probe's 503 says "not ready yet" (load balancers ask every second): not counted
    const probes = new Set(["/readyz", "/healthz", "/metrics"]);
    const statuses = family(samples, "sgvloc_http_requests", "status", (l) => !probes.has(l.route)) || {};
    $("c-localized").textContent = count(localized);
    $("c-not-localized").textContent = count(other);
    $("c-429").textContent = count(statuses["429"] || 0);
    $("c-503").textContent = count(statuses["503"] || 0);
  }

  // -- maps -----------------------------------------------------------------------------

  function human(bytes) {
    if (bytes === undefined || bytes === null) return "–";
    const units = ["B", "KiB", "MiB", "GiB", "TiB"];
    let v = bytes;
    let i = 0;
    while (v >= 1024 && i < units.length - 1) {
      v /= 1024;
      i += 1;
    }
    return `${v.toFixed(i ? 1 : 0)} ${units[i]}`;
  }

  function extentText(stats) {
    if (!stats) return "–";
    if (!stats.extent) return "empty";
    const { min, max } = stats.extent;
    return `${(max[0] - min[0]).toFixed(1)} × ${(max[1] - min[1]).toFixed(1)}`;
  }

  function cell(row, text, cls) {
    const td = row.insertCell();
    td.textContent = text;
    if (cls) td.className = cls;
    return td;
  }

  function renderMaps() {
    const body = $("maps").tBodies[0];
    const focused = document.activeElement && document.activeElement.dataset ? document.activeElement.dataset.map : undefined;
    body.replaceChildren();
    for (const m of state.maps) {
      const stats = state.stats[m.name];
      const row = body.insertRow();
      row.className = "map-row";
      row.dataset.map = m.name;
      row.id = `map-${m.name}`;
      row.classList.toggle("selected", m.name === state.selected);
      row.title = `show map ${m.name}`;
      row.tabIndex = 0; // reachable with Tab; Enter or Space shows the map
      if (m.name === state.selected) row.setAttribute("aria-current", "true");
      cell(row, m.name);
      cell(row, count(m.keyframes), "num");
      cell(row, String(m.version), "num");
      cell(row, m.encoder ? `${m.encoder.kind} (${m.encoder.name})` : "–");
      cell(row, m.index_kind || "–");
      cell(row, extentText(stats), "num");
      cell(row, stats ? human(stats.disk_bytes) : "–", "num");
      row.addEventListener("click", () => select(m.name));
      row.addEventListener("keydown", (ev) => {
        if (ev.key === "Enter" || ev.key === " ") {
          ev.preventDefault();
          select(m.name);
        }
      });
    }
    const prefix = $("maps-filter").value;
    $("maps-empty").textContent = prefix ? `No map names start with "${prefix}".` : "No maps.";
    $("maps-empty").hidden = state.maps.length > 0;
    const paged = state.mapsAfter !== null || state.mapsNext !== null;
    $("maps-pager").hidden = !paged;
    const keyboard = document.activeElement;
    $("maps-prev").disabled = state.mapsAfter === null;
    $("maps-next").disabled = state.mapsNext === null;
    // a button that became disabled under the keyboard hands the focus to the other one
    if (keyboard === $("maps-next") && $("maps-next").disabled) $("maps-prev").focus();
    if (keyboard === $("maps-prev") && $("maps-prev").disabled) $("maps-next").focus();
    if (focused !== undefined) {
      const again = body.querySelector(`tr[data-map="${CSS.escape(focused)}"]`);
      if (again) again.focus(); // the row rebuilt under the keyboard keeps it
    }
    const n = state.maps.length;
    if (!n) {
      $("maps-range").textContent = "";
    } else if (state.mapsBefore === null) {
      // opened at a page of the address: its place in the list is not known
      $("maps-range").textContent = `maps after ${state.mapsAfter}${ofTotal()}`;
    } else {
      const first = state.mapsBefore.length * MAPS_PAGE + 1;
      $("maps-range").textContent = `${first}–${first + n - 1}${ofTotal()}`;
    }
  }

  const ofTotal = () => (state.mapsTotal === null ? "" : ` of ${count(state.mapsTotal)}`);

  function hashParams() {
    return new URLSearchParams(location.hash.slice(1));
  }

  function setHashParam(name, value) {
    const params = hashParams();
    if (value) params.set(name, value);
    else params.delete(name);
    const rest = params.toString();
    history.replaceState(null, "", `${location.pathname}${location.search}${rest ? `#${rest}` : ""}`);
  }

  // the maps table shows one page; its cursor and the filter live in the address
  // (#after=NAME, #filter=PREFIX), so a reload shows the same rows
  function turnMapsPage(after, before) {
    state.mapsAfter = after;
    state.mapsBefore = before;
    state.mapsNext = null;
    $("maps-prev").disabled = true; // one turn at a time: a second click waits for this one
    $("maps-next").disabled = true;
    setHashParam("after", after);
    refreshMaps().catch((exc) => handle(exc, "maps"));
  }

  async function refreshStats(generation) {
    await Promise.all(
      state.maps.map(async (m) => {
        try {
          const stats = await api(`${mapPath(m.name)}/stats`);
          if (generation === state.generation) state.stats[m.name] = stats;
        } catch (exc) {
          if (exc instanceof Refused) throw exc;
          // stats are optional (an older service, or a busy one): the row shows "–"
        }
      }),
    );
  }

  function mapsQuery() {
    const params = new URLSearchParams({ limit: String(MAPS_PAGE) });
    const prefix = $("maps-filter").value;
    if (prefix) params.set("prefix", prefix);
    if (state.mapsAfter !== null) params.set("cursor", state.mapsAfter);
    return `v1/maps?${params}`;
  }

  async function refreshMaps() {
    const generation = state.generation;
    const seq = ++state.mapsSeq;
    const current = () => generation === state.generation && seq === state.mapsSeq;
    let body;
    try {
      body = await api(mapsQuery());
    } catch (exc) {
      if (!(exc instanceof HttpError && exc.status === 422)) throw exc;
      // a page or filter the service refuses (an edited address): the first page of all
      $("maps-filter").value = "";
      state.mapsAfter = null;
      state.mapsBefore = [];
      setHashParam("filter", null);
      setHashParam("after", null);
      body = await api(mapsQuery());
    }
    if (!current()) return;
    if (!body.maps.length && state.mapsAfter !== null) {
      // the maps of this page are gone: back to the first page
      state.mapsAfter = null;
      state.mapsBefore = [];
      setHashParam("after", null);
      body = await api(mapsQuery());
      if (!current()) return;
    }
    state.maps = body.maps;
    state.mapsNext = body.next_cursor || null;
    state.mapsTotal = Number.isInteger(body.total) ? body.total : null;
    state.updated = new Date().toISOString().slice(11, 19);
    state.failing.delete("maps");
    showProgress();
    $("auth").hidden = true;
    $("content").hidden = false;
    $("forget").hidden = false;
    await refreshStats(generation);
    if (!current()) return;
    renderMaps();
    const names = state.maps.map((m) => m.name);
    if (state.selected) {
      // the selected map may be on another page: read it on its own
      const info = await mapInfo(state.selected);
      if (generation !== state.generation) return;
      if (!info) {
        state.selected = null;
        state.selectedInfo = null;
        $("map-section").hidden = true;
      } else {
        state.selectedInfo = info;
        renderSelfTest();
        if (info.version !== state.keyframesVersion) await loadKeyframes(generation);
        return;
      }
    }
    const wanted = hashParams().get("map");
    if (wanted && !names.includes(wanted)) {
      const info = await mapInfo(wanted);
      if (generation !== state.generation) return;
      if (info) {
        await select(wanted, info);
        return;
      }
    }
    if (names.length) await select(names.includes(wanted) ? wanted : names[0]);
  }

  // a map's MapInfo, or null when there is no such map (any more) or this key may not
  // use it (a bookmark made with another key)
  async function mapInfo(name) {
    const listed = state.maps.find((m) => m.name === name);
    if (listed) return listed;
    try {
      return await api(mapPath(name), { one: true });
    } catch (exc) {
      if (exc instanceof HttpError && (exc.status === 404 || exc.status === 403)) return null;
      throw exc;
    }
  }

  // -- the selected map -----------------------------------------------------------------

  // the latest self-test of a map (MapInfo.last_self_test) in a sentence or two, null if none
  function selfTestText(info) {
    const st = info && info.last_self_test;
    if (!st || !st.figures) return null;
    const f = st.figures;
    const pct = (v) => (typeof v === "number" ? `${v.toFixed(1)} %` : "–");
    let text =
      `Self-test of version ${st.map_version}` +
      (st.map_version === info.version ? "" : " (the map has changed since)") +
      `: R@1 ${pct(f.recall_at_1)}, pose success ${pct(f.pose_success)}, ` +
      `${f.false_accepts} false accepts over ${f.queries} keyframes with a revisit and ` +
      `${f.negatives} without.`;
    if (st.encoders && st.chosen && st.encoders[st.chosen]) {
      const rows = Object.entries(st.encoders);
      const fp = info.encoder ? info.encoder.fingerprint : null;
      const own = rows.find(([, e]) => e.fingerprint === fp);
      const parts = rows.map(
        ([name, e]) => `${name}${own && own[0] === name ? " (this map's)" : ""} ${e.figures.localized_correct}`,
      );
      text += ` Localized correctly by encoder: ${parts.join(", ")}; best: ${st.chosen}.`;
      // the map's own encoder wins ties: another one chosen did better by the rule
      if (own && own[0] !== st.chosen) {
        text += ` ${st.chosen} does better on this map's keyframes than its own encoder.`;
      }
    }
    if (st.warning) text += ` Warning: ${st.warning}`;
    return text;
  }

  function renderSelfTest() {
    const text = selfTestText(state.selectedInfo);
    const el = $("map-self-test");
    el.textContent = text || "";
    el.hidden = !text;
    el.classList.toggle("warn", Boolean(text && state.selectedInfo.last_self_test.warning));
  }

  async function select(name, info = null) {
    state.selected = name;
    state.selectedInfo = info || state.maps.find((m) => m.name === name) || null;
    state.view = null;
    setHashParam("map", name);
    for (const row of $("maps").tBodies[0].rows) {
      row.classList.toggle("selected", row.dataset.map === name);
      if (row.dataset.map === name) row.setAttribute("aria-current", "true");
      else row.removeAttribute("aria-current");
    }
    $("map-title").textContent = name;
    renderSelfTest();
    $("map-section").hidden = false;
    state.keyframes = [];
    state.keyframeById = new Map();
    state.localizations = [];
    $("kf-layer").replaceChildren();
    $("loc-layer").replaceChildren();
    $("recent").tBodies[0].replaceChildren();
    const generation = state.generation;
    try {
      await loadKeyframes(generation);
      await refreshLocalizations();
      // fitted again with the answers too: an estimate beyond the keyframes stays in view
      state.view = null;
      applyView();
      if (generation === state.generation) succeeded("map");
    } catch (exc) {
      if (generation === state.generation) handle(exc, `map ${name}`, "map");
    }
  }

  async function loadKeyframes(generation) {
    const name = state.selected;
    const info = state.selectedInfo;
    const version = info ? info.version : null;
    const out = [];
    let cursor = null;
    let truncated = false;
    try {
      do {
        const query = `limit=${PAGE}${cursor ? `&cursor=${encodeURIComponent(cursor)}` : ""}`;
        const page = await api(`${mapPath(name)}/keyframes?${query}`);
        if (generation !== state.generation || name !== state.selected) return;
        for (const kf of page.keyframes) {
          const p = kf.position || [kf.T_map_sensor[0][3], kf.T_map_sensor[1][3]];
          out.push({ id: kf.id, key: kf.key, x: p[0], y: p[1] });
        }
        cursor = page.next_cursor;
        if (out.length >= MAX_KEYFRAMES && cursor) {
          truncated = true;
          break;
        }
      } while (cursor);
    } catch (exc) {
      if (exc instanceof HttpError && exc.status === 404 && state.selectedInfo) {
        $("map-note").textContent = "(this service does not list keyframes)";
        return;
      }
      throw exc;
    }
    state.keyframes = out.slice(0, MAX_KEYFRAMES);
    state.keyframeById = new Map(state.keyframes.map((k) => [k.id, k]));
    state.keyframesVersion = version;
    $("map-note").textContent =
      `${count(state.keyframes.length)} keyframes` +
      (truncated ? ` (the first ${count(MAX_KEYFRAMES)} drawn)` : "") +
      (version === null ? "" : `, version ${version}`);
    drawKeyframes();
  }

  async function refreshLocalizations() {
    const name = state.selected;
    if (!name) return;
    const generation = state.generation;
    const body = await api(`${mapPath(name)}/localizations?limit=${RECENT}`);
    if (generation !== state.generation || name !== state.selected) return;
    state.localizations = body.localizations;
    drawLocalizations();
    renderRecent();
    state.updated = new Date().toISOString().slice(11, 19);
    state.failing.delete("localizations");
    showProgress();
  }

  // -- drawing --------------------------------------------------------------------------

  function svgEl(tag, attrs, parent) {
    const el = document.createElementNS(SVG_NS, tag);
    for (const [k, v] of Object.entries(attrs)) el.setAttribute(k, v);
    if (parent) parent.appendChild(el);
    return el;
  }

  function titled(el, text) {
    svgEl("title", {}, el).textContent = text;
    return el;
  }

  function verdictClass(loc) {
    if (loc.localized) return "localized";
    return loc.verdict === "low_confidence" ? "low" : "failed";
  }

  // where a localization is drawn: its estimate, else the keyframe it was matched to
  function locPoint(loc) {
    if (loc.translation) return { x: loc.translation[0], y: loc.translation[1], estimate: true };
    const kf = loc.keyframe_id === null ? undefined : state.keyframeById.get(loc.keyframe_id);
    return kf ? { x: kf.x, y: kf.y, estimate: false } : null;
  }

  function viewSize() {
    const svg = $("view");
    return { w: svg.clientWidth || 800, h: svg.clientHeight || 440 };
  }

  function fit() {
    const pts = state.keyframes.map((k) => [k.x, k.y]);
    for (const loc of state.localizations) {
      const p = locPoint(loc);
      if (p) pts.push([p.x, p.y]);
    }
    const { w, h } = viewSize();
    if (!pts.length) {
      state.view = { s: 10, tx: w / 2, ty: h / 2, empty: true }; // fitted again with data
      return;
    }
    let [x0, y0, x1, y1] = [Infinity, Infinity, -Infinity, -Infinity];
    for (const [x, y] of pts) {
      x0 = Math.min(x0, x);
      x1 = Math.max(x1, x);
      y0 = Math.min(y0, y);
      y1 = Math.max(y1, y);
    }
    const dx = Math.max(x1 - x0, 1);
    const dy = Math.max(y1 - y0, 1);
    const s = 0.9 * Math.min(w / dx, h / dy);
    state.view = { s, tx: w / 2 - s * (x0 + x1) / 2, ty: h / 2 + s * (y0 + y1) / 2 };
  }

  // x right, y up: world (x, y) -> screen (tx + s x, ty - s y)
  function applyView() {
    if (!state.view) fit();
    const { s, tx, ty } = state.view;
    $("world").setAttribute("transform", `translate(${tx} ${ty}) scale(${s} ${-s})`);
    for (const c of $("kf-layer").children) c.setAttribute("r", KF_RADIUS_PX / s);
    for (const c of $("loc-layer").children) {
      c.setAttribute("r", (c.classList.contains("newest") ? LOC_RADIUS_PX + 4 : LOC_RADIUS_PX) / s);
    }
    drawScaleBar();
  }

  function drawScaleBar() {
    const { s } = state.view;
    const { h } = viewSize();
    const target = 100 / s; // metres in about 100 px
    const step = 10 ** Math.floor(Math.log10(target));
    const metres = [5, 2, 1].map((f) => f * step).find((m) => m <= target) || step;
    const px = metres * s;
    const line = $("scale-line");
    line.setAttribute("x1", 12);
    line.setAttribute("x2", 12 + px);
    line.setAttribute("y1", h - 12);
    line.setAttribute("y2", h - 12);
    const text = $("scale-text");
    text.setAttribute("x", 12);
    text.setAttribute("y", h - 18);
    text.textContent = `${metres >= 1 ? metres : metres.toPrecision(1)} m`;
  }

  function drawKeyframes() {
    const layer = $("kf-layer");
    const frag = document.createDocumentFragment();
    for (const k of state.keyframes) {
      const c = svgEl("circle", { class: "kf", id: `kf-${k.id}`, cx: k.x, cy: k.y, r: 0 }, frag);
      titled(c, `keyframe ${k.id}${k.key ? ` (${k.key})` : ""}: x ${k.x.toFixed(2)}, y ${k.y.toFixed(2)}`);
    }
    layer.replaceChildren(frag);
    state.view = null;
    applyView();
  }

  function drawLocalizations() {
    const layer = $("loc-layer");
    const frag = document.createDocumentFragment();
    // oldest first, so that the newest are drawn on top
    const items = state.localizations.slice().reverse();
    items.forEach((loc, i) => {
      const p = locPoint(loc);
      if (!p) return;
      const cls = `loc ${verdictClass(loc)}${p.estimate ? "" : " noest"}`;
      const c = svgEl("circle", { class: cls, cx: p.x, cy: p.y, r: 0 }, frag);
      c.setAttribute("fill-opacity", (0.4 + 0.6 * Math.min(1, Math.max(0, loc.confidence))).toFixed(2));
      titled(
        c,
        `${loc.time}: ${loc.verdict}, confidence ${loc.confidence.toFixed(2)}` +
          `${loc.keyframe_id === null ? "" : `, keyframe ${loc.keyframe_id}`}, map version ${loc.map_version}` +
          (p.estimate ? "" : " (no estimate: drawn at its keyframe)"),
      );
      if (i === items.length - 1) {
        svgEl("circle", { class: "newest", cx: p.x, cy: p.y, r: 0 }, frag);
      }
    });
    layer.replaceChildren(frag);
    if (state.view && state.view.empty) state.view = null;
    applyView();
  }

  function renderRecent() {
    const body = $("recent").tBodies[0];
    body.replaceChildren();
    for (const loc of state.localizations.slice(0, 10)) {
      const row = body.insertRow();
      row.className = "loc-row";
      cell(row, loc.time.replace("T", " ").replace("Z", ""));
      cell(row, loc.verdict, `verdict-${verdictClass(loc)}`);
      cell(row, loc.confidence.toFixed(2), "num");
      cell(row, loc.keyframe_id === null ? "–" : String(loc.keyframe_id), "num");
      cell(row, loc.translation ? `${loc.translation[0].toFixed(2)}, ${loc.translation[1].toFixed(2)}` : "–", "num");
      cell(row, String(loc.map_version), "num");
    }
    $("recent-empty").hidden = state.localizations.length > 0;
  }

  // -- pan and zoom ---------------------------------------------------------------------

  function installPanZoom() {
    const svg = $("view");
    svg.addEventListener(
      "wheel",
      (ev) => {
        if (!state.view) return;
        ev.preventDefault();
        const rect = svg.getBoundingClientRect();
        const mx = ev.clientX - rect.left;
        const my = ev.clientY - rect.top;
        const f = Math.exp(-ev.deltaY * 0.0015);
        const v = state.view;
        state.view = { s: v.s * f, tx: mx - (mx - v.tx) * f, ty: my - (my - v.ty) * f };
        applyView();
      },
      { passive: false },
    );
    let drag = null;
    svg.addEventListener("pointerdown", (ev) => {
      if (!state.view) return;
      drag = { x: ev.clientX, y: ev.clientY, tx: state.view.tx, ty: state.view.ty };
      svg.setPointerCapture(ev.pointerId);
      svg.classList.add("dragging");
    });
    svg.addEventListener("pointermove", (ev) => {
      if (!drag) return;
      state.view = { s: state.view.s, tx: drag.tx + ev.clientX - drag.x, ty: drag.ty + ev.clientY - drag.y };
      applyView();
    });
    const end = () => {
      drag = null;
      svg.classList.remove("dragging");
    };
    svg.addEventListener("pointerup", end);
    svg.addEventListener("pointercancel", end);
    svg.addEventListener("dblclick", () => {
      state.view = null;
      applyView();
    });
  }

  // -- start ----------------------------------------------------------------------------

  // the maps table's page and filter from the address (#after=NAME&filter=PREFIX; a value
  // longer than a map name is dropped); true if either changed
  function readAddress() {
    const params = hashParams();
    const clip = (v) => (v && v.length <= 64 ? v : "");
    const filter = clip(params.get("filter"));
    const after = clip(params.get("after")) || null;
    const changed = filter !== $("maps-filter").value || after !== state.mapsAfter;
    $("maps-filter").value = filter;
    if (changed) {
      state.mapsAfter = after;
      state.mapsBefore = after === null ? [] : null;
    }
    return changed;
  }

  function every(ms, fn, what) {
    const generation = state.generation;
    state.timers.push(
      setInterval(() => {
        fn()
          .then(() => generation === state.generation && succeeded(what))
          .catch((exc) => generation === state.generation && handle(exc, what));
      }, ms),
    );
  }

  async function start() {
    stopPolling();
    if (!storedKey()) {
      showKeyForm("Enter an API key to see the service's status.", false);
      return;
    }
    $("auth").hidden = true;
    setStatus("connecting…");
    const generation = state.generation;
    try {
      await refreshMaps();
    } catch (exc) {
      if (generation !== state.generation) return;
      handle(exc, "maps");
      if (!(exc instanceof Refused)) {
        // not ready, unreachable, an error: try again (a refused key waits for another)
        const wait = exc instanceof Loading ? EVERY_MS.loading : EVERY_MS.retry;
        setTimeout(() => generation === state.generation && start(), wait);
      }
      return;
    }
    if (generation !== state.generation) return;
    api("v1/config")
      .then((cfg) => {
        $("version").textContent = `version ${cfg.version}`;
      })
      .catch(() => {}); // a key that may not read the configuration: no version shown
    refreshMetrics().catch((exc) => handle(exc, "metrics"));
    every(EVERY_MS.localizations, refreshLocalizations, "localizations");
    every(EVERY_MS.metrics, refreshMetrics, "metrics");
    every(EVERY_MS.maps, refreshMaps, "maps");
  }

  document.addEventListener("DOMContentLoaded", () => {
    keyFromFragment();
    installPanZoom();
    readAddress();
    let typing = null;
    $("maps-filter").addEventListener("input", () => {
      clearTimeout(typing);
      typing = setTimeout(() => {
        setHashParam("filter", $("maps-filter").value);
        turnMapsPage(null, []);
      }, 300);
    });
    $("maps-next").addEventListener("click", () => {
      if (state.mapsNext === null) return;
      const before = state.mapsBefore === null ? null : [...state.mapsBefore, state.mapsAfter];
      turnMapsPage(state.mapsNext, before);
    });
    $("maps-prev").addEventListener("click", () => {
      const before = state.mapsBefore || []; // not known: back to the first page
      turnMapsPage(before.length ? before.at(-1) : null, before.slice(0, -1));
    });
    $("key-form").addEventListener("submit", (ev) => {
      ev.preventDefault();
      const key = $("key-input").value.trim();
      $("key-input").value = "";
      if (!key) return;
      sessionStorage.setItem(KEY_ITEM, key);
      start();
    });
    $("forget").addEventListener("click", () => {
      sessionStorage.removeItem(KEY_ITEM);
      showKeyForm("The key was forgotten. Enter an API key to see the service's status.", false);
    });
    window.addEventListener("hashchange", () => {
      if (hashParams().has("key")) {
        keyFromFragment();
        readAddress();
        start();
        return;
      }
      // an edited or pasted address: show what it names
      const wanted = hashParams().get("map");
      if (!readAddress() && (!wanted || wanted === state.selected)) return;
      if (wanted && wanted !== state.selected) {
        state.selected = null; // refreshMaps selects the map the address names
        state.selectedInfo = null;
      }
      refreshMaps().catch((exc) => handle(exc, "maps"));
    });
    start();
  });
})();
