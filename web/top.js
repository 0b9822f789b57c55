// The top view: one map seen from above, drawn on a canvas with pan, zoom and a scale bar, and
// what lies under a click.
import { xAxis, zAxis, wallSegment, spaceOutline, insidePolygon } from "./geometry.js";

export const ROBOT_COLOURS = ["#e5484d", "#3fb8e6", "#f5d90a", "#9b6ef3", "#4cc38a", "#ff8b3e", "#e93d82", "#a1e3f5"];
const SPACE_FILL = { room: "rgba(143, 209, 158, 0.16)", corridor: "rgba(120, 160, 230, 0.16)" };

export class TopView {
  constructor(canvas, onPick) {
    this.canvas = canvas;
    this.onPick = onPick;
    // Map metres to pixels: screen = (x - cx) * scale, up = z.
    this.view = { cx: 0, cz: 0, scale: 40 };
    this.userMoved = false;
    this.shapes = { spaces: [], doorways: [], robots: [], markers: [] };
    this.listen();
  }

  listen() {
    const c = this.canvas;
    let drag = null;
    c.addEventListener("pointerdown", (e) => {
      drag = { x: e.clientX, y: e.clientY, moved: false };
      c.setPointerCapture(e.pointerId);
    });
    c.addEventListener("pointermove", (e) => {
      if (!drag) return;
      const [dx, dy] = [e.clientX - drag.x, e.clientY - drag.y];
      if (Math.abs(dx) + Math.abs(dy) > 3) drag.moved = true;
      if (!drag.moved) return;
      this.view.cx -= dx / this.view.scale;
      this.view.cz += dy / this.view.scale;
      drag.x = e.clientX;
      drag.y = e.clientY;
      this.userMoved = true;
      this.redraw();
    });
    c.addEventListener("pointerup", (e) => {
      if (drag && !drag.moved) {
        const r = c.getBoundingClientRect();
        this.onPick(this.pick(e.clientX - r.left, e.clientY - r.top));
      }
      drag = null;
    });
    c.addEventListener("wheel", (e) => {
      e.preventDefault();
      const r = c.getBoundingClientRect();
      const [x, z] = this.toMap(e.clientX - r.left, e.clientY - r.top);
      const factor = Math.exp(-e.deltaY * 0.0015);
      this.view.scale = Math.min(2000, Math.max(2, this.view.scale * factor));
      // Keep the point under the cursor where it is.
      const [x2, z2] = this.toMap(e.clientX - r.left, e.clientY - r.top);
      this.view.cx += x - x2;
      this.view.cz += z - z2;
      this.userMoved = true;
      this.redraw();
    }, { passive: false });
  }

  size() {
    const r = this.canvas.getBoundingClientRect();
    return [r.width, r.height];
  }
  toScreen(x, z) {
    const [w, h] = this.size();
    return [w / 2 + (x - this.view.cx) * this.view.scale, h / 2 - (z - this.view.cz) * this.view.scale];
  }
  toMap(u, v) {
    const [w, h] = this.size();
    return [this.view.cx + (u - w / 2) / this.view.scale, this.view.cz - (v - h / 2) / this.view.scale];
  }

  // Frames the whole map (unless the user moved the view, or `force`).
  fit(map, force = false) {
    if (!map || (this.userMoved && !force)) return;
    const xs = [], zs = [];
    for (const k of map.keyframes.values()) { xs.push(k.world_from_camera.translation_m[0]); zs.push(k.world_from_camera.translation_m[2]); }
    for (const m of map.markers.values()) { xs.push(m.world_from_marker.translation_m[0]); zs.push(m.world_from_marker.translation_m[2]); }
    if (!xs.length) return;
    const [x0, x1, z0, z1] = [Math.min(...xs) - 1, Math.max(...xs) + 1, Math.min(...zs) - 1, Math.max(...zs) + 1];
    const [w, h] = this.size();
    this.view = { cx: (x0 + x1) / 2, cz: (z0 + z1) / 2, scale: Math.max(2, Math.min(w / (x1 - x0), h / (z1 - z0))) };
    if (force) this.userMoved = false;
  }

  centreOn(x, z) {
    this.view.cx = x;
    this.view.cz = z;
  }

  // Draws `map` (the page's copy of one server map) with the robots in it.
  draw(map, robots, paths, selection) {
    this.last = [map, robots, paths, selection];
    const c = this.canvas;
    const [w, h] = this.size();
    const dpr = window.devicePixelRatio || 1;
    if (c.width !== Math.round(w * dpr) || c.height !== Math.round(h * dpr)) {
      c.width = Math.round(w * dpr);
      c.height = Math.round(h * dpr);
    }
    const ctx = c.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    this.shapes = { spaces: [], doorways: [], robots: [], markers: [] };
    if (!map) return;
    const S = (x, z) => this.toScreen(x, z);
    const markerAt = new Map([...map.markers.values()].map((m) => [m.id, m.world_from_marker.translation_m]));
    const isSelected = (kind, id) => selection && selection.kind === kind && selection.id === id;

    // Rooms and corridors, filled.
    for (const s of map.spaces) {
      const outline = spaceOutline(s, map.walls, markerAt, map.doorways);
      this.shapes.spaces.push({ id: s.id, outline, centre: [s.centre[0], s.centre[2]] });
      if (!outline) continue;
      ctx.beginPath();
      outline.forEach(([x, z], i) => (i ? ctx.lineTo(...S(x, z)) : ctx.moveTo(...S(x, z))));
      ctx.closePath();
      ctx.fillStyle = isSelected("space", s.id) ? "rgba(47, 111, 222, 0.35)" : SPACE_FILL[s.kind];
      ctx.fill();
    }

    // Points, one per 2-pixel cell: thinned for the zoom.
    ctx.fillStyle = "rgba(200, 205, 215, 0.5)";
    const cells = new Set();
    for (const [x, , z] of map.points) {
      const [u, v] = S(x, z);
      if (u < 0 || v < 0 || u > w || v > h) continue;
      const key = ((u >> 1) << 16) | (v >> 1);
      if (cells.has(key)) continue;
      cells.add(key);
      ctx.fillRect(u, v, 1.5, 1.5);
    }

    // Walls.
    ctx.strokeStyle = "#8fd19e";
    ctx.lineWidth = 3;
    for (const wall of map.walls.values()) {
      const seg = wallSegment(wall, markerAt);
      if (!seg) continue;
      ctx.beginPath();
      ctx.moveTo(...S(...seg[0]));
      ctx.lineTo(...S(...seg[1]));
      ctx.stroke();
    }

    // Paths, per robot in its colour.
    ctx.lineWidth = 1.5;
    const drawnPaths = [];
    for (const [robot, positions] of paths) {
      if (positions.length < 2) continue;
      drawnPaths.push({ robot, positions: positions.length });
      ctx.strokeStyle = robots.colour(robot);
      ctx.beginPath();
      positions.forEach(([x, , z], i) => (i ? ctx.lineTo(...S(x, z)) : ctx.moveTo(...S(x, z))));
      ctx.stroke();
    }

    // Doorways: the opening across its threshold (the doorway's x axis lies along the wall).
    ctx.font = "12px system-ui, sans-serif";
    for (const d of map.doorways.values()) {
      const [x, , z] = d.world_from_doorway.translation_m;
      const a = xAxis(d.world_from_doorway.rotation_xyzw);
      const len = Math.hypot(a[0], a[2]) || 1;
      const [dx, dz] = [(a[0] / len) * d.width_m / 2, (a[2] / len) * d.width_m / 2];
      ctx.strokeStyle = isSelected("doorway", d.id) ? "#ffffff" : "#d98cf2";
      ctx.lineWidth = 6;
      ctx.beginPath();
      ctx.moveTo(...S(x - dx, z - dz));
      ctx.lineTo(...S(x + dx, z + dz));
      ctx.stroke();
      this.shapes.doorways.push({ id: d.id, at: [x, z] });
      if (d.name) {
        ctx.fillStyle = "#d98cf2";
        const [u, v] = S(x, z);
        ctx.fillText(d.name, u + 6, v + 14);
      }
    }

    // Markers with their ids.
    for (const m of map.markers.values()) {
      const [x, , z] = m.world_from_marker.translation_m;
      const [u, v] = S(x, z);
      ctx.fillStyle = "#f29b30";
      ctx.fillRect(u - 3, v - 3, 6, 6);
      if (this.view.scale > 15) {
        ctx.fillStyle = "#f7c98f";
        ctx.fillText(String(m.id), u + 5, v - 5);
      }
      this.shapes.markers.push({ id: m.id, at: [x, z] });
    }

    // Names at the spaces' centres.
    ctx.font = "bold 13px system-ui, sans-serif";
    ctx.textAlign = "center";
    for (const s of map.spaces) {
      const [u, v] = S(s.centre[0], s.centre[2]);
      ctx.fillStyle = "#e8f5eb";
      ctx.fillText(s.name, u, v);
      ctx.fillRect(u - 2, v + 4, 4, 4);
    }
    ctx.textAlign = "start";

    // Robots in this map: a triangle along the camera's forward axis.
    for (const r of robots.inMap(map.id)) {
      const pose = r.tracking.world_from_camera;
      const [x, , z] = pose.translation_m;
      const f = zAxis(pose.rotation_xyzw);
      const angle = Math.atan2(-f[2], f[0]);
      const [u, v] = S(x, z);
      ctx.save();
      ctx.translate(u, v);
      ctx.rotate(angle);
      ctx.fillStyle = robots.colour(r.robot_id);
      ctx.strokeStyle = isSelected("robot", r.robot_id) ? "#ffffff" : "#000000";
      ctx.lineWidth = 1.5;
      ctx.beginPath();
      ctx.moveTo(12, 0);
      ctx.lineTo(-7, 7);
      ctx.lineTo(-7, -7);
      ctx.closePath();
      ctx.fill();
      ctx.stroke();
      ctx.restore();
      this.shapes.robots.push({ id: r.robot_id, at: [x, z] });
    }
    this.scaleBar(ctx, w, h);
    // What was drawn where, for tests and tools that read the page (a canvas has no DOM).
    c.dataset.drawn = JSON.stringify({
      spaces: this.shapes.spaces.map((s) => ({ id: s.id, outline: Boolean(s.outline), at: S(...s.centre) })),
      doorways: this.shapes.doorways.map((d) => ({ id: d.id, at: S(...d.at) })),
      robots: this.shapes.robots.map((r) => ({ id: r.id, at: S(...r.at) })),
      markers: this.shapes.markers.length,
      paths: drawnPaths,
    });
  }

  redraw() {
    if (this.last) this.draw(...this.last);
  }

  // A bar of a round length near 100 pixels, bottom left.
  scaleBar(ctx, w, h) {
    const metres = 100 / this.view.scale;
    const step = 10 ** Math.floor(Math.log10(metres));
    const length = [1, 2, 5, 10].map((k) => k * step).filter((m) => m <= metres).pop() || step;
    const px = length * this.view.scale;
    ctx.strokeStyle = "#ffffff";
    ctx.fillStyle = "#ffffff";
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.moveTo(16, h - 16);
    ctx.lineTo(16 + px, h - 16);
    ctx.moveTo(16, h - 21);
    ctx.lineTo(16, h - 11);
    ctx.moveTo(16 + px, h - 21);
    ctx.lineTo(16 + px, h - 11);
    ctx.stroke();
    ctx.font = "12px system-ui, sans-serif";
    ctx.fillText(length >= 1 ? `${length} m` : `${Math.round(length * 100)} cm`, 20, h - 24);
  }

  // What lies under a click: a robot, a doorway or marker near it, else the space it is in.
  pick(u, v) {
    const near = (list, radius) => {
      let best = null, bestD = radius;
      for (const s of list) {
        const [su, sv] = this.toScreen(...s.at);
        const d = Math.hypot(su - u, sv - v);
        if (d < bestD) { best = s; bestD = d; }
      }
      return best;
    };
    const robot = near(this.shapes.robots, 14);
    if (robot) return { kind: "robot", id: robot.id };
    const doorway = near(this.shapes.doorways, 12);
    if (doorway) return { kind: "doorway", id: doorway.id };
    const [x, z] = this.toMap(u, v);
    const space = this.shapes.spaces.find((s) => s.outline && insidePolygon([x, z], s.outline))
      || this.shapes.spaces.find((s) => Math.hypot(...this.toScreen(...s.centre).map((p, i) => p - [u, v][i])) < 20);
    if (space) return { kind: "space", id: space.id };
    return null;
  }
}
