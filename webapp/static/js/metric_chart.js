// One metric's line chart, shared by the Run and Compare pages.
//
//   const mc = new MetricChart(canvas, { name: "loss", runs: [{ id, label }] })
//   mc.setSeries(runId, { step: [...], wall_time: [...], value: [...] })   (replaces that run's arrays)
//   mc.append(runId, { step, wall_time, value })                            (live: points after the last)
//   mc.configure({ smoothing, xMode: "step" | "wall", logY, refs: [{ y, label, color, dash }] })
//   mc.render(); mc.resetZoom(); mc.destroy()
//   fetchSeries(ctx.api, runId, names[, after])   the points of any number of names
//
// The raw arrays stay here; every change of smoothing or axis rebuilds the datasets from them. Per
// run there are two datasets: the raw values ({x, y}, faint once smoothing is on) and, when the
// smoothing weight is > 0, TensorBoard's debiased EMA of them (drawn on top). Chart.getChart(canvas)
// .data.datasets[i].data holds exactly what is drawn (tests read it); a dataset's `hopeRun` and
// `hopeKind` ("raw" | "smoothed") say which is which.
//
// 100k points stay interactive on a phone: parsing off, a linear x (wall time is shown as elapsed
// time by the tick callback: Chart.js's time scale needs a date adapter we do not ship), no
// animation and Chart.js's LTTB decimation down to about two points per pixel of the visible range.
// Zoom and pan (x only: wheel, pinch, drag) come from chartjs-plugin-zoom; the reference lines (a
// run's held-out figures and their baselines) from the small plugin below.

export const COLORS = ["#2364d2", "#d2422c", "#1f8a4c", "#8e44ad", "#c77c02"];

// TensorBoard's smoothing: an EMA whose start is debiased (divided by 1 - w^n) so it does not
// begin at 0. Non-finite values are passed through and do not enter the average.
export function ema(values, weight) {
  const out = new Array(values.length);
  let last = 0, n = 0;
  for (let i = 0; i < values.length; i++) {
    const v = values[i];
    if (typeof v !== "number" || !isFinite(v)) { out[i] = v; continue; }
    last = last * weight + (1 - weight) * v;
    n += 1;
    out[i] = weight > 0 ? last / (1 - Math.pow(weight, n)) : v;
  }
  return out;
}

// "12:05" (m:ss) or "1:02:05" (h:mm:ss) from seconds
export function elapsed(seconds) {
  const s = Math.max(0, Math.round(seconds));
  const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), r = s % 60;
  const pad = (x) => String(x).padStart(2, "0");
  return h ? `${h}:${pad(m)}:${pad(r)}` : `${m}:${pad(r)}`;
}

const GATE_VQVAE_MAX_NMSE = 0.05;  // settings.gate_vqvae_max_nmse's default (hope_models/promote/baselines.py)

// The horizontal lines a chart of `metric` gets from a finished run's held-out figures
// (result.json summary.val): the figure itself and its baselines of the same horizon.
const MAX_NAMES = 12;  // the series API's limit per request

// GET /api/runs/<id>/series?names=... for any number of names (in requests of MAX_NAMES):
// {series: {name: {step, wall_time, value}}, last: the newest step any answer had, or null}
export async function fetchSeries(api, runId, names, after = null) {
  const series = {};
  let last = null;
  for (let i = 0; i < names.length; i += MAX_NAMES) {
    const chunk = names.slice(i, i + MAX_NAMES).map(encodeURIComponent).join(",");
    const q = after === null ? "" : `&after=${after}`;
    const data = await api(`/api/runs/${encodeURIComponent(runId)}/series?names=${chunk}${q}`);
    Object.assign(series, data.series);
    if (typeof data.last_step === "number") last = Math.max(last ?? data.last_step, data.last_step);
  }
  return { series, last };
}

export function referenceLines(metric, validation, component) {
  const v = validation || {};
  const out = [];
  const add = (key, label, color, dash = []) => {
    if (typeof v[key] === "number" && isFinite(v[key])) out.push({ y: v[key], label: `${label} ${fmt(v[key])}`, color, dash });
  };
  add(metric, `held-out ${metric}`, "#1f8a4c");
  add(`copy_last_${metric}`, "copy-last baseline (held-out)", "#c77c02", [6, 4]);
  add(`code_freq_${metric}`, "code-frequency baseline (held-out)", "#8e44ad", [6, 4]);
  if (metric.startsWith("wm_obs_mse")) add(metric.replace("wm_obs_mse", "wm_copy_obs_mse"), "copy-last baseline (held-out)", "#c77c02", [6, 4]);
  if (component === "vqvae" && metric === "recon_nmse") {
    out.push({ y: GATE_VQVAE_MAX_NMSE, label: `gate: at most ${GATE_VQVAE_MAX_NMSE} (default)`, color: "#c0392b", dash: [2, 3] });
  }
  return out;
}

const fmt = (v) => Number(v.toPrecision(4)).toString();

// Draws options.plugins.refLines.lines after the datasets, each labelled at the right edge.
const refLinesPlugin = {
  id: "refLines",
  afterDatasetsDraw(chart, _args, opts) {
    const lines = (opts && opts.lines) || [];
    const { ctx, chartArea: area, scales: { y } } = chart;
    if (!lines.length || !y) return;
    ctx.save();
    ctx.font = "11px system-ui, sans-serif";
    const right = [];  // the label heights taken at the right edge: a close one goes to the left
    for (const line of lines) {
      const py = y.getPixelForValue(line.y);
      if (!isFinite(py) || py < area.top || py > area.bottom) continue;
      ctx.strokeStyle = line.color; ctx.lineWidth = 1.5; ctx.setLineDash(line.dash || []);
      ctx.beginPath(); ctx.moveTo(area.left, py); ctx.lineTo(area.right, py); ctx.stroke();
      ctx.fillStyle = line.color;
      const crowded = right.some((other) => Math.abs(other - py) < 12);
      ctx.textAlign = crowded ? "left" : "right";
      ctx.fillText(line.label, crowded ? area.left + 4 : area.right - 4, py - 3);
      if (!crowded) right.push(py);
    }
    ctx.restore();
  },
};

export class MetricChart {
  constructor(canvas, { name, runs }) {
    this.name = name;
    this.runs = runs;                           // [{ id, label }], one colour each
    this.series = new Map();                    // run id -> { step, wall_time, value }
    this.opts = { smoothing: 0, xMode: "step", logY: false, refs: [] };
    this.canvas = canvas;
    this.chart = typeof Chart === "function" ? this._make(canvas) : null;
  }

  _make(canvas) {
    const self = this;
    function xTicks(value, index, ticks) {  // `this` is the scale: Chart.js's own numbers for steps
      return self.opts.xMode === "wall" ? elapsed(value) : Chart.Ticks.formatters.numeric.call(this, value, index, ticks);
    }
    return new Chart(canvas, {
      type: "line",
      data: { datasets: [] },
      plugins: [refLinesPlugin],
      options: {
        animation: false, maintainAspectRatio: false, parsing: false, normalized: true, spanGaps: true,
        interaction: { mode: "nearest", axis: "x", intersect: false },
        scales: {
          x: { type: "linear", title: { display: true, text: "step" }, ticks: { callback: xTicks, maxRotation: 0 } },
          y: { type: "linear", title: { display: false, text: this.name } },
        },
        plugins: {
          legend: { display: this.runs.length > 1, labels: { filter: (item, data) => data.datasets[item.datasetIndex].hopeKind !== "raw" || !this.opts.smoothing } },
          decimation: { enabled: true, algorithm: "lttb" },
          refLines: { lines: [] },
          tooltip: { callbacks: { title: (items) => items.length ? `${this.opts.xMode === "wall" ? "time " + elapsed(items[0].parsed.x) : "step " + items[0].parsed.x}` : "" } },
          zoom: {
            zoom: { wheel: { enabled: true }, pinch: { enabled: true }, mode: "x" },
            pan: { enabled: true, mode: "x" },
            limits: { x: { min: "original", max: "original" } },
          },
        },
      },
    });
  }

  setSeries(runId, s) {
    this.series.set(runId, { step: [...s.step], wall_time: [...s.wall_time], value: [...s.value] });
  }

  // live points: only those after the run's last step
  append(runId, s) {
    const cur = this.series.get(runId);
    if (!cur) { this.setSeries(runId, s); return s.step.length; }
    const last = cur.step.length ? cur.step[cur.step.length - 1] : -Infinity;
    let added = 0;
    for (let i = 0; i < s.step.length; i++) {
      if (s.step[i] <= last) continue;
      cur.step.push(s.step[i]); cur.wall_time.push(s.wall_time[i]); cur.value.push(s.value[i]);
      added += 1;
    }
    return added;
  }

  configure(opts) { Object.assign(this.opts, opts); }

  points() { return [...this.series.values()].reduce((n, s) => n + s.step.length, 0); }

  // rebuild the datasets from the raw arrays and draw (synchronously: animation is off)
  render() {
    const chart = this.chart;
    if (!chart) return;
    const { smoothing, xMode, logY, refs } = this.opts;
    const datasets = [];
    this.runs.forEach((run, i) => {
      const s = this.series.get(run.id);
      if (!s) return;
      const color = COLORS[i % COLORS.length];
      const t0 = s.wall_time.length ? s.wall_time[0] : 0;
      const xs = xMode === "wall" ? s.wall_time.map((t) => t - t0) : s.step;
      const raw = [], smooth = [];
      const sm = smoothing > 0 ? ema(s.value, smoothing) : null;
      for (let k = 0; k < xs.length; k++) {
        const y = s.value[k];
        if (typeof y !== "number" || !isFinite(y)) continue;  // a gap, not a zero
        raw.push({ x: xs[k], y });
        if (sm) smooth.push({ x: xs[k], y: sm[k] });
      }
      const label = run.label || this.name;
      datasets.push({ label, data: raw, hopeRun: run.id, hopeKind: "raw", borderColor: smoothing > 0 ? color + "44" : color,
                      borderWidth: smoothing > 0 ? 1 : 1.5, pointRadius: 0, order: 2 });
      if (sm) datasets.push({ label: `${label} (smoothed)`, data: smooth, hopeRun: run.id, hopeKind: "smoothed",
                              borderColor: color, borderWidth: 2, pointRadius: 0, order: 1 });
    });
    chart.data.datasets = datasets;
    const width = Math.max(100, chart.width || this.canvas.clientWidth || 300);
    Object.assign(chart.options.plugins.decimation, { samples: Math.round(2 * width), threshold: Math.round(2 * width) });
    chart.options.plugins.refLines.lines = refs || [];
    const ys = (refs || []).map((r) => r.y).filter((y) => !logY || y > 0);
    const y = chart.options.scales.y;
    y.type = logY ? "logarithmic" : "linear";
    y.suggestedMin = ys.length ? Math.min(...ys) : undefined;
    y.suggestedMax = ys.length ? Math.max(...ys) : undefined;
    chart.options.scales.x.title.text = xMode === "wall" ? "wall time (elapsed)" : "step";
    chart.update("none");
  }

  resetZoom() { if (this.chart && this.chart.resetZoom) this.chart.resetZoom("none"); }

  destroy() { if (this.chart) this.chart.destroy(); this.chart = null; }
}
