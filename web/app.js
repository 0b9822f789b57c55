// The vsgraphs page: follows the server's events (`/api/v1/events`, pushed, only what changed)
// and shows one map's building from above or as a layered graph, its rooms, doorways and
// robots in lists, and what is selected in detail. Every name from the server is set as text.
import { TopView, ROBOT_COLOURS } from "./top.js";
import { spaceOutline, polygonArea } from "./geometry.js";

const $ = (id) => document.getElementById(id);
const fmt = (v, digits = 1) => (v === null || v === undefined ? "–" : v.toFixed(digits));
// Samples of each robot's rate and latency kept for its sparkline (30 s at two a second).
const HISTORY = 60;
const EVENTS_KEPT = 100;

// A server with a read token is opened as http://HOST:PORT/#token=TOKEN.
const token = new URLSearchParams(location.hash.slice(1)).get("token");
const headers = token ? { Authorization: `Bearer ${token}` } : {};

// Main-thread time spent on events and drawing, and when the page reached each step (ms since
// navigation began), for benchmarks (`window.pageTiming`).
const timing = { started: performance.now(), events: 0, eventMs: 0, renders: 0, renderMs: 0, renderMsMax: 0 };
window.pageTiming = timing;

const state = {
  robots: new Map(), // robot id -> RobotStatus
  history: new Map(), // robot id -> [{ rate, latency }]
  colours: new Map(),
  maps: new Map(), // map id -> the page's copy (see newMap)
  paths: new Map(), // map id -> Map(robot id -> positions)
  mapId: null,
  mapChosen: false,
  selection: null, // { kind: "space" | "doorway" | "robot", id }
  view: "top",
};

function newMap(id) {
  return {
    id, summary: null, keyframes: new Map(), markers: new Map(), walls: new Map(),
    doorways: new Map(), spaces: [], missing: [], points: [], loops: 0,
  };
}

const robots = {
  colour(id) {
    if (!state.colours.has(id)) state.colours.set(id, ROBOT_COLOURS[state.colours.size % ROBOT_COLOURS.length]);
    return state.colours.get(id);
  },
  inMap(mapId) {
    return [...state.robots.values()].filter((r) => r.tracking && r.tracking.map_id === mapId && r.tracking.world_from_camera);
  },
};

const top = new TopView($("top"), (picked) => select(picked));
let graph = null; // the graph view, loaded with three.js when first shown

// ---- events from the server ----

const handlers = {
  robots(change) {
    for (const id of change.gone) { state.robots.delete(id); state.history.delete(id); }
    for (const r of change.robots) {
      const before = state.robots.get(r.robot_id);
      state.robots.set(r.robot_id, r);
      const h = state.history.get(r.robot_id) || [];
      h.push({ rate: r.timing.rate_hz || 0, latency: r.timing.latency_ms_mean || 0 });
      if (h.length > HISTORY) h.shift();
      state.history.set(r.robot_id, h);
      trackingEvents(before, r);
    }
    schedule({ robots: true });
  },
  map(change) {
    const id = change.summary.id;
    const map = change.full || !state.maps.has(id) ? newMap(id) : state.maps.get(id);
    state.maps.set(id, map);
    map.summary = change.summary;
    timing.firstMap = timing.firstMap || performance.now();
    for (const k of change.keyframes) map.keyframes.set(k.id, k);
    for (const m of change.markers) map.markers.set(m.id, m);
    for (const m of change.markers_gone) map.markers.delete(m);
    if (change.walls) map.walls = new Map(change.walls.map((w) => [w.id, w]));
    if (change.doorways) map.doorways = new Map(change.doorways.map((d) => [d.id, d]));
    if (change.spaces) map.spaces = change.spaces;
    if (change.missing_spaces) map.missing = change.missing_spaces;
    if (change.points) map.points = change.points;
    // Loops of a first (whole) event closed before the page opened: not news.
    if (!change.full) for (const l of change.loops) log(`map ${id}: loop closed, keyframe ${l.newer} seen again at ${l.older} (${l.inliers} points)`);
    if (!state.mapChosen && (state.mapId === null || biggest() === id)) state.mapId = id;
    schedule({ map: id, lists: Boolean(change.spaces || change.doorways), maps: true });
  },
  path(change) {
    const byRobot = state.paths.get(change.map_id) || new Map();
    state.paths.set(change.map_id, byRobot);
    const before = change.full ? [] : byRobot.get(change.robot) || [];
    byRobot.set(change.robot, before.concat(change.positions));
    schedule({ map: change.map_id });
  },
  merge(m) {
    const how = m.place_keyframes ? "a place both saw" : `${m.markers.length} shared markers`;
    log(`maps merged: map ${m.source} into map ${m.target} (${how}, ${m.point_inliers} points)`, new Date(m.at_ns / 1e6));
    if (state.mapId === m.source) state.mapId = m.target;
  },
  map_gone({ id }) {
    state.maps.delete(id);
    state.paths.delete(id);
    if (state.mapId === id) { state.mapId = biggest(); state.mapChosen = false; }
    schedule({ maps: true, lists: true, map: state.mapId });
  },
};

function biggest() {
  let best = null;
  for (const m of state.maps.values()) {
    if (!best || (m.summary && m.summary.keyframes > best.summary.keyframes)) best = m;
  }
  return best ? best.id : null;
}

function trackingEvents(before, r) {
  const seen = new Set(((before && before.tracking && before.tracking.recent_events) || []).map((e) => `${e.timestamp_ns} ${e.event}`));
  for (const e of (r.tracking && r.tracking.recent_events) || []) {
    if (before && !seen.has(`${e.timestamp_ns} ${e.event}`)) log(`${r.robot_id}: ${e.event}`);
  }
}

function log(text, at = new Date()) {
  const li = document.createElement("li");
  li.textContent = `${at.toLocaleTimeString()} ${text}`;
  const list = $("events");
  list.prepend(li);
  while (list.children.length > EVENTS_KEPT) list.lastChild.remove();
}

// Reads the event stream with fetch (so the read token goes in a header, not the address).
async function follow() {
  for (;;) {
    try {
      const response = await fetch("/api/v1/events", { headers });
      if (!response.ok) throw new Error(`${response.status} ${(await response.json()).message}`);
      $("connection").textContent = "live";
      timing.streamOpen = timing.streamOpen || performance.now();
      // A new stream starts from nothing: its first events bring everything.
      state.maps.clear();
      state.paths.clear();
      const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
      let buffer = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        buffer += value;
        let end;
        while ((end = buffer.indexOf("\n\n")) >= 0) {
          const block = buffer.slice(0, end);
          buffer = buffer.slice(end + 2);
          let name = "message", data = "";
          for (const line of block.split("\n")) {
            if (line.startsWith("event:")) name = line.slice(6).trim();
            else if (line.startsWith("data:")) data += line.slice(5).replace(/^ /, "");
          }
          if (data && handlers[name]) {
            const start = performance.now();
            handlers[name](JSON.parse(data));
            timing.events += 1;
            timing.eventMs += performance.now() - start;
          }
        }
      }
      throw new Error("the server closed the stream");
    } catch (error) {
      $("connection").textContent = `disconnected (${error.message}); retrying`;
      $("connection").className = "warning";
    }
    await new Promise((resolve) => setTimeout(resolve, 2000));
    $("connection").className = "muted";
  }
}

// ---- drawing, once per animation frame at most ----

let pending = null;
function schedule(what) {
  pending = Object.assign(pending || {}, what);
  if (pending.scheduled) return;
  pending.scheduled = true;
  // The first draw at once (a page's first animation frame can wait for its loading to settle);
  // then at most once per frame, and not at all while the page is hidden.
  if (timing.renders === 0) setTimeout(render, 0);
  else requestAnimationFrame(render);
}

function render() {
  const start = performance.now();
  draw();
  const ms = performance.now() - start;
  timing.renders += 1;
  timing.renderMs += ms;
  timing.renderMsMax = Math.max(timing.renderMsMax, ms);
}

function draw() {
  const what = pending;
  pending = null;
  if (what.maps) renderMapSelect();
  if (what.robots) renderRobots();
  const map = state.maps.get(state.mapId) || null;
  if (what.lists || what.maps || what.map === state.mapId) renderLists(map);
  follow_();
  if (state.view === "top") {
    top.fit(map);
    top.draw(map, robots, (state.paths.get(state.mapId) || new Map()), state.selection);
  } else if (graph) {
    graph.update(map, state.selection, robots.inMap(state.mapId));
  }
  renderStats(map);
  renderDetails(map);
  if (map && map.summary && map.summary.keyframes > 0 && !document.body.dataset.firstMapDraw) {
    document.body.dataset.firstMapDraw = String(performance.now());
  }
}

function follow_() {
  if (!$("follow").checked || !state.selection || state.selection.kind !== "robot") return;
  const r = state.robots.get(state.selection.id);
  if (!r || !r.tracking || r.tracking.map_id == null) return;
  if (r.tracking.map_id !== state.mapId) { state.mapId = r.tracking.map_id; renderMapSelect(); }
  const map = state.maps.get(state.mapId);
  const space = r.tracking.space && map && map.spaces.find((s) => s.id === r.tracking.space.id);
  // The room it is in, else the robot itself.
  const at = space ? [space.centre[0], space.centre[2]] : r.tracking.world_from_camera
    ? [r.tracking.world_from_camera.translation_m[0], r.tracking.world_from_camera.translation_m[2]] : null;
  if (at) { top.centreOn(...at); top.userMoved = true; }
}

function renderMapSelect() {
  const select = $("map-select");
  const ids = [...state.maps.keys()].sort((a, b) => a - b);
  const options = ids.map((id) => {
    const s = state.maps.get(id).summary;
    const o = document.createElement("option");
    o.value = String(id);
    o.textContent = `map ${id} · ${s.keyframes} keyframes · ${s.robots.join(", ")}`;
    return o;
  });
  if (!options.length) {
    const o = document.createElement("option");
    o.value = "";
    o.textContent = "none yet";
    options.push(o);
  }
  select.replaceChildren(...options);
  select.value = state.mapId === null ? "" : String(state.mapId);
}

function renderStats(map) {
  const el = $("map-stats");
  if (!map || !map.summary) { el.textContent = ""; delete el.dataset.keyframes; return; }
  const s = map.summary;
  el.dataset.keyframes = String(s.keyframes);
  el.dataset.mapId = String(s.id);
  el.textContent = `${s.keyframes} keyframes · ${s.points} points · ${s.markers} markers · ${s.walls} walls · ${s.doorways} doorways · ${s.rooms} rooms · ${s.corridors} corridors`;
}

function spark(values, colour) {
  const c = document.createElement("canvas");
  c.className = "spark";
  c.width = 48;
  c.height = 20;
  const ctx = c.getContext("2d");
  const max = Math.max(1e-9, ...values);
  ctx.strokeStyle = colour;
  ctx.beginPath();
  values.forEach((v, i) => {
    const x = (i / Math.max(1, HISTORY - 1)) * 48, y = 19 - (v / max) * 18;
    i ? ctx.lineTo(x, y) : ctx.moveTo(x, y);
  });
  ctx.stroke();
  return c;
}

function cell(row, text, className) {
  const td = row.insertCell();
  td.textContent = text;
  if (className) td.className = className;
  return td;
}

function renderRobots() {
  const tbody = $("robots").tBodies[0];
  const rows = [];
  for (const r of state.robots.values()) {
    const row = document.createElement("tr");
    row.dataset.robot = r.robot_id;
    if (state.selection && state.selection.kind === "robot" && state.selection.id === r.robot_id) row.className = "selected";
    row.onclick = () => select({ kind: "robot", id: r.robot_id });
    const name = cell(row, r.robot_id);
    name.style.color = robots.colour(r.robot_id);
    name.title = r.robot_id;
    const t = r.tracking;
    cell(row, t ? t.state : r.presence, t ? `track-${t.state}` : `state-${r.presence}`);
    cell(row, `${fmt(r.timing.rate_hz)} Hz`);
    cell(row, `${fmt(r.timing.latency_ms_mean, 0)} ms`);
    cell(row, String(r.frames.dropped + r.frames.rejected + r.frames.lost));
    const h = state.history.get(r.robot_id) || [];
    const sparks = row.insertCell();
    sparks.append(spark(h.map((s) => s.rate), "#2f6fde"), spark(h.map((s) => s.latency), "#b3541e"));
    sparks.title = "frames per second (blue) and latency (brown), the last 30 s";
    rows.push(row);
  }
  tbody.replaceChildren(...rows);
  $("no-robots").hidden = rows.length > 0;
}

function renderLists(map) {
  const spaces = map ? [...map.spaces].sort((a, b) => a.name.localeCompare(b.name)) : [];
  $("spaces").replaceChildren(...spaces.map((s) => {
    const li = document.createElement("li");
    li.dataset.spaceId = String(s.id);
    li.textContent = `${s.name} · ${s.kind}`;
    if (state.selection && state.selection.kind === "space" && state.selection.id === s.id) li.className = "selected";
    li.onclick = () => select({ kind: "space", id: s.id });
    return li;
  }));
  $("missing").textContent = map && map.missing.length
    ? `Not found yet: ${map.missing.map((m) => m.name).join(", ")}` : "";
  const doorways = map ? [...map.doorways.values()] : [];
  $("doorways").replaceChildren(...doorways.map((d) => {
    const li = document.createElement("li");
    li.dataset.doorwayId = String(d.id);
    li.textContent = `${d.name || `doorway ${d.id}`} · ${d.between.join(" – ") || "spaces not known"}`;
    if (state.selection && state.selection.kind === "doorway" && state.selection.id === d.id) li.className = "selected";
    li.onclick = () => select({ kind: "doorway", id: d.id });
    return li;
  }));
}

// ---- details ----

function select(picked) {
  state.selection = picked;
  detailsFetched = 0;
  schedule({ robots: true, lists: true, map: state.mapId });
}

function dl(pairs) {
  const list = document.createElement("dl");
  for (const [k, v] of pairs) {
    const dt = document.createElement("dt");
    dt.textContent = k;
    const dd = document.createElement("dd");
    dd.textContent = v;
    list.append(dt, dd);
  }
  return list;
}

let detailsFetched = 0;
function renderDetails(map) {
  const title = $("details-title"), body = $("details-body");
  const sel = state.selection;
  body.className = "";
  if (!sel) { title.textContent = "Details"; body.className = "muted"; body.textContent = "Click a room, a doorway or a robot."; return; }
  const spaceName = (id) => { const s = map && map.spaces.find((x) => x.id === id); return s ? s.name : `space ${id}`; };
  if (sel.kind === "space") {
    const s = map && map.spaces.find((x) => x.id === sel.id);
    if (!s) { body.textContent = "Not in this map."; return; }
    title.textContent = s.name;
    const markerAt = new Map([...map.markers.values()].map((m) => [m.id, m.world_from_marker.translation_m]));
    const outline = spaceOutline(s, map.walls, markerAt, map.doorways);
    const walls = s.walls.map((id) => { const w = map.walls.get(id); return `wall ${id}${w ? ` (markers ${w.markers.join(", ")})` : ""}`; });
    const doors = s.doorways.map((id) => { const d = map.doorways.get(id); return d && d.name ? d.name : `doorway ${id}`; });
    body.replaceChildren(dl([
      ["kind", s.kind],
      ["centre", s.centre.map((v) => v.toFixed(2)).join(", ") + " m"],
      ["area", outline ? `${polygonArea(outline).toFixed(1)} m²` : "–"],
      ["walls", walls.join("; ") || "–"],
      ["doorways", doors.join(", ") || "–"],
      ["neighbours", s.neighbours.map(spaceName).join(", ") || "–"],
      ["robots in it", [...state.robots.values()].filter((r) => r.tracking && r.tracking.space && r.tracking.space.id === s.id && r.tracking.map_id === map.id).map((r) => r.robot_id).join(", ") || "–"],
    ]));
    body.dataset.kind = "space";
  } else if (sel.kind === "doorway") {
    const d = map && map.doorways.get(sel.id);
    if (!d) { body.textContent = "Not in this map."; return; }
    title.textContent = d.name || `doorway ${d.id}`;
    body.replaceChildren(dl([
      ["between", d.between.join(" and ") || "–"],
      ["spaces in the map", d.spaces.map(spaceName).join(", ") || "–"],
      ["width", `${d.width_m.toFixed(2)} m`],
      ["markers", d.markers.join(", ")],
      ["walls", d.walls.join(", ") || "–"],
    ]));
    body.dataset.kind = "doorway";
  } else if (sel.kind === "robot") {
    const r = state.robots.get(sel.id);
    if (!r) { body.textContent = "Gone."; return; }
    title.textContent = r.robot_id;
    const t = r.tracking;
    const f = r.frames;
    const events = document.createElement("ul");
    events.className = "log";
    for (const e of (t && t.recent_events) || []) {
      const li = document.createElement("li");
      li.textContent = e.event;
      events.prepend(li);
    }
    const detections = document.createElement("canvas");
    detections.id = "detections";
    const detectionsNote = document.createElement("p");
    detectionsNote.className = "muted";
    body.replaceChildren(dl([
      ["presence", r.presence],
      ["tracking", t ? `${t.state} (${t.frames_tracked} tracked, ${t.frames_untracked} not)` : "off"],
      ["in", t && t.space ? t.space.name : "–"],
      ["map", t && t.map_id != null ? `map ${t.map_id}` : "–"],
      ["rate", `${fmt(r.timing.rate_hz)} Hz`],
      ["latency", `${fmt(r.timing.latency_ms_mean)} ms mean, ${fmt(r.timing.latency_ms_max)} ms max`],
      ["frames", `${f.processed} processed, ${f.dropped} dropped, ${f.rejected} rejected, ${f.lost} lost`],
      ["last rejection", r.last_rejection ? `${r.last_rejection.reason}: ${r.last_rejection.message}` : "–"],
    ]), events, detectionsNote, detections);
    body.dataset.kind = "robot";
    showDetections(r.robot_id, detections, detectionsNote);
  }
}

// The markers in a robot's latest frame, drawn where they were seen. Asked for while the
// robot's details are open, at most once a second: they change every frame, and no other view
// needs them.
let detectionsFor = null;
async function showDetections(robotId, canvas, note) {
  const now = performance.now();
  if (detectionsFor && detectionsFor.robot === robotId && now - detectionsFor.at < 1000) {
    paintDetections(detectionsFor.frame, canvas, note);
    return;
  }
  detectionsFor = { robot: robotId, at: now, frame: detectionsFor && detectionsFor.robot === robotId ? detectionsFor.frame : null };
  try {
    const response = await fetch(`/api/v1/robots/${encodeURIComponent(robotId)}/detections`, { headers });
    detectionsFor.frame = response.ok ? await response.json() : null;
  } catch {
    detectionsFor.frame = null;
  }
  // The details may have been redrawn meanwhile: paint the canvas that is shown now.
  const shown = $("detections");
  if (shown) paintDetections(detectionsFor.frame, shown, shown.previousSibling);
}

function paintDetections(frame, canvas, note) {
  if (!frame) { note.textContent = "No frame processed yet."; canvas.hidden = true; return; }
  canvas.width = frame.image_width;
  canvas.height = frame.image_height;
  const ctx = canvas.getContext("2d");
  ctx.lineWidth = 3;
  ctx.font = "28px system-ui, sans-serif";
  for (const m of frame.markers) {
    const c = m.corners_px;
    ctx.strokeStyle = "#4fd18b";
    ctx.beginPath();
    c.forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
    ctx.closePath();
    ctx.stroke();
    ctx.fillStyle = "#ffffff";
    ctx.fillText(String(m.id), c[0][0], c[0][1] - 6);
  }
  note.textContent = `Frame ${frame.sequence}: ${frame.markers.length} markers (${frame.markers.map((m) => m.id).join(", ") || "none"})`;
}

// ---- controls ----

function show(view) {
  state.view = view;
  $("tab-top").classList.toggle("active", view === "top");
  $("tab-graph").classList.toggle("active", view === "graph");
  $("top-view").hidden = view !== "top";
  $("graph-view").hidden = view !== "graph";
  $("legend").textContent = LEGENDS[view];
  if (view === "graph" && !graph) {
    import("./graph.js").then(({ GraphView }) => {
      graph = new GraphView($("graph-view"), (picked) => select(picked));
      schedule({ map: state.mapId });
    }).catch((error) => { $("graph-view").textContent = `The graph view did not load: ${error.message}`; });
  }
  schedule({ map: state.mapId });
}

const LEGENDS = {
  top: $("legend").textContent,
  graph: "The Situational Graph in layers: keyframes (blue) and markers (orange) at the bottom, " +
    "walls (green) and doorways (violet) above, rooms and corridors on top; edges join each " +
    "node to those it rests on. Drag to orbit, right-drag to pan, wheel to zoom, click a room " +
    "or doorway to select it.",
};

$("tab-top").onclick = () => show("top");
$("tab-graph").onclick = () => show("graph");
$("fit").onclick = () => { top.fit(state.maps.get(state.mapId), true); if (graph) graph.fit(); schedule({ map: state.mapId }); };
$("map-select").onchange = (e) => {
  state.mapId = e.target.value === "" ? null : Number(e.target.value);
  state.mapChosen = true;
  top.userMoved = false;
  schedule({ lists: true, map: state.mapId });
};
window.addEventListener("resize", () => schedule({ map: state.mapId }));

follow();
