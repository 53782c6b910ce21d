// livecap review page: the rig from /rig.glb (morph targets driven by the weights), markers vs fitted
// sites, head pose, a timeline of weight curves and marker residuals; spacetime edits, drags, keys.
import * as THREE from 'three';
import { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';
import { drawTimeline, frameAt } from './timeline.js';

const MM = 0.001;
const $ = (id) => document.getElementById(id);
const state = { frame: 0, meta: null, curves: null, keys: null, selected: [], pins: [], playing: false,
  lastDrag: null, ready: false };
window.review = state; // read by the browser test and handy in the console

// the session's secret (docs/review.md) and this tab's id: each tab undoes only its own edits
const TOKEN = document.querySelector('meta[name="livecap-token"]').content;
const CLIENT = sessionStorage.getItem('livecap-client') || Math.random().toString(36).slice(2, 14);
sessionStorage.setItem('livecap-client', CLIENT);
const HEADERS = { 'X-Livecap-Token': TOKEN, 'X-Livecap-Client': CLIENT };

async function api(path, body) {
  const r = await fetch(path, body === undefined ? { headers: HEADERS } : {
    method: 'POST', headers: { ...HEADERS, 'Content-Type': 'application/json' }, body: JSON.stringify(body) });
  const j = await r.json();
  if (!r.ok) throw new Error(j.error || r.statusText);
  return j;
}

function status(text) { $('status').textContent = text; }

// ---------------------------------------------------------------- 3D view
const canvas = $('face');
const renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true });
renderer.setPixelRatio(1);
renderer.setSize(640, 480, false);
renderer.setClearColor(new THREE.Color().setRGB(0.11, 0.12, 0.14, THREE.SRGBColorSpace), 1);
const scene = new THREE.Scene();
scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 1.6));
const sun = new THREE.DirectionalLight(0xffffff, 1.6);
scene.add(sun);
const camera = new THREE.PerspectiveCamera(28, 640 / 480, 0.01, 100);
const head = new THREE.Group(); // rotated by the head pose
scene.add(head);
let face = null, truthFace = null, sitesPts = null, obsPts = null, pinPts = null;

function points(n, color, size) {
  const g = new THREE.BufferGeometry();
  g.setAttribute('position', new THREE.BufferAttribute(new Float32Array(3 * Math.max(n, 1)), 3));
  const p = new THREE.Points(g, new THREE.PointsMaterial({ color, size, sizeAttenuation: false, depthTest: false }));
  p.renderOrder = 2;
  return p;
}

function setPoints(p, pts, valid) {
  const a = p.geometry.attributes.position;
  let k = 0;
  pts.forEach((q, i) => { if (!valid || valid[i]) { a.setXYZ(k++, q[0] * MM, q[1] * MM, q[2] * MM); } });
  p.geometry.setDrawRange(0, k);
  a.needsUpdate = true;
}

function setWeights(mesh, w) { // by name: the glTF's targets are in the rig's order, w in the solve's
  if (!mesh) return;
  const inf = mesh.morphTargetInfluences, dict = mesh.morphTargetDictionary;
  state.names.forEach((n, j) => { if (n in dict) inf[dict[n]] = w[j]; });
}

function render() { renderer.render(scene, camera); }

async function loadRig() {
  const gltf = await new GLTFLoader().loadAsync('/rig.glb');
  gltf.scene.traverse((o) => { if (o.isMesh) face = o; });
  face.geometry.computeVertexNormals();
  face.material = new THREE.MeshStandardMaterial({ color: 0xd9a68c, roughness: 0.7, metalness: 0.0,
    side: THREE.DoubleSide });
  head.add(face);
  truthFace = face.clone();
  truthFace.material = face.material.clone();
  truthFace.material.color.set(0x8cb4d9);
  truthFace.morphTargetInfluences = face.morphTargetInfluences.slice();
  truthFace.visible = false;
  scene.add(truthFace);
  const n = state.meta.labels.length;
  sitesPts = points(n, 0x40d0ff, 5); obsPts = points(n, 0xffd040, 5); pinPts = points(16, 0xff3050, 9);
  head.add(sitesPts); head.add(obsPts); head.add(pinPts);
  const c = state.meta.camera;
  camera.fov = c.fov_y; camera.near = c.near * MM; camera.far = c.far * MM;
  const box = new THREE.Box3().setFromObject(face);
  state.centre = box.getCenter(new THREE.Vector3());
  truthFace.position.x = -(box.max.x - box.min.x) * 1.1;
  aim(false);
}

function aim(both) { // the preview's camera; with the truth face beside, back off to frame both
  const c = state.meta.camera;
  const eye = new THREE.Vector3(...c.eye).multiplyScalar(MM), target = new THREE.Vector3(...c.target).multiplyScalar(MM);
  if (both) {
    const shift = new THREE.Vector3(truthFace.position.x / 2, 0, 0);
    eye.sub(target).multiplyScalar(1.6).add(target).add(shift);
    target.add(shift);
    camera.far = c.far * MM * 2;
  }
  camera.position.copy(eye);
  camera.up.set(0, 1, 0);
  camera.lookAt(target);
  camera.updateProjectionMatrix();
  sun.position.copy(camera.position);
}

async function showFrame(i) {
  const n = state.meta.n_frames;
  i = Math.max(0, Math.min(n - 1, Math.round(i)));
  state.frame = i;
  $('frame').value = i;
  $('time').textContent = (i / state.meta.rate).toFixed(3) + ' s';
  const f = await api(`/api/frame/${i}`);
  if (state.frame !== i) return;
  state.current = f;
  setWeights(face, f.weights);
  const showPose = $('show-pose').checked;
  const [x, y, z, w] = f.rotation;
  head.quaternion.set(0, 0, 0, 1);
  head.position.set(0, 0, 0);
  if (showPose) { // rotate about the face's centre so the face stays in view
    const q = new THREE.Quaternion(x, y, z, w);
    head.quaternion.copy(q);
    head.position.copy(state.centre.clone().sub(state.centre.clone().applyQuaternion(q)));
  }
  const showMarkers = $('show-markers').checked;
  sitesPts.visible = obsPts.visible = showMarkers;
  setPoints(sitesPts, f.sites);
  setPoints(obsPts, f.observed, f.valid);
  truthFace.visible = $('show-truth').checked && f.truth !== null;
  aim(truthFace.visible);
  if (f.truth) setWeights(truthFace, f.truth);
  label('label-solve', state.centre, true);
  label('label-truth', state.centre.clone().add(truthFace.position), truthFace.visible);
  setPoints(pinPts, state.pins.map((p) => p.goal));
  render();
  timeline();
}

function label(id, centre, visible) { // a name above each face, placed where the face is drawn
  const el = $(id);
  el.style.display = visible ? '' : 'none';
  if (!visible) return;
  camera.updateMatrixWorld();
  const p = centre.clone().project(camera);
  el.style.left = `${Math.round((p.x + 1) / 2 * 640 - el.offsetWidth / 2)}px`;
}

// ---------------------------------------------------------------- timeline
function timeline() {
  if (!state.curves) return;
  state.axis = drawTimeline($('timeline'), { ...state, names: state.meta.names });
}

$('timeline').addEventListener('mousedown', (e) => {
  const scrub = (ev) => showFrame(frameAt($('timeline'), ev, state.meta.n_frames));
  scrub(e);
  const move = (ev) => scrub(ev);
  const up = () => { window.removeEventListener('mousemove', move); window.removeEventListener('mouseup', up); };
  window.addEventListener('mousemove', move);
  window.addEventListener('mouseup', up);
});
$('frame').addEventListener('change', () => showFrame(+$('frame').value));
$('shapes').addEventListener('change', () => {
  state.selected = [...$('shapes').selectedOptions].map((o) => +o.value);
  timeline();
});
for (const id of ['show-pose', 'show-markers', 'show-truth']) $(id).addEventListener('change', () => showFrame(state.frame));

$('play').addEventListener('click', () => {
  state.playing = !state.playing;
  $('play').textContent = state.playing ? 'pause' : 'play';
  let last = performance.now(), acc = state.frame;
  const tick = async (now) => {
    if (!state.playing) return;
    acc += (now - last) / 1000 * state.meta.rate; last = now;
    if (acc >= state.meta.n_frames) acc = 0;
    await showFrame(acc);
    requestAnimationFrame(tick);
  };
  requestAnimationFrame(tick);
});

// ---------------------------------------------------------------- spacetime edits
function applyChange(c) {
  if (!c) return;
  for (let j = 0; j < state.meta.names.length; j++) {
    for (let t = c.a; t <= c.b; t++) state.curves.weights[j][t] = c.weights[t - c.a][j];
  }
  state.undo = c.undo; state.redo = c.redo;
}

async function refreshCurves() {
  state.curves = await api('/api/curves');
  state.undo = state.curves.undo; state.redo = state.curves.redo;
}

$('edit-value').addEventListener('input', () => { $('edit-value-text').textContent = (+$('edit-value').value).toFixed(2); });
$('edit-shape').addEventListener('change', () => {
  const j = +$('edit-shape').value;
  $('edit-value').value = state.curves.weights[j][state.frame];
  $('edit-value-text').textContent = (+$('edit-value').value).toFixed(2);
  if (!state.selected.includes(j)) { state.selected.push(j); timeline(); }
});
$('edit-apply').addEventListener('click', async () => {
  const j = +$('edit-shape').value, k = state.frame;
  const a = $('edit-a').value === '' ? k - 12 : +$('edit-a').value;
  const b = $('edit-b').value === '' ? k + 12 : +$('edit-b').value;
  try {
    const c = await api('/api/edit', { frame: k, weights: { [state.meta.names[j]]: +$('edit-value').value }, range: [a, b] });
    applyChange(c);
    await refreshCurves();
    status(`edit: frames ${c.a}..${c.b} re-solved in ${c.server_ms.toFixed(2)} ms`);
    state.lastEdit = c;
    await showFrame(k);
  } catch (err) { status('edit: ' + err.message); }
});
for (const op of ['undo', 'redo']) {
  $(op).addEventListener('click', async () => {
    try {
      const c = await api(`/api/${op}`, {});
      await refreshCurves();
      status(c ? `${op}: frames ${c.a}..${c.b}` : `nothing to ${op} (in this tab)`);
      await showFrame(state.frame);
    } catch (err) { status(err.message); }
  });
}

// ---------------------------------------------------------------- direct manipulation
const ws = new WebSocket(`ws://${location.host}/ws?token=${encodeURIComponent(TOKEN)}&client=${CLIENT}`);
let inflight = false, pending = null;
ws.onmessage = (ev) => {
  const r = JSON.parse(ev.data);
  inflight = false;
  if (r.error) { status('drag: ' + r.error); return; }
  state.lastDrag = r;
  setWeights(face, r.weights);
  render();
  status(`drag solve ${r.server_ms.toFixed(3)} ms (server)`);
  if (pending) { const p = pending; pending = null; sendDrag(p); }
};
function sendDrag(msg) {
  if (inflight) { pending = msg; return; }
  inflight = true;
  ws.send(JSON.stringify(msg));
}

const ray = new THREE.Raycaster();
function pick(ev) {
  const r = canvas.getBoundingClientRect();
  const ndc = new THREE.Vector2(((ev.clientX - r.left) / r.width) * 2 - 1, -((ev.clientY - r.top) / r.height) * 2 + 1);
  ray.setFromCamera(ndc, camera);
  return ray;
}

function nearestVertex(mesh, worldPoint, face3) {
  const pos = new THREE.Vector3(), local = mesh.worldToLocal(worldPoint.clone());
  let best = face3.a, bd = Infinity;
  for (const v of [face3.a, face3.b, face3.c]) {
    mesh.getVertexPosition(v, pos);
    const d = pos.distanceToSquared(local);
    if (d < bd) { bd = d; best = v; }
  }
  return best;
}

// a marker's site, picked on screen, dropped on the face: the binding the next calibration uses
state.screenOf = (q) => { // a head-frame point (mm) in the page's client pixels
  const r = canvas.getBoundingClientRect();
  const s = head.localToWorld(new THREE.Vector3(q[0] * MM, q[1] * MM, q[2] * MM)).project(camera);
  return [(s.x + 1) / 2 * r.width + r.left, (1 - s.y) / 2 * r.height + r.top];
};

function nearestSite(ev) {
  let best = -1, bd = 15 * 15; // pixels
  (state.current ? state.current.sites : []).forEach((q, i) => {
    const [x, y] = state.screenOf(q), d = (x - ev.clientX) ** 2 + (y - ev.clientY) ** 2;
    if (d < bd) { bd = d; best = i; }
  });
  return best;
}

function moveMarker(ev) {
  const i = nearestSite(ev);
  if (i < 0) { status('no marker site under the pointer'); return; }
  const label = state.meta.labels[i], sites = state.current.sites.map((q) => q.slice());
  let drop = null;
  const move = (e) => {
    const hit = pick(e).intersectObject(face, false)[0];
    if (!hit) return;
    const p = face.worldToLocal(hit.point.clone());
    drop = { triangle: [hit.face.a, hit.face.b, hit.face.c], point: [p.x / MM, p.y / MM, p.z / MM] };
    sites[i] = drop.point;
    setPoints(sitesPts, sites); render();
  };
  const up = async (e) => {
    window.removeEventListener('mousemove', move); window.removeEventListener('mouseup', up);
    move(e);
    if (!drop) { status('drop the marker on the face'); return; }
    try {
      const r = await api('/api/markers', { frame: state.frame, label, ...drop });
      state.lastMarker = r;
      $('moved-markers').textContent = `moved: ${r.moved.join(', ')} (save, then recalibrate)`;
      status(`marker ${label} bound to triangle ${r.triangle.join(',')}`);
    } catch (err) { status('marker: ' + err.message); }
    await showFrame(state.frame);
  };
  window.addEventListener('mousemove', move);
  window.addEventListener('mouseup', up);
}

canvas.addEventListener('mousedown', (ev) => {
  if (!face) return;
  if ($('move-markers').checked) { moveMarker(ev); return; }
  const hit = pick(ev).intersectObject(face, false)[0];
  if (!hit) return;
  const v = nearestVertex(face, hit.point, hit.face);
  const p = new THREE.Vector3();
  face.getVertexPosition(v, p);
  const goal = [p.x / MM, p.y / MM, p.z / MM];
  if (ev.shiftKey) { // a pin that holds its place while others are dragged
    state.pins.push({ vertex: v, goal });
    setPoints(pinPts, state.pins.map((q) => q.goal)); render();
    status(`pinned vertex ${v}`);
    return;
  }
  const world = face.localToWorld(p.clone());
  const plane = new THREE.Plane().setFromNormalAndCoplanarPoint(camera.getWorldDirection(new THREE.Vector3()).negate(), world);
  const drag = { vertex: v, goal };
  const message = (commit) => {
    const range = +$('drag-range').value;
    return { frame: state.frame, pins: [...state.pins, drag], commit,
      range: [state.frame - range, state.frame + range] };
  };
  const move = (e) => {
    const at = new THREE.Vector3();
    if (!pick(e).ray.intersectPlane(plane, at)) return;
    const local = head.worldToLocal(at);
    drag.goal = [local.x / MM, local.y / MM, local.z / MM];
    sendDrag(message(false));
  };
  const up = async (e) => {
    window.removeEventListener('mousemove', move); window.removeEventListener('mouseup', up);
    move(e);
    try {
      const r = await api('/api/pose', message(true));
      applyChange(r.change);
      await refreshCurves();
      state.lastCommit = r;
      status(`drag committed at frame ${r.frame}: solve ${r.server_ms.toFixed(3)} ms, edit ${r.change.server_ms.toFixed(2)} ms`);
      await showFrame(state.frame);
    } catch (err) { status('drag: ' + err.message); }
  };
  window.addEventListener('mousemove', move);
  window.addEventListener('mouseup', up);
});
$('clear-pins').addEventListener('click', () => { state.pins = []; showFrame(state.frame); });

// ---------------------------------------------------------------- keys
$('keys').addEventListener('click', async () => {
  const e = +$('key-error').value;
  try {
    state.keys = await api(`/api/keys?max_error=${e}`);
    $('key-report').textContent = `${state.keys.keys} keys (${(100 * state.keys.fraction).toFixed(2)} % of samples), worst ${state.keys.worst.toFixed(4)}`;
    for (const id of ['save-keys-csv', 'save-keys-glb', 'save-keys-linear-glb']) $(id).href = $(id).href.split('?')[0] + `?max_error=${e}`;
    timeline();
  } catch (err) { status('keys: ' + err.message); }
});

// ---------------------------------------------------------------- start
async function main() {
  state.meta = await api('/api/meta');
  state.names = state.meta.names;
  await refreshCurves();
  const names = state.meta.names;
  for (const id of ['shapes', 'edit-shape']) {
    names.forEach((n, j) => { const o = document.createElement('option'); o.value = j; o.textContent = n; $(id).appendChild(o); });
  }
  const energy = names.map((_, j) => state.curves.weights[j].reduce((s, x) => s + Math.abs(x), 0));
  state.selected = names.map((_, j) => j).sort((a, b) => energy[b] - energy[a]).slice(0, 4);
  for (const o of $('shapes').options) o.selected = state.selected.includes(+o.value);
  if (!state.meta.has_truth) $('show-truth').disabled = true;
  await loadRig();
  await showFrame(0);
  state.ready = true;
  status(`${state.meta.n_frames} frames, ${names.length} shapes`);
}
main().catch((err) => status('error: ' + err.message));
