// ibr-service browser preview (issue 7). Plain ES module, no dependencies, nothing from the network
// but this API. See the Help section of index.html for what the controls do.

const KEY_STORAGE = "ibr.apiKey";
const FALLBACK_METHODS = ["reference"]; // used only when /openapi.json cannot be read
const DEFAULT_CAMERA = { type: "perspective", eye: [0, 1, 4], look_at: [0, 0.5, 0], up: [0, 1, 0], fov_y_deg: 45 };
const RENDER_WAIT_S = 0.25; // server-side wait of POST /v1/renders; then the page polls the job
const JOB_POLL_MS = [50, 250]; // first and longest interval between polls of a running job
const MIN_REQUEST_GAP_MS = 100; // during a drag, at most one new view request per this interval
const JOBS_LIST_MS = 1000;

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);

// Instrumentation read by tests and bench/preview_latency.py.
const perf = { inputAt: null, requests: 0, loads: 0, latencies: [], last: null, scheduled: false };
window.__preview = perf;

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
    if (res.status === 401 && !problem.detail) problem.detail = "the API key is missing or not accepted";
    if (res.status === 401) problem.detail = `${problem.detail} — enter a valid API key above`;
    throw new ApiError(res.status, problem);
  }
  if (raw) return res;
  return { status: res.status, data: res.status === 204 ? null : await res.json() };
}

function showError(err) {
  const box = $("error");
  if (!err) { box.hidden = true; box.replaceChildren(); return; }
  const p = err instanceof ApiError ? err.problem : { title: "Error", detail: String(err.message || err) };
  const head = document.createElement("strong");
  head.textContent = err instanceof ApiError && err.status ? `${p.title} (HTTP ${err.status})` : p.title;
  const parts = [head];
  if (p.detail) parts.push(document.createTextNode(`: ${p.detail}`));
  if (p.errors && p.errors.length) {
    const ul = document.createElement("ul");
    for (const e of p.errors) {
      const li = document.createElement("li");
      const f = document.createElement("code");
      f.textContent = e.field || "request";
      li.append(f, document.createTextNode(`: ${e.message}`));
      ul.append(li);
    }
    parts.push(ul);
  }
  box.replaceChildren(...parts);
  box.hidden = false;
}

const isAbort = (e) => e && (e.name === "AbortError" || e === ABORTED);
const ABORTED = new Error("aborted");
const sleep = (ms, signal) => new Promise((resolve, reject) => {
  const t = setTimeout(resolve, ms);
  signal?.addEventListener("abort", () => { clearTimeout(t); reject(ABORTED); }, { once: true });
});

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
  base: null, // {camera, pivot} the scene started from
  cam: null, // {type, eye, look_at, up, fov_y_deg | ortho_height}
  pivot: null,
};

function setCamera(base) {
  view.base = base;
  view.cam = structuredClone(base.camera);
  view.cam.up = view.cam.up || [0, 1, 0];
  view.pivot = (base.pivot || view.cam.look_at).slice();
  // Orbit around the pivot: aim at it, keeping the distance.
  view.cam.look_at = view.pivot.slice();
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
    view.cam.ortho_height = Math.max(1e-4, view.cam.ortho_height * factor);
    return;
  }
  const off = sub(view.cam.eye, view.pivot);
  const d = len(off);
  const nd = Math.min(Math.max(d * factor, 1e-3), 1e6);
  view.cam.eye = add(view.pivot, scale(off, nd / d));
}

// ------------------------------------------------------------------ rendering (latest request wins)

let current = null; // {seq, controller, jobId, body}
let seq = 0;
let scheduled = false;
let lastStart = -Infinity;

function viewSize() { return Number($("size").value) || 256; }

function sizeViewport() {
  const px = `${viewSize()}px`;
  $("viewport").style.width = px;
  $("viewport").style.height = px;
}

function requestBody() {
  const size = viewSize();
  const cam = { ...view.cam, width: size, height: size };
  const round = (v) => v.map((x) => Math.round(x * 1e6) / 1e6);
  cam.eye = round(cam.eye); cam.look_at = round(cam.look_at); cam.up = round(cam.up);
  const sppText = $("spp").value.trim();
  const spp = sppText === "" ? undefined : Number(sppText);
  const p = {};
  if (spp !== undefined) p.spp = Number.isFinite(spp) ? spp : sppText; // let the API judge it
  return { scene_id: view.scene.id, camera: cam, method: $("method").value, params: p };
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
  api(`/v1/jobs/${encodeURIComponent(req.jobId)}/cancel`, { method: "POST" }).catch(() => {});
}

function startRender(inputAt) {
  const body = requestBody();
  const bodyText = JSON.stringify(body);
  const prev = current;
  if (prev) {
    if (prev.bodyText === bodyText && !prev.done) return; // the same view is already on its way
    prev.controller.abort();
  }
  const me = { seq: ++seq, controller: new AbortController(), jobId: null, bodyText, done: false, inputAt };
  current = me;
  if (prev) cancelStale(prev);
  perf.requests += 1;
  render(me, body).catch((err) => {
    if (isAbort(err) || me !== current) return;
    me.done = true;
    setStatus("");
    $("render-progress").hidden = true;
    showError(err);
  });
}

function setStatus(text) { $("view-status").textContent = text; }

function showProgress(job) {
  const pr = job.progress || {};
  $("render-progress").hidden = false;
  $("render-bar").value = pr.fraction || 0;
  const eta = pr.eta_s != null ? `, ~${pr.eta_s.toFixed(1)} s left` : "";
  $("render-stage").textContent = `${job.state}${pr.stage ? ` · ${pr.stage}` : ""} ${Math.round((pr.fraction || 0) * 100)}%${eta}`;
}

async function render(me, body) {
  const { signal } = me.controller;
  const t0 = performance.now();
  setStatus("rendering…");
  // The POST is short (wait <= 0.25 s) and not aborted: its answer names the job, which is
  // canceled when a newer view superseded this one meanwhile.
  let { data: r } = await api(`/v1/renders?wait=${RENDER_WAIT_S}`, { method: "POST", body });
  if (r.job) me.jobId = r.job.id;
  if (signal.aborted) {
    if (r.status === "queued" || r.status === "running") cancelStale(me);
    throw ABORTED;
  }
  let manifest = r.artifact;
  let delay = JOB_POLL_MS[0];
  while (!manifest) {
    if (r.status === "failed" || (r.job && (r.job.state === "failed" || r.job.state === "canceled"))) {
      const job = r.job || {};
      throw new ApiError(0, { title: "Render failed", detail: job.error || `job ${job.state}` });
    }
    if (r.job) showProgress(r.job);
    await sleep(delay, signal);
    delay = Math.min(JOB_POLL_MS[1], delay * 1.3);
    const { data: job } = await api(`/v1/jobs/${encodeURIComponent(me.jobId)}`, { signal });
    if (job.state === "finished") {
      manifest = (await api(`/v1/artifacts/${r.artifact_key}`, { signal })).data;
      r = { ...r, status: "finished", job };
    } else {
      r = { ...r, status: job.state, job };
    }
  }
  const res = await api(`/v1/artifacts/${manifest.key}/image.png`, { signal, raw: true });
  const blob = await res.blob();
  if (me !== current) return; // a newer request owns the view
  const url = URL.createObjectURL(blob);
  const img = $("view");
  const old = img.dataset.blobUrl;
  img.onload = () => {
    if (old) URL.revokeObjectURL(old);
    if (me !== current) return;
    const now = performance.now();
    perf.loads += 1;
    const timings = { ...((manifest.result && manifest.result.timings) || {}),
      ...((r.job && r.job.result && r.job.result.timings) || {}) };
    perf.last = { seq: me.seq, key: manifest.key, latency: now - me.inputAt, request: now - t0, status: r.status,
      timings };
    perf.latencies.push(now - me.inputAt);
    setStatus("");
  };
  img.dataset.blobUrl = url;
  img.dataset.key = manifest.key;
  img.src = url;
  me.done = true;
  $("render-progress").hidden = true;
  showError(null);
  showTimings(manifest, r.job, r.status, performance.now() - t0);
}

function showTimings(manifest, job, status, clientMs) {
  // the job's result adds the stages after the manifest was written (store, job_total)
  const timings = { ...((manifest.result && manifest.result.timings) || {}),
    ...((status !== "cached" && job && job.result && job.result.timings) || {}) };
  const rows = Object.entries(timings)
    .filter(([, v]) => typeof v === "number")
    .map(([k, v]) => [k, `${(v * 1000).toFixed(1)} ms`]);
  rows.push([status === "cached" ? "round trip (cached)" : "round trip (page)", `${clientMs.toFixed(0)} ms`]);
  $("timings").tBodies[0].replaceChildren(...rows.map(([k, v]) => {
    const tr = document.createElement("tr");
    const a = document.createElement("td"); a.textContent = k;
    const b = document.createElement("td"); b.textContent = v;
    tr.append(a, b);
    return tr;
  }));
}

// ------------------------------------------------------------------ scenes

let sampleCameras = {};

async function loadSampleCameras() {
  try {
    const res = await fetch("/preview/sample-cameras.json");
    if (res.ok) sampleCameras = await res.json();
  } catch { /* no samples: default camera */ }
}

async function loadScenes() {
  try {
    const { data } = await api("/v1/scenes?limit=1000");
    const list = $("scene-list");
    list.replaceChildren(...data.items.map((s) => {
      const li = document.createElement("li");
      const b = document.createElement("button");
      b.type = "button";
      b.textContent = s.name || s.id.slice(0, 12);
      b.title = `${s.id}\n${s.n_objects} objects, ${s.n_lights} lights`;
      b.dataset.sceneId = s.id;
      b.dataset.sceneName = s.name;
      b.addEventListener("click", () => openScene(s));
      li.append(b);
      return li;
    }));
    $("scene-empty").hidden = data.items.length > 0;
    showError(null);
    return data.items;
  } catch (err) {
    showError(err);
    return [];
  }
}

function openScene(s) {
  view.scene = s;
  for (const b of $("scene-list").querySelectorAll("button")) {
    b.setAttribute("aria-current", String(b.dataset.sceneId === s.id));
  }
  $("scene-name").textContent = `— ${s.name}`;
  $("reset-camera").disabled = false;
  const sample = sampleCameras[s.name];
  setCamera(sample ? { camera: sample.camera, pivot: sample.pivot } : { camera: DEFAULT_CAMERA, pivot: null });
  changed();
}

// ------------------------------------------------------------------ methods

async function loadMethods() {
  let methods = FALLBACK_METHODS;
  try {
    const res = await fetch("/openapi.json");
    if (res.ok) {
      const doc = await res.json();
      const schemas = (doc.components && doc.components.schemas) || {};
      let m = schemas.RenderRequest && schemas.RenderRequest.properties && schemas.RenderRequest.properties.method;
      if (m && m.$ref) m = schemas[m.$ref.split("/").pop()];
      if (m && Array.isArray(m.enum) && m.enum.length) methods = m.enum;
      else if (m && typeof m.const === "string") methods = [m.const];
    }
  } catch { /* keep the fallback */ }
  $("method").replaceChildren(...methods.map((name) => new Option(name, name)));
}

// ------------------------------------------------------------------ jobs panel

let jobsBusy = false;

async function pollJobs() {
  if (jobsBusy || document.hidden) return;
  jobsBusy = true;
  const keyUsed = apiKey();
  try {
    const { data } = await api("/v1/jobs?limit=25");
    $("jobs").tBodies[0].replaceChildren(...data.items.map((j) => {
      const tr = document.createElement("tr");
      tr.dataset.state = j.state;
      tr.dataset.jobId = j.id;
      const id = document.createElement("td");
      id.textContent = `${j.kind} ${j.id.replace(/^(render|bake)-/, "").slice(0, 8)}`;
      id.title = j.id;
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
    if (!view.cam) return;
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
    else orbit(-dx * 0.01, -dy * 0.01);
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
    if (!view.cam) return;
    e.preventDefault();
    const t = performance.now();
    zoom(Math.exp(Math.max(-1, Math.min(1, e.deltaY * 0.0015))));
    changed(t);
  }, { passive: false });
  vp.addEventListener("keydown", (e) => {
    if (!view.cam) return;
    const t = performance.now();
    const step = 0.15, px = 20;
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
  $("method").addEventListener("change", () => changed());
  $("spp").addEventListener("change", () => changed());
  $("size").addEventListener("change", () => { sizeViewport(); changed(); });
  $("reset-camera").addEventListener("click", () => { if (view.base) { setCamera(view.base); changed(); } });
  const applyBrightness = () => {
    const v = Number($("brightness").value);
    $("view").style.filter = v === 1 ? "" : `brightness(${v})`;
    $("brightness-out").textContent = `${v.toFixed(2)}x`;
  };
  $("brightness").addEventListener("input", applyBrightness);
  $("reload-scenes").addEventListener("click", () => loadScenes());
  $("api-key").value = apiKey();
  const keyState = () => { $("key-state").textContent = apiKey() ? "key set for this tab" : "no key"; };
  keyState();
  $("key-form").addEventListener("submit", async (e) => {
    e.preventDefault();
    const k = $("api-key").value.trim();
    if (k) sessionStorage.setItem(KEY_STORAGE, k); else sessionStorage.removeItem(KEY_STORAGE);
    keyState();
    await loadScenes();
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
  sizeViewport();
  bindControls();
  bindViewport();
  const [, , scenes] = await Promise.all([loadMethods(), loadSampleCameras(), loadScenes()]);
  const want = params.get("scene");
  if (want) {
    const s = scenes.find((x) => x.name === want || x.id === want);
    if (s) openScene(s);
  }
  pollJobs();
  setInterval(pollJobs, JOBS_LIST_MS);
  document.body.dataset.ready = "true";
}

main();
