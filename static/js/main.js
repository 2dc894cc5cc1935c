// STREP Studio's page: launch comparisons, follow them live. Plain ES modules, no dependencies,
// every asset served by the app (works offline). The service reduces each job's events to a
// typed snapshot (GET /api/jobs/{id}/state); this page draws snapshots and keeps no rules.

import { api, download, isApiDownload, token } from "./api.js";
import { followJob } from "./events.js";
import { COLORS, FINAL, followedStates, state } from "./state.js";
import {
  $, chosenStart, say, showJobs, showLive, showMethods, showSequence, showSequences, showStart, showStarts, showTitle,
} from "./views.js";

let redrawPending = false;
function scheduleRedraw() {
  if (redrawPending) return;
  redrawPending = true;
  requestAnimationFrame(() => { redrawPending = false; showLive(); });
}

/** Refresh the past jobs; returns them (newest first). */
async function loadJobs() {
  /** @type {{data: import("./state.js").Job[]}} */
  const { data } = await api("/api/jobs?limit=50").catch(() => ({ data: [] }));
  showJobs(data);
  return data;
}

/** @param {string | null} [selectId] */
async function loadSequences(selectId) {
  state.sequences = (await api("/api/sequences")).data;
  showSequences(selectId);
}

/**
 * Show a comparison (or one job) in the live panel and follow its jobs; the address keeps it,
 * so a reload shows it again.
 * @param {{id: string | null, sequence_id: string, methods: string[], jobs: import("./state.js").Job[], files?: string[]}} cmp
 */
function showComparison(cmp) {
  state.generation++;
  state.comparison = cmp.id;
  state.comparisonFiles = cmp.files || [];
  state.followed = cmp.jobs.map((job, i) => ({ id: job.id, method: job.method, color: COLORS[i % COLORS.length], state: null }));
  history.replaceState(null, "", `${location.pathname}${location.search}#${cmp.id ? `comparison=${cmp.id}` : `job=${cmp.jobs[0]?.id}`}`);
  showTitle(cmp.sequence_id, cmp.methods);
  showLive();
  for (const entry of state.followed) followJob(entry, scheduleRedraw).then(() => finished(entry.id));
  loadJobs();
}

/** A followed job ended: refresh the past jobs; at the comparison's end, say so and get its files.
 * @param {string} jobId */
async function finished(jobId) {
  if (!state.followed.some((f) => f.id === jobId)) return;
  loadJobs();
  const states = followedStates();
  if (!state.comparison || states.length < state.followed.length || !states.every((j) => FINAL.has(j.status))) return;
  const id = state.comparison;
  if (state.started === id) {
    /** @type {Record<string, number>} */
    const counts = {};
    for (const j of states) counts[j.status] = (counts[j.status] || 0) + 1;
    say(`comparison ${id} finished: ${Object.entries(counts).map(([k, n]) => `${n} ${k}`).join(", ")}`,
      states.some((j) => j.status !== "succeeded"));
    state.started = null;
  }
  // the comparison's recording is written shortly after its last job: ask until it is there
  for (let i = 0; i < 20 && state.comparison === id; i++) {
    /** @type {import("./state.js").Comparison | null} */
    const cmp = await api(`/api/comparisons/${id}`).catch(() => null);
    if (cmp && state.comparison === id) state.comparisonFiles = cmp.files;
    if (!cmp || cmp.files.length || !FINAL.has(cmp.status)) break;
    await new Promise((r) => setTimeout(r, 1e3));
  }
  scheduleRedraw();
}

async function start() {
  const methods = [...document.querySelectorAll("#methods input:checked")].map((i) => /** @type {HTMLInputElement} */ (i).value);
  if (!methods.length) return say("choose at least one method", true);
  // no iteration count unless one is typed: the service's defaults apply (they depend on the start)
  const typed = /** @type {HTMLInputElement} */ ($("#iterations")).value.trim();
  const iterations = typed ? Number(typed) : null;
  if (typed && !(Number.isInteger(iterations) && Number(iterations) >= 1)) return say("iterations: a whole number, 1 or more", true);
  const planned = iterations ?? chosenStart()?.iterations ?? 60;
  // about 60 points per curve: an event (losses, poses, ATE) every few iterations
  /** @type {{event_interval: number, iterations?: number}} */
  const optim = { event_interval: Math.max(1, Math.ceil(planned / 60)) };
  if (iterations != null) optim.iterations = iterations;
  const button = /** @type {HTMLButtonElement} */ ($("#start"));
  button.disabled = true;
  try {
    /** @type {import("./state.js").Comparison} */
    const cmp = await api("/api/comparisons", {
      method: "POST",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify({
        sequence_id: /** @type {HTMLSelectElement} */ ($("#sequence")).value, methods,
        config: { start: /** @type {HTMLSelectElement} */ ($("#start-mode")).value, optim },
      }),
    });
    say(`comparison ${cmp.id} started`);
    state.started = cmp.id;
    showComparison(cmp);
  } catch (err) {
    say(/** @type {Error} */ (err).message, true);
  } finally {
    button.disabled = false;
  }
}

/** @param {SubmitEvent} ev */
async function upload(ev) {
  ev.preventDefault();
  const file = /** @type {HTMLInputElement} */ ($("#upload-file")).files?.[0];
  if (!file) return say("choose a file to upload", true);
  const form = new FormData();
  form.append("file", file);
  const frames = /** @type {HTMLInputElement} */ ($("#upload-frames")).value.trim();
  if (frames) form.append("frames", frames);
  const button = /** @type {HTMLButtonElement} */ ($("#upload-button"));
  button.disabled = true;
  say(`uploading ${file.name}…`);
  try {
    /** @type {import("./state.js").Sequence} */
    const seq = await api("/api/sequences", { method: "POST", body: form });
    say(`uploaded ${seq.name}: ${seq.frames} frames`);
    await loadSequences(seq.id);
  } catch (err) {
    say(`upload failed: ${/** @type {Error} */ (err).message}`, true);
  } finally {
    button.disabled = false;
  }
}

/** Open `comparison=ID` or `job=ID` (a past job's link, or the address after a reload).
 * @param {string} key */
async function openEntry(key) {
  const [kind, id] = key.split("=");
  if (kind === "comparison") {
    showComparison(await api(`/api/comparisons/${id}`));
  } else if (kind === "job") {
    /** @type {import("./state.js").Job} */
    const job = await api(`/api/jobs/${id}`);
    showComparison({ id: null, sequence_id: job.sequence_id, methods: [job.method], jobs: [job] });
  }
}

document.addEventListener("click", async (ev) => {
  const t = /** @type {HTMLElement} */ (ev.target);
  const link = /** @type {HTMLAnchorElement | null} */ (t.closest?.("a[download]"));
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
  $("#upload-form").addEventListener("submit", (ev) => upload(/** @type {SubmitEvent} */ (ev)));
  $("#sequence").addEventListener("change", showSequence);
  $("#start-mode").addEventListener("change", showStart);
  try {
    const health = await api("/api/health");
    // the viewer listens on the API's host: reach it through the name this page was loaded from
    state.viewer = health.viewer_port ? `${location.protocol}//${location.hostname}:${health.viewer_port}/` : null;
    for (const link of [/** @type {HTMLAnchorElement} */ ($("#viewer-link")), /** @type {HTMLAnchorElement} */ ($("#view-3d"))]) {
      if (state.viewer) link.href = state.viewer;
      else link.hidden = true;
    }
    const [methods, starts, preset] = await Promise.all([api("/api/methods"), api("/api/starts"), api("/api/preset")]);
    state.methods = methods.data;
    state.starts = starts.data;
    state.preset = preset;
    await loadSequences();
    showMethods();
    showStarts(preset.start);
    if (location.hash.length > 1) {
      await openEntry(location.hash.slice(1));
    } else {
      // a fresh page while a run goes on (another tab started it): show that run
      const running = (await loadJobs()).find((j) => j.status === "running" || j.status === "queued");
      if (running) await openEntry(running.comparison_id ? `comparison=${running.comparison_id}` : `job=${running.id}`);
      else showLive();
    }
  } catch (err) {
    say(`cannot reach the service: ${/** @type {Error} */ (err).message}`, true);
  }
}

// for tests and the console: the page's state (read-only by convention)
Object.assign(window, { strepPage: state });
init();
