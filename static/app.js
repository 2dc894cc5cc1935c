// STREP Studio web page: launch comparisons, follow them live over Server-Sent Events.
// Plain JavaScript, no dependencies: every asset is served by the app (works offline).
"use strict";

const COLORS = ["#2f6fde", "#e67e22", "#27ae60", "#8e44ad", "#c0392b", "#16a085", "#7f8c8d"];
const FINAL = new Set(["succeeded", "failed", "cancelled", "interrupted"]);
const token = new URLSearchParams(location.search).get("token") || sessionStorage.getItem("strep-token");
if (token) sessionStorage.setItem("strep-token", token);

const $ = (sel) => document.querySelector(sel);
const state = { jobs: new Map(), follow: new Set(), methods: [], sequences: [], comparison: null, viewer: null };

function headers(extra = {}) {
  return token ? { ...extra, Authorization: `Bearer ${token}` } : extra;
}

async function api(path, options = {}) {
  const res = await fetch(path, { ...options, headers: headers(options.headers || {}) });
  const body = res.headers.get("content-type")?.includes("json") ? await res.json() : await res.text();
  if (!res.ok) throw new Error((body && body.detail) || `${res.status} ${res.statusText}`);
  return body;
}

function say(text, isError = false) {
  const el = $("#message");
  el.textContent = text;
  el.className = isError ? "error" : "";
}

function fmt(v, digits = 3) {
  return typeof v === "number" && isFinite(v) ? v.toPrecision(digits) : "–";
}

// Text from the service (names, errors, uploaded file names) goes into HTML only through this.
function esc(value) {
  return String(value ?? "").replace(/[&<>"']/g, (c) => `&#${c.charCodeAt(0)};`);
}

// ---- charts ---------------------------------------------------------------------------------

// Size a canvas's pixels to its box on screen (sharp on any display); returns its context and CSS size.
function fitCanvas(canvas) {
  const dpr = window.devicePixelRatio || 1;
  const W = canvas.clientWidth || canvas.width, H = canvas.clientHeight || canvas.height;
  if (canvas.width !== Math.round(W * dpr) || canvas.height !== Math.round(H * dpr)) {
    canvas.width = Math.round(W * dpr);
    canvas.height = Math.round(H * dpr);
  }
  const ctx = canvas.getContext("2d");
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  return { ctx, W, H };
}

function drawChart(canvas, series, { log = false, empty = "waiting for iterations…", xFrom = null } = {}) {
  const { ctx, W, H } = fitCanvas(canvas);
  const R = 10, T = 10, B = 26;
  let L = 52;
  ctx.clearRect(0, 0, W, H);
  const pts = series.flatMap((s) => s.points).filter(([, y]) => isFinite(y) && (!log || y > 0));
  ctx.font = "11px system-ui, sans-serif";
  ctx.fillStyle = "#6b7385";
  if (!pts.length) {
    ctx.fillText(empty, L, H / 2);
    return;
  }
  const tx = (y) => (log ? Math.log10(y) : y);
  let x0 = Math.min(xFrom ?? Infinity, ...pts.map((p) => p[0])), x1 = Math.max(...pts.map((p) => p[0]));
  let y0 = Math.min(...pts.map((p) => tx(p[1]))), y1 = Math.max(...pts.map((p) => tx(p[1])));
  if (x1 === x0) x1 = x0 + 1;
  if (y1 === y0) { y0 -= 0.5; y1 += 0.5; }
  // tick labels first: the plot starts right of the widest one, so no label lies on a curve
  const ticks = [0, 1, 2, 3, 4].map((i) => {
    const yv = y0 + ((y1 - y0) * i) / 4;
    return { text: fmt(log ? 10 ** yv : yv, 3), yy: T + (1 - i / 4) * (H - T - B) };
  });
  L = Math.ceil(Math.max(...ticks.map((t) => ctx.measureText(t.text).width))) + 12;
  const px = (x) => L + ((x - x0) / (x1 - x0)) * (W - L - R);
  const py = (y) => T + (1 - (tx(y) - y0) / (y1 - y0)) * (H - T - B);
  ctx.strokeStyle = "#dde1e8";
  ctx.lineWidth = 1;
  ctx.textAlign = "right";
  for (const { text, yy } of ticks) {
    ctx.beginPath(); ctx.moveTo(L, yy); ctx.lineTo(W - R, yy); ctx.stroke();
    ctx.fillText(text, L - 6, yy + 4);
  }
  ctx.textAlign = "left";
  ctx.fillText(String(Math.round(x0)), L, H - 8);
  ctx.textAlign = "right";
  ctx.fillText(`${Math.round(x1)} iterations`, W - R, H - 8);
  ctx.textAlign = "left";
  // earlier series wider, so a curve that another one covers still shows at its edges
  series.forEach((s, i) => {
    const p = s.points.filter(([, y]) => isFinite(y) && (!log || y > 0));
    if (!p.length) return;
    ctx.strokeStyle = s.color;
    ctx.lineWidth = Math.max(1.5, 2 + 1.5 * (series.length - 1 - i));
    ctx.beginPath();
    p.forEach(([x, y], k) => (k ? ctx.lineTo(px(x), py(y)) : ctx.moveTo(px(x), py(y))));
    ctx.stroke();
  });
}

function redraw() {
  const jobs = [...state.follow].map((id) => state.jobs.get(id)).filter(Boolean);
  const waiting = jobs.some((j) => j.status === "running") ? "waiting for the first iteration…" : "no iterations yet";
  drawChart($("#loss-chart"), jobs.map((j) => ({ color: j.color, points: j.loss })), { log: true, empty: waiting, xFrom: 0 });
  drawChart($("#ate-chart"), jobs.map((j) => ({ color: j.color, points: j.ate })), { empty: waiting, xFrom: 0 });
  const unit = jobs.map((j) => j.metrics?.unit || j.unit).find(Boolean);
  $("#ate-caption").textContent = unit ? `ATE (${unit}), from the starting poses (iteration 0)` : "ATE";
  $("#legend").innerHTML = jobs
    .map((j) => `<span class="legend-item"><span class="swatch" style="background:${j.color}"></span>${esc(j.method)}</span>`)
    .join("");
  const body = $("#results tbody");
  body.innerHTML = "";
  for (const j of jobs) {
    const m = j.metrics || {};
    const tr = document.createElement("tr");
    tr.dataset.jobId = j.id;
    const files = j.status === "succeeded"
      ? ["recording.rrd", "trajectory.tum", "map.ply", "metrics.json"]
          .filter((f) => !j.files || j.files.includes(f))
          .map((f) => `<a href="/api/jobs/${j.id}/files/${f}" download title="${f}">${f.split(".").pop()}</a>`).join("")
      : j.status === "running" || j.status === "queued"
        ? `<a href="#" data-cancel="${j.id}">cancel</a>` : "";
    const unit = m.unit ? ` ${esc(m.unit)}` : "";
    tr.innerHTML = `<td><span class="swatch" style="background:${j.color}"></span>${esc(j.method)}</td>
      <td class="status status-${j.status}" title="${esc(j.error)}">${j.status}</td>
      <td class="stage">${esc(stageText(j))}</td>
      <td class="num">${j.iteration ?? "–"}${j.total ? " / " + j.total : ""}</td>
      <td class="num ate">${fmt(m.ate ?? j.lastAte)}${m.ate != null || j.lastAte != null ? unit : ""}</td>
      <td class="num">${fmt(m.point_l2)}${m.point_l2 != null ? unit : ""}</td>
      <td class="num">${fmt(m.wall_seconds ?? j.elapsed, 3)}</td>
      <td class="links">${files}</td>`;
    body.appendChild(tr);
  }
  showActions(jobs);
}

// Where a job is: loading, warm start (and the ATE it reached), optimising, writing, done.
const STAGES = { load: "loading the sequence", init: "warm start", optimise: "optimising", write: "writing files" };
function stageName(stage) {
  const [head, detail] = stage.split(/:(.*)/);
  return (STAGES[head] || head) + (detail ? ` (${detail})` : "");
}

function stageText(j) {
  const unit = j.metrics?.unit || j.unit || "";
  const start = j.startAte != null ? `ATE ${fmt(j.startAte)} ${unit}`.trim() : "";
  if (j.status === "queued") return "queued";
  if (j.status === "succeeded") {
    const end = j.metrics?.ate;
    return start && end != null ? `done: ATE ${fmt(j.startAte)} → ${fmt(end)} ${unit}`.trim() : "done";
  }
  if (FINAL.has(j.status)) return j.status;
  if (j.stage === "write" || j.metrics) return "writing files";
  if (j.iteration > 0) return `optimising${start ? ` from ${start}` : ""}`;
  if (j.iteration === 0) {
    const head = j.stage?.startsWith("init") ? `${stageName(j.stage)} done` : "starting";
    return `${head}${start ? `: ${start}` : ""}`;
  }
  if (j.started && !j.stage?.startsWith("init")) return "preparing the optimisation…";
  return j.stage ? `${stageName(j.stage)}…` : "loading the sequence…";
}

// The run's links: the 3D viewer (shows this run there) and the comparison's recording.
function showActions(jobs) {
  const view = $("#view-3d"), rrd = $("#comparison-rrd");
  const started = jobs.some((j) => j.status !== "queued");
  view.hidden = !state.viewer || !jobs.length;
  view.classList.toggle("disabled", !started);
  view.dataset.view = state.comparison ? `comparisons/${state.comparison}` : jobs.length ? `jobs/${jobs[0].id}` : "";
  rrd.hidden = !state.comparisonFiles?.includes("recording.rrd");
  if (!rrd.hidden) rrd.href = `/api/comparisons/${state.comparison}/files/recording.rrd`;
}

// The comparison's recording is written shortly after its last job finishes: ask until it is there.
async function fetchComparisonFiles(id) {
  for (let i = 0; i < 20 && state.comparison === id; i++) {
    const cmp = await api(`/api/comparisons/${id}`).catch(() => null);
    if (!cmp || cmp.files.length || !FINAL.has(cmp.status)) {
      if (cmp && state.comparison === id) state.comparisonFiles = cmp.files;
      break;
    }
    await new Promise((r) => setTimeout(r, 1000));
  }
  scheduleRedraw();
}

// ---- Server-Sent Events over fetch (so the token header can be sent) ------------------------

async function follow(job) {
  const entry = state.jobs.get(job.id) || {
    id: job.id, method: job.method, color: COLORS[state.follow.size % COLORS.length],
    loss: [], ate: [], status: job.status, metrics: job.metrics, files: job.files, lastId: 0,
  };
  state.jobs.set(job.id, entry);
  state.follow.add(job.id);
  redraw();
  while (true) {
    try {
      const res = await fetch(`/api/jobs/${job.id}/events`, {
        headers: headers(entry.lastId ? { "Last-Event-ID": String(entry.lastId) } : {}),
      });
      if (!res.ok) throw new Error(`events: ${res.status}`);
      const reader = res.body.getReader();
      const decoder = new TextDecoder();
      let buf = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        buf += decoder.decode(value, { stream: true });
        let cut;
        while ((cut = buf.indexOf("\n\n")) >= 0) {
          handleMessage(entry, buf.slice(0, cut));
          buf = buf.slice(cut + 2);
        }
      }
    } catch (err) {
      console.warn(err);
    }
    if (FINAL.has(entry.status)) break;
    await new Promise((r) => setTimeout(r, 1000)); // reconnect; Last-Event-ID resumes the stream
  }
  const fresh = await api(`/api/jobs/${job.id}`).catch(() => null);
  if (fresh) Object.assign(entry, { status: fresh.status, metrics: fresh.metrics, files: fresh.files, error: fresh.error });
  redraw();
  loadJobs();
  const followed = [...state.follow].map((id) => state.jobs.get(id));
  if (state.comparison && followed.every((j) => j && FINAL.has(j.status))) {
    if (state.started === state.comparison) {
      const counts = {};
      for (const j of followed) counts[j.status] = (counts[j.status] || 0) + 1;
      const failed = followed.some((j) => j.status !== "succeeded");
      say(`comparison ${state.comparison} finished: ${Object.entries(counts).map(([k, n]) => `${n} ${k}`).join(", ")}`, failed);
      state.started = null;
    }
    fetchComparisonFiles(state.comparison);
  }
}

// How each event kind changes a job's entry: the rules the service serves (GET /api/events/rules:
// strep_core.runstate.PAGE_RULES plus the job store's "status" records), loaded at start and
// applied here; a kind without rules changes nothing (docs/design/extending.md).
let RULES = {};
const pick = (ev, path) => path.split(".").reduce((v, k) => (v == null ? v : v[k]), ev);
function applyRules(entry, ev, rules) {
  for (const r of rules) {
    if (r.if && Object.entries(r.if).some(([path, want]) => pick(ev, path) !== want)) continue;
    const value = "value" in r ? r.value : Array.isArray(r.from) ? r.from.map((p) => pick(ev, p)) : pick(ev, r.from);
    if (r.push) {
      if (!value.some((v) => v == null)) entry[r.push].push(value);
    } else if (!(r.skip_null && value == null)) {
      entry[r.set] = value;
    }
  }
}

function handleMessage(entry, block) {
  let kind = "message", id = null;
  const data = [];
  for (const line of block.split("\n")) {
    if (line.startsWith("event:")) kind = line.slice(6).trim();
    else if (line.startsWith("id:")) id = Number(line.slice(3).trim());
    else if (line.startsWith("data:")) data.push(line.slice(5).replace(/^ /, ""));
  }
  if (id) entry.lastId = id;
  if (!data.length) return;
  let ev;
  try { ev = JSON.parse(data.join("\n")); } catch { return; }
  if (Object.hasOwn(RULES, kind)) applyRules(entry, ev, RULES[kind]);
  scheduleRedraw();
}

let redrawPending = false;
function scheduleRedraw() {
  if (redrawPending) return;
  redrawPending = true;
  requestAnimationFrame(() => { redrawPending = false; redraw(); });
}

// ---- launching ------------------------------------------------------------------------------

async function loadSequences(selectId) {
  const { data } = await api("/api/sequences");
  state.sequences = data;
  const sel = $("#sequence");
  sel.innerHTML = data
    .map((s) => `<option value="${esc(s.id)}">${esc(s.name)} (${s.dims}D, ${s.frames} frames${s.source === "upload" ? ", uploaded" : ""})</option>`)
    .join("");
  // the first preset: the 256-frame 2D sample, from scratch, strep vs strep-nolink (a few minutes):
  // there the link decides the outcome (0.45 px against 134 px, docs/design/from-scratch.md)
  const preset = data.find((s) => s.id === "sample:sim2d");
  if (selectId) sel.value = selectId;
  else if (preset) sel.value = preset.id;
  showSequence();
}

function showSequence() {
  const s = state.sequences.find((x) => x.id === $("#sequence").value);
  $("#sequence-info").textContent = s
    ? `${s.points} points, unit ${s.unit || "?"}, ${s.has_ground_truth ? "ground truth: ATE shown" : "no ground truth"}`
    : "";
}

async function loadMethods() {
  const { data } = await api("/api/methods");
  state.methods = data;
  $("#methods").innerHTML = data
    .map((m) => `<label title="${esc(m.description)}"><input type="checkbox" value="${esc(m.name)}"
      ${m.name === "strep" || m.name === "strep-nolink" ? "checked" : ""}> ${esc(m.name)}</label>`)
    .join("");
}

async function start() {
  const methods = [...document.querySelectorAll("#methods input:checked")].map((i) => i.value);
  if (!methods.length) return say("choose at least one method", true);
  // no iteration count unless one is typed: the service's defaults apply (they depend on the start)
  const typed = $("#iterations").value.trim();
  const iterations = typed ? Number(typed) : null;
  if (typed && !(Number.isInteger(iterations) && iterations >= 1)) return say("iterations: a whole number, 1 or more", true);
  const planned = iterations ?? Number($("#start-mode").selectedOptions[0].dataset.iterations);
  // about 60 points per curve: an event (losses, poses, ATE) every few iterations
  const optim = { event_interval: Math.max(1, Math.ceil(planned / 60)) };
  if (iterations != null) optim.iterations = iterations;
  $("#start").disabled = true;
  try {
    const cmp = await api("/api/comparisons", {
      method: "POST",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ sequence_id: $("#sequence").value, methods, config: { start: $("#start-mode").value, optim } }),
    });
    say(`comparison ${cmp.id} started`);
    state.started = cmp.id;
    showComparison(cmp);
  } catch (err) {
    say(err.message, true);
  } finally {
    $("#start").disabled = false;
  }
}

function showComparison(cmp) {
  state.follow.clear();
  state.comparison = cmp.id;
  state.comparisonFiles = cmp.files || [];
  $("#live-title").textContent = `${cmp.sequence_id}: ${cmp.methods.join(" vs ")}`;
  for (const job of cmp.jobs || []) {
    state.jobs.delete(job.id);
    follow(job);
  }
  loadJobs();
}

async function upload(ev) {
  ev.preventDefault();
  const file = $("#upload-file").files[0];
  if (!file) return say("choose a file to upload", true);
  const form = new FormData();
  form.append("file", file);
  const frames = $("#upload-frames").value.trim();
  if (frames) form.append("frames", frames);
  $("#upload-button").disabled = true;
  say(`uploading ${file.name}…`);
  try {
    const seq = await api("/api/sequences", { method: "POST", body: form });
    say(`uploaded ${seq.name}: ${seq.frames} frames`);
    await loadSequences(seq.id);
  } catch (err) {
    say(`upload failed: ${err.message}`, true);
  } finally {
    $("#upload-button").disabled = false;
  }
}

// ---- history --------------------------------------------------------------------------------

async function loadJobs() {
  const { data } = await api("/api/jobs?limit=50").catch(() => ({ data: [] }));
  const body = $("#jobs tbody");
  body.innerHTML = data
    .map((j) => `<tr><td>${new Date(j.created_at).toLocaleString()}</td><td>${esc(j.sequence_id)}</td><td>${esc(j.method)}</td>
      <td class="status status-${j.status}" title="${esc(j.error)}">${j.status}</td>
      <td class="num">${fmt(j.metrics?.ate)}</td><td class="id">${esc(j.comparison_id || "")}</td>
      <td class="links"><a href="#" data-open="${j.comparison_id ? "c:" + j.comparison_id : "j:" + j.id}">open</a></td></tr>`)
    .join("");
}

async function openEntry(key) {
  if (key.startsWith("c:")) {
    showComparison(await api(`/api/comparisons/${key.slice(2)}`));
  } else {
    const job = await api(`/api/jobs/${key.slice(2)}`);
    showComparison({ id: null, sequence_id: job.sequence_id, methods: [job.method], jobs: [job] });
  }
}

// ---- downloads: a link cannot send the token, so with one the file is fetched and saved ------
// Without a token the browser follows the link itself (streamed to disk). With one, a plain link
// would get 401: the file is fetched with the Authorization header and saved from a blob URL,
// under the name the server gives (Content-Disposition). The token never goes into a URL.
function isApiDownload(link) {
  return Boolean(link) && new URL(link.href, location.href).pathname.startsWith("/api/");
}

async function download(link) {
  const res = await fetch(link.href, { headers: headers() });
  if (!res.ok) {
    const body = await res.json().catch(() => null);
    throw new Error(`download: ${(body && body.detail) || `${res.status} ${res.statusText}`}`);
  }
  const named = /filename="?([^";]+)"?/.exec(res.headers.get("content-disposition") || "");
  const url = URL.createObjectURL(await res.blob());
  const a = document.createElement("a");
  a.href = url;
  a.download = named ? named[1] : new URL(link.href).pathname.split("/").pop();
  document.body.appendChild(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 60_000);
}

document.addEventListener("click", async (ev) => {
  const t = ev.target;
  const link = t.closest?.("a[download]");
  if (token && isApiDownload(link)) {
    ev.preventDefault();
    download(link).catch((e) => say(e.message, true));
    return;
  }
  if (t.dataset?.open) { ev.preventDefault(); openEntry(t.dataset.open).catch((e) => say(e.message, true)); }
  if (t.dataset?.view) {
    // the link opens the viewer in its tab; the viewer (shared by all its tabs) switches to this run
    if (t.classList.contains("disabled")) { ev.preventDefault(); return; }
    api(`/api/${t.dataset.view}/view`, { method: "POST" }).catch((e) => say(`3D viewer: ${e.message}`, true));
  }
  if (t.dataset?.cancel) {
    ev.preventDefault();
    await api(`/api/jobs/${t.dataset.cancel}`, { method: "DELETE" }).catch((e) => say(e.message, true));
  }
});

async function init() {
  $("#start").addEventListener("click", start);
  window.addEventListener("resize", scheduleRedraw);
  $("#upload-form").addEventListener("submit", upload);
  $("#sequence").addEventListener("change", showSequence);
  // each start has its own default budget (the service's: SCRATCH_PROFILE, OptimConfig), shown, not sent
  const showDefault = () => {
    $("#iterations").placeholder = `default ${$("#start-mode").selectedOptions[0].dataset.iterations}`;
  };
  $("#start-mode").addEventListener("change", showDefault);
  showDefault();
  try {
    const health = await api("/api/health");
    // the viewer listens on the API's host: reach it through the name this page was loaded from
    state.viewer = health.viewer_port ? `${location.protocol}//${location.hostname}:${health.viewer_port}/` : null;
    for (const link of [$("#viewer-link"), $("#view-3d")]) {
      if (state.viewer) link.href = state.viewer;
      else link.hidden = true;
    }
    RULES = (await api("/api/events/rules")).rules;
    await Promise.all([loadSequences(), loadMethods(), loadJobs()]);
    redraw();
  } catch (err) {
    say(`cannot reach the service: ${err.message}`, true);
  }
}

init();
