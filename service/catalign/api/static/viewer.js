/*
 * catalign viewer: register a point cloud with POST /register and look at the answer in 3D.
 *
 * The chosen file is uploaded unchanged (multipart field "file"); the page also reads it
 * (formats.js: .npy, .xyz, .ply, .pcd) to draw the observed points. A file it cannot read is
 * still registered; then only the model is drawn.
 * The answer's model comes from GET /models/{id}/points, placed by the answer's 4x4 row-major
 * pose (x_obs = R x_model + t). The library list (GET /models) draws one model on its own.
 * Every request goes to this page's origin; the API key lives only in the `apiKey` variable:
 * never stored, never put in a URL.
 */
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

import { readCloud, readFloats } from './formats.js';

const COLORS = { background: 0xfafafa, observed: 0x1f5fa8, model: 0xe8730c };
const POINT_SIZE_PX = 3;
const MODEL_POINTS = 5000;
const MODEL_UP = [0, 1, 0]; // library models stand on +Y (catalign.frames.MODEL_UP)
const VIEW_AZIMUTH_DEG = -60; // initial camera: around the up axis ...
const VIEW_ELEVATION_DEG = 25; // ... and above the horizon
const FIT_MARGIN = 0.85; // < 1: the bounding sphere is looser than the cloud's outline

let apiKey = ''; // in memory only
let chosenFile = null;
const LIBRARY_ERROR = 'library: ';
const $ = (id) => document.getElementById(id);
const view = createView($('canvas'));

wireControls();
loadLibrary();
document.body.dataset.state = 'ready'; // the module ran (tests wait for it)

// ---------------------------------------------------------------------------------------------
// Requests: same origin, the API key when one was typed, the server's error message on failure.

async function request(path, options = {}) {
  const headers = new Headers(options.headers);
  if (apiKey) headers.set('X-API-Key', apiKey);
  const settings = { ...options, headers, credentials: 'omit', cache: 'no-store' };
  const response = await fetch(path, settings);
  if (!response.ok) throw new Error(await errorMessage(response));
  return response;
}

async function errorMessage(response) {
  try {
    const { error } = await response.json();
    if (error?.message) return `${error.message} (${error.code}, HTTP ${response.status})`;
  } catch {
    // not the server's JSON error body: fall through to the status line
  }
  return `HTTP ${response.status} ${response.statusText}`;
}

async function postRegister(file, up, category) {
  const body = new FormData();
  body.append('file', file, file.name);
  const options = {};
  if (up) options.up = up;
  if (category) options.category = category;
  const query = Object.keys(options).length ? `?${new URLSearchParams(options)}` : '';
  return (await request(`/register${query}`, { method: 'POST', body })).json();
}

async function fetchModelPoints(modelId) {
  const path = `/models/${encodeURIComponent(modelId)}/points?max_points=${MODEL_POINTS}`;
  const buffer = await (await request(path)).arrayBuffer();
  return readFloats(new DataView(buffer), 0, buffer.byteLength / 4, 4, true);
}

// ---------------------------------------------------------------------------------------------
// Page actions.

function wireControls() {
  $('file').addEventListener('change', () => chooseFile($('file').files[0]));
  const drop = $('drop');
  drop.addEventListener('dragover', (event) => {
    event.preventDefault();
    drop.classList.add('over');
  });
  drop.addEventListener('dragleave', () => drop.classList.remove('over'));
  drop.addEventListener('drop', (event) => {
    event.preventDefault();
    drop.classList.remove('over');
    chooseFile(event.dataTransfer.files[0]);
  });
  $('api-key').addEventListener('input', () => { apiKey = $('api-key').value; });
  $('api-key').addEventListener('change', loadLibrary);
  $('register').addEventListener('click', register);
  $('reload').addEventListener('click', loadLibrary);
}

async function chooseFile(file) {
  if (!file) return;
  chosenFile = file;
  $('file-name').textContent = `${file.name} (${(file.size / 1024).toFixed(0)} KiB)`;
  clearError();
  const observed = await readCloud(file);
  clearClouds(view);
  if (observed) {
    addCloud(view, observed, COLORS.observed);
    fitCamera(view, observed, parseUp($('up').value) ?? [0, 0, 1]);
  }
  setStatus(observed ? describeCloud(observed) : 'cannot draw this file; it can still be sent');
}

async function register() {
  if (!chosenFile) return showError('Choose a point cloud file first.');
  clearError();
  setBusy(true);
  setStatus(`registering ${chosenFile.name} ...`);
  const started = performance.now();
  try {
    const up = $('up').value.trim();
    const category = $('category').value.trim();
    const [observed, answer] = await Promise.all([
      readCloud(chosenFile),
      postRegister(chosenFile, up, category),
    ]);
    const model = await fetchModelPoints(answer.model_id);
    drawAnswer(observed, model, answer.pose, parseUp(up) ?? poseUp(answer.pose));
    showAnswer(answer);
    setStatus(`${answer.model_id} in ${(performance.now() - started).toFixed(0)} ms`);
  } catch (error) {
    setStatus('');
    showError(error.message);
  } finally {
    setBusy(false);
  }
}

async function loadLibrary() {
  const list = $('models');
  try {
    const { models } = await (await request('/models')).json();
    list.replaceChildren(...models.map(libraryItem));
    if ($('error').textContent.startsWith(LIBRARY_ERROR)) clearError();
  } catch (error) {
    list.replaceChildren();
    showError(`${LIBRARY_ERROR}${error.message}`);
  }
}

function libraryItem(model) {
  const button = document.createElement('button');
  button.type = 'button';
  button.dataset.modelId = model.model_id;
  const size = model.size.map((v) => v.toFixed(2)).join(' x ');
  button.append(model.model_id, ' ', small(`${size} m`));
  button.addEventListener('click', () => showModel(model.model_id, button));
  const item = document.createElement('li');
  item.append(button);
  return item;
}

async function showModel(modelId, button) {
  clearError();
  try {
    const points = await fetchModelPoints(modelId);
    clearClouds(view);
    addCloud(view, points, COLORS.model);
    fitCamera(view, points, MODEL_UP);
    for (const other of document.querySelectorAll('.models button')) {
      other.classList.toggle('current', other === button);
    }
    setStatus(`${modelId}: ${points.length / 3} points, model frame`);
  } catch (error) {
    showError(error.message);
  }
}

// ---------------------------------------------------------------------------------------------
// The answer panel (textContent only: ids and messages are never parsed as HTML).

// The turns about its up under which the answer's model looks the same.
function symmetryText(symmetry) {
  if (!symmetry) return '';
  if (symmetry.order === 0) return 'any turn';
  if (symmetry.order === 1) return 'no turn';
  return symmetry.yaws_deg.slice(1).map((yaw) => `${yaw}°`).join(', ');
}

function showAnswer(answer) {
  $('answer').hidden = false;
  $('model-id').textContent = answer.model_id;
  $('answer-category').textContent = answer.category ?? '';
  $('answer-symmetry').textContent = symmetryText(answer.symmetry);
  $('fitness').textContent = answer.fitness.toFixed(3);
  $('inlier-rmse').textContent = `${(answer.inlier_rmse * 1000).toFixed(1)} mm`;
  $('inlier-ratio').textContent = answer.inlier_ratio.toFixed(3);
  $('points-set-aside').textContent = String(answer.points_set_aside);
  $('timings').replaceChildren(...Object.entries(answer.timings_ms).map(timingRow));
  $('candidates').replaceChildren(...answer.candidates.map((c) => listItem(c.model_id, c.score)));
  showOptional(answer);
  document.body.dataset.state = 'answered';
}

function showOptional(answer) {
  const hasConfidence = answer.confidence !== undefined && answer.confidence !== null;
  $('confidence').hidden = $('confidence-label').hidden = !hasConfidence;
  $('confidence').textContent = hasConfidence ? describe(answer.confidence) : '';
  const alternatives = Array.isArray(answer.alternatives) ? answer.alternatives : [];
  $('alternatives-box').hidden = alternatives.length === 0;
  $('alternatives').replaceChildren(
    ...alternatives.map((a) => listItem(a?.model_id ?? describe(a), a?.score ?? a?.confidence)),
  );
}

function timingRow([stage, ms]) {
  const row = document.createElement('tr');
  for (const text of [stage, ms.toFixed(1)]) {
    const cell = document.createElement('td');
    cell.textContent = text;
    row.append(cell);
  }
  return row;
}

function listItem(label, score) {
  const item = document.createElement('li');
  item.append(label);
  if (typeof score === 'number') item.append(small(score.toFixed(3), 'span'));
  return item;
}

function small(text, tag = 'small') {
  const element = document.createElement(tag);
  element.textContent = text;
  return element;
}

function describe(value) {
  return typeof value === 'number' ? value.toFixed(3) : JSON.stringify(value);
}

function setStatus(text) { $('status').textContent = text; }
function setBusy(busy) { $('register').disabled = busy; }
function clearError() { $('error').hidden = true; $('error').textContent = ''; }
function showError(message) { $('error').textContent = message; $('error').hidden = false; }

function describeCloud(positions) {
  const box = new THREE.Box3().setFromBufferAttribute(new THREE.BufferAttribute(positions, 3));
  const size = box.getSize(new THREE.Vector3()).toArray().map((v) => v.toFixed(2)).join(' x ');
  return `${positions.length / 3} points read, ${size} (file units)`;
}

function parseUp(text) {
  const values = text.split(',').map((v) => Number(v.trim()));
  const valid = values.length === 3 && values.every(Number.isFinite) && values.some((v) => v !== 0);
  return valid ? values : null;
}

function poseUp(pose) {
  // R @ MODEL_UP: where the placed model's up points in the observation's frame.
  return pose.slice(0, 3).map((row) => MODEL_UP.reduce((sum, v, j) => sum + row[j] * v, 0));
}

// ---------------------------------------------------------------------------------------------
// The 3D view: points drawn on demand (after a change, a camera move or a resize).

function createView(canvas) {
  const renderer = new THREE.WebGLRenderer({
    canvas, antialias: true, preserveDrawingBuffer: true, // keeps frames for screenshots
  });
  renderer.setPixelRatio(window.devicePixelRatio);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(COLORS.background);
  const clouds = new THREE.Group();
  scene.add(clouds);
  const camera = new THREE.PerspectiveCamera(35, 1, 0.01, 100);
  camera.position.set(2, 2, 2);
  const state = { renderer, scene, camera, clouds, controls: null };
  setCameraUp(state, [0, 0, 1]);
  new ResizeObserver(() => resize(state)).observe(canvas.parentElement);
  return state;
}

function render(state) {
  state.renderer.render(state.scene, state.camera);
}

function resize(state) {
  const parent = state.renderer.domElement.parentElement;
  state.renderer.setSize(parent.clientWidth, parent.clientHeight, false);
  state.camera.aspect = parent.clientWidth / Math.max(parent.clientHeight, 1);
  state.camera.updateProjectionMatrix();
  render(state);
}

function setCameraUp(state, up) {
  // OrbitControls orbits around camera.up as it was when they were made: make new ones.
  state.camera.up.set(...up).normalize();
  state.controls?.dispose();
  state.controls = new OrbitControls(state.camera, state.renderer.domElement);
  state.controls.addEventListener('change', () => render(state));
}

function clearClouds(state) {
  for (const cloud of [...state.clouds.children]) {
    cloud.geometry.dispose();
    cloud.material.dispose();
    state.clouds.remove(cloud);
  }
  render(state);
}

function addCloud(state, positions, color, pose = null) {
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute('position', new THREE.BufferAttribute(positions, 3));
  const material = new THREE.PointsMaterial({ color, size: POINT_SIZE_PX, sizeAttenuation: false });
  const cloud = new THREE.Points(geometry, material);
  if (pose) {
    cloud.matrixAutoUpdate = false;
    cloud.matrix.set(...pose.flat()); // Matrix4.set takes row-major values, like the answer
  }
  state.clouds.add(cloud);
  render(state);
}

function drawAnswer(observed, model, pose, up) {
  clearClouds(view);
  if (observed) addCloud(view, observed, COLORS.observed);
  addCloud(view, model, COLORS.model, pose);
  fitCamera(view, observed ?? transformed(model, pose), up);
}

function transformed(positions, pose) {
  const matrix = new THREE.Matrix4().set(...pose.flat());
  const attribute = new THREE.BufferAttribute(positions.slice(), 3);
  return attribute.applyMatrix4(matrix).array;
}

function fitCamera(state, positions, up) {
  // A fixed start: the whole cloud in view, seen from above the horizon, orbiting its centre.
  setCameraUp(state, up);
  const box = new THREE.Box3().setFromBufferAttribute(new THREE.BufferAttribute(positions, 3));
  const center = box.getCenter(new THREE.Vector3());
  const radius = Math.max(box.getSize(new THREE.Vector3()).length() / 2, 1e-3);
  const distance = FIT_MARGIN * radius / Math.sin(THREE.MathUtils.degToRad(state.camera.fov / 2));
  state.camera.position.copy(center).addScaledVector(viewDirection(state.camera.up), distance);
  state.camera.near = distance / 100;
  state.camera.far = distance * 100;
  state.camera.updateProjectionMatrix();
  state.controls.target.copy(center);
  state.controls.update();
  render(state);
}

function viewDirection(up) {
  // Two horizontal axes from the world axis least aligned with up, then azimuth and elevation.
  const axes = [new THREE.Vector3(1, 0, 0), new THREE.Vector3(0, 1, 0), new THREE.Vector3(0, 0, 1)];
  const reference = axes.reduce((a, b) => (Math.abs(b.dot(up)) < Math.abs(a.dot(up)) ? b : a));
  const first = reference.clone().addScaledVector(up, -reference.dot(up)).normalize();
  const second = new THREE.Vector3().crossVectors(up, first);
  const azimuth = THREE.MathUtils.degToRad(VIEW_AZIMUTH_DEG);
  const elevation = THREE.MathUtils.degToRad(VIEW_ELEVATION_DEG);
  return first.multiplyScalar(Math.cos(azimuth) * Math.cos(elevation))
    .addScaledVector(second, Math.sin(azimuth) * Math.cos(elevation))
    .addScaledVector(up, Math.sin(elevation));
}
