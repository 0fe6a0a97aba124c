// posediff's viewer: frusta with thumbnails, sparse points, the aligned ground truth, an orbit
// camera. World = the cameras' frame (OpenCV: x_cam = R x_world + t, pixel centres at integers).
const data = JSON.parse(document.getElementById('posediff-data').textContent);
const source = document.getElementById('three-source').textContent;
const THREE = await import(URL.createObjectURL(new Blob([source], { type: 'text/javascript' })));

const V = (a) => new THREE.Vector3(a[0], a[1], a[2]);
// Camera centre −Rᵀt and the world direction of pixel (u, v): Rᵀ K⁻¹ [u, v, 1].
function centre(c) {
  const r = c.r, t = c.t;
  return new THREE.Vector3(
    -(r[0][0] * t[0] + r[1][0] * t[1] + r[2][0] * t[2]),
    -(r[0][1] * t[0] + r[1][1] * t[1] + r[2][1] * t[2]),
    -(r[0][2] * t[0] + r[1][2] * t[1] + r[2][2] * t[2]));
}
function ray(c, u, v) {
  const x = (u - c.cx) / c.fx, y = (v - c.cy) / c.fy, r = c.r;
  return new THREE.Vector3(
    r[0][0] * x + r[1][0] * y + r[2][0],
    r[0][1] * x + r[1][1] * y + r[2][1],
    r[0][2] * x + r[1][2] * y + r[2][2]);
}

const scene = new THREE.Scene();
scene.background = new THREE.Color(0x1e1f24);
const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio || 1);
renderer.setSize(window.innerWidth, window.innerHeight);
document.body.appendChild(renderer.domElement);

// Scene extent from the camera centres (and the points when there are fewer than 2 cameras).
const centres = data.cameras.map(centre);
const mid = new THREE.Vector3();
centres.forEach((c) => mid.add(c));
if (centres.length) mid.multiplyScalar(1 / centres.length);
let radius = 0;
centres.forEach((c) => { radius = Math.max(radius, c.distanceTo(mid)); });
const pts = data.points;
if (radius === 0 && pts.length) {
  for (let i = 0; i < pts.length; i += 3) radius = Math.max(radius, mid.distanceTo(V([pts[i], pts[i + 1], pts[i + 2]])));
}
if (!(radius > 0)) radius = 1;
// Look at the points' median when there are points (object-centric sets), else the centres' mean.
const target = mid.clone();
if (pts.length >= 30) {
  const med = [0, 1, 2].map((k) => {
    const v = []; for (let i = k; i < pts.length; i += 3) v.push(pts[i]);
    v.sort((a, b) => a - b); return v[v.length >> 1];
  });
  const m = V(med);
  if (m.distanceTo(mid) < 3 * radius) target.copy(m);
}
// Up: the mean of the cameras' −y axes (OpenCV y points down in the image).
const up = new THREE.Vector3();
data.cameras.forEach((c) => up.add(new THREE.Vector3(-c.r[1][0], -c.r[1][1], -c.r[1][2])));
if (up.lengthSq() < 1e-12) up.set(0, -1, 0);
up.normalize();

const depth = 0.15 * radius;
function frustum(c, colour, withImage) {
  const o = centre(c);
  const corners = [[-0.5, -0.5], [c.w - 0.5, -0.5], [c.w - 0.5, c.h - 0.5], [-0.5, c.h - 0.5]]
    .map(([u, v]) => o.clone().add(ray(c, u, v).multiplyScalar(depth)));
  const top = o.clone().add(ray(c, (c.w - 1) / 2, -0.5 - 0.25 * c.h).multiplyScalar(depth));
  const seg = [];
  for (let i = 0; i < 4; i++) seg.push(o, corners[i], corners[i], corners[(i + 1) % 4]);
  seg.push(corners[0], top, top, corners[1]);
  const g = new THREE.BufferGeometry().setFromPoints(seg);
  scene.add(new THREE.LineSegments(g, new THREE.LineBasicMaterial({ color: colour })));
  if (withImage && c.thumbnail) {
    const quad = new THREE.BufferGeometry();
    quad.setAttribute('position', new THREE.Float32BufferAttribute(
      [corners[0], corners[1], corners[2], corners[3]].flatMap((p) => [p.x, p.y, p.z]), 3));
    quad.setAttribute('uv', new THREE.Float32BufferAttribute([0, 1, 1, 1, 1, 0, 0, 0], 2));
    quad.setIndex([0, 1, 2, 0, 2, 3]);
    const tex = new THREE.TextureLoader().load(c.thumbnail, () => requestRender());
    tex.colorSpace = THREE.SRGBColorSpace;
    const mat = new THREE.MeshBasicMaterial({ map: tex, side: THREE.DoubleSide, transparent: true, opacity: 0.9 });
    scene.add(new THREE.Mesh(quad, mat));
  }
}
data.cameras.forEach((c) => frustum(c, 0xff9f43, true));
data.ground_truth.forEach((c) => frustum(c, 0x2ecc71, false));

if (pts.length) {
  const g = new THREE.BufferGeometry();
  g.setAttribute('position', new THREE.Float32BufferAttribute(pts, 3));
  g.setAttribute('color', new THREE.Uint8BufferAttribute(data.colours, 3, true));
  const m = new THREE.PointsMaterial({ size: 2.5, sizeAttenuation: false, vertexColors: true });
  scene.add(new THREE.Points(g, m));
}

// Orbit camera around `target`: azimuth θ and elevation φ in the basis (e1, e2, up).
const view = new THREE.PerspectiveCamera(50, window.innerWidth / window.innerHeight, radius * 1e-3, radius * 1e3);
const e1 = new THREE.Vector3(1, 0, 0);
if (Math.abs(e1.dot(up)) > 0.9) e1.set(0, 0, 1);
e1.sub(up.clone().multiplyScalar(e1.dot(up))).normalize();
const e2 = new THREE.Vector3().crossVectors(up, e1);
const home = { target: target.clone(), distance: 2.6 * radius, theta: 0, phi: 0.6 };
// Start behind the mean camera, looking where the cameras look.
const look = new THREE.Vector3();
data.cameras.forEach((c) => look.add(ray(c, c.cx, c.cy).normalize()));
if (look.lengthSq() > 1e-12) home.theta = Math.atan2(-look.dot(e2), -look.dot(e1));
let state = { ...home, target: home.target.clone() };
function place() {
  const d = e1.clone().multiplyScalar(Math.cos(state.phi) * Math.cos(state.theta))
    .add(e2.clone().multiplyScalar(Math.cos(state.phi) * Math.sin(state.theta)))
    .add(up.clone().multiplyScalar(Math.sin(state.phi)));
  view.position.copy(state.target).add(d.multiplyScalar(state.distance));
  view.up.copy(up);
  view.lookAt(state.target);
}
let pending = false;
function requestRender() {
  if (pending) return;
  pending = true;
  requestAnimationFrame(() => {
    pending = false;
    place();
    renderer.render(scene, view);
    document.body.dataset.status = 'rendered';
  });
}
const canvas = renderer.domElement;
let drag = null;
canvas.addEventListener('contextmenu', (e) => e.preventDefault());
canvas.addEventListener('pointerdown', (e) => {
  drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey };
  canvas.setPointerCapture(e.pointerId);
});
canvas.addEventListener('pointerup', () => { drag = null; });
canvas.addEventListener('pointermove', (e) => {
  if (!drag) return;
  const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
  drag.x = e.clientX; drag.y = e.clientY;
  if (drag.pan) {
    const s = state.distance / window.innerHeight;
    const right = new THREE.Vector3().setFromMatrixColumn(view.matrixWorld, 0);
    const camUp = new THREE.Vector3().setFromMatrixColumn(view.matrixWorld, 1);
    state.target.add(right.multiplyScalar(-dx * s)).add(camUp.multiplyScalar(dy * s));
  } else {
    state.theta -= dx * 0.008;
    state.phi = Math.max(-1.55, Math.min(1.55, state.phi + dy * 0.008));
  }
  requestRender();
});
canvas.addEventListener('wheel', (e) => {
  e.preventDefault();
  state.distance *= Math.exp(Math.sign(e.deltaY) * 0.1);
  requestRender();
}, { passive: false });
canvas.addEventListener('dblclick', () => { state = { ...home, target: home.target.clone() }; requestRender(); });
window.addEventListener('resize', () => {
  view.aspect = window.innerWidth / window.innerHeight;
  view.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight);
  requestRender();
});

// The panel: counts, legend, per-camera errors against the ground truth.
const shown = pts.length / 3;
document.getElementById('summary').textContent =
  `${data.cameras.length} cameras, ${data.total_points} points` +
  (shown < data.total_points ? ` (${shown} shown)` : '');
document.getElementById('legend').innerHTML =
  '<span style="color:#ff9f43">■</span> estimate' +
  (data.ground_truth.length ? ' · <span style="color:#2ecc71">■</span> ground truth (aligned by a similarity of the centres)' : '');
if (data.ground_truth.length) {
  const rows = ['<tr><th>image</th><th>rotation °</th><th>centre</th></tr>'];
  for (const c of data.cameras) {
    if (c.rotation_error_deg === undefined) continue;
    const name = c.name.replace(/[&<>"]/g, (x) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;' }[x]));
    rows.push(`<tr><td>${name}</td><td>${c.rotation_error_deg.toFixed(2)}</td><td>${c.centre_error.toFixed(3)}</td></tr>`);
  }
  document.getElementById('table').innerHTML = rows.join('');
}
requestRender();
