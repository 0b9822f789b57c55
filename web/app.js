// The vsgraphs page: polls the REST API and draws the selected robot's latest detections.
const POLL_MS = 500;
let selected = null;

const $ = (id) => document.getElementById(id);
const fmt = (v, digits = 1) => (v === null || v === undefined ? "–" : v.toFixed(digits));

async function getJson(path) {
  const response = await fetch(path);
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

async function refresh() {
  try {
    const health = await getJson("/api/v1/health");
    $("health").textContent = `server ${health.version} · up ${Math.round(health.uptime_s)} s`;
    renderRobots(await getJson("/api/v1/robots"));
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
