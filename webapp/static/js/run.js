// Run (#run/<run id>): one run read in full. Its state and summary; a metric picker over every
// numeric series it recorded (GET /api/runs/<id>/series; loss preselected, picks remembered per
// component in localStorage), one chart per picked metric (metric_chart.js: EMA smoothing, linear or
// log y per chart, zoom/pan with a reset, step or wall-time x, the held-out figures and their
// baselines as reference lines); a frame VQ-VAE's held-out picture (run_picture.js); the config and
// provenance; the downloads.
//
// DOM contract (tests/test_browser_run.py):
//   #page-run[data-run]           the run shown; [data-rendered="1"] once every picked chart has
//                                 drawn its data (set again after each full load)
//   #run-metric-picker input[type=checkbox][value=<name>]
//   #run-smoothing (range 0..0.99), #run-xaxis (select: step | wall)
//   #run-charts .metric-card[data-metric=<name>][data-points=<n>] canvas; its buttons
//                                 [data-action=log] (aria-pressed) and [data-action=reset]
//   #run-facts dd[data-key], #run-config tr[data-key], #run-dataset dd[data-key="fingerprint"],
//   #run-downloads li[data-artifact] button
//   #run-picture (hidden without a picture), #run-picture img[data-loaded="1"], figcaption
//
// Live: run.progress moves the header; while the run is not finished and the tab is visible, the
// picked series are refetched every 2 s with ?after=<last step> (only the new points). run.state to
// a finished state reloads the page's data (the held-out figures arrive with it).
import { $, el, fillKv, num, duration } from "./util.js";
import { MetricChart, referenceLines, fetchSeries as fetchSeriesOf } from "./metric_chart.js";
import { MetricPicker } from "./metric_picker.js";
import { renderProvenance, renderDownloads } from "./run_provenance.js";
import { renderPicture, clearPicture } from "./run_picture.js";

const FINISHED = new Set(["completed", "failed", "cancelled"]);
const PICKS_KEY = (component) => `hope.run.metrics.${component}`;
const SMOOTH_KEY = "hope.run.smoothing";
const XMODE_KEY = "hope.run.xaxis";
const LAST_KEY = "hope.run.last";
const POLL_MS = 2000;

let ctx, picker;
let runId = null;
let run = null;
let loadSeq = 0;            // a newer show() makes an older one's late answers moot
let lastStep = null;        // the newest step fetched, for ?after=
let pollTimer = null;
const charts = new Map();   // metric name -> { mc: MetricChart, card }

export function init(c) {
  ctx = c;
  picker = new MetricPicker($("#run-metric-picker"), (names) => onPick(names));
  const smoothing = $("#run-smoothing");
  smoothing.value = localStorage.getItem(SMOOTH_KEY) ?? "0";
  showSmoothing();
  smoothing.addEventListener("input", () => {
    localStorage.setItem(SMOOTH_KEY, smoothing.value);
    showSmoothing();
    redraw();
  });
  const xaxis = $("#run-xaxis");
  xaxis.value = localStorage.getItem(XMODE_KEY) === "wall" ? "wall" : "step";
  xaxis.addEventListener("change", () => {
    localStorage.setItem(XMODE_KEY, xaxis.value);
    for (const { mc } of charts.values()) mc.resetZoom();  // a step range means nothing in seconds
    redraw();
  });
  $("#run-reset-all").addEventListener("click", () => { for (const { mc } of charts.values()) mc.resetZoom(); });
  $("#run-compare").addEventListener("click", () => { if (runId) location.hash = `#compare/${encodeURIComponent(runId)}`; });
  document.addEventListener("visibilitychange", schedulePoll);
}

let inflight = null;         // { arg, promise } of the load under way

// app.js calls show() at login and again when the socket connects, often while the first load is
// still under way: the same run's load is shared rather than started twice
export function show(arg) {
  if (inflight && inflight.arg === arg) return inflight.promise;
  return reload(arg);
}

function reload(arg) {
  const mine = { arg };
  mine.promise = load(arg).finally(() => { if (inflight === mine) inflight = null; });
  inflight = mine;
  return mine.promise;
}

async function load(arg) {
  stopPoll();
  arg = arg || localStorage.getItem(LAST_KEY);  // the Run tab alone reopens the last run read
  const page = $("#page-run");
  page.dataset.rendered = "0";
  page.dataset.run = arg || "";
  $("#run-empty").hidden = Boolean(arg);
  $("#run-body").hidden = !arg;
  if (arg !== runId) clearPicture();  // another run's picture never stands under this one's title
  if (!arg) { clearCharts(); runId = null; return; }
  const seq = ++loadSeq;
  runId = arg;
  localStorage.setItem(LAST_KEY, arg);
  const enc = encodeURIComponent(arg);
  // loss is nearly always picked: its points are asked for beside the listing, not after it
  const lossFirst = fetchSeries(["loss"]).catch(() => null);
  let r, list;
  try {
    [r, list] = await Promise.all([ctx.api(`/api/runs/${enc}`), ctx.api(`/api/runs/${enc}/series`)]);
  } catch (err) {
    if (err.status === 404 && localStorage.getItem(LAST_KEY) === arg) localStorage.removeItem(LAST_KEY);
    throw err;
  }
  if (seq !== loadSeq) return;
  run = r.run;
  renderHead();
  const available = new Set(list.series.map((s) => s.name));
  let stored = null;
  try { stored = JSON.parse(localStorage.getItem(PICKS_KEY(run.component)) || "null"); } catch { /* ignore */ }
  let picks = (Array.isArray(stored) ? stored : ["loss"]).filter((n) => available.has(n));
  if (!picks.length && list.series.length) picks = [list.series[0].name];
  picker.setNames(list.series, picks);
  const side = loadSide(seq, enc);  // config, provenance and downloads: beside the charts, not before them
  clearCharts();
  await buildCharts(picks, seq, picks.includes("loss") ? await lossFirst : null);
  if (seq !== loadSeq) return;
  page.dataset.rendered = "1";
  page.dataset.renderedMs = String(Math.round(performance.now()));  // since navigation start
  schedulePoll();
  await side;
}

export const events = {
  "run.progress": (d) => {
    if (!run || d.run_id !== runId) return;
    Object.assign(run, { step: d.step, total_steps: d.total ?? run.total_steps, loss: d.loss });
    if (run.state === "queued" || run.state === "starting") run.state = "running";
    renderHead();
    schedulePoll();
  },
  "run.state": (d) => {
    if (!run || d.run_id !== runId) return;
    run.state = d.state;
    renderHead();
    if (FINISHED.has(d.state) && !$("#page-run").hidden) reload(runId).catch((err) => ctx.flash(err.message, true));
  },
};

async function loadSide(seq, enc) {
  const [prov, arts] = await Promise.allSettled([ctx.api(`/api/runs/${enc}/provenance`), ctx.api(`/api/runs/${enc}/artifacts`)]);
  if (seq !== loadSeq) return;
  if (prov.status === "fulfilled") renderProvenance(prov.value);
  else $("#run-code").textContent = `provenance unavailable: ${prov.reason.message}`;
  if (arts.status === "fulfilled") renderDownloads(ctx, arts.value);
  else $("#run-downloads").replaceChildren(el("li", { class: "error", text: `artifacts unavailable: ${arts.reason.message}` }));
  await renderPicture(ctx, arts.status === "fulfilled" ? arts.value.artifacts : [], run, () => seq === loadSeq);
}

function renderHead() {
  $("#run-title").textContent = `${run.id} · ${run.component}`;
  const badge = $("#run-state");
  badge.textContent = run.state;
  badge.className = `state ${run.state}`;
  $("#page-run").dataset.state = run.state;
  const pct = run.total_steps ? Math.min(100, (100 * (run.step || 0)) / run.total_steps) : 0;
  $("#run-bar").style.width = `${pct}%`;
  const took = run.started_at ? ((run.finished_at ? new Date(run.finished_at) : new Date()) - new Date(run.started_at)) / 1000 : null;
  const rows = [
    ["steps", `${run.step ?? 0} of ${run.total_steps ?? "?"}`],
    ["loss", num(run.loss)],
    ["started", run.started_at ? new Date(run.started_at).toLocaleString() : null],
    ["duration", duration(took)],
  ];
  if (run.error) rows.push(["error", run.error]);
  for (const [k, v] of Object.entries(run.validation || {})) {
    if (typeof v === "number") rows.push([`held-out ${k}`, num(v)]);
  }
  fillKv("#run-facts", rows);
}

// -- charts -----------------------------------------------------------------------------------

function chartOpts(name) {
  return {
    smoothing: Number($("#run-smoothing").value) || 0,
    xMode: $("#run-xaxis").value,
    refs: referenceLines(name, run && run.validation, run && run.component),
  };
}

function showSmoothing() { $("#run-smoothing-value").textContent = Number($("#run-smoothing").value).toFixed(2); }

function redraw() {
  for (const [name, { mc, card }] of charts) {
    mc.configure(chartOpts(name));
    mc.render();
    card.dataset.points = String(mc.points());
  }
}

function clearCharts() {
  for (const { mc } of charts.values()) mc.destroy();
  charts.clear();
  $("#run-charts").replaceChildren();
  lastStep = null;
}

function makeCard(name) {
  const canvas = el("canvas", {});
  canvas.setAttribute("aria-label", `${name} chart`);
  const log = el("button", { type: "button", class: "small secondary", text: "log y", "data-action": "log" });
  log.setAttribute("aria-pressed", "false");
  const reset = el("button", { type: "button", class: "small secondary", text: "Reset zoom", "data-action": "reset" });
  const card = el("div", { class: "card metric-card", "data-metric": name },
    el("h3", {}, el("span", { class: "metric-name", text: name }), log, reset),
    el("div", { class: "chart-box" }, canvas));
  const mc = new MetricChart(canvas, { name, runs: [{ id: runId, label: name }] });
  log.addEventListener("click", () => {
    const on = log.getAttribute("aria-pressed") !== "true";
    log.setAttribute("aria-pressed", String(on));
    mc.configure({ logY: on });
    mc.resetZoom();
    mc.render();
  });
  reset.addEventListener("click", () => mc.resetZoom());
  return { mc, card };
}

function fetchSeries(names, after = null) { return fetchSeriesOf(ctx.api, runId, names, after); }

// one card per picked name, in picking order; only the new ones fetch their data
async function buildCharts(picks, seq, prefetched = null) {
  for (const [name, { mc, card }] of charts) {
    if (!picks.includes(name)) { mc.destroy(); card.remove(); charts.delete(name); }
  }
  const fresh = picks.filter((n) => !charts.has(n));
  const box = $("#run-charts");
  for (const name of fresh) charts.set(name, makeCard(name));
  for (const name of picks) box.append(charts.get(name).card);  // keeps the picking order
  if (!fresh.length) return;
  const have = prefetched ? prefetched.series : {};
  const rest = fresh.filter((n) => !(n in have));
  const more = rest.length ? await fetchSeries(rest) : { series: {}, last: null };
  if (seq !== loadSeq) return;
  const series = { ...have, ...more.series };
  const lasts = [prefetched && prefetched.last, more.last].filter((x) => typeof x === "number");
  const last = lasts.length ? Math.min(...lasts) : null;  // the older answer: a refresh skips what it has
  // a chart added later fetched further: the older ones' next refresh skips the steps it has
  if (lastStep === null && last !== null) lastStep = last;
  for (const name of fresh) {
    const entry = charts.get(name);
    if (!entry) continue;
    entry.mc.setSeries(runId, series[name] || { step: [], wall_time: [], value: [] });
    entry.mc.configure(chartOpts(name));
    entry.mc.render();
    entry.card.dataset.points = String(entry.mc.points());
  }
}

async function onPick(names) {
  if (!run) return;
  localStorage.setItem(PICKS_KEY(run.component), JSON.stringify(names));
  $("#page-run").dataset.rendered = "0";
  await buildCharts(names, loadSeq).catch((err) => ctx.flash(err.message, true));
  $("#page-run").dataset.rendered = "1";
}

// -- live -------------------------------------------------------------------------------------

function stopPoll() { clearTimeout(pollTimer); pollTimer = null; }

function schedulePoll() {
  if (pollTimer || !run || FINISHED.has(run.state) || document.hidden || $("#page-run").hidden) return;
  pollTimer = setTimeout(poll, POLL_MS);
}

async function poll() {
  pollTimer = null;
  const seq = loadSeq;
  if (!run) return;
  if (!charts.size) {  // nothing recorded at the last load: look for the first series again
    await reload(runId).catch((err) => console.warn("run reload", err));
    return;
  }
  try {
    const { series, last } = await fetchSeries([...charts.keys()], lastStep);
    if (seq !== loadSeq) return;
    let added = 0;
    for (const [name, { mc, card }] of charts) {
      const n = series[name] ? mc.append(runId, series[name]) : 0;
      if (n) { mc.render(); card.dataset.points = String(mc.points()); added += n; }
    }
    // how many refreshes brought points (the browser test checks live updates come this way)
    if (added) $("#page-run").dataset.polled = String(Number($("#page-run").dataset.polled || 0) + 1);
    if (last !== null) lastStep = lastStep === null ? last : Math.max(lastStep, last);
  } catch (err) {
    console.warn("run series refresh", err);
  }
  schedulePoll();
}
