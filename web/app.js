// The vsgraphs page: polls the REST API and draws the selected robot's latest detections and
// a top view of its map.
const POLL_MS = 500;
// Maps change per keyframe and carry thousands of points: fetched less often.
const MAP_POLL_MS = 2000;
let selected = null;
let mapFetched = 0;
let lastMap = null;

const $ = (id) => document.getElementById(id);
const fmt = (v, digits = 1) => (v === null || v === undefined ? "–" : v.toFixed(digits));

// A server with a read token is opened as http://HOST:PORT/#token=TOKEN.
const token = new URLSearchParams(location.hash.slice(1)).get("token");
const headers = token ? { Authorization: `Bearer ${token}` } : {};

async function getJson(path) {
  const response = await fetch(path, { headers });
  const body = await response.json();
  if (!response.ok) throw Object.assign(new Error(body.message), { code: body.error });
  return body;
}

function cell(row, text, className) {
  const td = row.insertCell();
  td.textContent = text;
  if (className) td.className = className;
}

function renderRobots(robots) {
  const tbody = $("robots").tBodies[0];
  tbody.replaceChildren();
  $("no-robots").hidden = robots.length > 0;
  if (!selected && robots.length) selected = robots[0].robot_id;
  for (const robot of robots) {
    const row = tbody.insertRow();
    row.className = robot.robot_id === selected ? "selected" : "";
    row.onclick = () => { selected = robot.robot_id; refresh(); };
    const f = robot.frames;
    cell(row, robot.robot_id);
    cell(row, robot.presence, `state-${robot.presence}`);
    cell(row, f.processed);
    cell(row, f.dropped);
    cell(row, f.rejected);
    cell(row, f.lost);
    cell(row, `${fmt(robot.timing.rate_hz)} Hz`);
    cell(row, `${fmt(robot.timing.latency_ms_mean)} ms`);
    // Distinct marker ids detected so far; hover for how many frames each was in.
    const seen = Object.entries(robot.markers_detected || {});
    cell(row, seen.length);
    row.cells[row.cells.length - 1].title = seen.map(([id, n]) => `${id}: ${n} frames`).join("\n");
    const t = robot.tracking;
    cell(row, t ? `${t.state} · ${t.keyframes} kf · ${t.markers} mk` : "–", t ? `track-${t.state}` : "");
    if (t && t.last_event) row.cells[row.cells.length - 1].title = t.last_event;
  }
  const current = robots.find((r) => r.robot_id === selected);
  const rejection = current && current.last_rejection;
  $("rejection").hidden = !rejection;
  if (rejection) {
    $("rejection").textContent =
      `Last rejected frame of ${current.robot_id}: ${rejection.reason} — ${rejection.message}`;
  }
}

function drawDetections(frame) {
  const canvas = $("view");
  if (canvas.width !== frame.image_width || canvas.height !== frame.image_height) {
    canvas.width = frame.image_width;
    canvas.height = frame.image_height;
  }
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  ctx.lineWidth = 2;
  ctx.font = "16px system-ui, sans-serif";
  for (const marker of frame.markers) {
    const c = marker.corners_px;
    ctx.strokeStyle = "#4fd18b";
    ctx.beginPath();
    ctx.moveTo(c[0][0], c[0][1]);
    for (const [x, y] of c.slice(1)) ctx.lineTo(x, y);
    ctx.closePath();
    ctx.stroke();
    ctx.fillStyle = "#f2c84b";
    ctx.fillRect(c[0][0] - 3, c[0][1] - 3, 6, 6); // the marker's top-left corner
    const cx = c.reduce((s, p) => s + p[0], 0) / 4;
    const cy = c.reduce((s, p) => s + p[1], 0) / 4;
    ctx.fillStyle = "#ffffff";
    ctx.fillText(String(marker.id), cx - 6, cy + 5);
  }
  const tbody = $("markers").tBodies[0];
  tbody.replaceChildren();
  for (const marker of frame.markers) {
    const row = tbody.insertRow();
    const t = marker.pose ? marker.pose.translation_m : [null, null, null];
    cell(row, marker.id);
    cell(row, fmt(t[0], 3));
    cell(row, fmt(t[1], 3));
    cell(row, fmt(t[2], 3));
    cell(row, marker.pose ? marker.pose.distance_source : "–");
    cell(row, marker.pose ? fmt(marker.pose.reprojection_error_px, 2) : "–");
  }
  $("selected").textContent = `${frame.robot_id} · frame ${frame.sequence} · ${frame.markers.length} markers`;
}

// Top view: map x to the right and z (forward from the first keyframe) up, fitted to the canvas.
function drawMap(view, robot) {
  const canvas = $("top");
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  if (!view) return;
  const pose = robot && robot.tracking && robot.tracking.world_from_camera;
  const xs = [], zs = [];
  const add = ([x, , z]) => { xs.push(x); zs.push(z); };
  view.keyframes.forEach((k) => add(k.world_from_camera.translation_m));
  view.markers.forEach((m) => add(m.world_from_marker.translation_m));
  if (pose) add(pose.translation_m);
  if (!xs.length) return;
  const pad = 1.0;
  const [x0, x1] = [Math.min(...xs) - pad, Math.max(...xs) + pad];
  const [z0, z1] = [Math.min(...zs) - pad, Math.max(...zs) + pad];
  const scale = Math.min(canvas.width / (x1 - x0), canvas.height / (z1 - z0));
  const u = (x) => (x - x0) * scale + (canvas.width - (x1 - x0) * scale) / 2;
  const v = (z) => canvas.height - ((z - z0) * scale + (canvas.height - (z1 - z0) * scale) / 2);
  ctx.fillStyle = "rgba(200, 205, 215, 0.6)";
  for (const [x, , z] of view.points) ctx.fillRect(u(x), v(z), 1.5, 1.5);
  ctx.strokeStyle = "#2f6fde";
  ctx.lineWidth = 1.5;
  ctx.beginPath();
  view.keyframes.forEach((k, i) => {
    const [x, , z] = k.world_from_camera.translation_m;
    if (i === 0) ctx.moveTo(u(x), v(z)); else ctx.lineTo(u(x), v(z));
  });
  ctx.stroke();
  ctx.fillStyle = "#2f6fde";
  for (const k of view.keyframes) {
    if (k.culled) continue; // still on the path above, no longer in the map
    const [x, , z] = k.world_from_camera.translation_m;
    ctx.fillRect(u(x) - 1.5, v(z) - 1.5, 3, 3);
  }
  // Walls: a metre of each, across its markers' centre, seen from above (the normal's x–z part
  // gives the wall's direction on the floor).
  ctx.strokeStyle = "#8fd19e";
  ctx.lineWidth = 3;
  const markerAt = new Map(view.markers.map((m) => [m.id, m.world_from_marker.translation_m]));
  for (const w of view.walls || []) {
    const at = w.markers.map((id) => markerAt.get(id)).filter(Boolean);
    if (!at.length) continue;
    const cx = at.reduce((s, p) => s + p[0], 0) / at.length;
    const cz = at.reduce((s, p) => s + p[2], 0) / at.length;
    const [nx, , nz] = w.normal;
    const len = Math.hypot(nx, nz) || 1;
    const [dx, dz] = [-nz / len * 0.5, nx / len * 0.5];
    ctx.beginPath();
    ctx.moveTo(u(cx - dx), v(cz - dz));
    ctx.lineTo(u(cx + dx), v(cz + dz));
    ctx.stroke();
  }
  // Doorways: the opening's width across its threshold (the doorway's x axis lies along the
  // wall), named.
  ctx.strokeStyle = "#d98cf2";
  ctx.lineWidth = 5;
  for (const d of view.doorways || []) {
    const [x, , z] = d.world_from_doorway.translation_m;
    const [qx, qy, qz, qw] = d.world_from_doorway.rotation_xyzw;
    const ax = 1 - 2 * (qy * qy + qz * qz), az = 2 * (qx * qz - qw * qy);
    const len = Math.hypot(ax, az) || 1;
    const [dx, dz] = [ax / len * d.width_m / 2, az / len * d.width_m / 2];
    ctx.beginPath();
    ctx.moveTo(u(x - dx), v(z - dz));
    ctx.lineTo(u(x + dx), v(z + dz));
    ctx.stroke();
  }
  ctx.font = "12px system-ui, sans-serif";
  ctx.fillStyle = "#d98cf2";
  for (const d of view.doorways || []) {
    const [x, , z] = d.world_from_doorway.translation_m;
    if (d.name) ctx.fillText(d.name, u(x) + 6, v(z) + 14);
  }
  // Rooms and corridors: their names at their centres.
  ctx.fillStyle = "#8fd19e";
  for (const s of view.spaces || []) {
    const [x, , z] = s.centre;
    ctx.fillText(`${s.name} (${s.kind})`, u(x) - 20, v(z));
  }
  for (const m of view.markers) {
    const [x, , z] = m.world_from_marker.translation_m;
    ctx.fillStyle = "#f29b30";
    ctx.fillRect(u(x) - 4, v(z) - 4, 8, 8);
    ctx.fillStyle = "#ffffff";
    ctx.fillText(String(m.id), u(x) + 6, v(z) - 6);
  }
  if (pose) {
    const [x, , z] = pose.translation_m;
    const [qx, qy, qz, qw] = pose.rotation_xyzw;
    // The camera's forward axis (its z) in the map, projected on x–z.
    const fx = 2 * (qx * qz + qw * qy), fz = 1 - 2 * (qx * qx + qy * qy);
    const angle = Math.atan2(-fz, fx);
    ctx.save();
    ctx.translate(u(x), v(z));
    ctx.rotate(angle);
    ctx.fillStyle = "#e5484d";
    ctx.beginPath();
    ctx.moveTo(10, 0);
    ctx.lineTo(-6, 6);
    ctx.lineTo(-6, -6);
    ctx.closePath();
    ctx.fill();
    ctx.restore();
  }
  $("map-title").textContent =
    `${selected} · map ${view.map} · ${view.keyframe_count} keyframes · ${view.point_count} points · ${view.marker_count} markers · ${(view.walls || []).length} walls · ${(view.doorways || []).length} doorways · ${(view.spaces || []).length} rooms and corridors` +
    (robot && robot.tracking && robot.tracking.space ? ` · ${selected} is in ${robot.tracking.space.name}` : "");
}

async function refreshMap(robots) {
  const robot = robots.find((r) => r.robot_id === selected);
  if (!robot || !robot.tracking) {
    $("map-title").textContent = robot ? "· not tracked" : "";
    lastMap = null;
    drawMap(null, robot);
    return;
  }
  const id = encodeURIComponent(selected);
  if (Date.now() - mapFetched > MAP_POLL_MS || !lastMap || lastMap.robot !== selected) {
    mapFetched = Date.now();
    try {
      const view = await getJson(`/api/v1/robots/${id}/maps/${robot.tracking.map}?max_points=4000`);
      lastMap = { robot: selected, view };
    } catch (error) {
      $("map-title").textContent = `· ${error.message}`;
      return;
    }
  }
  drawMap(lastMap.view, robot);
}

async function refresh() {
  try {
    const health = await getJson("/api/v1/health");
    $("health").textContent = `server ${health.version} · up ${Math.round(health.uptime_s)} s`;
    const robots = await getJson("/api/v1/robots");
    renderRobots(robots);
    await refreshMap(robots);
    if (selected) {
      try {
        drawDetections(await getJson(`/api/v1/robots/${encodeURIComponent(selected)}/detections`));
      } catch (error) {
        $("selected").textContent = `${selected} · ${error.message}`;
      }
    }
  } catch (error) {
    $("health").textContent = `server unreachable (${error.message})`;
  }
}

refresh();
setInterval(refresh, POLL_MS);
