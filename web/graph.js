// The graph view: a map's Situational Graph in 3-D, its layers stacked as the paper draws
// them — keyframes and markers at the bottom, walls and doorways above, rooms and corridors on
// top — with the edges between layers; orbit, pan and zoom with the mouse, click to select.
import * as THREE from "three";
import { OrbitControls } from "/vendor/three/OrbitControls.js";

const COLOURS = { robot: 0xe5484d, keyframe: 0x2f6fde, marker: 0xf29b30, wall: 0x8fd19e, doorway: 0xd98cf2, room: 0xe8f5eb, corridor: 0x9fb8ee };
// Farther apart than this, keyframes with consecutive ids are not one robot's steps.
const KEYFRAME_STEP_M = 1.5;
// Rebuilding the scene costs a few milliseconds for a building-sized map: at most this often.
const REBUILD_MS = 1000;

export class GraphView {
  constructor(container, onPick) {
    this.container = container;
    this.onPick = onPick;
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    this.renderer.setClearColor(0x20242c);
    container.append(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(50, 1, 0.05, 2000);
    this.camera.position.set(0, 20, 20);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.addEventListener("change", () => this.render());
    this.group = new THREE.Group();
    this.scene.add(this.group);
    this.pickable = [];
    this.sphere = new THREE.SphereGeometry(1, 16, 12);
    this.materials = new Map();
    this.labels = new Map();
    this.builtAt = 0;
    this.fitted = false;
    this.listen();
  }

  listen() {
    const el = this.renderer.domElement;
    let down = null;
    el.addEventListener("pointerdown", (e) => { down = [e.clientX, e.clientY]; });
    el.addEventListener("pointerup", (e) => {
      if (!down || Math.hypot(e.clientX - down[0], e.clientY - down[1]) > 4) return;
      const r = el.getBoundingClientRect();
      const ndc = new THREE.Vector2(((e.clientX - r.left) / r.width) * 2 - 1, -((e.clientY - r.top) / r.height) * 2 + 1);
      const ray = new THREE.Raycaster();
      ray.setFromCamera(ndc, this.camera);
      const hit = ray.intersectObjects(this.pickable)[0];
      this.onPick(hit ? hit.object.userData.pick : null);
    });
  }

  // The map's x–z floor with map z drawn away from the viewer (as in the top view) and the
  // layers stacked up.
  at(p, layer) {
    return new THREE.Vector3(p[0], layer * this.layerGap, -p[2]);
  }

  update(map, selection, robotsHere = []) {
    const now = performance.now();
    const sameMap = this.mapId === (map && map.id);
    if (sameMap && now - this.builtAt < REBUILD_MS && this.selection === selection) {
      clearTimeout(this.later);
      this.later = setTimeout(() => this.update(map, selection, robotsHere), REBUILD_MS);
      return;
    }
    if (!sameMap) this.fitted = false;
    this.mapId = map && map.id;
    this.selection = selection;
    this.builtAt = now;
    this.build(map, selection, robotsHere);
    this.render();
  }

  build(map, selection, robotsHere) {
    // Spheres share one geometry and a material per colour, labels a material per text: a
    // rebuild makes only the point and line buffers anew.
    for (const child of [...this.group.children]) {
      this.group.remove(child);
      if (child.userData.shared) continue;
      if (child.geometry) child.geometry.dispose();
      if (child.material) child.material.dispose();
    }
    this.pickable = [];
    if (!map) return;
    const keyframes = [...map.keyframes.values()].filter((k) => !k.culled).sort((a, b) => a.id - b.id);
    const xs = keyframes.map((k) => k.world_from_camera.translation_m[0]);
    const zs = keyframes.map((k) => k.world_from_camera.translation_m[2]);
    const extent = xs.length ? Math.max(Math.max(...xs) - Math.min(...xs), Math.max(...zs) - Math.min(...zs)) : 5;
    // Layers apart by a quarter of the map's size, so edges between them can be told apart.
    this.layerGap = Math.max(2, extent / 4);
    this.centre = xs.length ? [(Math.max(...xs) + Math.min(...xs)) / 2, (Math.max(...zs) + Math.min(...zs)) / 2] : [0, 0];

    const nodes = new Map();
    const kfPositions = [];
    for (const k of keyframes) {
      const v = this.at(k.world_from_camera.translation_m, 0);
      nodes.set(`keyframe/${k.id}`, v);
      kfPositions.push(v.x, v.y, v.z);
    }
    const kfGeometry = new THREE.BufferGeometry();
    kfGeometry.setAttribute("position", new THREE.Float32BufferAttribute(kfPositions, 3));
    this.group.add(new THREE.Points(kfGeometry, new THREE.PointsMaterial({ color: COLOURS.keyframe, size: 4, sizeAttenuation: false })));

    const ball = (kind, id, p, radius, pick, label, selected) => {
      const colour = selected ? 0xffffff : COLOURS[kind];
      if (!this.materials.has(colour)) this.materials.set(colour, new THREE.MeshBasicMaterial({ color: colour }));
      const mesh = new THREE.Mesh(this.sphere, this.materials.get(colour));
      mesh.scale.setScalar(selected ? radius * 1.8 : radius);
      mesh.userData.shared = true;
      mesh.position.copy(p);
      mesh.userData.pick = pick;
      this.group.add(mesh);
      if (pick) this.pickable.push(mesh);
      if (label) this.group.add(this.label(label, p, radius));
      nodes.set(`${kind}/${id}`, p);
    };
    const r0 = Math.max(0.06, this.layerGap / 40);
    for (const m of map.markers.values()) ball("marker", m.id, this.at(m.world_from_marker.translation_m, 0), r0, null, null, false);
    const markerAt = new Map([...map.markers.values()].map((m) => [m.id, m.world_from_marker.translation_m]));
    for (const w of map.walls.values()) {
      const at = w.markers.map((id) => markerAt.get(id)).filter(Boolean);
      if (!at.length) continue;
      const mid = [0, 1, 2].map((i) => at.reduce((s, p) => s + p[i], 0) / at.length);
      ball("wall", w.id, this.at(mid, 1), r0 * 1.5, null, null, false);
    }
    const isSel = (kind, id) => selection && selection.kind === kind && selection.id === id;
    for (const d of map.doorways.values()) {
      ball("doorway", d.id, this.at(d.world_from_doorway.translation_m, 1), r0 * 2, { kind: "doorway", id: d.id }, d.name, isSel("doorway", d.id));
    }
    for (const s of map.spaces) {
      ball(s.kind, s.id, this.at(s.centre, 2), r0 * 3, { kind: "space", id: s.id }, s.name, isSel("space", s.id));
    }
    // Robots where they are now, on the keyframes' layer.
    for (const r of robotsHere) {
      ball("robot", r.robot_id, this.at(r.tracking.world_from_camera.translation_m, 0), r0 * 2.5, { kind: "robot", id: r.robot_id }, r.robot_id, isSel("robot", r.robot_id));
    }

    // Edges: keyframe to keyframe, keyframe to the markers it saw, marker to wall and
    // doorway, wall and doorway to space.
    const lines = { keyframe: [], marker: [], structure: [] };
    const edge = (list, a, b) => {
      const p = nodes.get(a), q = nodes.get(b);
      if (p && q) list.push(p.x, p.y, p.z, q.x, q.y, q.z);
    };
    // Keyframes in the order they were made; in a merged map two robots' keyframes interleave,
    // so only neighbours as close as a robot's keyframes follow each other are joined.
    for (let i = 1; i < keyframes.length; i++) {
      const a = nodes.get(`keyframe/${keyframes[i - 1].id}`), b = nodes.get(`keyframe/${keyframes[i].id}`);
      if (a.distanceTo(b) < KEYFRAME_STEP_M) edge(lines.keyframe, `keyframe/${keyframes[i - 1].id}`, `keyframe/${keyframes[i].id}`);
    }
    for (const m of map.markers.values()) for (const k of m.keyframes || []) edge(lines.marker, `keyframe/${k}`, `marker/${m.id}`);
    for (const w of map.walls.values()) for (const m of w.markers) edge(lines.structure, `marker/${m}`, `wall/${w.id}`);
    for (const d of map.doorways.values()) {
      for (const m of d.markers) edge(lines.structure, `marker/${m}`, `doorway/${d.id}`);
      for (const s of d.spaces) {
        const space = map.spaces.find((x) => x.id === s);
        if (space) edge(lines.structure, `doorway/${d.id}`, `${space.kind}/${s}`);
      }
    }
    for (const s of map.spaces) for (const w of s.walls) edge(lines.structure, `wall/${w}`, `${s.kind}/${s.id}`);
    const segments = (positions, colour, opacity) => {
      const g = new THREE.BufferGeometry();
      g.setAttribute("position", new THREE.Float32BufferAttribute(positions, 3));
      this.group.add(new THREE.LineSegments(g, new THREE.LineBasicMaterial({ color: colour, transparent: true, opacity })));
    };
    segments(lines.keyframe, COLOURS.keyframe, 0.8);
    segments(lines.marker, COLOURS.marker, 0.15);
    segments(lines.structure, 0xc8ccd6, 0.7);
    if (!this.fitted) this.fit();
  }

  // A name that always faces the camera.
  label(text, p, radius) {
    if (!this.labels.has(text)) this.labels.set(text, this.labelMaterial(text));
    const { material, aspect } = this.labels.get(text);
    const sprite = new THREE.Sprite(material);
    sprite.userData.shared = true;
    const h = this.layerGap / 8;
    sprite.scale.set(h * aspect, h, 1);
    sprite.position.set(p.x, p.y + radius + h, p.z);
    return sprite;
  }

  labelMaterial(text) {
    const canvas = document.createElement("canvas");
    const ctx = canvas.getContext("2d");
    ctx.font = "bold 28px system-ui, sans-serif";
    canvas.width = Math.ceil(ctx.measureText(text).width) + 8;
    canvas.height = 36;
    ctx.font = "bold 28px system-ui, sans-serif";
    ctx.fillStyle = "#ffffff";
    ctx.fillText(text, 4, 28);
    const material = new THREE.SpriteMaterial({ map: new THREE.CanvasTexture(canvas), depthTest: false });
    return { material, aspect: canvas.width / canvas.height };
  }

  fit() {
    if (!this.layerGap) return;
    const [cx, cz] = this.centre;
    const target = new THREE.Vector3(cx, this.layerGap, -cz);
    this.controls.target.copy(target);
    // From the side and a little above, so the three layers read as layers.
    const d = this.layerGap * 6;
    this.camera.position.set(cx + d * 0.35, this.layerGap + d * 0.45, -cz + d);
    this.controls.update();
    this.fitted = true;
  }

  render() {
    const r = this.container.getBoundingClientRect();
    if (!r.width || !r.height) return;
    const size = this.renderer.getSize(new THREE.Vector2());
    if (size.x !== r.width || size.y !== r.height) {
      this.renderer.setSize(r.width, r.height, false);
      this.camera.aspect = r.width / r.height;
      this.camera.updateProjectionMatrix();
    }
    this.renderer.render(this.scene, this.camera);
  }
}
