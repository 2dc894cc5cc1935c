// Line charts on a canvas: linear or log y (log when the values span decades), an x axis in the
// runs' own terms (iterations, frames), start and end markers for one-step methods.

/**
 * @typedef {import("./state.js").Point} Point
 * @typedef {object} Series
 * @property {string} color
 * @property {Point[]} points
 * @property {Point | null} [start]  drawn as a hollow marker (e.g. the initial guess)
 * @property {Point | null} [end]  drawn as a filled marker (the result), joined by a dashed step
 * @typedef {object} ChartOptions
 * @property {string} xLabel  what x counts ("iterations", "frames": the server's word)
 * @property {number} xMax  the x axis's end (at least every point's x)
 * @property {string} empty  the text of a chart without points
 * @property {boolean | "auto"} [log]  a log y axis; "auto": when the values span over DECADES
 */

/** max / min of the values above which "auto" draws a log axis: over 1.5 decades */
export const DECADES = 30;

/**
 * A number with 3 significant digits (whole from a thousand up, as the server words them), or "–".
 * @param {number | null | undefined} v
 * @returns {string}
 */
export function fmt(v) {
  if (typeof v !== "number" || !isFinite(v)) return "–";
  return Math.abs(v) >= 1e3 ? Math.round(v).toString() : Number(v.toPrecision(3)).toString();
}

/**
 * Size a canvas's pixels to its box on screen (sharp on any display).
 * @param {HTMLCanvasElement} canvas
 */
function fitCanvas(canvas) {
  const dpr = window.devicePixelRatio || 1;
  const W = canvas.clientWidth || canvas.width, H = canvas.clientHeight || canvas.height;
  if (canvas.width !== Math.round(W * dpr) || canvas.height !== Math.round(H * dpr)) {
    canvas.width = Math.round(W * dpr);
    canvas.height = Math.round(H * dpr);
  }
  const ctx = /** @type {CanvasRenderingContext2D} */ (canvas.getContext("2d"));
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  return { ctx, W, H };
}

/**
 * Y ticks: each power of ten in range on a log axis spanning over one, else 5 even steps.
 * @param {number} y0 @param {number} y1 @param {boolean} log
 * @returns {number[]} tick positions in axis units (log10 of the value on a log axis)
 */
function yTicks(y0, y1, log) {
  if (log && y1 - y0 >= 1) {
    const out = [];
    for (let k = Math.ceil(y0); k <= Math.floor(y1); k++) out.push(k);
    if (out.length >= 2) return out;
  }
  return [0, 1, 2, 3, 4].map((i) => y0 + ((y1 - y0) * i) / 4);
}

/**
 * Draw `series` on `canvas`; returns whether the y axis is logarithmic.
 * @param {HTMLCanvasElement} canvas
 * @param {Series[]} series
 * @param {ChartOptions} options
 * @returns {boolean}
 */
export function drawChart(canvas, series, { xLabel, xMax, empty, log = "auto" }) {
  const { ctx, W, H } = fitCanvas(canvas);
  const R = 12, T = 10, B = 26;
  ctx.clearRect(0, 0, W, H);
  ctx.font = "11px system-ui, sans-serif";
  ctx.fillStyle = "#6b7385";
  /** @param {Series} s @returns {Point[]} */
  const all = (s) => [...s.points, ...(s.start ? [s.start] : []), ...(s.end ? [s.end] : [])];
  const values = series.flatMap(all).map((p) => p[1]).filter((y) => isFinite(y));
  const positive = values.filter((y) => y > 0);
  const isLog = log === "auto"
    ? positive.length === values.length && positive.length > 1 && Math.max(...positive) / Math.min(...positive) > DECADES
    : log && positive.length > 0;
  const ok = (/** @type {number} */ y) => isFinite(y) && (!isLog || y > 0);
  const ys = values.filter(ok);
  if (!ys.length) {
    ctx.fillText(empty, 12, H / 2);
    canvas.dataset.x = "";
    canvas.dataset.y = "";
    return isLog;
  }
  /** @param {number} y */
  const ty = (y) => (isLog ? Math.log10(y) : y);
  const x0 = 0;
  const x1 = Math.max(xMax, 1, ...series.flatMap(all).map((p) => p[0]));
  let y0 = Math.min(...ys.map(ty)), y1 = Math.max(...ys.map(ty));
  if (y1 === y0) { y0 -= 0.5; y1 += 0.5; }
  if (!isLog) { const pad = (y1 - y0) * 0.05; y0 = Math.max(y0 - pad, Math.min(0, y0)); y1 += pad; }
  else if (y1 - y0 >= 1) { y0 = Math.floor(y0); y1 = Math.ceil(y1); }  // whole decades, each labelled
  const ticks = yTicks(y0, y1, isLog).map((v) => ({ v, text: fmt(isLog ? 10 ** v : v) }));
  // the plot starts right of the widest tick label, so no label lies on a curve
  const L = Math.ceil(Math.max(...ticks.map((t) => ctx.measureText(t.text).width))) + 12;
  /** @param {number} x */
  const px = (x) => L + ((x - x0) / (x1 - x0)) * (W - L - R);
  /** @param {number} y */
  const py = (y) => T + (1 - (ty(y) - y0) / (y1 - y0)) * (H - T - B);
  ctx.strokeStyle = "#dde1e8";
  ctx.lineWidth = 1;
  ctx.textAlign = "right";
  for (const { v, text } of ticks) {
    const yy = T + (1 - (v - y0) / (y1 - y0)) * (H - T - B);
    ctx.beginPath(); ctx.moveTo(L, yy); ctx.lineTo(W - R, yy); ctx.stroke();
    ctx.fillText(text, L - 6, yy + 4);
  }
  ctx.textAlign = "left";
  ctx.fillText("0", L, H - 8);
  ctx.textAlign = "right";
  ctx.fillText(`${Math.round(x1)} ${xLabel}`, W - R, H - 8);
  // what the axes say, for tests and tools (a canvas's text cannot be read back)
  canvas.dataset.x = `${Math.round(x1)} ${xLabel}`;
  canvas.dataset.y = isLog ? "log" : "linear";
  ctx.textAlign = "left";
  // earlier series wider, so a curve that another one covers still shows at its edges
  series.forEach((s, i) => {
    const p = s.points.filter(([, y]) => ok(y));
    ctx.strokeStyle = s.color;
    ctx.fillStyle = s.color;
    ctx.lineWidth = Math.max(1.5, 2 + 1.5 * (series.length - 1 - i));
    ctx.setLineDash([]);
    ctx.beginPath();
    p.forEach(([x, y], k) => (k ? ctx.lineTo(px(x), py(y)) : ctx.moveTo(px(x), py(y))));
    ctx.stroke();
    const from = p.length ? p[p.length - 1] : s.start;
    if (s.end && ok(s.end[1])) {
      if (from && ok(from[1])) {  // the step to the result, dashed
        ctx.setLineDash([4, 3]);
        ctx.lineWidth = 1.5;
        ctx.beginPath(); ctx.moveTo(px(from[0]), py(from[1])); ctx.lineTo(px(s.end[0]), py(s.end[1])); ctx.stroke();
        ctx.setLineDash([]);
      }
      ctx.beginPath(); ctx.arc(px(s.end[0]), py(s.end[1]), 4.5, 0, 2 * Math.PI); ctx.fill();
    }
    if (s.start && ok(s.start[1])) {
      ctx.lineWidth = 2;
      ctx.fillStyle = "#fff";
      ctx.beginPath(); ctx.arc(px(s.start[0]), py(s.start[1]), 4, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
    }
  });
  return isLog;
}
