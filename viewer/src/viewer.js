// The iarcs room viewer: one static page per export (iarcs_env/viewer.py writes it). The page holds the rooms
// as glTF binaries (base64) in a JSON script element with id "iarcs-rooms"; this script, bundled with three.js
// at build time, shows them with orbit and top views, a class legend, and the PNG renders' overlays
// (collisions, out of bound, off the floor) as toggles. No network is used at view time.
//
// For tests, <body> gets data-ready="1" after a room's first frame, data-objects (the objects in the room shown)
// and data-errors (script errors).
import * as THREE from 'three';
import { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';
import { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';

const BACKGROUND = 0xf4f4f2;
const OVERLAYS = [
  // [flag in the node extras, label, colour]: the colours of the PNG renders (iarcs_env/render.py)
  ['colliding', 'collisions', 0xe60000],
  ['out_of_bound', 'out of bound', 0xc800c8],
  ['off_floor', 'off the floor', 0x0046ff],
];

const errors = [];
window.addEventListener('error', (e) => { errors.push(String(e.message)); document.body.dataset.errors = errors.join(' | '); });
window.addEventListener('unhandledrejection', (e) => { errors.push(String(e.reason)); document.body.dataset.errors = errors.join(' | '); });

const rooms = JSON.parse(document.getElementById('iarcs-rooms').textContent);
const canvasHolder = document.getElementById('view');
const renderer = new THREE.WebGLRenderer({ antialias: true });
renderer.setPixelRatio(window.devicePixelRatio);
renderer.setClearColor(BACKGROUND);
canvasHolder.appendChild(renderer.domElement);

const scene = new THREE.Scene();
scene.add(new THREE.HemisphereLight(0xffffff, 0x888880, 2.2));
const sun = new THREE.DirectionalLight(0xffffff, 1.6);
sun.position.set(3, 8, 5);
scene.add(sun);

const perspective = new THREE.PerspectiveCamera(45, 1, 0.05, 200);
const top = new THREE.OrthographicCamera(-1, 1, 1, -1, 0.05, 200);
let camera = perspective;
const controls = new OrbitControls(perspective, renderer.domElement);
controls.addEventListener('change', () => draw());

let room = null; // { root, centre, size, objects, outlines }
const loader = new GLTFLoader();

function decode(b64) {
  const bin = atob(b64);
  const bytes = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  return bytes.buffer;
}

function colourHex(obj) {
  let hex = '#888888';
  obj.traverse((m) => { if (m.isMesh && m.material && m.material.color && hex === '#888888') hex = '#' + m.material.color.getHexString(THREE.SRGBColorSpace); });
  return hex;
}

function outline(obj, colour) {
  // A wire box around the object's bounds, in the object's own frame so it turns with it.
  const box = new THREE.Box3();
  obj.traverse((m) => {
    if (!m.isMesh || m.userData.kind === 'front') return;
    m.geometry.computeBoundingBox();
    box.union(m.geometry.boundingBox);
  });
  const size = box.getSize(new THREE.Vector3()).addScalar(0.03);
  const lines = new THREE.LineSegments(new THREE.EdgesGeometry(new THREE.BoxGeometry(size.x, size.y, size.z)),
    new THREE.LineBasicMaterial({ color: colour, depthTest: false }));
  lines.position.copy(box.getCenter(new THREE.Vector3()));
  lines.renderOrder = 10;
  obj.add(lines);
  return lines;
}

function fitCameras() {
  const { centre, size, height } = room;
  const w = canvasHolder.clientWidth, h = canvasHolder.clientHeight;
  renderer.setSize(w, h);
  perspective.aspect = w / h;
  perspective.updateProjectionMatrix();
  const half = 0.55 * Math.max(size.x, size.z) + 0.3;
  const aspect = w / h;
  top.left = -half * Math.max(aspect, 1); top.right = half * Math.max(aspect, 1);
  top.top = half / Math.min(aspect, 1); top.bottom = -half / Math.min(aspect, 1);
  top.position.set(centre.x, height + 20, centre.z);
  top.up.set(0, 0, -1);
  top.lookAt(centre.x, 0, centre.z);
  top.updateProjectionMatrix();
  return half;
}

function resetOrbit() {
  const half = fitCameras();
  const { centre } = room;
  perspective.position.set(centre.x + 1.1 * half, 2.3 * half + 1.5, centre.z + 2.3 * half);
  controls.target.set(centre.x, 0.4, centre.z);
  controls.update();
}

function draw() {
  renderer.render(scene, camera);
}

function applyToggles() {
  if (!room) return;
  const on = (id) => document.getElementById(id).checked;
  room.walls.forEach((w) => { w.visible = on('show-walls') && camera === perspective; });
  room.outlines.forEach(({ flag, lines }) => { lines.visible = on('show-' + flag); });
  draw();
}

function legend() {
  const counts = new Map();
  room.objects.forEach((o) => {
    const c = o.userData.class;
    if (!counts.has(c)) counts.set(c, { n: 0, hex: colourHex(o) });
    counts.get(c).n++;
  });
  const list = document.getElementById('legend');
  list.innerHTML = '';
  [...counts.entries()].sort().forEach(([cls, { n, hex }]) => {
    const li = document.createElement('li');
    li.innerHTML = `<span class="swatch" style="background:${hex}"></span>${cls.replace(/_/g, ' ')}${n > 1 ? ' &times;' + n : ''}`;
    list.appendChild(li);
  });
  OVERLAYS.forEach(([flag]) => {
    const n = room.objects.filter((o) => o.userData[flag]).length;
    document.getElementById('count-' + flag).textContent = `(${n})`;
  });
}

function show(index) {
  const entry = rooms[index];
  document.body.dataset.ready = '0';
  if (room) scene.remove(room.root);
  loader.parse(decode(entry.glb), '', (gltf) => {
    const root = gltf.scene;
    const objects = [], walls = [], outlines = [];
    root.traverse((node) => {
      if (node.userData.kind === 'object') objects.push(node);
      if (node.userData.kind === 'walls') {
        walls.push(node);
        node.traverse((m) => { if (m.isMesh) { m.material.side = THREE.FrontSide; m.material.transparent = true; m.material.opacity = 0.55; m.material.depthWrite = false; } });
      }
    });
    objects.forEach((o) => OVERLAYS.forEach(([flag, , colour]) => {
      if (o.userData[flag]) outlines.push({ flag, lines: outline(o, colour) });
    }));
    scene.add(root);
    const bounds = new THREE.Box3();
    root.traverse((n) => { if (n.userData.kind === 'floor') bounds.expandByObject(n); });
    if (bounds.isEmpty()) bounds.setFromObject(root);
    const meta = entry.meta || {};
    room = { root, objects, walls, outlines, centre: bounds.getCenter(new THREE.Vector3()),
      size: bounds.getSize(new THREE.Vector3()), height: meta.ceiling_height || 2.6 };
    document.getElementById('room-info').textContent =
      `${meta.room_type || ''} · ${objects.length} objects${meta.id ? ' · ' + meta.id : ''}`;
    document.getElementById('picked').textContent = 'Click an object for its class and size.';
    legend();
    resetOrbit();
    applyToggles();
    document.body.dataset.objects = String(objects.length);
    document.body.dataset.ready = '1';
  }, (err) => { errors.push('glTF: ' + err); document.body.dataset.errors = errors.join(' | '); });
}

function setView(name) {
  camera = name === 'top' ? top : perspective;
  controls.enabled = camera === perspective;
  document.getElementById('view-orbit').classList.toggle('active', camera === perspective);
  document.getElementById('view-top').classList.toggle('active', camera === top);
  applyToggles();
}

// Picking: click an object for its label, size and flags.
const ray = new THREE.Raycaster();
renderer.domElement.addEventListener('click', (e) => {
  if (!room) return;
  const r = renderer.domElement.getBoundingClientRect();
  ray.setFromCamera(new THREE.Vector2(((e.clientX - r.left) / r.width) * 2 - 1, -((e.clientY - r.top) / r.height) * 2 + 1), camera);
  const hit = ray.intersectObjects(room.objects, true).find((h) => h.object.isMesh);
  let node = hit ? hit.object : null;
  while (node && node.userData.kind !== 'object') node = node.parent;
  const out = document.getElementById('picked');
  if (!node) { out.textContent = 'Click an object for its class and size.'; return; }
  const u = node.userData;
  const size = new THREE.Box3().setFromObject(node).getSize(new THREE.Vector3());
  const flags = OVERLAYS.filter(([f]) => u[f]).map(([, label]) => label.replace(/s$/, ''));
  out.textContent = `${u.label} (${u.class}${u.jid ? ', ' + u.jid : ''}): ${size.x.toFixed(2)} x ${size.y.toFixed(2)} x ${size.z.toFixed(2)} m` +
    (u.model && u.model !== 'box' ? `, model ${u.model}` : '') + (flags.length ? ' — ' + flags.join(', ') : '');
});

const select = document.getElementById('room');
rooms.forEach((entry, i) => {
  const opt = document.createElement('option');
  opt.value = String(i);
  opt.textContent = entry.name;
  select.appendChild(opt);
});
select.addEventListener('change', () => show(Number(select.value)));
document.getElementById('view-orbit').addEventListener('click', () => setView('orbit'));
document.getElementById('view-top').addEventListener('click', () => setView('top'));
['show-walls', ...OVERLAYS.map(([f]) => 'show-' + f)].forEach((id) => document.getElementById(id).addEventListener('change', applyToggles));
window.addEventListener('resize', () => { if (room) { fitCameras(); draw(); } });
if (rooms.length) show(0);
