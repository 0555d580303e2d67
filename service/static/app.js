// ibr-service browser preview. Plain ES module, no dependencies, nothing from the network
// but this API. See the Help section of index.html for what the controls do.

const KEY_STORAGE = "ibr.apiKey";
const DEFAULT_CAMERA = { type: "perspective", eye: [0, 1, 4], look_at: [0, 0.5, 0], up: [0, 1, 0], fov_y_deg: 45 };
const RENDER_WAIT_S = 0.25; // server-side wait of POST /v1/renders; then the page polls the job
const JOB_POLL_MS = [50, 250]; // first and longest interval between polls of a running job
const MIN_REQUEST_GAP_MS = 100; // during a drag, at most one new view request per this interval
const COMPARE_REST_MS = 400; // the reference view for Compare is asked for once the camera rests this long
const BAKE_POLL_MS = 300;
const JOBS_LIST_MS = 1000;

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);

// Instrumentation read by tests and bench/preview_latency.py.
const perf = { inputAt: null, requests: 0, loads: 0, latencies: [], last: null, scheduled: false };
const relightPerf = { requests: 0, loads: 0, last: null, scheduled: false, inputAt: null };
const bakePerf = { state: null, fraction: 0, key: null };
const comparePerf = { runs: 0, last: null };
const walkPerf = { status: null, progress: 0, key: null, loaded: 0, frames: 0, shown: -1, played: 0, contract: null };
window.__walk = walkPerf;
window.__preview = perf;
window.__relight = relightPerf;
window.__bake = bakePerf;
window.__compare = comparePerf;
const relightComparePerf = { runs: 0, last: null };
const walkComparePerf = { runs: 0, last: null };
window.__relightCompare = relightComparePerf;
window.__walkCompare = walkComparePerf;

// ------------------------------------------------------------------ API access and errors

class ApiError extends Error {
  constructor(status, problem) {
    super(formatProblemText(status, problem));
    this.status = status;
    this.problem = problem;
  }
}

function formatProblemText(status, p) {
  let s = status ? `${p.title || "Error"} (HTTP ${status})` : `${p.title || "Error"}`;
  if (p.detail) s += `: ${p.detail}`;
  for (const e of p.errors || []) s += `\n${e.field || "request"}: ${e.message}`;
  return s;
}

function apiKey() { return sessionStorage.getItem(KEY_STORAGE) || ""; }

async function api(path, { method = "GET", body, signal, raw = false } = {}) {
  const headers = {};
  const key = apiKey();
  if (key) headers.Authorization = `Bearer ${key}`;
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const res = await fetch(path, { method, headers, signal, body: body === undefined ? undefined : JSON.stringify(body) });
  if (!res.ok) {
    let problem;
    try {
      const text = await res.text();
      const parsed = text ? JSON.parse(text) : {};
      problem = typeof parsed === "object" && parsed !== null ? parsed : { detail: String(parsed) };
    } catch {
      problem = {};
    }
    if (!problem.title) problem.title = res.statusText || "Request failed";
    if (typeof problem.detail !== "string") problem.detail = problem.detail ? JSON.stringify(problem.detail) : "";
    if (res.status === 401 && !problem.detail) problem.detail = "the API key is missing or not accepted";
    if (res.status === 401) problem.detail = `${problem.detail} — enter a valid API key above`;
    throw new ApiError(res.status, problem);
  }
  if (raw) return res;
  return { status: res.status, data: res.status === 204 ? null : await res.json() };
}

// The error banner: the problem's title, detail, per-field errors and hint as separate blocks (each
// part also separated by a space in the text, so read as text it never runs words together), long
// tokens (hashes, paths) wrapped inside the box, and a button to dismiss it.
function showError(err) {
  const box = $("error");
  const body = $("error-body");
  if (!err) { box.hidden = true; body.replaceChildren(); return; }
  const p = err instanceof ApiError ? err.problem : { title: "Error", detail: String(err.message || err) };
  const head = document.createElement("p");
  const title = document.createElement("strong");
  title.textContent = err instanceof ApiError && err.status ? `${p.title} (HTTP ${err.status})` : p.title;
  head.append(title);
  if (p.detail) head.append(document.createTextNode(`: ${p.detail}`));
  const parts = [head];
  if (p.errors && p.errors.length) {
    const ul = document.createElement("ul");
    for (const e of p.errors) {
      const li = document.createElement("li");
      const f = document.createElement("code");
      f.textContent = e.field || "request";
      li.append(f, document.createTextNode(`: ${e.message}`));
      ul.append(" ", li);
    }
    parts.push(ul);
  }
  if (p.hint) {
    const hint = document.createElement("p");
    hint.textContent = p.hint;
    parts.push(hint);
  }
  body.replaceChildren(...parts.flatMap((x, i) => (i ? [" ", x] : [x])));
  box.hidden = false;
}

const isAbort = (e) => e && (e.name === "AbortError" || e === ABORTED);
const ABORTED = new Error("aborted");
const sleep = (ms, signal) => new Promise((resolve, reject) => {
  if (signal?.aborted) { reject(ABORTED); return; }
  const t = setTimeout(resolve, ms);
  signal?.addEventListener("abort", () => { clearTimeout(t); reject(ABORTED); }, { once: true });
});

// Readable names of jobs (the API's job ids are "<kind>-<hash>"): what the page asked for, by job id.
const jobNames = new Map();
function nameJob(jobId, label) { if (jobId && label) jobNames.set(jobId, label); }

function cancelJob(jobId) {
  if (jobId) api(`/v1/jobs/${encodeURIComponent(jobId)}/cancel`, { method: "POST" }).catch(() => {});
}

// POST a render-like request (renders, relights: the same answer shape), poll its job until the
// artifact exists. `req.jobId` is set as soon as the job is known so a superseding request can
// cancel it. Returns {manifest, answer}.
async function runToArtifact(req, postPath, body, manifestPath, signal, onProgress) {
  let { data: r } = await api(`${postPath}?wait=${RENDER_WAIT_S}`, { method: "POST", body });
  if (r.job) req.jobId = r.job.id;
  if (r.job && req.label) nameJob(r.job.id, req.label);
  if (signal.aborted) throw ABORTED;
  let manifest = r.artifact;
  let delay = JOB_POLL_MS[0];
  while (!manifest) {
    if (r.status === "failed" || (r.job && (r.job.state === "failed" || r.job.state === "canceled"))) {
      const job = r.job || {};
      throw new ApiError(0, { title: "Job failed", detail: job.error || `job ${job.state}` });
    }
    if (r.job && onProgress) onProgress(r.job);
    await sleep(delay, signal);
    delay = Math.min(JOB_POLL_MS[1], delay * 1.3);
    const { data: job } = await api(`/v1/jobs/${encodeURIComponent(req.jobId)}`, { signal });
    if (job.state === "finished") {
      manifest = (await api(`${manifestPath}/${r.artifact_key}`, { signal })).data;
      r = { ...r, status: "finished", job };
    } else {
      r = { ...r, status: job.state, job };
    }
  }
  return { manifest, answer: r };
}

async function fetchBlobUrl(path, signal) {
  const res = await api(path, { signal, raw: true });
  return URL.createObjectURL(await res.blob());
}

// Swap an <img>'s blob URL, revoking the old one once the new one shows. Resolves on load.
function showBlob(img, url, key) {
  return new Promise((resolve, reject) => {
    const old = img.dataset.blobUrl;
    img.onload = () => { if (old && old !== url) URL.revokeObjectURL(old); resolve(); };
    img.onerror = () => reject(new Error("the image could not be decoded"));
    img.dataset.blobUrl = url;
    if (key !== undefined) img.dataset.key = key;
    img.src = url;
  });
}

function fillTable(table, rows) {
  table.tBodies[0].replaceChildren(...rows.map(([k, v]) => {
    const tr = document.createElement("tr");
    const a = document.createElement("td"); a.textContent = k;
    const b = document.createElement("td"); b.textContent = v;
    tr.append(a, b);
    return tr;
  }));
}

const fmtMs = (s) => `${(s * 1000).toFixed(1)} ms`;
const fmtEv = (v) => `${v >= 0 ? "+" : ""}${v.toFixed(1)} EV`;

// ------------------------------------------------------------------ capabilities

let caps = { methods: [{ name: "reference", needs_bake: false, k: [] }], bakes: false, datasets: false,
  relights: false, walkthroughs: false, compare: false, provenance: {} };

async function loadCapabilities() {
  try {
    const res = await fetch("/v1/preview/capabilities");
    if (res.ok) caps = await res.json();
  } catch { /* keep the minimal set: the reference renderer only */ }
  const sel = $("method");
  sel.replaceChildren(...caps.methods.map((m) => {
    const o = new Option(m.name, m.name);
    // the registry's description (engine/methods.py): what the method renders, from which bake, at what cost
    if (m.summary) o.title = [m.summary, m.bake && m.bake.length ? `bake: ${m.bake.join(" + ")}` : "no bake",
      m.cost ? `cost: ${m.cost}` : ""].filter(Boolean).join("\n");
    return o;
  }));
  const spp = ((caps.methods.find((m) => m.name === "reference") || {}).params || []).find((q) => q.name === "spp");
  if (spp) Object.assign($("spp"), { min: spp.low, max: spp.high, title: `${spp.doc} (${spp.low}..${spp.high})` });
  const ibrt = caps.methods.find((m) => m.k && m.k.length);
  if (ibrt) {
    $("ibrt-k").replaceChildren(...ibrt.k.map((k) => new Option(String(k), String(k))));
    $("ibrt-k").value = String(ibrt.k.includes(ibrt.k_default) ? ibrt.k_default : ibrt.k[0]);
  }
  if (["method", "error", "time"].includes(params.get("ask"))) $("ask").value = params.get("ask");
  if (params.get("target") && Number(params.get("target")) > 0) $("target").value = String(Number(params.get("target")));
  askChanged(false);
  const want = params.get("method");
  if (want) {
    const [name, k] = want.split(":");
    if (caps.methods.some((m) => m.name === name)) sel.value = name;
    if (k !== undefined) $("ibrt-k").value = k;
  }
  $("compare-label").hidden = !caps.compare;
  $("walks-panel").hidden = !caps.walkthroughs;
  const opts = caps.walkthrough_options || {};
  // the bake presets, then frames path-traced without a bake at the noise targets a calibration measures
  $("wt-quality").replaceChildren(...(opts.quality || []).map((q) => new Option(q, q)),
    ...(opts.path_noise || []).map((n) => new Option(`path-traced, noise ${n}`, `${PATH_PREFIX}${n}`)));
  if ((opts.quality || []).includes("low")) $("wt-quality").value = "low";
  $("wt-quality").addEventListener("change", walkQualityChanged);
  WALK_CALIBRATION_PARAMS.path_noises = (opts.path_noise || []).map(Number);
  $("wt-fill").replaceChildren(...(opts.fill || []).map((f) => new Option(f, f)));
  if ((opts.fill || []).includes("both")) $("wt-fill").value = "both";
  if (["settings", "error", "time"].includes(params.get("wt_ask"))) $("wt-ask").value = params.get("wt_ask");
  if ($("wt-ask").value !== "settings" && Number(params.get("wt_target")) > 0) {
    walkTargets[$("wt-ask").value] = String(Number(params.get("wt_target")));
  }
  walkAskChanged();
  $("datasets-panel").hidden = !(caps.datasets && caps.relights);
  const legend = Object.entries(caps.provenance || {}).map(([code, [name, colour]]) => {
    const s = document.createElement("span");
    const sw = document.createElement("i");
    sw.style.background = colour;
    s.append(sw, document.createTextNode(` ${name}`));
    s.dataset.code = code;
    return s;
  });
  $("provenance-legend").replaceChildren(...legend);
  methodChanged(false);
}

function currentMethod() {
  const name = $("method").value;
  const info = caps.methods.find((m) => m.name === name) || { name, needs_bake: false, k: [] };
  return { name: info.k && info.k.length ? `${name}:${$("ibrt-k").value}` : name, needsBake: info.needs_bake,
    hasK: Boolean(info.k && info.k.length) };
}

function methodChanged(render = true) {
  const m = currentMethod();
  $("k-label").hidden = !m.hasK || $("ask").value !== "method";
  $("aa-label").hidden = !m.needsBake || $("ask").value !== "method";
  $("glossy-label").hidden = !m.hasK || $("ask").value !== "method"; // traced lobes: ldc+ibrt only
  $("spp-label").hidden = m.needsBake || $("ask").value !== "method"; // the LDC methods render from the bake
  $("provenance-label").hidden = !m.needsBake;
  if (!m.needsBake) $("provenance").checked = false;
  updateProvenanceView();
  if (render) changed();
}

// ------------------------------------------------------------------ vector helpers

const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const len = (a) => Math.hypot(a[0], a[1], a[2]);
const norm = (a) => scale(a, 1 / (len(a) || 1));
// Rodrigues: rotate v around unit axis k by angle t.
function rotate(v, k, t) {
  const c = Math.cos(t), s = Math.sin(t);
  return add(add(scale(v, c), scale(cross(k, v), s)), scale(k, dot(k, v) * (1 - c)));
}

// ------------------------------------------------------------------ camera (orbit around a pivot)

const view = {
  scene: null, // ScenePublic
  bounds: null, // {center, radius}: bounding sphere of the scene's objects (null: not known)
  base: null, // {camera, pivot} the scene started from
  cam: null, // {type, eye, look_at, up, fov_y_deg | ortho_height}
  pivot: null,
  manifest: null, // the shown render's manifest
};

function setCamera(base) {
  view.base = base;
  view.cam = structuredClone(base.camera);
  view.cam.up = view.cam.up || [0, 1, 0];
  view.pivot = (base.pivot || view.cam.look_at).slice();
  // Orbit around the pivot: aim at it, keeping the distance.
  view.cam.look_at = view.pivot.slice();
}

// ---- scale of the scene: how far a drag turns, pans and zooms

const ORBIT_TURN_PER_VIEW = [Math.PI / 4, 2 * Math.PI]; // least and most a drag across the whole view turns

// 3x3 rotation (rows) of a scene Transform: extrinsic x, y, z Euler angles or an (x, y, z, w) quaternion.
function rotationOf(t) {
  if (t.quaternion) {
    const [x0, y0, z0, w0] = t.quaternion;
    const n = Math.hypot(x0, y0, z0, w0) || 1;
    const x = x0 / n, y = y0 / n, z = z0 / n, w = w0 / n;
    return [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]];
  }
  const [a, b, c] = (t.rotate_deg || [0, 0, 0]).map((v) => v * Math.PI / 180);
  const rx = [[1, 0, 0], [0, Math.cos(a), -Math.sin(a)], [0, Math.sin(a), Math.cos(a)]];
  const ry = [[Math.cos(b), 0, Math.sin(b)], [0, 1, 0], [-Math.sin(b), 0, Math.cos(b)]];
  const rz = [[Math.cos(c), -Math.sin(c), 0], [Math.sin(c), Math.cos(c), 0], [0, 0, 1]];
  const mul = (p, q) => p.map((row) => [0, 1, 2].map((j) => row[0] * q[0][j] + row[1] * q[1][j] + row[2] * q[2][j]));
  return mul(rz, mul(ry, rx));
}

// World bounding sphere of one object from its local one (centre, radius) and its transform.
function objectSphere(o) {
  const c = o.center || [0, 0, 0];
  let r = null;
  let centre = c;
  if (o.type === "sphere" || o.type === "disk") r = o.radius;
  else if (o.type === "box") r = len(o.size) / 2;
  else if (o.type === "cylinder") r = Math.hypot(o.radius, o.height / 2);
  else if (o.type === "plane") r = Math.hypot(o.size[0], o.size[1]) / 2;
  else if (o.type === "mesh" && o.vertices && o.vertices.length) {
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (const v of o.vertices) {
      for (let k = 0; k < 3; k++) { lo[k] = Math.min(lo[k], v[k]); hi[k] = Math.max(hi[k], v[k]); }
    }
    centre = scale(add(lo, hi), 0.5);
    r = len(sub(hi, lo)) / 2;
  }
  if (r === null) return null; // a mesh file: its extent is not in the scene document
  const t = o.transform || {};
  if (t.matrix) {
    const m = t.matrix;
    const col = (j) => [m[0][j], m[1][j], m[2][j]];
    const s = Math.max(len(col(0)), len(col(1)), len(col(2)));
    const w = [0, 1, 2].map((i) => dot(m[i].slice(0, 3), centre) + m[i][3]);
    return { center: w, radius: r * s };
  }
  const sc = t.scale || [1, 1, 1];
  const rot = rotationOf(t);
  const scaled = [centre[0] * sc[0], centre[1] * sc[1], centre[2] * sc[2]];
  const w = add(rot.map((row) => dot(row, scaled)), t.translate || [0, 0, 0]);
  return { center: w, radius: r * Math.max(...sc.map(Math.abs)) };
}

// A sphere (centre, radius) around the objects' spheres, centred on their bounding box; null if none is known.
function sceneBounds(doc) {
  const spheres = (doc.objects || []).map(objectSphere).filter(Boolean);
  if (!spheres.length) return null;
  const lo = [0, 1, 2].map((k) => Math.min(...spheres.map((q) => q.center[k] - q.radius)));
  const hi = [0, 1, 2].map((k) => Math.max(...spheres.map((q) => q.center[k] + q.radius)));
  const center = scale(add(lo, hi), 0.5);
  const radius = Math.max(...spheres.map((q) => len(sub(q.center, center)) + q.radius));
  return radius > 0 && Number.isFinite(radius) ? { center, radius } : null;
}

// World height the view spans at the pivot.
function viewHeightAtPivot() {
  if (view.cam.type === "orthographic") return view.cam.ortho_height;
  return 2 * len(sub(view.cam.eye, view.pivot)) * Math.tan((view.cam.fov_y_deg || 45) * Math.PI / 360);
}

// Radians per pixel of drag: the surface of the scene's bounding sphere follows the pointer (one
// pixel's world size at the pivot over the scene's radius); an unknown extent counts as filling the
// view. A drag across the whole view turns between ORBIT_TURN_PER_VIEW's bounds.
function orbitRadPerPx() {
  const px = viewSize();
  const h = viewHeightAtPivot();
  const r = view.bounds ? view.bounds.radius : h / 2;
  const perPx = h / px / r;
  return Math.min(Math.max(perPx, ORBIT_TURN_PER_VIEW[0] / px), ORBIT_TURN_PER_VIEW[1] / px);
}

function orbit(dTheta, dPhi) {
  const up = norm(view.cam.up);
  let off = sub(view.cam.eye, view.pivot);
  off = rotate(off, up, dTheta);
  const right = norm(cross(up, off));
  const rotated = rotate(off, right, dPhi);
  // keep away from the poles (the up hint must not be parallel to the view direction)
  if (Math.abs(dot(norm(rotated), up)) < 0.985) off = rotated;
  view.cam.eye = add(view.pivot, off);
  view.cam.look_at = view.pivot.slice();
}

function pan(dx, dy) {
  const up = norm(view.cam.up);
  const fwd = norm(sub(view.cam.look_at, view.cam.eye));
  const right = norm(cross(fwd, up));
  const camUp = cross(right, fwd);
  const size = view.cam.type === "orthographic" ? view.cam.ortho_height
    : 2 * len(sub(view.cam.eye, view.pivot)) * Math.tan((view.cam.fov_y_deg || 45) * Math.PI / 360);
  const px = viewSize();
  const move = add(scale(right, -dx * size / px), scale(camUp, dy * size / px));
  view.pivot = add(view.pivot, move);
  view.cam.eye = add(view.cam.eye, move);
  view.cam.look_at = view.pivot.slice();
}

function zoom(factor) {
  if (view.cam.type === "orthographic") {
    const r = view.bounds ? view.bounds.radius : view.cam.ortho_height;
    view.cam.ortho_height = Math.min(Math.max(r * 1e-3, view.cam.ortho_height * factor), r * 1e3);
    return;
  }
  const off = sub(view.cam.eye, view.pivot);
  const d = len(off);
  const r = view.bounds ? view.bounds.radius : d; // zoom from 1/1000 to 1000 scene radii away
  const nd = Math.min(Math.max(d * factor, r * 1e-3), r * 1e3);
  view.cam.eye = add(view.pivot, scale(off, nd / d));
}

// ------------------------------------------------------------------ rendering (latest request wins)

let current = null; // {seq, controller, jobId, bodyText, done, inputAt}
let seq = 0;
let scheduled = false;
let lastStart = -Infinity;

function viewSize() { return Number($("size").value) || 256; }

function sizeViewport() {
  const px = `${viewSize()}px`;
  for (const id of ["viewport", "compare-view"]) {
    $(id).style.width = px;
  }
  $("viewport").style.height = px;
}

function bakeParams() {
  if (bake.params) return bake.params;
  return { ldc_resolution: Number($("bake-res").value), llf: $("bake-llf").value,
           indirect: { mode: $("bake-indirect").value } };
}

// "Ask by error / time": a quality contract instead of a method (the planner picks it from the
// scene's calibration); null when asking by method.
function currentQuality() {
  const ask = $("ask").value;
  return ask === "method" ? null : qualityFor(ask, $("target").value);
}

// The quality contract of an "ask by" control: `ask` "error" (target in per cent) or "time" (ms).
// A time budget nothing meets still renders the closest setting, marked; an error target is strict.
function qualityFor(ask, targetText) {
  const t = Number(targetText);
  return ask === "error" ? { max_error: t / 100 } : { max_ms: t, on_miss: "best_effort" };
}

function askChanged(render = true) {
  const ask = $("ask").value;
  const byMethod = ask === "method";
  $("target-label").hidden = byMethod;
  $("method-label").hidden = !byMethod;
  $("spp-label").hidden = !byMethod;
  if (!byMethod) {
    $("k-label").hidden = true;
    $("aa-label").hidden = true;
    $("glossy-label").hidden = true;
    $("target-unit").textContent = ask === "error" ? "max error %" : "max ms";
    if (ask === "time" && Number($("target").value) < 20) $("target").value = "200";
    if (ask === "error" && Number($("target").value) > 50) $("target").value = "5";
  } else {
    $("contract").hidden = true;
    methodChanged(false);
  }
  if (render) changed();
}

function requestBody(explicit = null) {
  const method = explicit || currentMethod();
  const size = viewSize();
  const quality = explicit ? null : currentQuality(); // an explicit method (the compare view's reference) is not planned
  if (quality) {
    const c = { ...view.cam, width: size, height: size };
    const r6 = (v) => v.map((x) => Math.round(x * 1e6) / 1e6);
    c.eye = r6(c.eye); c.look_at = r6(c.look_at); c.up = r6(c.up);
    return { scene_id: view.scene.id, camera: c, quality, bake: bakeParams(), outputs: ["preview", "radiance"] };
  }
  const cam = { ...view.cam, width: size, height: size };
  const round = (v) => v.map((x) => Math.round(x * 1e6) / 1e6);
  cam.eye = round(cam.eye); cam.look_at = round(cam.look_at); cam.up = round(cam.up);
  const sppText = $("spp").value.trim();
  const spp = sppText === "" ? undefined : Number(sppText);
  const p = {};
  if (spp !== undefined) p.spp = Number.isFinite(spp) ? spp : sppText; // let the API judge it
  // Ask only for the images this page shows (the job then skips encoding the AOV EXRs): the preview,
  // the radiance (exposure and compare read it) and, for the LDC methods, the provenance overlay.
  const outputs = method.needsBake ? ["preview", "radiance", "provenance"] : ["preview", "radiance"];
  const body = { scene_id: view.scene.id, camera: cam, method: method.name, outputs };
  if (!method.needsBake) body.params = p;
  if (method.needsBake) {
    body.bake = bakeParams();
    const [s, mode] = $("aa").value.split("-");
    const v = {};
    if (Number(s) > 1) Object.assign(v, { supersample: Number(s), antialias: mode });
    // the glossy lobes: "auto" is the server's default (left out, so the artifact key stays the plain view's)
    // (with k >= 1 only: ldc+ibrt:0 traces no rays)
    if (method.hasK && !method.name.endsWith(":0") && $("glossy").value !== "auto") {
      v.glossy_rays = Number($("glossy").value);
    }
    if (Object.keys(v).length) body.view = v;
  }
  return body;
}

// Called for every camera / control change: coalesces events of one frame into one request.
function changed(inputAt = performance.now()) {
  if (!view.scene) return;
  perf.inputAt = inputAt;
  if (scheduled) return;
  scheduled = perf.scheduled = true;
  const go = () => { scheduled = perf.scheduled = false; lastStart = performance.now(); startRender(perf.inputAt); };
  const gap = MIN_REQUEST_GAP_MS - (performance.now() - lastStart);
  if (gap > 0) setTimeout(go, gap); else requestAnimationFrame(go);
}

// Cancel a superseded view's job so the worker moves on to the latest one.
function cancelStale(req) {
  if (!req.jobId || req.done || req.canceled) return;
  if (current && current.bodyText === req.bodyText) return; // the same job may serve the new request
  req.canceled = true;
  cancelJob(req.jobId);
}

function startRender(inputAt) {
  const body = requestBody();
  const bodyText = JSON.stringify(body);
  const prev = current;
  if (prev) {
    if (prev.bodyText === bodyText && !prev.done) return; // the same view is already on its way
    prev.controller.abort();
  }
  const me = { seq: ++seq, controller: new AbortController(), jobId: null, bodyText, done: false, inputAt, body,
    label: `${sceneLabel(view.scene)} · ${body.quality ? "contract" : body.method} view` };
  current = me;
  $("no-bake").hidden = true; // shown again if this view has no bake either
  if (prev) cancelStale(prev);
  stopCompare();
  perf.requests += 1;
  render(me, body).catch((err) => {
    if (me.controller.signal.aborted && me.jobId) cancelStale(me);
    if (isAbort(err) || me !== current) return;
    me.done = true;
    setStatus("");
    $("render-progress").hidden = true;
    if (err instanceof ApiError && body.quality) {
      $("contract").hidden = true;
      if (err.problem && err.problem.type === "urn:ibr:problem:calibration-missing") {
        err.problem.hint = "Asking by error or time plans from a calibration of the scene's bake: calibrate it "
          + `(POST /v1/scenes/${view.scene.id}/calibrations, or 'ibr calibrate'), or ask by method.`;
      }
      clearView();
    } else if (err instanceof ApiError && err.status === 409 && body.bake) {
      err.problem.hint = caps.bakes ? "Press Bake below (or pick a finished bake) before rendering with an LDC method."
        : "";
      // the image shown (another scene's, or another method's) is not this view: never leave it up
      clearView();
      showNoBake(body.method);
    }
    showError(err);
  });
}

// Empty the view: no image, no overlays, no numbers of a render that is not the one asked for.
function clearView() {
  const img = $("view");
  if (img.dataset.blobUrl) URL.revokeObjectURL(img.dataset.blobUrl);
  img.removeAttribute("src");
  delete img.dataset.blobUrl;
  delete img.dataset.key;
  view.manifest = null;
  provenanceKey = null;
  $("provenance-img").hidden = true;
  $("no-bake").hidden = true;
  stopCompare();
  $("compare-img").removeAttribute("src");
  $("lrms").textContent = "";
  $("compare-caption").textContent = "";
  fillTable($("timings"), []);
  fillTable($("counts"), []);
}

function showNoBake(method) {
  if (!view.scene) return;
  $("no-bake-text").textContent = `${sceneLabel(view.scene)} has no bake for ${method} yet.`;
  $("no-bake-text").title = "No bake of this scene with the bake settings below: an LDC method has nothing to render from.";
  $("no-bake-go").hidden = !caps.bakes;
  $("no-bake").hidden = false;
}

function setStatus(text) { $("view-status").textContent = text; }

function showProgress(job) {
  const pr = job.progress || {};
  $("render-progress").hidden = false;
  $("render-bar").value = pr.fraction || 0;
  const eta = pr.eta_s != null ? `, ~${pr.eta_s.toFixed(1)} s left` : "";
  $("render-stage").textContent = `${job.state}${pr.stage ? ` · ${pr.stage}` : ""} ${Math.round((pr.fraction || 0) * 100)}%${eta}`;
}

function imagePath(key) {
  const ev = Number($("exposure").value);
  return ev === 0 ? `/v1/artifacts/${key}/image.png` : `/v1/preview/artifacts/${key}/image.png?exposure=${ev}`;
}

async function render(me, body) {
  const { signal } = me.controller;
  const t0 = performance.now();
  setStatus("rendering…");
  // The POST is short (wait <= 0.25 s) and not aborted: its answer names the job, which is
  // canceled when a newer view superseded this one meanwhile.
  const { manifest, answer: r } = await runToArtifact(me, "/v1/renders", body, "/v1/artifacts", signal, showProgress);
  const url = await fetchBlobUrl(imagePath(manifest.key), signal);
  if (me !== current) { URL.revokeObjectURL(url); return; } // a newer request owns the view
  me.done = true;
  view.manifest = manifest;
  $("render-progress").hidden = true;
  $("no-bake").hidden = true;
  showError(null);
  showTimings(manifest, r.job, r.status, performance.now() - t0);
  await showBlob($("view"), url, manifest.key);
  if (me !== current) return;
  const now = performance.now();
  perf.loads += 1;
  const timings = { ...((manifest.result && manifest.result.timings) || {}),
    ...((r.job && r.job.result && r.job.result.timings) || {}) };
  const contract = r.contract ? showContract(r.contract, manifest) : null;
  $("contract").hidden = !contract;
  perf.last = { seq: me.seq, key: manifest.key, latency: now - me.inputAt, request: now - t0, status: r.status,
    method: contract ? contract.method : body.method, camera: body.camera, scene: body.scene_id, timings,
    counts: (manifest.result && manifest.result.counts) || {}, contract };
  perf.latencies.push(now - me.inputAt);
  setStatus("");
  updateProvenanceView();
  scheduleCompare(me);
}

// The plan a quality contract got and its predicted against achieved numbers; returns what it shows.
function showContract(con, manifest) {
  const res = (manifest && manifest.result) || {};
  const wall = res.timings && res.timings.render_wall;
  const achievedMs = typeof wall === "number" ? wall * 1000 : con.achieved_ms;
  let estimated = con.estimated_error;
  if (res.contract && typeof res.contract.estimated_error === "number") estimated = res.contract.estimated_error;
  else if (con.estimated_error_source === "render" && res.adaptive && con.error_scale) {
    estimated = con.error_scale * res.adaptive.estimated_error;
  }
  const p = con.params || {};
  const v = con.view || {};
  const plan = p.max_error != null ? `${con.method} adaptive (cap ${p.spp} spp)`
    : `${con.method}${p.spp != null ? ` at ${p.spp} spp` : ""}`
      + (v.supersample > 1 ? `, ${v.supersample}×${v.supersample} samples per ${v.antialias === "uniform" ? "" : "edge "}pixel` : "");
  const pct = contractPct;
  const ms = contractMs;
  const target = contractTarget(con);
  const src = con.estimated_error_source === "render" ? "estimated by the render" : "calibrated prediction";
  const rows = [["contract", target], ["plan", plan], ["rule", con.rule],
    ["predicted", con.met ? "meets the contract" : `misses ${con.unmet.join(", ")}`],
    ["error predicted", pct(con.predicted_error)], ["error achieved", `${pct(estimated)} (${src})`],
    ["time predicted", ms(con.predicted_ms)], ["time achieved", ms(achievedMs)]];
  if (con.reason) rows.push(["note", con.reason]);
  fillTable($("contract"), rows);
  return { method: con.method, plan, rule: con.rule, met: con.met, predicted_error: con.predicted_error,
    estimated_error: estimated, estimated_error_source: con.estimated_error_source,
    predicted_ms: con.predicted_ms, achieved_ms: achievedMs };
}

// Numbers in a quality contract's table (the view's and the walkthrough's); "–": not known.
const contractPct = (x) => (typeof x === "number" ? `${(x * 100).toFixed(2)} %` : "–");
const contractMs = (x) => (typeof x === "number" ? `${x.toFixed(1)} ms` : "–");

// What a contract asked for, e.g. "error ≤ 5.00 %, time ≤ 200.0 ms"; `per` qualifies each target
// (a walkthrough's hold for every frame).
function contractTarget(con, per = "") {
  return [con.max_error != null ? `error ≤ ${contractPct(con.max_error)}${per}` : null,
    con.max_ms != null ? `time ≤ ${contractMs(con.max_ms)}${per}` : null].filter(Boolean).join(", ");
}

function showTimings(manifest, job, status, clientMs) {
  // the job's result adds the stages after the manifest was written (store, job_total)
  const timings = { ...((manifest.result && manifest.result.timings) || {}),
    ...((status !== "cached" && job && job.result && job.result.timings) || {}) };
  const rows = Object.entries(timings).filter(([, v]) => typeof v === "number").map(([k, v]) => [k, fmtMs(v)]);
  rows.push([status === "cached" ? "round trip (cached)" : "round trip (page)", `${clientMs.toFixed(0)} ms`]);
  fillTable($("timings"), rows);
  const counts = (manifest.result && manifest.result.counts) || {};
  const crows = [];
  if (typeof counts.hole_pixels === "number") crows.push(["holes", String(counts.hole_pixels)]);
  if (counts.provenance && typeof counts.provenance === "object") {
    for (const [k, v] of Object.entries(counts.provenance)) crows.push([k, String(v)]);
  }
  if (manifest.result && manifest.result.bake_key) {
    const bk = manifest.result.bake_key;
    crows.push(["bake", bk === bake.key && bake.params ? `${bakeLabel(bake.params)} (${shortId(bk)})` : shortId(bk)]);
  }
  fillTable($("counts"), crows);
}

// Exposure changes only re-encode the shown artifact: no new render.
async function reexpose() {
  if (!view.manifest) return;
  const key = view.manifest.key;
  try {
    const url = await fetchBlobUrl(imagePath(key), undefined);
    if (!view.manifest || view.manifest.key !== key) { URL.revokeObjectURL(url); return; }
    await showBlob($("view"), url, key);
    showError(null);
  } catch (err) { showError(err); }
}

// ------------------------------------------------------------------ provenance

let provenanceKey = null;

async function updateProvenanceView() {
  const on = $("provenance").checked && !$("provenance-label").hidden;
  $("provenance-legend").hidden = !on;
  const img = $("provenance-img");
  const m = view.manifest;
  const has = m && m.blobs.some((b) => b.name === "provenance.png");
  if (!on || !has) { img.hidden = true; return; }
  img.hidden = false;
  if (provenanceKey === m.key) return;
  provenanceKey = m.key;
  try {
    const url = await fetchBlobUrl(`/v1/preview/artifacts/${m.key}/provenance.png`);
    if (provenanceKey !== m.key) { URL.revokeObjectURL(url); return; }
    await showBlob(img, url, m.key);
  } catch (err) { provenanceKey = null; showError(err); }
}

// ------------------------------------------------------------------ compare with the reference renderer

let cmp = null; // {controller, jobId, done}
let cmpTimer = null;

function stopCompare() {
  clearTimeout(cmpTimer);
  cmpTimer = null;
  if (cmp) {
    cmp.controller.abort();
    if (cmp.jobId && !cmp.done) cancelJob(cmp.jobId);
    cmp = null;
  }
}

function scheduleCompare(me) {
  stopCompare();
  const mode = $("compare").value;
  $("compare-view").hidden = mode === "off";
  if (mode === "off") return;
  $("lrms").textContent = "";
  $("compare-caption").textContent = "reference: waiting for the camera to rest…";
  cmpTimer = setTimeout(() => { cmpTimer = null; runCompare(me).catch(() => {}); }, COMPARE_REST_MS);
}

async function runCompare(me) {
  if (me !== current || !view.manifest) return;
  const mode = $("compare").value;
  const c = { controller: new AbortController(), jobId: null, done: false,
    label: `${sceneLabel(view.scene)} · reference for compare` };
  cmp = c;
  const { signal } = c.controller;
  const testKey = view.manifest.key;
  const refBody = requestBody({ name: "reference", needsBake: false });
  $("compare-caption").textContent = "reference: rendering…";
  try {
    const { manifest: ref } = await runToArtifact(c, "/v1/renders", refBody, "/v1/artifacts", signal, (job) => {
      $("compare-caption").textContent = `reference: ${job.state} ${Math.round((job.progress?.fraction || 0) * 100)}%`;
    });
    c.done = true;
    const q = `test=${testKey}&ref=${ref.key}`;
    const { data: result } = await api(`/v1/preview/compare?${q}`, { signal });
    const url = await fetchBlobUrl(mode === "diff" ? `/v1/preview/compare/heatmap.png?${q}` : imagePath(ref.key),
      signal);
    if (cmp !== c) { URL.revokeObjectURL(url); return; }
    await showBlob($("compare-img"), url, ref.key);
    $("compare-caption").textContent = mode === "diff" ? "difference vs reference," : "reference,";
    $("lrms").textContent = result.lrms === null ? "LRMS ∞ (black reference)" : `LRMS ${result.lrms.toFixed(4)}`;
    $("lrms").title = `${(result.fraction_over_5pct * 100).toFixed(1)} % of pixels off by more than 5 % of the mean `
      + `reference luminance (${result.n_pixels} pixels)`;
    comparePerf.runs += 1;
    comparePerf.last = { ...result, mode, seq: me.seq };
  } catch (err) {
    if (isAbort(err) || cmp !== c) return;
    $("compare-caption").textContent = "reference: failed";
    showError(err);
  }
}

// Compare an image with its reference through the preview API (the same LRMS and difference map as
// the view's Compare): `query` names both; `refPng` is the reference as shown side by side.
async function showComparison(els, mode, query, refPng, signal) {
  const { data: result } = await api(`/v1/preview/compare?${query}`, { signal });
  const url = await fetchBlobUrl(mode === "diff" ? `/v1/preview/compare/heatmap.png?${query}` : refPng, signal);
  await showBlob(els.img, url, query);
  els.lrms.textContent = result.lrms === null ? "LRMS ∞ (black reference)" : `LRMS ${result.lrms.toFixed(4)}`;
  els.lrms.title = `${(result.fraction_over_5pct * 100).toFixed(1)} % of pixels off by more than 5 % of the mean `
    + `reference luminance (${result.n_pixels} pixels)`;
  return result;
}

// ------------------------------------------------------------------ bakes

const bake = { params: null, controller: null, key: null };

function bakeLabel(p) {
  const gi = p.indirect && p.indirect.mode === "off" ? ", no GI" : "";
  return `LDC ${p.ldc_resolution}, llf ${p.llf}${p.llf !== "never" ? ` f${p.llf_f}` : ""}${gi}`;
}

async function loadBakes() {
  const list = $("bake-list");
  if (!caps.bakes || !view.scene) { list.replaceChildren(); return []; }
  const sceneId = view.scene.id;
  try {
    const { data } = await api(`/v1/scenes/${sceneId}/bakes`);
    if (!view.scene || view.scene.id !== sceneId) return [];
    list.replaceChildren(...data.items.map((b) => {
      const li = document.createElement("li");
      const btn = document.createElement("button");
      btn.type = "button";
      btn.textContent = `${bakeLabel(b.params)} — ${b.state}${b.state === "finished" ? "" : ` ${Math.round(b.progress.fraction * 100)}%`}`;
      btn.title = `bake ${b.key}\nclick to render the LDC methods from this bake`;
      btn.dataset.key = b.key;
      btn.dataset.state = b.state;
      btn.setAttribute("aria-pressed", String(bake.key === b.key));
      btn.addEventListener("click", () => useBake(b));
      li.append(btn);
      return li;
    }));
    return data.items;
  } catch (err) {
    showError(err);
    return [];
  }
}

function useBake(b) {
  bake.params = b.params;
  bake.key = b.key;
  $("bake-res").value = String(b.params.ldc_resolution);
  $("bake-llf").value = b.params.llf;
  $("bake-indirect").value = b.params.indirect ? b.params.indirect.mode : "auto";
  for (const btn of $("bake-list").querySelectorAll("button")) btn.setAttribute("aria-pressed", String(btn.dataset.key === b.key));
  if (b.state !== "finished") followBake(b);
  if (currentMethod().needsBake) changed();
}

function nameBakeJobs(b) {
  const scene = sceneNames.get(b.scene_id) || "scene";
  nameJob(b.job?.id, `${scene} · bake ${bakeLabel(b.params)}`);
  for (const p of b.parts || []) nameJob(p.job_id, `${scene} · bake ${p.name}`);
}

function showBake(b) {
  nameBakeJobs(b);
  bakePerf.state = b.state;
  bakePerf.fraction = b.progress.fraction;
  bakePerf.key = b.key;
  $("bake-progress").hidden = false;
  $("bake-bar").value = b.state === "finished" ? 1 : b.progress.fraction;
  const pct = `${Math.round($("bake-bar").value * 100)}%`;
  const ind = b.plan && b.plan.indirect;
  const gi = !ind ? "" : ind.state === "baked" && ind.summary
    ? ` · indirect light: ${(ind.summary.rel_stderr_p95_of_chunks * 100).toFixed(1)} % noise (p95)`
    : ` · indirect light: ${ind.state}${ind.state === "skipped" ? ` (${ind.reason})` : ""}`;
  $("bake-stage").textContent = b.state === "finished" ? `done (${pct})${b.cached ? ", already baked" : ""}${gi}`
    : `${b.state} · ${b.progress.stage} ${pct}${gi}${b.error ? ` — ${b.error}` : ""}`;
  $("bake-stage").dataset.state = b.state;
  $("bake-parts").replaceChildren(...b.parts.map((p) => {
    const li = document.createElement("li");
    li.dataset.state = p.state;
    const bar = document.createElement("progress");
    bar.max = 1;
    bar.value = p.state === "finished" ? 1 : p.progress;
    const label = document.createElement("span");
    label.textContent = ` ${p.name}: ${p.state}${p.error ? ` — ${p.error}` : ""}`;
    li.append(bar, label);
    return li;
  }));
}

async function startBake() {
  if (!view.scene) return;
  bake.params = null; // the controls define the bake
  const body = bakeParams();
  $("bake").disabled = true;
  try {
    const { data: b } = await api(`/v1/scenes/${view.scene.id}/bakes`, { method: "POST", body });
    bake.params = b.params;
    bake.key = b.key;
    showError(null);
    await followBake(b);
  } catch (err) {
    if (!isAbort(err)) showError(err);
  } finally {
    $("bake").disabled = !view.scene;
  }
}

async function followBake(b) {
  bake.controller?.abort();
  const controller = new AbortController();
  bake.controller = controller;
  const sceneId = b.scene_id;
  showBake(b);
  loadBakes();
  try {
    while (!["finished", "failed", "canceled", "missing"].includes(b.state)) {
      await sleep(BAKE_POLL_MS, controller.signal);
      b = (await api(`/v1/scenes/${sceneId}/bakes/${b.key}`, { signal: controller.signal })).data;
      showBake(b);
    }
  } catch (err) {
    if (isAbort(err)) return;
    throw err;
  }
  if (view.scene) bakeBadges([view.scene]);
  if (b.state !== "finished") {
    showError(new ApiError(0, { title: "Bake failed", detail: b.error || `the bake is ${b.state}` }));
  } else if (currentMethod().needsBake && view.scene && view.scene.id === sceneId) {
    changed(); // the view this bake was waited for
  }
  loadBakes();
}

// ------------------------------------------------------------------ scenes

let sampleCameras = {};

async function loadSampleCameras() {
  try {
    const res = await fetch("/preview/sample-cameras.json");
    if (res.ok) sampleCameras = await res.json();
  } catch { /* no samples: default camera */ }
}

// Names, not hashes: the API's documents carry names; the short id is secondary text (not part of
// the button's accessible name), the full id is in the tooltip.
const shortId = (id) => String(id || "").slice(0, 8);
const sceneNames = new Map(); // scene id -> name, from the scene list
function sceneLabel(s) { return s ? s.name || sceneNames.get(s.id) || `scene ${shortId(s.id)}` : "scene"; }
function datasetLabel(d) {
  if (!d) return "dataset";
  const src = d.source || {};
  // a generated dataset's own name is "generated-<scene id>": name it by its scene instead
  if (src.kind === "generated" && (!d.name || d.name.startsWith("generated-"))) {
    return `${sceneNames.get(src.scene_id) || `scene ${shortId(src.scene_id)}`} (generated)`;
  }
  return d.name || `dataset ${shortId(d.id)}`;
}

function pickList(list, items, label, title, onPick) {
  list.replaceChildren(...items.map((s) => {
    const li = document.createElement("li");
    const b = document.createElement("button");
    b.type = "button";
    b.textContent = label(s);
    const hash = document.createElement("span");
    hash.className = "hash";
    hash.setAttribute("aria-hidden", "true");
    hash.textContent = shortId(s.id);
    b.append(hash);
    b.title = title(s);
    b.dataset.id = s.id;
    b.dataset.name = s.name;
    b.addEventListener("click", () => onPick(s));
    li.append(b);
    return li;
  }));
}

function markCurrent(id) {
  for (const b of document.querySelectorAll(".pick-list button")) b.setAttribute("aria-current", String(b.dataset.id === id));
}

async function loadScenes() {
  try {
    const { data } = await api("/v1/scenes?limit=1000");
    for (const s of data.items) sceneNames.set(s.id, s.name);
    pickList($("scene-list"), data.items, sceneLabel,
      (s) => `${s.id}\n${s.n_objects} objects, ${s.n_lights} lights`, openScene);
    for (const b of $("scene-list").querySelectorAll("button")) b.dataset.sceneId = b.dataset.id;
    $("scene-empty").hidden = data.items.length > 0;
    showError(null);
    bakeBadges(data.items);
    return data.items;
  } catch (err) {
    showError(err);
    return [];
  }
}

// "N baked" next to each scene that has finished bakes (one request per scene, two at a time).
async function bakeBadges(items) {
  if (!caps.bakes) return;
  const queue = items.slice();
  const one = async () => {
    for (let s = queue.shift(); s; s = queue.shift()) {
      let n = 0, running = 0;
      try {
        const { data } = await api(`/v1/scenes/${s.id}/bakes`);
        n = data.items.filter((b) => b.state === "finished").length;
        running = data.items.filter((b) => b.state === "queued" || b.state === "running").length;
      } catch { continue; }
      const btn = $("scene-list").querySelector(`button[data-id="${s.id}"]`);
      if (!btn) continue;
      btn.querySelector(".badge")?.remove();
      if (!n && !running) continue;
      const badge = document.createElement("span");
      badge.className = "badge";
      badge.setAttribute("aria-hidden", "true"); // the button keeps the scene name as its name
      badge.textContent = [n ? `${n} baked` : "", running ? `${running} baking` : ""].filter(Boolean).join(", ");
      btn.append(badge);
    }
  };
  await Promise.all([one(), one()]);
}

function openScene(s) {
  closeDataset();
  closeWalk();
  stopScene();
  clearView();
  view.scene = s;
  markCurrent(s.id);
  $("view-panel").hidden = false;
  $("scene-name").textContent = `— ${sceneLabel(s)}`;
  $("reset-camera").disabled = false;
  $("bake-box").hidden = !caps.bakes;
  $("bake").disabled = false;
  $("bake-progress").hidden = true;
  bake.controller?.abort();
  bake.params = null;
  bake.key = null;
  const sample = sampleCameras[s.name];
  view.bounds = null;
  setCamera(sample ? { camera: sample.camera, pivot: sample.pivot } : { camera: DEFAULT_CAMERA, pivot: null });
  // The stored document gives the scene's own camera (for scenes that are not samples) and its extent
  // (how far a drag turns); the bakes say whether the LDC methods can render now.
  const doc = api(`/v1/scenes/${s.id}/document`).then((r) => r.data).catch(() => null);
  const bakes = caps.bakes ? loadBakes() : Promise.resolve([]);
  Promise.all([doc, bakes]).then(([d, items]) => {
    if (!view.scene || view.scene.id !== s.id) return;
    if (d) {
      view.bounds = sceneBounds(d);
      if (!sample && d.camera) {
        const { width: _w, height: _h, ...camera } = d.camera;
        setCamera({ camera, pivot: null });
      }
    }
    // Render the LDC methods from a finished bake matching the controls, if there is one.
    const want = bakeParams();
    const done = items.filter((b) => b.state === "finished");
    const match = done.find((b) => b.params.ldc_resolution === want.ldc_resolution && b.params.llf === want.llf);
    if (match && !bake.key) {
      bake.params = match.params;
      bake.key = match.key;
      loadBakes();
    }
    changed();
  });
}

// ------------------------------------------------------------------ datasets and relighting

const DEG = Math.PI / 180;
const ds = {
  dataset: null, center: [0, 0, 0], front: [0, 0, 1], up: [0, 1, 0], dist0: 1, int0: 1, distant: false,
  lights: [], sel: 0, baked: false, dirs: [], controller: null,
};
let relightCur = null;
let relightSeq = 0;
let relightScheduled = false;
let relightLastStart = -Infinity;

async function loadDatasets() {
  if (!(caps.datasets && caps.relights)) return [];
  try {
    const { data } = await api("/v1/datasets?limit=1000");
    pickList($("dataset-list"), data.items, datasetLabel,
      (d) => `${d.id}\n${d.n_images} images, ${d.width} x ${d.height}${d.distant ? ", distant lights" : ""}`,
      openDataset);
    $("dataset-empty").hidden = data.items.length > 0;
    return data.items;
  } catch (err) {
    showError(err);
    return [];
  }
}

function closeDataset() {
  ds.controller?.abort();
  relightCur?.controller.abort();
  stopRelightCompare();
  ds.dataset = null;
  $("relight-panel").hidden = true;
  $("coverage-warning").hidden = true;
}

function cameraEye(cam) {
  if (!cam) return null;
  if (Array.isArray(cam.eye)) return cam.eye;
  if (Array.isArray(cam.world_from_camera)) return cam.world_from_camera.slice(0, 3).map((row) => row[3]);
  return null;
}

// The widget looks at the sphere from the dataset's camera: azimuth 0 = toward the camera.
function dirOf(az, el) {
  const right = norm(cross(ds.up, ds.front));
  const h = add(scale(ds.front, Math.cos(az * DEG)), scale(right, Math.sin(az * DEG)));
  return norm(add(scale(h, Math.cos(el * DEG)), scale(ds.up, Math.sin(el * DEG))));
}

function azElOf(d) {
  const right = norm(cross(ds.up, ds.front));
  return [Math.atan2(dot(d, right), dot(d, ds.front)) / DEG, Math.asin(Math.max(-1, Math.min(1, dot(d, ds.up)))) / DEG];
}

async function openDataset(d) {
  stopScene();
  closeWalk();
  ds.controller?.abort();
  const controller = new AbortController();
  ds.controller = controller;
  ds.dataset = d;
  ds.baked = false;
  markCurrent(d.id);
  $("view-panel").hidden = true;
  $("relight-panel").hidden = false;
  $("dataset-name").textContent = `— ${datasetLabel(d)}`;
  const gt = hasGroundTruth(d);
  $("relight-compare").disabled = !gt;
  if (!gt) $("relight-compare").value = "off";
  $("relight-compare").title = gt ? "" : "This dataset was uploaded, not generated from a scene: it has no ground truth.";
  $("relight-compare-view").hidden = true;
  $("relight-compare-img").removeAttribute("src");
  const man = d.manifest;
  const positions = man.images.map((im) => im.position).filter(Boolean);
  const directions = man.images.map((im) => im.direction).filter(Boolean);
  ds.distant = d.distant;
  ds.center = man.sphere_center || (positions.length ? scale(positions.reduce(add, [0, 0, 0]), 1 / positions.length) : [0, 0, 0]);
  const eye = cameraEye(man.camera);
  ds.up = [0, 1, 0];
  let front = eye ? sub(eye, ds.center) : [0, 0, 1];
  front = sub(front, scale(ds.up, dot(front, ds.up)));
  ds.front = len(front) > 1e-9 ? norm(front) : [0, 0, 1];
  const dists = positions.map((p) => len(sub(p, ds.center))).sort((a, b) => a - b);
  ds.dist0 = dists.length ? dists[dists.length >> 1] : 1;
  const ints = man.images.map((im) => (Array.isArray(im.intensity) ? im.intensity[0] : im.intensity)).filter((v) => v > 0);
  ds.int0 = ints.length ? ints.sort((a, b) => a - b)[ints.length >> 1] : 1;
  // the dataset's own light directions, drawn on the sphere: the coverage the relighting can use
  ds.dirs = positions.length ? positions.map((p) => norm(sub(p, ds.center))) : directions.map((v) => norm(scale(v, -1)));
  $("light-dist-label").hidden = ds.distant;
  ds.lights = [{ az: 30, el: 30, dist: 0, int: 0 }];
  ds.sel = 0;
  syncLightControls();
  drawSphere();
  $("relight-status").textContent = "baking the dataset…";
  try {
    await bakeDataset(d, controller.signal);
  } catch (err) {
    if (!isAbort(err)) { $("relight-status").textContent = ""; showError(err); }
    return;
  }
  ds.baked = true;
  relightChanged();
}

async function bakeDataset(d, signal) {
  const req = { jobId: null, label: `${datasetLabel(d)} · dataset bake` };
  $("dbake-progress").hidden = false;
  const show = (job) => {
    const f = job.state === "finished" ? 1 : job.progress?.fraction || 0;
    $("dbake-bar").value = f;
    $("dbake-stage").textContent = `dataset bake: ${job.state} ${job.progress?.stage || ""} ${Math.round(f * 100)}%`;
  };
  await runToArtifact(req, `/v1/datasets/${d.id}/bake`, {}, "/v1/artifacts", signal, show);
  $("dbake-bar").value = 1;
  $("dbake-stage").textContent = "dataset bake: done";
}

function syncLightControls() {
  const l = ds.lights[ds.sel];
  $("light-az").value = String(Math.round(l.az));
  $("light-el").value = String(Math.round(l.el));
  $("light-dist").value = String(l.dist);
  $("light-int").value = String(l.int);
  $("light-dist-out").textContent = (ds.dist0 * 2 ** l.dist).toPrecision(3);
  $("light-int-out").textContent = (ds.int0 * 2 ** l.int).toPrecision(3);
  $("light-list").replaceChildren(...ds.lights.map((li, i) => {
    const item = document.createElement("li");
    const b = document.createElement("button");
    b.type = "button";
    b.textContent = `light ${i + 1}: ${Math.round(li.az)}°, ${Math.round(li.el)}°`;
    b.setAttribute("aria-pressed", String(i === ds.sel));
    b.addEventListener("click", () => { ds.sel = i; syncLightControls(); drawSphere(); });
    item.append(b);
    if (ds.lights.length > 1) {
      const x = document.createElement("button");
      x.type = "button";
      x.textContent = "×";
      x.title = `remove light ${i + 1}`;
      x.setAttribute("aria-label", `remove light ${i + 1}`);
      x.addEventListener("click", () => {
        ds.lights.splice(i, 1);
        ds.sel = Math.min(ds.sel, ds.lights.length - 1);
        syncLightControls(); drawSphere(); relightChanged();
      });
      item.append(x);
    }
    return item;
  }));
}

function drawSphere() {
  const c = $("light-sphere");
  const g = c.getContext("2d");
  const W = c.width, R = W / 2 - 8, cx = W / 2, cy = W / 2;
  const img = g.createImageData(W, W);
  const lightDirs = ds.lights.map((l) => dirOf(l.az, l.el));
  const right = norm(cross(ds.up, ds.front));
  for (let y = 0; y < W; y++) {
    for (let x = 0; x < W; x++) {
      const nx = (x + 0.5 - cx) / R, ny = (cy - y - 0.5) / R;
      const r2 = nx * nx + ny * ny;
      const o = 4 * (y * W + x);
      if (r2 > 1) { img.data[o + 3] = 0; continue; }
      const n = add(add(scale(right, nx), scale(ds.up, ny)), scale(ds.front, Math.sqrt(1 - r2)));
      let s = 0.08;
      for (const d of lightDirs) s += Math.max(0, dot(n, d)) / lightDirs.length;
      const v = Math.round(255 * Math.min(1, s) ** (1 / 2.2));
      img.data[o] = v; img.data[o + 1] = v; img.data[o + 2] = Math.min(255, v + 12); img.data[o + 3] = 255;
    }
  }
  g.clearRect(0, 0, W, W);
  g.putImageData(img, 0, 0);
  const proj = (d) => [cx + R * dot(d, right), cy - R * dot(d, ds.up), dot(d, ds.front) >= 0];
  g.fillStyle = "rgba(255,193,7,.55)";
  for (const d of ds.dirs) {
    const [x, y, front] = proj(d);
    if (front) g.fillRect(x - 1, y - 1, 2, 2);
  }
  ds.lights.forEach((l, i) => {
    const [x, y, front] = proj(dirOf(l.az, l.el));
    g.beginPath();
    g.arc(x, y, i === ds.sel ? 7 : 5, 0, 2 * Math.PI);
    g.lineWidth = 2;
    g.strokeStyle = i === ds.sel ? "#e53935" : "#fb8c00";
    g.fillStyle = front ? g.strokeStyle : "transparent";
    g.fill();
    g.stroke();
  });
}

function lightsBody() {
  return ds.lights.map((l) => {
    const d = dirOf(l.az, l.el);
    const v = ds.int0 * 2 ** l.int;
    const round = (a) => a.map((x) => Math.round(x * 1e6) / 1e6);
    if (ds.distant) return { type: "directional", direction: round(scale(d, -1)), irradiance: [v, v, v] };
    return { type: "point", position: round(add(ds.center, scale(d, ds.dist0 * 2 ** l.dist))), intensity: [v, v, v] };
  });
}

function relightChanged(inputAt = performance.now()) {
  if (!ds.dataset || !ds.baked) return;
  relightPerf.inputAt = inputAt;
  if (relightScheduled) return;
  relightScheduled = relightPerf.scheduled = true;
  const go = () => {
    relightScheduled = relightPerf.scheduled = false;
    relightLastStart = performance.now();
    startRelight(relightPerf.inputAt);
  };
  const gap = MIN_REQUEST_GAP_MS - (performance.now() - relightLastStart);
  if (gap > 0) setTimeout(go, gap); else requestAnimationFrame(go);
}

function startRelight(inputAt) {
  const body = { dataset_id: ds.dataset.id, lights: lightsBody(), exposure_stops: Number($("relight-exposure").value) };
  const bodyText = JSON.stringify(body);
  const prev = relightCur;
  if (prev) {
    if (prev.bodyText === bodyText && !prev.done) return;
    prev.controller.abort();
    if (prev.jobId && !prev.done) cancelJob(prev.jobId);
  }
  const me = { seq: ++relightSeq, controller: new AbortController(), jobId: null, bodyText, done: false, inputAt,
    label: `${datasetLabel(ds.dataset)} · relight` };
  relightCur = me;
  relightPerf.requests += 1;
  stopRelightCompare();
  relight(me, body).catch((err) => {
    if (me.controller.signal.aborted && me.jobId && !me.done) cancelJob(me.jobId);
    if (isAbort(err) || me !== relightCur) return;
    me.done = true;
    $("relight-status").textContent = "";
    showError(err);
  });
}

async function relight(me, body) {
  const { signal } = me.controller;
  const t0 = performance.now();
  $("relight-status").textContent = "relighting…";
  const { manifest, answer: r } = await runToArtifact(me, "/v1/relights", body, "/v1/relights", signal, (job) => {
    $("relight-status").textContent = `relighting… ${Math.round((job.progress?.fraction || 0) * 100)}%`;
  });
  const url = await fetchBlobUrl(`/v1/relights/${manifest.key}/image.png`, signal);
  if (me !== relightCur) { URL.revokeObjectURL(url); return; }
  me.done = true;
  await showBlob($("relit"), url, manifest.key);
  if (me !== relightCur) return;
  const now = performance.now();
  relightPerf.loads += 1;
  relightPerf.last = { seq: me.seq, key: manifest.key, latency: now - me.inputAt, status: r.status,
    counts: manifest.result?.counts || {}, lights: body.lights };
  $("relight-status").textContent = "";
  showError(null);
  const timings = { ...(manifest.result?.timings || {}), ...((r.status !== "cached" && r.job?.result?.timings) || {}) };
  const rows = Object.entries(timings).filter(([, v]) => typeof v === "number").map(([k, v]) => [k, fmtMs(v)]);
  rows.push(["round trip (page)", `${(now - t0).toFixed(0)} ms`]);
  const counts = manifest.result?.counts || {};
  for (const [k, v] of Object.entries(counts)) if (typeof v === "number") rows.push([k, String(v)]);
  fillTable($("relight-stats"), rows);
  showCoverageWarning(counts, body.lights.length);
  updateCoverage();
  scheduleRelightCompare();
}

// counts.n_outside: pixels where some light's direction fell outside the dataset's coverage (that
// light adds nothing there; the relighting never extrapolates). Said in words, not only in the table.
function showCoverageWarning(counts, nLights) {
  const n = Number(counts.n_outside) || 0;
  $("coverage-warning").hidden = n === 0;
  if (!n) return;
  const total = (Number(counts.width) || 0) * (Number(counts.height) || 0);
  const pct = total ? ` (${(100 * n / total).toFixed(n / total < 0.001 ? 2 : 1)} % of the image)` : "";
  const which = nLights > 1 ? "at least one of the lights" : "the light";
  $("coverage-warning-text").textContent = `Outside the dataset's coverage: ${n} pixels${pct} get no light from `
    + `${which}, which comes from a direction the dataset was not lit from (nothing is extrapolated there).`;
  $("coverage-show").hidden = $("coverage").checked;
}

// ---- relit image vs ground truth (datasets generated from a scene)

let relightCmp = null; // {controller, jobId, done}
let relightCmpTimer = null;
const relightCmpEls = () => ({ img: $("relight-compare-img"), lrms: $("relight-lrms") });

function stopRelightCompare() {
  clearTimeout(relightCmpTimer);
  relightCmpTimer = null;
  if (relightCmp) {
    relightCmp.controller.abort();
    if (relightCmp.jobId && !relightCmp.done) cancelJob(relightCmp.jobId);
    relightCmp = null;
  }
}

function hasGroundTruth(d) {
  return Boolean(d && d.source && d.source.kind === "generated" && d.source.generation_key && d.source.scene_id);
}

function scheduleRelightCompare() {
  stopRelightCompare();
  const mode = $("relight-compare").value;
  $("relight-compare-view").hidden = mode === "off";
  if (mode === "off" || !relightCur || !relightCur.done || !relightPerf.last) return;
  $("relight-lrms").textContent = "";
  $("relight-compare-caption").textContent = "ground truth: waiting for the lights to rest…";
  const me = relightCur;
  relightCmpTimer = setTimeout(() => { relightCmpTimer = null; runRelightCompare(me).catch(() => {}); },
    COMPARE_REST_MS);
}

async function runRelightCompare(me) {
  if (me !== relightCur || !hasGroundTruth(ds.dataset)) return;
  const mode = $("relight-compare").value;
  const c = { controller: new AbortController(), jobId: null, done: false,
    label: `${datasetLabel(ds.dataset)} · ground truth` };
  relightCmp = c;
  const { signal } = c.controller;
  const relitKey = relightPerf.last.key;
  const lights = relightPerf.last.lights;
  const src = ds.dataset.source;
  const caption = $("relight-compare-caption");
  caption.textContent = "ground truth: rendering…";
  try {
    // the generation that made this dataset, asked again with these lights as its ground truth: the API
    // reuses the stored dataset and renders only the scene under each light
    if (!ds.generation || ds.generation.key !== src.generation_key) {
      const { data: m } = await api(`/v1/datasets/generations/${src.generation_key}`, { signal });
      ds.generation = { key: src.generation_key, params: m.params };
    }
    const body = { ...ds.generation.params, scene_id: src.scene_id, ground_truth: lights };
    const { manifest: gen } = await runToArtifact(c, "/v1/datasets/generate", body, "/v1/datasets/generations", signal,
      (job) => { caption.textContent = `ground truth: ${job.state} ${Math.round((job.progress?.fraction || 0) * 100)}%`; });
    c.done = true;
    const query = `test=${relitKey}&test_kind=relight&ref=${gen.key}&ref_kind=ground_truth`;
    const ev = Number($("relight-exposure").value);
    const result = await showComparison(relightCmpEls(), mode, query,
      `/v1/preview/reference.png?ref=${gen.key}&ref_kind=ground_truth&exposure=${ev}`, signal);
    if (relightCmp !== c) return;
    caption.textContent = mode === "diff" ? "difference vs ground truth," : "ground truth,";
    relightComparePerf.runs += 1;
    relightComparePerf.last = { ...result, mode, seq: me.seq, relight: relitKey, generation: gen.key };
  } catch (err) {
    if (isAbort(err) || relightCmp !== c) return;
    caption.textContent = "ground truth: failed";
    showError(err);
  }
}

let coverageKey = null;

// outside.png is white where a light fell outside the coverage: drawn as a magenta overlay.
async function updateCoverage() {
  const img = $("coverage-img");
  const canvas = $("coverage-mask");
  const key = $("relit").dataset.key;
  if (!$("coverage").checked || !key) { canvas.hidden = true; return; }
  canvas.hidden = false;
  if (coverageKey === key) return;
  coverageKey = key;
  try {
    const url = await fetchBlobUrl(`/v1/relights/${key}/outside.png`);
    if (coverageKey !== key) { URL.revokeObjectURL(url); return; }
    await showBlob(img, url, key);
    canvas.width = img.naturalWidth;
    canvas.height = img.naturalHeight;
    const g = canvas.getContext("2d");
    g.drawImage(img, 0, 0);
    const px = g.getImageData(0, 0, canvas.width, canvas.height);
    let n = 0;
    for (let i = 0; i < px.data.length; i += 4) {
      const on = px.data[i] > 127;
      n += on;
      px.data[i] = 233; px.data[i + 1] = 30; px.data[i + 2] = 99; px.data[i + 3] = on ? 170 : 0;
    }
    g.putImageData(px, 0, 0);
    canvas.dataset.key = key;
    canvas.dataset.outside = String(n);
  } catch (err) { coverageKey = null; showError(err); }
}

function bindSphere() {
  const c = $("light-sphere");
  let dragging = false;
  const setFrom = (e) => {
    const r = c.getBoundingClientRect();
    const R = c.width / 2 - 8;
    let nx = (e.clientX - r.left - r.width / 2) / R * (c.width / r.width);
    let ny = (r.top + r.height / 2 - e.clientY) / R * (c.height / r.height);
    const m = Math.hypot(nx, ny);
    if (m > 1) { nx /= m; ny /= m; }
    const z = Math.sqrt(Math.max(0, 1 - nx * nx - ny * ny)) * (e.shiftKey ? -1 : 1);
    const right = norm(cross(ds.up, ds.front));
    const d = add(add(scale(right, nx), scale(ds.up, ny)), scale(ds.front, z));
    const [az, el] = azElOf(norm(d));
    const l = ds.lights[ds.sel];
    l.az = az; l.el = el;
    syncLightControls();
    drawSphere();
    relightChanged(performance.now());
  };
  c.addEventListener("pointerdown", (e) => {
    if (!ds.dataset) return;
    dragging = true;
    c.setPointerCapture(e.pointerId);
    c.focus();
    setFrom(e);
    e.preventDefault();
  });
  c.addEventListener("pointermove", (e) => { if (dragging) setFrom(e); });
  const end = (e) => { dragging = false; if (c.hasPointerCapture(e.pointerId)) c.releasePointerCapture(e.pointerId); };
  c.addEventListener("pointerup", end);
  c.addEventListener("pointercancel", end);
  c.addEventListener("keydown", (e) => {
    if (!ds.dataset) return;
    const l = ds.lights[ds.sel];
    const steps = { ArrowLeft: [-5, 0], ArrowRight: [5, 0], ArrowUp: [0, 5], ArrowDown: [0, -5] };
    const s = steps[e.key];
    if (!s) return;
    e.preventDefault();
    l.az = ((l.az + s[0] + 540) % 360) - 180;
    l.el = Math.max(-90, Math.min(90, l.el + s[1]));
    syncLightControls();
    drawSphere();
    relightChanged(performance.now());
  });
  const numeric = (id, field, lo, hi) => $(id).addEventListener("change", () => {
    const v = Number($(id).value);
    if (!Number.isFinite(v)) return;
    ds.lights[ds.sel][field] = Math.max(lo, Math.min(hi, v));
    syncLightControls(); drawSphere(); relightChanged();
  });
  numeric("light-az", "az", -180, 180);
  numeric("light-el", "el", -90, 90);
  for (const [id, field] of [["light-dist", "dist"], ["light-int", "int"]]) {
    $(id).addEventListener("input", () => {
      ds.lights[ds.sel][field] = Number($(id).value);
      syncLightControls(); drawSphere(); relightChanged();
    });
  }
  $("relight-exposure").addEventListener("input", () => {
    $("relight-exposure-out").textContent = fmtEv(Number($("relight-exposure").value));
    relightChanged();
  });
  $("add-light").addEventListener("click", () => {
    const l = ds.lights[ds.sel];
    ds.lights.push({ az: ((l.az + 60 + 540) % 360) - 180, el: l.el, dist: l.dist, int: l.int });
    ds.sel = ds.lights.length - 1;
    syncLightControls(); drawSphere(); relightChanged();
  });
  $("relight-compare").addEventListener("change", () => scheduleRelightCompare());
  $("coverage").addEventListener("change", () => { $("coverage-show").hidden = $("coverage").checked; updateCoverage(); });
  $("coverage-show").addEventListener("click", () => {
    $("coverage").checked = true;
    $("coverage-show").hidden = true;
    updateCoverage();
  });
  $("reload-datasets").addEventListener("click", () => loadDatasets());
}

function stopScene() {
  current?.controller.abort();
  if (current && current.jobId && !current.done) cancelJob(current.jobId);
  stopCompare();
  view.scene = null;
  $("view-panel").hidden = true;
}

// ------------------------------------------------------------------ walkthroughs

const walk = { scene: null, info: null, key: null, urls: [], timer: null, controller: null, index: 0, request: null };

function walkScenes(scenes) {
  return scenes.filter((s) => sampleCameras[s.name] && sampleCameras[s.name].view_space);
}

function loadWalkList(scenes) {
  if (!caps.walkthroughs) return;
  const items = walkScenes(scenes);
  pickList($("walk-list"), items, (s) => s.name, (s) => `${s.id}\nview space: ${sampleCameras[s.name].view_space.type}`,
    openWalk);
  for (const b of $("walk-list").querySelectorAll("button")) b.dataset.id = `walk-${b.dataset.id}`;
  $("walk-empty").hidden = items.length > 0;
}

function closeWalk() {
  stopWalk();
  stopWalkCalibration();
  walk.scene = null;
  $("walk-panel").hidden = true;
}

function stopWalk() {
  stopWalkCompare();
  $("wt-compare-view").hidden = true;
  walk.controller?.abort();
  walk.controller = null;
  clearInterval(walk.timer);
  walk.timer = null;
  $("wt-play").textContent = "Play";
  for (const u of walk.urls) URL.revokeObjectURL(u);
  walk.urls = [];
}

function openWalk(s) {
  stopScene();
  closeDataset();
  stopWalk();
  stopWalkCalibration(); // another scene: its calibration (if any) is not this one's
  hideWalkNote();
  $("wt-contract").hidden = true;
  walk.scene = s;
  walk.info = sampleCameras[s.name];
  markCurrent(`walk-${s.id}`);
  $("walk-panel").hidden = false;
  $("walk-name").textContent = `— ${s.name}`;
  $("wt-progress").hidden = true;
  $("wt-player").hidden = true;
  const vs = walk.info.view_space;
  const anim = walk.info.animation;
  const how = { path: "along the view-space path", box: "across the view-space box",
    polygon: "looking around from the camera's position in the view-space polygon" }[vs.type] || vs.type;
  $("walk-path-desc").textContent = `Camera path: ${how}` +
    (anim ? `; time ${anim.start} → ${anim.end}.` : "; the scene is static.");
}

const lerp3 = (a, b, t) => [0, 1, 2].map((k) => a[k] + (b[k] - a[k]) * t);

// Eye (and target) of frame i of n, inside the scene's view space.
function walkCamera(info, i, n) {
  const cam = info.camera;
  const vs = info.view_space;
  const t = n > 1 ? i / (n - 1) : 0;
  let eye = cam.eye, target = cam.look_at;
  if (vs.type === "path") {
    const pts = vs.points;
    const seg = pts.slice(1).map((p, k) => len(sub(p, pts[k])));
    const total = seg.reduce((a, b) => a + b, 0);
    let d = t * total, k = 0;
    while (k < seg.length - 1 && d > seg[k]) { d -= seg[k]; k += 1; }
    eye = lerp3(pts[k], pts[k + 1], seg[k] > 0 ? Math.min(1, d / seg[k]) : 0);
  } else if (vs.type === "box") {
    const span = sub(vs.max, vs.min);
    const axis = Math.abs(span[0]) >= Math.abs(span[2]) ? 0 : 2;
    const c = lerp3(vs.min, vs.max, 0.5);
    c[axis] = vs.min[axis] + span[axis] * (0.1 + 0.8 * t);
    eye = c;
  } else if (vs.type === "polygon") {
    eye = [cam.eye[0], vs.eye_height, cam.eye[2]];
    const d0 = sub(cam.look_at, cam.eye);
    target = add(eye, rotate(d0, [0, 1, 0], (t - 0.5) * Math.PI / 3));
  }
  return { eye, target };
}

function walkRequest() {
  const info = walk.info;
  const n = Number($("wt-frames").value);
  const w = Number($("wt-size").value);
  const aspect = info.camera.height && info.camera.width ? info.camera.height / info.camera.width : 0.75;
  const h = Math.max(2, 2 * Math.round((w * aspect) / 2));
  const anim = info.animation;
  const frames = [];
  for (let i = 0; i < n; i++) {
    const { eye, target } = walkCamera(info, i, n);
    const round = (v) => v.map((x) => Math.round(x * 1e6) / 1e6);
    frames.push({
      time: anim ? anim.start + (anim.end - anim.start) * (n > 1 ? i / (n - 1) : 0) : 0,
      camera: { type: "perspective", eye: round(eye), look_at: round(target), up: info.camera.up || [0, 1, 0],
        fov_y_deg: info.camera.fov_y_deg || 60, width: w, height: h },
    });
  }
  const choice = $("wt-quality").value;
  const bake = { quality: choice };
  for (const [param, field] of [["wt_face", "face_res"], ["wt_views", "max_views"], ["wt_times", "max_time_samples"],
    ["wt_indirect", "indirect_samples"]]) {
    if (params.get(param) !== null) bake[field] = Number(params.get(param));
  }
  const fpsText = $("wt-fps").value.trim();
  const request = { scene_id: walk.scene.id, frames, chunk_frames: 8,
    fps: Number.isFinite(Number(fpsText)) && fpsText !== "" ? Number(fpsText) : fpsText };
  const quality = walkQuality();
  // asked by error or time, the planner picks the bake preset and the fill: naming them too is a 422
  if (quality) return { ...request, quality };
  if (choice.startsWith(PATH_PREFIX)) {  // every frame path-traced: no bake and no fill to name
    return { ...request, path_traced: { noise: Number(choice.slice(PATH_PREFIX.length)) } };
  }
  return { ...request, bake, fill: $("wt-fill").value };
}

// A walkthrough setting that path-traces every frame: its option's value is this prefix and the noise.
const PATH_PREFIX = "path:";

function walkQualityChanged() {
  // path-traced frames fill no holes: the fill does not apply to them
  $("wt-fill").disabled = $("wt-quality").value.startsWith(PATH_PREFIX);
}

// ---- asking a walkthrough by error or by time (a quality contract instead of a preset and a fill)

// Each kind of target keeps its own value: a per cent is no time budget. Error: every frame's LRMS
// against its converged frame, in per cent; time: every frame's render time in the worker, in ms.
const walkTargets = { error: "20", time: "50" };
let walkAskShown = "settings"; // the ask whose target the input holds

function walkQuality() {
  const ask = $("wt-ask").value;
  return ask === "settings" ? null : qualityFor(ask, $("wt-target").value);
}

function walkAskChanged() {
  const ask = $("wt-ask").value;
  if (walkAskShown !== "settings") walkTargets[walkAskShown] = $("wt-target").value;
  walkAskShown = ask;
  const bySettings = ask === "settings";
  $("wt-target-label").hidden = bySettings;
  $("wt-quality-label").hidden = !bySettings;
  $("wt-fill-label").hidden = !bySettings;
  if (bySettings) {
    // a plan and a contract's problem belong to the contract asked: none is asked now
    $("wt-contract").hidden = true;
    hideWalkNote();
    return;
  }
  $("wt-target").value = walkTargets[ask];
  $("wt-target-unit").textContent = ask === "error" ? "max error % per frame" : "max ms per frame";
  $("wt-target-label").title = ask === "error"
    ? "Largest error of every frame: LRMS against its converged frame, in per cent (the planner picks the cheapest "
      + "bake preset and fill predicted to stay under it; none: the panel says what the scene can do)"
    : "Largest render time of every frame in the worker, in milliseconds (the planner picks the most accurate "
      + "setting predicted within it; none: the fastest, marked as missing the budget)";
}

// The plan a walkthrough's quality contract got: the setting, the rule, the predictions and, once
// every frame is rendered, the frames' achieved render times. A walkthrough renders no converged
// frames: its error is the calibration's prediction, and path-traced frames' own estimates.
function showWalkContract(con, status) {
  const achieved = con.achieved_frame_ms;
  const rows = [
    ["contract", contractTarget(con, " per frame") + (con.on_miss === "best_effort" ? " (best effort)" : "")],
    ["plan", con.path_noise != null
      ? `path-traced frames (noise ${con.path_noise}, no bake)` : `bake preset ${con.preset}, fill ${con.fill}`],
    ["rule", con.rule],
    ["predicted", con.met ? "meets the contract" : `misses ${con.unmet.join(", ")}`],
    ["error predicted", `${contractPct(con.predicted_error)} (the calibration's worst probe frame)`],
    ["error achieved", con.achieved_estimated_error
      ? `estimated by the frames: median ${contractPct(con.achieved_estimated_error.median)}, `
        + `max ${contractPct(con.achieved_estimated_error.max)}`
      : con.path_noise != null && status !== "finished" ? "estimated by each frame once every frame is rendered"
        : "not measured (a walkthrough renders no converged frames)"],
    ["time predicted", `${contractMs(con.predicted_frame_ms)} per frame`],
    ["time achieved", achieved ? `median ${contractMs(achieved.median)}, max ${contractMs(achieved.max)} per frame`
      : status === "finished" ? "–" : "measured once every frame is rendered"],
    ["bake", con.bake === "ready" ? "ready (in the store)" : con.bake === "none" ? "none needed"
      : `waited: made first, predicted ${(con.predicted_bake_ms / 1000).toFixed(1)} s`],
  ];
  if (con.reason) rows.push([con.met ? "note" : "reason", con.reason]);
  fillTable($("wt-contract"), rows);
  $("wt-contract").hidden = false;
  walkPerf.contract = con;
}

// The panel's note: `parts` are strings and {code} (shown as code); `calibrate` shows the button
// that makes a walkthrough calibration.
function showWalkNote(parts, calibrate = false) {
  $("wt-note-text").replaceChildren(...parts.map((x) => {
    if (typeof x === "string") return document.createTextNode(x);
    const c = document.createElement("code");
    c.textContent = x.code;
    return c;
  }));
  $("wt-calibrate").hidden = !calibrate;
  $("wt-note").hidden = false;
}

function hideWalkNote() {
  $("wt-note").hidden = true;
  $("wt-note-text").replaceChildren();
  $("wt-calibrate").hidden = true;
}

// A contract the API could not plan, said in the panel next to what fixes it: 409 (the scene has no
// walkthrough calibration: how to make one, and the button) or 422 (no setting meets the target:
// the API's account of what the scene can do). True when `err` was one of them.
function showWalkContractProblem(err) {
  if (!(err instanceof ApiError) || !walk.scene) return false;
  const type = err.problem && err.problem.type;
  const sid = walk.scene.id;
  if (type === "urn:ibr:problem:calibration-missing") {
    if (walkCal.running) showWalkNote(calibratingNote());
    else {
      showWalkNote([`${sceneLabel(walk.scene)} has no walkthrough calibration yet. Asking by error or time plans `
        + "the bake preset and the fill, or path-traced frames, from one: each setting measured on a few probe frames against converged "
        + "frames. Calibrate it here, or with ", { code: `POST /v1/scenes/${sid}/walkthrough-calibrations` },
      " or ", { code: `ibr calibrate-walkthroughs ${sid}` }, "; or ask by settings."], true);
      $("wt-calibrate").title = `POST /v1/scenes/${sid}/walkthrough-calibrations with params `
        + `${JSON.stringify(WALK_CALIBRATION_PARAMS).replaceAll(",", ", ").replaceAll(":", ": ")}: bakes each `
        + "preset not in the store yet and measures it with the fill, and path-traced frames, on a few probe "
        + "frames against converged frames (the high preset and the other fills are left out, for a shorter "
        + "calibration); then the "
        + "walkthrough is asked again";
    }
    return true;
  }
  if (type === "urn:ibr:problem:contract-unmet") {
    // the detail alone: the problem's per-target errors repeat it
    showWalkNote([`${err.problem.title} (HTTP ${err.status}): ${err.problem.detail.replace(/\.$/, "")}. `
      + "Raise the target, or ask by settings."]);
    return true;
  }
  return false;
}

// ---- walkthrough calibration (what asking by error or time plans from)

// What "Calibrate walkthroughs" asks for: the two cheaper presets with the fill that covers the most
// holes, and path-traced frames at the calibration's default noise targets (no bake: seconds of the calibration); the
// bakes stay in the store, so a walkthrough planned onto one renders at once. The high preset and the
// other fills are left out: they would make the calibration several times longer.
// (path_noises: the calibration's defaults, from the capabilities)
const WALK_CALIBRATION_PARAMS = { presets: ["low", "medium"], fills: ["both"], path_noises: [] };
const walkCal = { running: false, controller: null };
const walkCalPerf = { state: null, fraction: 0, stage: "", key: null, runs: 0 };
window.__walkCalibration = walkCalPerf;

function calibratingNote() {
  return [`Calibrating the walkthroughs of ${walk.scene ? sceneLabel(walk.scene) : "the scene"} (presets `
    + `${WALK_CALIBRATION_PARAMS.presets.join(" and ")}, fill ${WALK_CALIBRATION_PARAMS.fills.join(", ")}; `
    + `path-traced frames at noise ${WALK_CALIBRATION_PARAMS.path_noises.join(", ")}): `
    + "once it is done, a walkthrough asked by error or time is asked again."];
}

function stopWalkCalibration() {
  walkCal.controller?.abort(); // the page stops following it; the job itself runs on
  walkCal.controller = null;
  walkCal.running = false;
  $("wt-calibrate").disabled = false;
  $("wt-cal-progress").hidden = true;
}

function showWalkCalibration(cal) {
  if (cal.job) nameJob(cal.job.id, `${walk.scene ? sceneLabel(walk.scene) : "scene"} · walkthrough calibration`);
  const pr = (cal.job && cal.job.progress) || {};
  const fraction = cal.state === "finished" ? 1 : pr.fraction || 0;
  Object.assign(walkCalPerf, { state: cal.state, fraction, stage: pr.stage || "", key: cal.key });
  $("wt-cal-progress").hidden = false;
  $("wt-cal-bar").value = fraction;
  const cost = cal.model && typeof cal.model.cost_s === "number" ? ` (it took ${cal.model.cost_s.toFixed(1)} s)` : "";
  const eta = pr.eta_s != null ? `, ~${pr.eta_s.toFixed(0)} s left` : "";
  $("wt-cal-stage").textContent = cal.state === "finished"
    ? `walkthrough calibration finished${cal.cached ? ", already made" : ""}${cost}`
    : `walkthrough calibration ${cal.state}${pr.stage ? ` · ${pr.stage}` : ""} ${Math.round(fraction * 100)}%${eta}`;
}

async function calibrateWalkthroughs() {
  if (!walk.scene || walkCal.running) return;
  const scene = walk.scene;
  const controller = new AbortController();
  const { signal } = controller;
  Object.assign(walkCal, { running: true, controller });
  $("wt-calibrate").disabled = true;
  showWalkNote(calibratingNote());
  const path = `/v1/scenes/${scene.id}/walkthrough-calibrations`;
  try {
    let { data: cal } = await api(path, { method: "POST", body: { params: WALK_CALIBRATION_PARAMS } });
    walkCalPerf.runs += 1;
    showWalkCalibration(cal);
    while (cal.state === "queued" || cal.state === "running") {
      await sleep(500, signal);
      cal = (await api(`${path}?key=${cal.key}`, { signal })).data;
      showWalkCalibration(cal);
    }
    if (cal.state !== "finished") {
      throw new ApiError(0, { title: "Walkthrough calibration failed",
        detail: (cal.job && cal.job.error) || `the calibration is ${cal.state}` });
    }
    Object.assign(walkCal, { running: false, controller: null });
    $("wt-calibrate").disabled = false;
    hideWalkNote();
    // the scene can plan contracts now: ask again, unless the page moved on to settings or another walkthrough
    if (walk.scene === scene && $("wt-ask").value !== "settings" && !walk.controller) startWalk();
  } catch (err) {
    if (isAbort(err) || walkCal.controller !== controller) return;
    Object.assign(walkCal, { running: false, controller: null });
    $("wt-calibrate").disabled = false;
    // the problem's title, detail and per-field errors (formatProblemText); the button tries again
    showWalkNote([String(err.message || err), " "], true);
  }
}

function showWalk(pub) {
  for (const j of pub.jobs || []) nameJob(j.id, `${walk.scene ? walk.scene.name : "scene"} · walkthrough`);
  // only a walkthrough asked by error or time: the API also states the contract of an earlier request
  // that planned the same frames when they are asked by settings
  if (pub.contract && walk.request && walk.request.quality) showWalkContract(pub.contract, pub.status);
  walkPerf.status = pub.status;
  walkPerf.progress = pub.progress;
  walkPerf.key = pub.key;
  $("wt-progress").hidden = false;
  $("wt-bar").value = pub.status === "finished" ? 1 : pub.progress;
  $("wt-stage").textContent = pub.status === "finished" ? `done: ${pub.frames} frames`
    : `${pub.status} · ${pub.frames_done} of ${pub.frames} frames ${Math.round(pub.progress * 100)}%`
      + `${pub.error ? ` — ${pub.error}` : ""}`;
}

async function startWalk() {
  if (!walk.scene) return;
  stopWalk();
  const controller = new AbortController();
  walk.controller = controller;
  const { signal } = controller;
  $("wt-go").disabled = true;
  $("wt-player").hidden = true;
  $("wt-progress").hidden = true; // a previous walkthrough's "done" is not this one's
  $("wt-contract").hidden = true;
  if (!walkCal.running) hideWalkNote();
  walkPerf.loaded = 0;
  walkPerf.shown = -1;
  walkPerf.contract = null;
  let request = null;
  try {
    request = walkRequest();
    walk.request = request;
    let { data: pub } = await api("/v1/walkthroughs", { method: "POST", body: request });
    showError(null);
    walk.key = pub.key;
    showWalk(pub);
    while (pub.status === "queued" || pub.status === "running") {
      await sleep(500, signal);
      pub = (await api(`/v1/walkthroughs/${pub.key}`, { signal })).data;
      showWalk(pub);
    }
    if (pub.status !== "finished") throw new ApiError(0, { title: "Walkthrough failed", detail: pub.error || pub.status });
    await loadWalkFrames(pub, signal);
  } catch (err) {
    if (isAbort(err)) return;
    if (request && request.quality && showWalkContractProblem(err)) return;
    showError(err);
  } finally {
    $("wt-go").disabled = false;
    if (walk.controller === controller) walk.controller = null; // none in flight (a calibration may ask again)
  }
}

async function loadWalkFrames(pub, signal) {
  const n = pub.frames;
  const urls = new Array(n);
  walkPerf.frames = n;
  let next = 0;
  const worker = async () => {
    for (let i = next++; i < n; i = next++) {
      urls[i] = await fetchBlobUrl(`/v1/walkthroughs/${pub.key}/frames/${i}.png`, signal);
      walkPerf.loaded += 1;
      $("wt-stage").textContent = `done: ${n} frames · loading ${walkPerf.loaded} of ${n}`;
    }
  };
  await Promise.all([worker(), worker(), worker(), worker()]);
  walk.urls = urls;
  $("wt-stage").textContent = `done: ${n} frames`;
  $("wt-slider").max = String(n - 1);
  $("wt-player").hidden = false;
  await showWalkFrame(0);
  playWalk(true);
}

async function showWalkFrame(i) {
  if (!walk.urls.length) return;
  walk.index = ((i % walk.urls.length) + walk.urls.length) % walk.urls.length;
  const img = $("wt-frame");
  img.src = walk.urls[walk.index];
  img.dataset.index = String(walk.index);
  $("wt-slider").value = String(walk.index);
  $("wt-label").textContent = `frame ${walk.index + 1} / ${walk.urls.length}`;
  walkPerf.shown = walk.index;
  scheduleWalkCompare();
}

// ---- walkthrough frame vs a reference render of its camera (shown while paused)

let walkCmp = null;
let walkCmpTimer = null;

function stopWalkCompare() {
  clearTimeout(walkCmpTimer);
  walkCmpTimer = null;
  if (walkCmp) {
    walkCmp.controller.abort();
    if (walkCmp.jobId && !walkCmp.done) cancelJob(walkCmp.jobId);
    walkCmp = null;
  }
}

function scheduleWalkCompare() {
  stopWalkCompare();
  const mode = $("wt-compare").value;
  $("wt-compare-view").hidden = mode === "off";
  if (mode === "off" || !walk.urls.length || !walk.request) return;
  $("wt-lrms").textContent = "";
  if (walk.timer) { $("wt-compare-caption").textContent = "reference: pause to compare the shown frame"; return; }
  $("wt-compare-caption").textContent = "reference: waiting…";
  const index = walk.index;
  walkCmpTimer = setTimeout(() => { walkCmpTimer = null; runWalkCompare(index).catch(() => {}); }, COMPARE_REST_MS);
}

async function runWalkCompare(index) {
  const mode = $("wt-compare").value;
  const c = { controller: new AbortController(), jobId: null, done: false,
    label: `${walk.scene ? walk.scene.name : "scene"} · reference of walkthrough frame ${index + 1}` };
  walkCmp = c;
  const { signal } = c.controller;
  const wkey = walk.key;
  const frame = walk.request.frames[index];
  const sppText = $("spp").value.trim();
  const body = { scene_id: walk.request.scene_id, camera: frame.camera, method: "reference",
    params: { spp: Number(sppText) || 4 }, outputs: ["preview", "radiance"] };
  // an animated scene: the reference is the scene at the frame's moment (a static scene takes no time)
  const animated = Boolean(walk.info && walk.info.animation);
  if (animated) body.time = frame.time;
  const caption = $("wt-compare-caption");
  caption.textContent = "reference: rendering…";
  try {
    const { manifest: ref } = await runToArtifact(c, "/v1/renders", body, "/v1/artifacts", signal, (job) => {
      caption.textContent = `reference: ${job.state} ${Math.round((job.progress?.fraction || 0) * 100)}%`;
    });
    c.done = true;
    const query = `test=${wkey}&test_kind=walkthrough&frame=${index}&ref=${ref.key}`;
    const result = await showComparison({ img: $("wt-compare-img"), lrms: $("wt-lrms") }, mode, query,
      `/v1/artifacts/${ref.key}/image.png`, signal);
    if (walkCmp !== c) return;
    caption.textContent = `${mode === "diff" ? "difference vs reference" : "reference"} (${body.params.spp} spp) `
      + `of frame ${index + 1}${animated ? ` at time ${+frame.time.toFixed(4)}` : ""},`;
    walkComparePerf.runs += 1;
    walkComparePerf.last = { ...result, mode, frame: index, walkthrough: wkey, ref: ref.key,
      time: animated ? frame.time : null };
  } catch (err) {
    if (isAbort(err) || walkCmp !== c) return;
    caption.textContent = "reference: failed";
    showError(err);
  }
}

function playWalk(on) {
  clearInterval(walk.timer);
  walk.timer = null;
  if (!on) scheduleWalkCompare(); // the shown frame rests: compare it
  $("wt-play").textContent = on ? "Pause" : "Play";
  if (!on) return;
  const fps = Math.max(1, Math.min(120, Number($("wt-fps").value) || 12));
  walk.timer = setInterval(() => {
    showWalkFrame(walk.index + 1);
    walkPerf.played += 1;
  }, 1000 / fps);
}

async function downloadWalkVideo() {
  if (!walk.key) return;
  try {
    const url = await fetchBlobUrl(`/v1/walkthroughs/${walk.key}/video.mp4`);
    const a = document.createElement("a");
    a.href = url;
    a.download = `walkthrough-${walk.key.slice(0, 12)}.mp4`;
    a.click();
    setTimeout(() => URL.revokeObjectURL(url), 10_000);
  } catch (err) { showError(err); }
}

function bindWalk() {
  $("wt-go").addEventListener("click", () => startWalk());
  $("wt-ask").addEventListener("change", () => walkAskChanged());
  $("wt-calibrate").addEventListener("click", () => calibrateWalkthroughs());
  $("wt-play").addEventListener("click", () => playWalk(!walk.timer));
  $("wt-slider").addEventListener("input", () => { playWalk(false); showWalkFrame(Number($("wt-slider").value)); });
  $("wt-video").addEventListener("click", () => downloadWalkVideo());
  $("wt-compare").addEventListener("change", () => scheduleWalkCompare());
  $("wt-viewport").addEventListener("keydown", (e) => {
    if (e.key === " ") { e.preventDefault(); playWalk(!walk.timer); }
    else if (e.key === "ArrowRight") { e.preventDefault(); playWalk(false); showWalkFrame(walk.index + 1); }
    else if (e.key === "ArrowLeft") { e.preventDefault(); playWalk(false); showWalkFrame(walk.index - 1); }
  });
}

// ------------------------------------------------------------------ jobs panel

let jobsBusy = false;

function jobKind(j) {
  // "render-<key>", "bake-<key>", "bake-part-<key>", ...: the prefix says what the job is
  const m = /^(.*?)-?([0-9a-f]{16,})$/.exec(j.id);
  return m ? { what: m[1] || j.kind, key: m[2] } : { what: j.kind, key: "" };
}

// A job the page did not start: a finished render names its scene and method in its artifact.
const jobLookups = new Set();
async function lookUpJobName(j) {
  const { what, key } = jobKind(j);
  if (what !== "render" || j.state !== "finished" || !key || jobLookups.has(j.id)) return;
  jobLookups.add(j.id);
  try {
    const { data: m } = await api(`/v1/artifacts/${key}`);
    const scene = sceneNames.get(m.inputs && m.inputs.scene);
    if (scene) nameJob(j.id, `${scene} · ${(m.params && m.params.method) || "reference"} view`);
  } catch { /* not visible to this key, or gone: keep the kind and the short id */ }
}

function jobCell(j) {
  const { what, key } = jobKind(j);
  const td = document.createElement("td");
  const name = document.createElement("span");
  name.className = "job-name";
  name.textContent = jobNames.get(j.id) || what;
  const hash = document.createElement("span");
  hash.className = "hash";
  hash.textContent = jobNames.has(j.id) ? `${what} ${shortId(key)}` : shortId(key);
  td.append(name, " ", hash);
  td.title = j.id;
  return td;
}

async function pollJobs() {
  if (jobsBusy || document.hidden) return;
  jobsBusy = true;
  const keyUsed = apiKey();
  try {
    const { data } = await api("/v1/jobs?limit=30");
    $("jobs").tBodies[0].replaceChildren(...data.items.map((j) => {
      const tr = document.createElement("tr");
      tr.dataset.state = j.state;
      tr.dataset.jobId = j.id;
      tr.dataset.kind = j.kind;
      const id = jobCell(j);
      if (!jobNames.has(j.id)) lookUpJobName(j);
      const st = document.createElement("td");
      st.textContent = j.state;
      st.className = `state-${j.state}`;
      if (j.error) st.title = j.error;
      const pr = document.createElement("td");
      const bar = document.createElement("progress");
      bar.max = 1;
      bar.value = j.state === "finished" ? 1 : (j.progress && j.progress.fraction) || 0;
      const label = document.createElement("span");
      const stage = j.progress && j.progress.stage && j.state !== "finished" ? ` ${j.progress.stage}` : "";
      label.textContent = ` ${Math.round(bar.value * 100)}%${stage}`;
      pr.append(bar, label);
      tr.append(id, st, pr);
      return tr;
    }));
  } catch (err) {
    if (err instanceof ApiError && err.status === 401 && keyUsed === apiKey()) showError(err);
  } finally {
    jobsBusy = false;
  }
}

// ------------------------------------------------------------------ input

function bindViewport() {
  const vp = $("viewport");
  let drag = null;
  vp.addEventListener("contextmenu", (e) => e.preventDefault());
  vp.addEventListener("pointerdown", (e) => {
    if (!view.cam || !view.scene || e.target.closest("#no-bake")) return; // the overlay's button takes its clicks
    vp.focus();
    drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey || e.button === 1 };
    vp.setPointerCapture(e.pointerId);
    vp.classList.add("dragging");
    e.preventDefault();
  });
  vp.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const t = performance.now();
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    if (!dx && !dy) return;
    drag.x = e.clientX; drag.y = e.clientY;
    if (drag.pan) pan(dx, dy);
    else orbit(-dx * orbitRadPerPx(), -dy * orbitRadPerPx());
    changed(t);
  });
  const end = (e) => {
    if (!drag) return;
    drag = null;
    vp.classList.remove("dragging");
    if (vp.hasPointerCapture(e.pointerId)) vp.releasePointerCapture(e.pointerId);
  };
  vp.addEventListener("pointerup", end);
  vp.addEventListener("pointercancel", end);
  vp.addEventListener("wheel", (e) => {
    if (!view.cam || !view.scene) return;
    e.preventDefault();
    const t = performance.now();
    zoom(Math.exp(Math.max(-1, Math.min(1, e.deltaY * 0.0015))));
    changed(t);
  }, { passive: false });
  vp.addEventListener("keydown", (e) => {
    if (!view.cam || !view.scene) return;
    const t = performance.now();
    const px = 20, step = px * orbitRadPerPx(); // a key press moves like a 20-pixel drag
    const keys = {
      ArrowLeft: () => (e.shiftKey ? pan(px, 0) : orbit(step, 0)),
      ArrowRight: () => (e.shiftKey ? pan(-px, 0) : orbit(-step, 0)),
      ArrowUp: () => (e.shiftKey ? pan(0, px) : orbit(0, step)),
      ArrowDown: () => (e.shiftKey ? pan(0, -px) : orbit(0, -step)),
      "+": () => zoom(1 / 1.15), "=": () => zoom(1 / 1.15),
      "-": () => zoom(1.15), _: () => zoom(1.15),
    };
    const f = keys[e.key];
    if (!f) return;
    e.preventDefault();
    f();
    changed(t);
  });
}

function bindControls() {
  $("method").addEventListener("change", () => methodChanged());
  $("ask").addEventListener("change", () => askChanged());
  $("target").addEventListener("change", () => changed());
  $("ibrt-k").addEventListener("change", () => changed());
  $("aa").addEventListener("change", () => changed());
  $("glossy").addEventListener("change", () => changed());
  $("spp").addEventListener("change", () => changed());
  $("size").addEventListener("change", () => { sizeViewport(); changed(); });
  $("reset-camera").addEventListener("click", () => { if (view.base) { setCamera(view.base); changed(); } });
  $("exposure").addEventListener("input", () => { $("exposure-out").textContent = fmtEv(Number($("exposure").value)); });
  $("exposure").addEventListener("change", () => reexpose());
  $("compare").addEventListener("change", () => {
    if (current && current.done && view.manifest) scheduleCompare(current);
    else { stopCompare(); $("compare-view").hidden = $("compare").value === "off"; }
  });
  $("provenance").addEventListener("change", () => updateProvenanceView());
  $("bake").addEventListener("click", () => startBake());
  $("no-bake-go").addEventListener("click", () => {
    $("no-bake-text").textContent = "Baking: the view follows when the bake is done.";
    $("no-bake-go").hidden = true;
    startBake();
  });
  $("error-close").addEventListener("click", () => showError(null));
  for (const id of ["bake-res", "bake-llf", "bake-indirect"]) {
    $(id).addEventListener("change", () => {
      bake.params = null; bake.key = null;
      for (const b of $("bake-list").querySelectorAll("button")) b.setAttribute("aria-pressed", "false");
      if (currentMethod().needsBake) changed();
    });
  }
  $("reload-scenes").addEventListener("click", async () => loadWalkList(await loadScenes()));
  $("api-key").value = apiKey();
  const keyState = () => { $("key-state").textContent = apiKey() ? "key set for this tab" : "no key"; };
  keyState();
  $("key-form").addEventListener("submit", async (e) => {
    e.preventDefault();
    const k = $("api-key").value.trim();
    if (k) sessionStorage.setItem(KEY_STORAGE, k); else sessionStorage.removeItem(KEY_STORAGE);
    keyState();
    await loadScenes();
    loadDatasets();
    pollJobs();
  });
}

// ------------------------------------------------------------------ start

async function main() {
  if (params.get("size")) {
    const v = String(Number(params.get("size")) | 0);
    if (![...$("size").options].some((o) => o.value === v)) $("size").add(new Option(`${v} x ${v}`, v));
    $("size").value = v;
  }
  if (params.get("spp")) $("spp").value = params.get("spp");
  if (params.get("ldc")) {
    const v = String(Number(params.get("ldc")) | 0);
    if (![...$("bake-res").options].some((o) => o.value === v)) $("bake-res").add(new Option(v, v));
    $("bake-res").value = v;
  }
  sizeViewport();
  bindControls();
  bindViewport();
  bindSphere();
  bindWalk();
  const [, , scenes] = await Promise.all([loadCapabilities(), loadSampleCameras(), loadScenes()]);
  const datasets = await loadDatasets();
  loadWalkList(scenes);
  const want = params.get("scene");
  if (want) {
    const s = scenes.find((x) => x.name === want || x.id === want);
    if (s) openScene(s);
  }
  const wantDs = params.get("dataset");
  if (wantDs) {
    const d = datasets.find((x) => x.name === wantDs || x.id === wantDs);
    if (d) openDataset(d);
  }
  const wantWalk = params.get("walk");
  if (wantWalk) {
    const s = walkScenes(scenes).find((x) => x.name === wantWalk || x.id === wantWalk);
    if (s) openWalk(s);
  }
  pollJobs();
  setInterval(pollJobs, JOBS_LIST_MS);
  document.body.dataset.ready = "true";
}

main();
