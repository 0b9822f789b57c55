// Geometry of the building model on the floor: the map's x–z plane (the first keyframe's
// camera frame, y down), where walls are lines and rooms are polygons.

// The columns of a unit quaternion's rotation: the pose's x and z axes in the map.
export function xAxis([qx, qy, qz, qw]) {
  return [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy + qw * qz), 2 * (qx * qz - qw * qy)];
}
export function zAxis([qx, qy, qz, qw]) {
  return [2 * (qx * qz + qw * qy), 2 * (qy * qz - qw * qx), 1 - 2 * (qx * qx + qy * qy)];
}

// A wall's line on the floor: a point on it and its direction, from `normal·x + offset = 0`
// (the normal's floor part; walls stand upright).
export function wallLine(wall) {
  const [nx, , nz] = wall.normal;
  const n2 = nx * nx + nz * nz;
  if (n2 < 1e-6) return null;
  const len = Math.sqrt(n2);
  // The floor point nearest the origin; the offset is along the whole normal, whose floor part
  // is nearly all of it for an upright wall.
  const k = -wall.offset / n2;
  return { point: [k * nx, k * nz], dir: [-nz / len, nx / len], normal: [nx / len, nz / len] };
}

function intersect(a, b) {
  const [px, pz] = a.point, [dx, dz] = a.dir, [qx, qz] = b.point, [ex, ez] = b.dir;
  const det = dx * ez - dz * ex;
  if (Math.abs(det) < 0.2) return null; // nearly parallel: no corner
  const t = ((qx - px) * ez - (qz - pz) * ex) / det;
  return [px + t * dx, pz + t * dz];
}

// Where along a line points lie (their projections), for a wall's or corridor's extent.
function span(line, points) {
  const ts = points.map(([x, z]) => (x - line.point[0]) * line.dir[0] + (z - line.point[1]) * line.dir[1]);
  return ts.length ? [Math.min(...ts), Math.max(...ts)] : null;
}

function along(line, t) {
  return [line.point[0] + t * line.dir[0], line.point[1] + t * line.dir[1]];
}

// A wall drawn from its markers' extent, half a metre on each side.
export function wallSegment(wall, markerAt) {
  const line = wallLine(wall);
  if (!line) return null;
  const at = wall.markers.map((id) => markerAt.get(id)).filter(Boolean).map((p) => [p[0], p[2]]);
  const s = span(line, at);
  if (!s) return null;
  return [along(line, s[0] - 0.5), along(line, s[1] + 0.5)];
}

// A room's floor polygon: the corners where its two facing pairs of walls meet. A corridor's:
// the strip between its two walls, as long as its markers, doorways and centre reach (a metre
// beyond). Null when the walls give no shape.
export function spaceOutline(space, walls, markerAt, doorways) {
  const lines = space.walls.map((id) => walls.get(id)).filter(Boolean).map(wallLine);
  if (lines.some((l) => !l)) return null;
  if (space.kind === "room" && lines.length === 4) {
    const [a, b, c, d] = lines;
    const corners = [intersect(a, c), intersect(a, d), intersect(b, d), intersect(b, c)];
    return corners.every(Boolean) ? corners : null;
  }
  if (lines.length === 2) {
    const [a, b] = lines;
    const points = [[space.centre[0], space.centre[2]]];
    for (const id of space.walls) {
      for (const m of walls.get(id).markers) {
        const p = markerAt.get(m);
        if (p) points.push([p[0], p[2]]);
      }
    }
    for (const id of space.doorways || []) {
      const d = doorways.get(id);
      if (d) points.push([d.world_from_doorway.translation_m[0], d.world_from_doorway.translation_m[2]]);
    }
    const s = span(a, points);
    const [t0, t1] = [s[0] - 1, s[1] + 1];
    // b's points across from a's ends.
    const foot = (p) => {
      const [x, z] = p, [bx, bz] = b.point, [dx, dz] = b.dir;
      const t = (x - bx) * dx + (z - bz) * dz;
      return [bx + t * dx, bz + t * dz];
    };
    const [p0, p1] = [along(a, t0), along(a, t1)];
    return [p0, p1, foot(p1), foot(p0)];
  }
  return null;
}

export function polygonArea(points) {
  let twice = 0;
  for (let i = 0; i < points.length; i++) {
    const [x0, z0] = points[i], [x1, z1] = points[(i + 1) % points.length];
    twice += x0 * z1 - x1 * z0;
  }
  return Math.abs(twice) / 2;
}

export function insidePolygon([x, z], points) {
  let inside = false;
  for (let i = 0, j = points.length - 1; i < points.length; j = i++) {
    const [xi, zi] = points[i], [xj, zj] = points[j];
    if ((zi > z) !== (zj > z) && x < ((xj - xi) * (z - zi)) / (zj - zi) + xi) inside = !inside;
  }
  return inside;
}
