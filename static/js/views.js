// What the page shows, drawn from the state the service sent: the launch form's choices, the
// live panel (charts, legend, results) and past jobs. Nothing here knows an event kind.

import { drawChart, fmt } from "./charts.js";
import { followedStates, sequenceName, state } from "./state.js";

/** @param {string} sel @returns {HTMLElement} */
export const $ = (sel) => /** @type {HTMLElement} */ (document.querySelector(sel));

/**
 * Text from the service (names, errors, uploaded file names) goes into HTML only through this.
 * @param {unknown} value
 * @returns {string}
 */
export function esc(value) {
  return String(value ?? "").replace(/[&<>"']/g, (c) => `&#${c.charCodeAt(0)};`);
}

/** @param {string} text @param {boolean} [isError] */
export function say(text, isError = false) {
  const el = $("#message");
  el.textContent = text;
  el.className = isError ? "error" : "";
}

// ---- the launch form -------------------------------------------------------------------------

/** @param {string | null} [selectId] the sequence to select (a fresh upload; else the preset's) */
export function showSequences(selectId) {
  const sel = /** @type {HTMLSelectElement} */ ($("#sequence"));
  sel.innerHTML = state.sequences
    .map((s) => `<option value="${esc(s.id)}" title="${esc(s.name)}">${esc(s.name)} (${s.dims}D, ${s.frames} frames)</option>`)
    .join("");
  const preset = state.sequences.find((s) => s.id === state.preset?.sequence_id);
  if (selectId) sel.value = selectId;
  else if (preset) sel.value = preset.id;
  showSequence();
}

export function showSequence() {
  const s = state.sequences.find((x) => x.id === /** @type {HTMLSelectElement} */ ($("#sequence")).value);
  $("#sequence-info").textContent = s
    ? `${s.source === "upload" ? "uploaded; " : ""}${s.points} points, unit ${s.unit || "?"}, ` +
      `${s.has_ground_truth ? "ground truth: ATE shown" : "no ground truth"}`
    : "";
}

export function showMethods() {
  $("#methods").innerHTML = state.methods
    .map((m) => `<label title="${esc(m.description)}"><input type="checkbox" value="${esc(m.name)}"
      ${state.preset?.methods.includes(m.name) ? "checked" : ""}> ${esc(m.name)}</label>`)
    .join("");
}

/** @param {string} selected */
export function showStarts(selected) {
  const sel = /** @type {HTMLSelectElement} */ ($("#start-mode"));
  sel.innerHTML = state.starts.map((s) => `<option value="${esc(s.name)}">${esc(s.label)}</option>`).join("");
  sel.value = selected;
  showStart();
}

/** The chosen start's description and default budget (the service's), shown, not sent. */
export function showStart() {
  const start = chosenStart();
  if (!start) return;
  $("#start-info").textContent = start.description;
  /** @type {HTMLInputElement} */ ($("#iterations")).placeholder = `default ${start.iterations}`;
}

/** @returns {import("./state.js").Start | undefined} */
export function chosenStart() {
  const name = /** @type {HTMLSelectElement} */ ($("#start-mode")).value;
  return state.starts.find((s) => s.name === name);
}

// ---- the live panel --------------------------------------------------------------------------

/** @param {import("./state.js").Followed} f */
function learned(f) {
  return f.state ? f.state.run.learned : Boolean(state.methods.find((m) => m.name === f.method)?.learned);
}

/**
 * Show or hide a figure and set its caption.
 * @param {string} id @param {boolean} shown @param {string} caption
 */
function figure(id, shown, caption) {
  $(`#${id}-figure`).hidden = !shown;
  $(`#${id}-caption`).textContent = caption;
}

export function showLive() {
  const followed = state.followed;
  const states = followedStates();
  const running = states.some((j) => j.status === "running" || j.status === "queued") || states.length < followed.length;
  const empty = !followed.length ? "start a comparison to see its curves" : running ? "waiting for the first iteration…" : "no iterations";
  const unit = states.map((j) => j.run.unit).find(Boolean);
  /** @param {boolean} log */
  const u = (log) => (unit || log ? ` (${[unit, log ? "log scale" : ""].filter(Boolean).join(", ")})` : "");
  const lrn = followed.filter(learned), cls = followed.filter((f) => !learned(f));
  const xMax = (/** @type {import("./state.js").Followed[]} */ fs) => Math.max(0, ...fs.map((f) => f.state?.run.total ?? 0));

  // learned methods: loss and ATE over iterations, from the starting poses (iteration 0)
  const showIters = lrn.length > 0 || !followed.length;
  if (showIters) {
    const xs = { xLabel: "iterations", xMax: xMax(lrn), empty };
    const lossLog = drawChart(/** @type {HTMLCanvasElement} */ ($("#loss-chart")),
      lrn.map((f) => ({ color: f.color, points: f.state?.run.loss ?? [] })), { ...xs, log: true });
    const curves = lrn.map((f) => ({ color: f.color, points: f.state?.run.ate ?? [] }));
    const ateLog = drawChart(/** @type {HTMLCanvasElement} */ ($("#ate-chart")), curves, xs);
    const fromZero = curves.length > 0 && curves.every((c) => c.points.length && c.points[0][0] === 0);
    figure("loss", true, `Loss (total${lossLog ? ", log scale" : ""}) over iterations`);
    figure("ate", true, `ATE${u(ateLog)} over iterations` +
      (fromZero ? ", from the starting poses (iteration 0)" : ""));
  } else {
    figure("loss", false, "");
    figure("ate", false, "");
  }
  // classical methods: ATE over the frames placed, the initial guess and the result as markers
  if (cls.length) {
    const series = cls.map((f) => ({
      color: f.color, points: f.state?.run.ate ?? [], start: f.state?.run.ate_start, end: f.state?.run.ate_end,
    }));
    const log = drawChart(/** @type {HTMLCanvasElement} */ ($("#frames-chart")), series,
      { xLabel: "frames", xMax: xMax(cls), empty: running ? "waiting for the first frames…" : "no frames placed" });
    figure("frames", true, `ATE${u(log)} of the frames placed so far; ○ initial guess, ● result`);
  } else {
    figure("frames", false, "");
  }

  $("#legend").innerHTML = followed
    .map((f) => `<span class="legend-item"><span class="swatch" style="background:${f.color}"></span>${esc(f.method)}</span>`)
    .join("");
  const body = /** @type {HTMLTableSectionElement} */ ($("#results tbody"));
  body.innerHTML = followed.map(resultRow).join("");
  showActions();
}

/** @param {import("./state.js").Followed} f @returns {string} */
function resultRow(f) {
  const j = f.state;
  const status = j?.status ?? "queued";
  const run = j?.run;
  const unit = run?.unit ? ` ${esc(run.unit)}` : "";
  const files = j && j.status === "succeeded"
    ? j.files.map((name) => `<a href="/api/jobs/${j.id}/files/${encodeURIComponent(name)}" download title="${esc(name)}">${esc(name.split(".")[0])}</a>`).join(" ")
    : status === "running" || status === "queued" ? `<a href="#" data-cancel="${f.id}">cancel</a>` : "";
  return `<tr data-job-id="${f.id}"><td><span class="swatch" style="background:${f.color}"></span>${esc(f.method)}</td>
    <td class="status status-${status}" title="${esc(j?.error)}">${status}</td>
    <td class="stage">${esc(run?.stage_text ?? "waiting for the service…")}</td>
    <td class="num progress">${esc(run?.progress || "–")}</td>
    <td class="num ate">${fmt(run?.ate_now)}${run?.ate_now != null ? unit : ""}</td>
    <td class="num">${fmt(run?.point_l2)}${run?.point_l2 != null ? unit : ""}</td>
    <td class="num">${fmt(run?.seconds)}</td>
    <td class="links">${files}</td></tr>`;
}

/** The run's links: the 3D viewer (shows this run there) and the comparison's recording. */
function showActions() {
  const view = /** @type {HTMLAnchorElement} */ ($("#view-3d")), rrd = /** @type {HTMLAnchorElement} */ ($("#comparison-rrd"));
  const jobs = state.followed;
  const started = followedStates().some((j) => j.status !== "queued");
  view.hidden = !state.viewer || !jobs.length;
  view.classList.toggle("disabled", !started);
  view.dataset.view = state.comparison ? `comparisons/${state.comparison}` : jobs.length ? `jobs/${jobs[0].id}` : "";
  const name = state.comparisonFiles[0];
  rrd.hidden = !name;
  if (name) {
    rrd.href = `/api/comparisons/${state.comparison}/files/${encodeURIComponent(name)}`;
    rrd.textContent = `Comparison ${name.split(".")[0]}`;
  }
}

/** @param {string} sequenceId @param {string[]} methods */
export function showTitle(sequenceId, methods) {
  $("#live-title").textContent = `${sequenceName(sequenceId)}: ${methods.join(" vs ")}`;
}

// ---- past jobs -------------------------------------------------------------------------------

/** @param {import("./state.js").Job[]} jobs */
export function showJobs(jobs) {
  $("#jobs tbody").innerHTML = jobs
    .map((j) => `<tr><td>${new Date(j.created_at).toLocaleString()}</td><td>${esc(sequenceName(j.sequence_id))}</td><td>${esc(j.method)}</td>
      <td class="status status-${j.status}" title="${esc(j.error)}">${j.status}</td>
      <td class="num">${fmt(/** @type {number | undefined} */ (j.metrics?.ate))}</td><td class="id">${esc(j.comparison_id || "")}</td>
      <td class="links"><a href="#" data-open="${j.comparison_id ? "comparison=" + j.comparison_id : "job=" + j.id}">open</a></td></tr>`)
    .join("");
}
