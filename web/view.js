// Prism's live 3D view: polls prism-client (/api/state, /api/poses, /api/chunks/N.drc; see
// tools/view/view_server.h) and draws the map chunk by chunk, the camera's path and its frustum.
// window.prismView holds what the page has decoded and shows (read by tests/live_view_browser.mjs).
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const kPollMs = 500;          // how often the page asks prism-client for news
const kPointSizePx = 2;       // map points, screen pixels
const kFrustumFraction = 0.08; // the frustum's depth, as a fraction of the scene's size

const view = (window.prismView = {
  pointsDecoded: 0,   // over every chunk decoded, replaced ones included
  chunksDecoded: 0,
  pointsShown: 0,     // in the chunks shown now (from the last one that replaced the map on)
  chunksShown: 0,
  posesShown: 0,
  status: null,       // the last /api/state
  statesSeen: [],     // every session state the page has shown ("streaming", "closing", "finished", ...)
  mismatches: [],     // chunks whose decoded points differ from the points prism-client says they hold
  done: false,        // the session has ended and every chunk it lists is shown
  errors: [],
  // Pixels of the drawn scene that differ from the background (read back from the WebGL canvas).
  drawnPixels() {
    const c = renderer.domElement;
    const copy = document.createElement('canvas');
    copy.width = c.width;
    copy.height = c.height;
    const g = copy.getContext('2d');
    g.drawImage(c, 0, 0);
    const d = g.getImageData(0, 0, c.width, c.height).data;
    const background = [d[d.length - 4], d[d.length - 3], d[d.length - 2]]; // a corner
    let drawn = 0;
    for (let i = 0; i < d.length; i += 4) {
      if (Math.abs(d[i] - background[0]) + Math.abs(d[i + 1] - background[1]) + Math.abs(d[i + 2] - background[2]) > 24) ++drawn;
    }
    return { drawn, total: c.width * c.height };
  },
});

const $ = (id) => document.getElementById(id);

// --- scene -----------------------------------------------------------------------------------
const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
renderer.setSize(window.innerWidth, window.innerHeight);
renderer.outputColorSpace = THREE.LinearSRGBColorSpace; // chunk colours are shown as the camera saw them
renderer.setClearColor(0x15191e);
document.body.appendChild(renderer.domElement);

const scene = new THREE.Scene();
// Prism's world frame is the first keyframe's camera (x right, y down, z forward): turned so that
// y points up on screen.
const world = new THREE.Group();
world.rotation.x = Math.PI;
scene.add(world);
const mapGroup = new THREE.Group();
world.add(mapGroup);

const camera = new THREE.PerspectiveCamera(50, window.innerWidth / window.innerHeight, 0.001, 1000);
camera.position.set(0, 0.3, 1.2);
const controls = new OrbitControls(camera, renderer.domElement);
controls.enableDamping = true;

const pathGeometry = new THREE.BufferGeometry();
const path = new THREE.Line(pathGeometry, new THREE.LineBasicMaterial({ color: 0xffc04d }));
path.frustumCulled = false;
world.add(path);
const frustumGeometry = new THREE.BufferGeometry();
const frustum = new THREE.LineSegments(frustumGeometry, new THREE.LineBasicMaterial({ color: 0x4dd2ff }));
frustum.frustumCulled = false;
frustum.matrixAutoUpdate = false;
world.add(frustum);

window.addEventListener('resize', () => {
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight);
});
window.addEventListener('keydown', (e) => {
  if (e.key === 'f' || e.key === 'F') fitView();
});

// --- Draco ------------------------------------------------------------------------------------
const dracoReady = DracoDecoderModule({ locateFile: (file) => 'lib/draco/' + file });

// A .drc point cloud -> {positions: Float32Array, colors: Uint8Array | null, count}.
function decodeChunk(draco, buffer) {
  const decoder = new draco.Decoder();
  const cloud = new draco.PointCloud();
  try {
    const status = decoder.DecodeArrayToPointCloud(new Int8Array(buffer), buffer.byteLength, cloud);
    if (!status.ok()) throw new Error('Draco: ' + status.error_msg());
    const count = cloud.num_points();
    const read = (type, dracoType, Heap, arrayType) => {
      const id = decoder.GetAttributeId(cloud, type);
      if (id < 0) return null;
      const attribute = decoder.GetAttribute(cloud, id);
      const bytes = count * 3 * arrayType.BYTES_PER_ELEMENT;
      const ptr = draco._malloc(bytes);
      decoder.GetAttributeDataArrayForAllPoints(cloud, attribute, dracoType, bytes, ptr);
      const out = new arrayType(draco[Heap].buffer, ptr, count * 3).slice();
      draco._free(ptr);
      return out;
    };
    const positions = read(draco.POSITION, draco.DT_FLOAT32, 'HEAPF32', Float32Array);
    const colors = read(draco.COLOR, draco.DT_UINT8, 'HEAPU8', Uint8Array);
    if (!positions) throw new Error('chunk without positions');
    return { positions, colors, count };
  } finally {
    draco.destroy(cloud);
    draco.destroy(decoder);
  }
}

// --- state from prism-client ---------------------------------------------------------------------
const shown = new Map(); // chunk sequence -> THREE.Points
const loading = new Set();
const poses = new Map(); // frame -> {t, p, q, state, keyframe}
let poseRevision = 0;
let metresPerUnit = 1;
let cameraModel = null;
let fitted = false;

async function loadChunk(draco, chunk) {
  loading.add(chunk.sequence);
  try {
    const response = await fetch(`api/chunks/${chunk.sequence}.drc`);
    if (response.status === 204) return; // voided by a chunk that replaced the map meanwhile
    if (!response.ok) throw new Error(`chunk ${chunk.sequence}: HTTP ${response.status}`);
    const decoded = decodeChunk(draco, await response.arrayBuffer());
    if (decoded.count !== chunk.points) view.mismatches.push({ sequence: chunk.sequence, expected: chunk.points, decoded: decoded.count });
    if (chunk.replaces_map) fitted = false; // the rebuilt map: fit the view to it once
    view.pointsDecoded += decoded.count;
    view.chunksDecoded += 1;
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute('position', new THREE.BufferAttribute(decoded.positions, 3));
    if (decoded.colors) geometry.setAttribute('color', new THREE.BufferAttribute(decoded.colors, 3, true));
    const material = new THREE.PointsMaterial({ size: kPointSizePx, sizeAttenuation: false, vertexColors: !!decoded.colors });
    const points = new THREE.Points(geometry, material);
    points.userData.count = decoded.count;
    shown.set(chunk.sequence, points);
    mapGroup.add(points);
  } catch (e) {
    view.errors.push(String(e));
    $('error').textContent = String(e);
  } finally {
    loading.delete(chunk.sequence);
  }
}

function syncChunks(draco, chunks) {
  const listed = new Set(chunks.map((c) => c.sequence));
  for (const [sequence, points] of shown) {
    if (listed.has(sequence)) continue; // else: voided by a chunk that replaced the map
    mapGroup.remove(points);
    points.geometry.dispose();
    points.material.dispose();
    shown.delete(sequence);
  }
  return Promise.all(chunks.filter((c) => !shown.has(c.sequence) && !loading.has(c.sequence)).map((c) => loadChunk(draco, c)));
}

function updatePath() {
  const frames = [...poses.keys()].sort((a, b) => a - b);
  const tracked = frames.map((f) => poses.get(f)).filter((p) => p.state === 'tracking' || p.keyframe);
  const xyz = new Float32Array(tracked.length * 3);
  tracked.forEach((p, i) => xyz.set([p.p[0] * metresPerUnit, p.p[1] * metresPerUnit, p.p[2] * metresPerUnit], i * 3));
  pathGeometry.setAttribute('position', new THREE.BufferAttribute(xyz, 3));
  pathGeometry.computeBoundingSphere();
  view.posesShown = tracked.length;
  const last = frames.length ? poses.get(frames[frames.length - 1]) : null;
  if (last) updateFrustum(last);
}

function sceneSize() {
  const box = new THREE.Box3().setFromObject(mapGroup);
  if (pathGeometry.getAttribute('position')) box.union(new THREE.Box3().setFromBufferAttribute(pathGeometry.getAttribute('position')));
  return box.isEmpty() ? 0.5 : Math.max(box.getSize(new THREE.Vector3()).length(), 0.05);
}

function updateFrustum(pose) {
  const c = cameraModel && cameraModel.width > 0 ? cameraModel : { width: 4, height: 3, fx: 3.5, fy: 3.5, cx: 2, cy: 1.5 };
  const d = kFrustumFraction * sceneSize();
  const corner = (u, v) => [((u - c.cx) / c.fx) * d, ((v - c.cy) / c.fy) * d, d];
  const k = [corner(0, 0), corner(c.width, 0), corner(c.width, c.height), corner(0, c.height)];
  const lines = [];
  for (let i = 0; i < 4; ++i) lines.push(0, 0, 0, ...k[i], ...k[i], ...k[(i + 1) % 4]);
  frustumGeometry.setAttribute('position', new THREE.BufferAttribute(new Float32Array(lines), 3));
  frustumGeometry.computeBoundingSphere();
  const t = new THREE.Vector3(pose.p[0], pose.p[1], pose.p[2]).multiplyScalar(metresPerUnit);
  frustum.matrix.compose(t, new THREE.Quaternion(pose.q[0], pose.q[1], pose.q[2], pose.q[3]), new THREE.Vector3(1, 1, 1));
}

function fitView() {
  const box = new THREE.Box3().setFromObject(mapGroup);
  if (box.isEmpty() && pathGeometry.getAttribute('position')) box.setFromObject(path);
  if (box.isEmpty()) return false;
  const centre = box.getCenter(new THREE.Vector3());
  const radius = Math.max(box.getSize(new THREE.Vector3()).length() / 2, 0.02);
  const distance = radius / Math.sin((camera.fov * Math.PI) / 360);
  controls.target.copy(centre);
  camera.position.copy(centre).add(new THREE.Vector3(0.35, 0.45, 1).normalize().multiplyScalar(distance));
  camera.near = distance / 1000;
  camera.far = distance * 100;
  camera.updateProjectionMatrix();
  controls.update();
  return true;
}

function showStatus(s) {
  $('session').textContent = s.session || '-';
  $('source').textContent = s.source || '-';
  $('state').textContent = s.state;
  $('tracking').textContent = s.mode === 'folder' ? '-' : s.tracking;
  $('fps').textContent = s.mode === 'folder' ? '-' : s.frames_per_s.toFixed(1);
  $('frames').textContent = `${s.frames_sent} / ${s.frames_dropped}`;
  $('poses').textContent = String(s.poses);
  $('points').textContent = `${view.pointsShown} shown (map ${s.map_points})`;
  $('chunks').textContent = `${view.chunksShown} shown, ${s.chunks_received} received`;
}

async function poll(draco) {
  try {
    const s = await (await fetch('api/state')).json();
    view.status = s;
    if (!view.statesSeen.includes(s.state)) view.statesSeen.push(s.state);
    metresPerUnit = s.metres_per_unit > 0 ? s.metres_per_unit : 1;
    cameraModel = s.camera;
    await syncChunks(draco, s.chunks);
    if (s.pose_revision !== poseRevision) {
      const p = await (await fetch(`api/poses?since=${poseRevision}`)).json();
      for (const pose of p.poses) poses.set(pose.frame, pose);
      poseRevision = p.revision;
    }
    updatePath();
    view.chunksShown = shown.size;
    view.pointsShown = [...shown.values()].reduce((n, p) => n + p.userData.count, 0);
    if (!fitted && shown.size > 0) fitted = fitView();
    view.done = (s.state === 'finished' || s.state.startsWith('failed')) && s.chunks.every((c) => shown.has(c.sequence));
    showStatus(s);
    $('error').textContent = '';
  } catch (e) {
    $('state').textContent = 'prism-client is not answering (the stream has ended?)';
  }
  setTimeout(() => poll(draco), kPollMs);
}

function render() {
  controls.update();
  renderer.render(scene, camera);
  requestAnimationFrame(render);
}

render();
dracoReady.then(poll, (e) => {
  view.errors.push('Draco decoder: ' + e);
  $('error').textContent = 'cannot load the Draco decoder: ' + e;
});
