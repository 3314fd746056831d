// The live 3D view of a labeled mocap stream (served by `mocap-labeler view`, docs/viewer.md).
//
// Messages from the viewer (WebSocket /ws): text JSON {type: "model" | "stats" | "history_end"}
// and binary frames: u32 H | JSON header (H bytes) | f32 positions M×3 | f32 unlabeled K×3 |
// u8 state M (0 missing, 1 observed, 2 recovered). The page draws the newest frame at each
// display refresh and acknowledges it ({"ack": seq}); the viewer sends the next frame only
// after the acknowledgement (one in flight by default) and replaces the queued frame by a newer
// one when the page lags (a counted drop).
// Frames of the replayed history (sent on connect, before "history_end") are not acknowledged.
//
// window.viewerState = {seq, drawn: {subject: count}, recovered, unlabeled, fps, drops, ...}
// describes what is on screen: `drawn` counts the spheres actually placed this frame.
import * as THREE from 'three';
import { OrbitControls } from '/static/vendor/three/OrbitControls.js';

// distinct subject colours (no grey: grey is for unlabeled points); then golden-angle hues
const PALETTE = ['#1f9bff', '#ff7f0e', '#2ecc40', '#e8384f', '#a970ff', '#ffd400', '#00d4c8',
  '#ff5fb8', '#8c6d31', '#b0e000'];
const MARKER_R = 14;       // mm
const UNLABELED_R = 7;     // mm
const BUFFER_FRAMES = 600; // frames kept for pause / single-step
const FPS_WINDOW_MS = 2000;

const state = {
  seq: null, t: null, drawn: {}, observed: 0, recovered: 0, unlabeled: 0, fps: 0, drops: 0,
  frames: 0, pageSkipped: 0, connected: false, paused: false, stream: null, model: null,
  latencyMs: { p50: null, p99: null }, inputRate: 0, error: null,
};
window.viewerState = state;

const $ = (id) => document.getElementById(id);
const overlay = $('overlay');

// ------------------------------------------------------------------------------ scene
let renderer;
try {
  // no MSAA: with software WebGL it multiplies the fill cost, and sprites and lines stay crisp
  renderer = new THREE.WebGLRenderer({ canvas: $('scene'), antialias: false });
} catch (err) {
  state.error = `WebGL is not available: ${err.message}`;
  overlay.innerHTML = `<span class="bad">${state.error}</span>`;
  throw err;
}
renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 1.5));
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x14171c);
const camera = new THREE.PerspectiveCamera(45, 1, 10, 200000);
camera.up.set(0, 0, 1);                       // Z up, millimetres
camera.position.set(4000, -5200, 2800);
const controls = new OrbitControls(camera, renderer.domElement);
controls.target.set(0, 0, 900);
controls.update();
let needsRender = true;
controls.addEventListener('change', () => { needsRender = true; });

const grid = new THREE.GridHelper(10000, 20, 0x59687a, 0x2a323c); // 500 mm cells
grid.rotation.x = Math.PI / 2;                // XZ plane -> floor (XY)
scene.add(grid);
scene.add(new THREE.AxesHelper(600));         // x red, y green, z blue

// Markers are point sprites (one vertex each, a shaded-ball or ring texture, size in mm): a
// 500-marker scene costs the (often software) rasterizer a few thousand pixels, not 100 000
// sphere triangles.
function spriteTexture(draw) {
  const c = document.createElement('canvas');
  c.width = c.height = 64;
  draw(c.getContext('2d'));
  const t = new THREE.CanvasTexture(c);
  t.colorSpace = THREE.SRGBColorSpace;
  return t;
}
const ballTexture = spriteTexture((g) => {
  const grad = g.createRadialGradient(24, 22, 2, 32, 32, 31);
  grad.addColorStop(0, '#ffffff');
  grad.addColorStop(0.35, '#e6e6e6');
  grad.addColorStop(1, '#7a7a7a');
  g.fillStyle = grad;
  g.beginPath(); g.arc(32, 32, 30, 0, 2 * Math.PI); g.fill();
});
const ringTexture = spriteTexture((g) => {  // recovered: hollow (hidden, position estimated)
  g.strokeStyle = '#ffffff';
  g.lineWidth = 9;
  g.beginPath(); g.arc(32, 32, 26, 0, 2 * Math.PI); g.stroke();
});
// size in mm (perspective), but never below minPx pixels: a marker stays visible from afar
function spriteMat(map, size, minPx, extra = {}) {
  const m = new THREE.PointsMaterial({ map, size, sizeAttenuation: true, alphaTest: 0.5,
    vertexColors: true, ...extra });
  m.onBeforeCompile = (shader) => {
    shader.uniforms.minPx = { value: minPx * renderer.getPixelRatio() };
    shader.vertexShader = `uniform float minPx;\n${shader.vertexShader}`.replace(
      '#include <fog_vertex>', 'gl_PointSize = max(gl_PointSize, minPx);\n#include <fog_vertex>');
  };
  return m;
}
const observedMat = spriteMat(ballTexture, 2 * MARKER_R, 7);
const recoveredMat = spriteMat(ringTexture, 2.8 * MARKER_R, 10);
const unlabeledMat = spriteMat(ballTexture, 2 * UNLABELED_R, 4, { vertexColors: false,
  color: 0x9aa1a9 });
const stickMat = new THREE.LineBasicMaterial({ vertexColors: true, transparent: true,
  opacity: 0.75 });

function points(material, capacity) {
  const geom = new THREE.BufferGeometry();
  const n = Math.max(1, capacity);
  geom.setAttribute('position', new THREE.BufferAttribute(new Float32Array(3 * n), 3)
    .setUsage(THREE.DynamicDrawUsage));
  geom.setAttribute('color', new THREE.BufferAttribute(new Float32Array(3 * n), 3)
    .setUsage(THREE.DynamicDrawUsage));
  geom.setDrawRange(0, 0);
  const p = new THREE.Points(geom, material);
  p.frustumCulled = false;
  p.userData.index = new Int32Array(n); // draw slot -> marker index (hover names)
  p.userData.capacity = n;
  scene.add(p);
  return p;
}

function place(p, slot, x, y, z, color) {
  const P = p.geometry.attributes.position.array;
  P[3 * slot] = x; P[3 * slot + 1] = y; P[3 * slot + 2] = z;
  if (color) {
    const C = p.geometry.attributes.color.array;
    C[3 * slot] = color.r; C[3 * slot + 1] = color.g; C[3 * slot + 2] = color.b;
  }
}

function commit(p, n) {
  p.geometry.setDrawRange(0, n);
  p.geometry.attributes.position.needsUpdate = true;
  p.geometry.attributes.color.needsUpdate = true;
  p.geometry.boundingSphere = null; // the raycaster's early-out sphere: recomputed when picking
}

let model = null;      // {names, subjects, bodies, ...} + colours, meshes
let observed = null, recovered = null;
let unlabeled = points(unlabeledMat, 256);
let sticks = null;
const vec = new THREE.Vector3();

function subjectColor(i) {
  if (i < PALETTE.length) return new THREE.Color(PALETTE[i]);
  return new THREE.Color().setHSL(((i * 0.381966) % 1 + 1) % 1, 0.75, 0.55);
}

function setModel(m) {
  for (const mesh of [observed, recovered, sticks]) if (mesh) scene.remove(mesh);
  const M = m.names.length;
  model = m;
  model.colors = {};
  model.subjects.forEach(([name], i) => { model.colors[name] = subjectColor(i); });
  model.subjectOf = new Array(M);
  for (const [name, start, count] of model.subjects) {
    for (let i = start; i < start + count; i++) model.subjectOf[i] = name;
  }
  observed = points(observedMat, M);
  recovered = points(recoveredMat, M);
  // rigid bodies: a spanning tree per body, found on the first frame it is complete
  model.trees = (m.bodies || []).map(() => null);
  const segs = (m.bodies || []).reduce((n, b) => n + Math.max(0, b.length - 1), 0);
  const geom = new THREE.BufferGeometry();
  geom.setAttribute('position', new THREE.BufferAttribute(new Float32Array(Math.max(1, segs) * 6), 3)
    .setUsage(THREE.DynamicDrawUsage));
  geom.setAttribute('color', new THREE.BufferAttribute(new Float32Array(Math.max(1, segs) * 6), 3)
    .setUsage(THREE.DynamicDrawUsage));
  geom.setDrawRange(0, 0);
  sticks = new THREE.LineSegments(geom, stickMat);
  sticks.frustumCulled = false;
  scene.add(sticks);
  state.model = m.model;
  state.stream = m.stream;
  buildLegend();
  const follow = $('follow');
  const keep = follow.value;
  follow.innerHTML = '<option value="">none</option>' + model.subjects
    .map(([name]) => `<option value="${escapeHtml(name)}">${escapeHtml(name)}</option>`).join('');
  follow.value = model.colors[keep] ? keep : '';
  fitted = false;
  needsRender = true;
}

function escapeHtml(s) {
  return String(s).replace(/[&<>"']/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;',
    '"': '&quot;', "'": '&#39;' }[c]));
}

// Prim's minimum spanning tree over a body's markers (<= 8): sticks that read as a shape
function spanningTree(body, pos) {
  const n = body.length;
  const inTree = [0];
  const edges = [];
  const d = (a, b) => {
    const i = 3 * body[a], j = 3 * body[b];
    return (pos[i] - pos[j]) ** 2 + (pos[i + 1] - pos[j + 1]) ** 2 + (pos[i + 2] - pos[j + 2]) ** 2;
  };
  while (inTree.length < n) {
    let best = null;
    for (const a of inTree) {
      for (let b = 0; b < n; b++) {
        if (inTree.includes(b)) continue;
        const w = d(a, b);
        if (best === null || w < best[2]) best = [a, b, w];
      }
    }
    inTree.push(best[1]);
    edges.push([body[best[0]], body[best[1]]]);
  }
  return edges;
}

const finite3 = (p, i) => Number.isFinite(p[3 * i]) && Number.isFinite(p[3 * i + 1])
  && Number.isFinite(p[3 * i + 2]);

// ------------------------------------------------------------------------------ drawing
let fitted = false;
const drawTimes = [];
let legendCounts = {};

function draw(f) {
  const { pos, unl, st } = f;
  let no = 0, nr = 0;
  const drawn = {};
  legendCounts = {};
  for (const [name, start, count] of model.subjects) {
    const color = model.colors[name];
    let nObs = 0, nRec = 0;
    for (let i = start; i < start + count; i++) {
      const s = st[i];
      if (s === 0 || !finite3(pos, i)) continue;
      if (s === 1) {
        place(observed, no, pos[3 * i], pos[3 * i + 1], pos[3 * i + 2], color);
        observed.userData.index[no++] = i;
        nObs++;
      } else {
        place(recovered, nr, pos[3 * i], pos[3 * i + 1], pos[3 * i + 2], color);
        recovered.userData.index[nr++] = i;
        nRec++;
      }
    }
    drawn[name] = nObs + nRec;
    legendCounts[name] = [nObs, nRec, count - nObs - nRec];
  }
  commit(observed, no);
  commit(recovered, nr);
  const K = unl.length / 3;
  if (K > unlabeled.userData.capacity) {
    scene.remove(unlabeled);
    unlabeled.geometry.dispose();
    unlabeled = points(unlabeledMat, 2 * K);
  }
  for (let k = 0; k < K; k++) place(unlabeled, k, unl[3 * k], unl[3 * k + 1], unl[3 * k + 2]);
  commit(unlabeled, K);
  drawSticks(pos, st);

  state.seq = f.seq;
  state.t = f.t;
  state.drawn = drawn;
  state.observed = no;
  state.recovered = nr;
  state.unlabeled = K;
  state.frames++;
  shown = f;
  drawTimes.push(performance.now());
  if (!fitted) { fitView(); fitted = true; }
  if (followName) follow(followName);
  needsRender = true;
}

function drawSticks(pos, st) {
  const bodies = model.bodies || [];
  const P = sticks.geometry.attributes.position.array;
  const C = sticks.geometry.attributes.color.array;
  let v = 0;
  bodies.forEach((body, b) => {
    if (model.trees[b] === null && body.length > 1 && body.every((i) => st[i] !== 0 && finite3(pos, i))) {
      model.trees[b] = spanningTree(body, pos);
    }
    const tree = model.trees[b];
    if (!tree) return;
    const color = model.colors[model.subjectOf[body[0]]];
    for (const [i, j] of tree) {
      if (st[i] === 0 || st[j] === 0 || !finite3(pos, i) || !finite3(pos, j)) continue;
      for (const m of [i, j]) {
        P[3 * v] = pos[3 * m]; P[3 * v + 1] = pos[3 * m + 1]; P[3 * v + 2] = pos[3 * m + 2];
        C[3 * v] = color.r; C[3 * v + 1] = color.g; C[3 * v + 2] = color.b;
        v++;
      }
    }
  });
  sticks.geometry.setDrawRange(0, v);
  sticks.geometry.attributes.position.needsUpdate = true;
  sticks.geometry.attributes.color.needsUpdate = true;
}

function drawnBox(name) {
  const box = new THREE.Box3();
  for (const mesh of [observed, recovered]) {
    if (!mesh) continue;
    const P = mesh.geometry.attributes.position.array;
    for (let n = 0; n < mesh.geometry.drawRange.count; n++) {
      if (name && model.subjectOf[mesh.userData.index[n]] !== name) continue;
      box.expandByPoint(vec.fromArray(P, 3 * n));
    }
  }
  return box;
}

function fitView() {
  const box = drawnBox(null);
  if (box.isEmpty()) return;
  const centre = box.getCenter(new THREE.Vector3());
  const size = Math.max(box.getSize(new THREE.Vector3()).length(), 1500);
  const dir = camera.position.clone().sub(controls.target).normalize();
  controls.target.copy(centre);
  camera.position.copy(centre).addScaledVector(dir, 0.62 * size / Math.tan((camera.fov * Math.PI) / 360));
  controls.update();
  needsRender = true;
}

let followName = '';
function follow(name) {
  const box = drawnBox(name);
  if (box.isEmpty()) return;
  const centre = box.getCenter(new THREE.Vector3());
  const delta = centre.sub(controls.target);
  controls.target.add(delta);
  camera.position.add(delta);
  controls.update();
}

// ------------------------------------------------------------------------------ overlay, legend
function buildLegend() {
  const rows = model.subjects.map(([name, , count], i) =>
    `<tr><td><span class="sw" style="background:#${model.colors[name].getHexString()}"></span></td>`
    + `<td>${escapeHtml(name)}</td><td id="lo-${i}">-</td><td id="lr-${i}">-</td>`
    + `<td id="lm-${i}">-</td><td>${count}</td></tr>`).join('');
  $('legend').innerHTML = '<table><tr><th></th><th>subject</th><th>obs</th><th>rec</th>'
    + `<th>miss</th><th>of</th></tr>${rows}</table>`
    + '<div class="key">● observed &nbsp;◌ recovered &nbsp;<span style="color:#8d949c">•</span>'
    + ' unlabeled &nbsp;— rigid body</div>';
}

const fmt = (v, d = 1) => (v === null || v === undefined || Number.isNaN(v) ? '-' : Number(v).toFixed(d));
let stats = {};

// The panels describe the frame on screen: refreshed in the same display refresh as a draw (at
// most every PANEL_MS), by a timer while no frame comes, and at once on pause and step.
const PANEL_MS = 250;
let lastPanel = 0;

function updatePanels() {
  const now = performance.now();
  lastPanel = now;
  state.panelSeq = state.seq;
  while (drawTimes.length && drawTimes[0] < now - FPS_WINDOW_MS) drawTimes.shift();
  state.fps = drawTimes.length / (FPS_WINDOW_MS / 1000);
  state.inputRate = stats.rate_in ?? 0;
  state.latencyMs = { p50: stats.lat_p50 ?? null, p99: stats.lat_p99 ?? null };
  const queueDrops = stats.dropped ?? 0;
  const subDrops = stats.subscriber_dropped ?? 0;
  state.drops = queueDrops + subDrops + state.pageSkipped;
  state.dropsDetail = { queue: queueDrops, subscriber: subDrops, page: state.pageSkipped };
  const status = state.connected ? (stats.status || 'waiting for frames') : 'disconnected, retrying';
  overlay.innerHTML = [
    `<b>mocap-labeler</b> · ${escapeHtml(state.stream ?? '-')} · ${escapeHtml(status)}${state.paused ? ' · <b>PAUSED</b>' : ''}`,
    `seq ${state.seq ?? '-'}   t ${fmt(state.t, 3)} s`,
    `input      ${fmt(state.inputRate, 0)} frames/s`,
    `displayed  ${fmt(state.fps, 1)} fps`,
    `latency    p50 ${fmt(state.latencyMs.p50, 2)} ms  p99 ${fmt(state.latencyMs.p99, 2)} ms (last 5 s)`,
    `drops      ${state.drops} (queue ${queueDrops}, page ${state.pageSkipped}, subscriber ${subDrops})`,
    `markers    ${state.observed} observed  ${state.recovered} recovered  ${state.unlabeled} unlabeled`,
  ].join('\n');
  if (model) {
    model.subjects.forEach(([name], i) => {
      const c = legendCounts[name];
      if (!c) return;
      $(`lo-${i}`).textContent = c[0];
      $(`lr-${i}`).textContent = c[1];
      $(`lm-${i}`).textContent = c[2];
    });
  }
}
setInterval(() => { if (performance.now() - lastPanel > 4 * PANEL_MS) updatePanels(); }, PANEL_MS);

// ------------------------------------------------------------------------------ connection
let ws = null;
let latest = null;      // newest decodable frame received
let shown = null;       // frame on screen
let inHistory = true;   // frames before "history_end" replay the viewer's last frames
const buffer = [];      // the last BUFFER_FRAMES frames, for pause / single-step

function decodeFrame(buf) {
  const dv = new DataView(buf);
  const h = dv.getUint32(0, true);
  const head = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, h)));
  let off = 4 + h;
  const pos = new Float32Array(buf, off, head.m * 3); off += head.m * 12;
  const unl = new Float32Array(buf, off, head.k * 3); off += head.k * 12;
  const st = new Uint8Array(buf, off, head.m);
  return { seq: head.seq, t: head.t, model: head.model, latency: head.lat_ms, pos, unl, st };
}

function ack(seq) {
  if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify({ ack: seq }));
}

function onFrame(f) {
  if (!model || f.model !== model.model || f.st.length !== model.names.length) {
    if (!f.hist) ack(f.seq); // not decodable with the model we have: let the next one come
    return;
  }
  buffer.push(f);
  if (buffer.length > BUFFER_FRAMES) buffer.shift();
  if (!state.paused && latest && latest !== shown && !latest.hist) state.pageSkipped++;
  latest = f;
  if (state.paused && !f.hist) ack(f.seq); // paused: keep the stream flowing into the buffer
  updateStepButtons();
}

function connect() {
  const proto = location.protocol === 'https:' ? 'wss' : 'ws';
  ws = new WebSocket(`${proto}://${location.host}/ws`);
  ws.binaryType = 'arraybuffer';
  inHistory = true;
  ws.onopen = () => { state.connected = true; };
  ws.onmessage = (ev) => {
    if (typeof ev.data === 'string') {
      const m = JSON.parse(ev.data);
      if (m.type === 'model') setModel(m);
      else if (m.type === 'stats') stats = m;
      else if (m.type === 'history_end') inHistory = false;
      return;
    }
    const f = decodeFrame(ev.data);
    f.hist = inHistory;
    onFrame(f);
  };
  ws.onclose = () => {
    state.connected = false;
    setTimeout(connect, 1000);
  };
}
connect();

// ------------------------------------------------------------------------------ render loop
function loop() {
  requestAnimationFrame(loop);
  if (!state.paused && latest && latest !== shown) {
    draw(latest);
    if (!latest.hist) ack(latest.seq);
    if (performance.now() - lastPanel >= PANEL_MS) updatePanels();
  }
  if (hover) pick();
  if (needsRender) {
    needsRender = false;
    renderer.render(scene, camera);
  }
}

function resize() {
  const w = window.innerWidth, h = window.innerHeight;
  renderer.setSize(w, h, false);
  camera.aspect = w / Math.max(h, 1);
  camera.updateProjectionMatrix();
  needsRender = true;
}
window.addEventListener('resize', resize);
resize();
requestAnimationFrame(loop);

// ------------------------------------------------------------------------------ controls
function updateStepButtons() {
  const i = shown ? buffer.indexOf(shown) : -1;
  $('back').disabled = !state.paused || i <= 0;
  $('step').disabled = !state.paused || i < 0 || i >= buffer.length - 1;
}

function setPaused(p) {
  state.paused = p;
  $('pause').textContent = p ? 'resume' : 'pause';
  updatePanels();
  updateStepButtons();
}

function stepBy(d) {
  if (!state.paused || !model) return;
  const i = buffer.indexOf(shown);
  const j = i < 0 ? buffer.length - 1 : i + d;
  if (j >= 0 && j < buffer.length && buffer[j].model === model.model) draw(buffer[j]);
  updateStepButtons();
  updatePanels();
}

$('pause').onclick = () => setPaused(!state.paused);
$('step').onclick = () => stepBy(1);
$('back').onclick = () => stepBy(-1);
$('fit').onclick = fitView;
$('follow').onchange = (e) => { followName = e.target.value; if (followName) follow(followName); };
window.addEventListener('keydown', (e) => {
  if (e.target.tagName === 'SELECT') return;
  if (e.key === ' ') { setPaused(!state.paused); e.preventDefault(); }
  else if (e.key === 'ArrowRight') stepBy(1);
  else if (e.key === 'ArrowLeft') stepBy(-1);
  else if (e.key === 'f') fitView();
});

// marker name on hover
const raycaster = new THREE.Raycaster();
raycaster.params.Points.threshold = MARKER_R; // mm
const mouse = new THREE.Vector2();
const tooltip = $('tooltip');
let hover = null;
renderer.domElement.addEventListener('pointermove', (e) => {
  mouse.set((e.clientX / window.innerWidth) * 2 - 1, -(e.clientY / window.innerHeight) * 2 + 1);
  hover = { x: e.clientX, y: e.clientY };
});
renderer.domElement.addEventListener('pointerleave', () => { hover = null; tooltip.style.display = 'none'; });

function pick() {
  const { x, y } = hover;
  hover = null;
  if (!model) return;
  raycaster.setFromCamera(mouse, camera);
  // pick within the drawn ball (at least 7 px across): 4 px at the orbit target's distance
  const mmPerPx = 2 * camera.position.distanceTo(controls.target)
    * Math.tan((camera.fov * Math.PI) / 360) / Math.max(renderer.domElement.clientHeight, 1);
  raycaster.params.Points.threshold = Math.max(MARKER_R, 4 * mmPerPx);
  const hits = raycaster.intersectObjects([observed, recovered, unlabeled], false);
  if (!hits.length) { tooltip.style.display = 'none'; return; }
  const hit = hits[0];
  let text;
  if (hit.object === unlabeled) text = 'unlabeled point';
  else {
    const i = hit.object.userData.index[hit.index];
    text = `${model.names[i]} (${hit.object === observed ? 'observed' : 'recovered'})`;
  }
  vec.fromArray(hit.object.geometry.attributes.position.array, 3 * hit.index);
  tooltip.textContent = `${text}  ${vec.x.toFixed(0)}, ${vec.y.toFixed(0)}, ${vec.z.toFixed(0)} mm`;
  tooltip.style.left = `${x + 12}px`;
  tooltip.style.top = `${y + 12}px`;
  tooltip.style.display = 'block';
}
