// Compare (#compare/<id>,<id>[,...]): 2-5 runs side by side, of the same component or not.
//
// A run picker (checkboxes over GET /api/runs; "Compare" writes the URL, so the URL alone
// reproduces a comparison), then for the picked runs: one overlay chart per picked metric (a picker
// over the union of their series names; each run its own colour and legend entry), their summaries
// side by side and a table of the config keys whose values differ (one column per run, the count
// of the keys equal in all below it).
//
// DOM contract (tests/test_browser_run.py):
//   #page-compare[data-runs="<id>,<id>"][data-rendered="1"] once the charts have drawn
//   #compare-runs input[type=checkbox][value=<run id>], #compare-apply, #compare-message
//   #compare-metric-picker input[value=<name>]; #compare-charts .metric-card[data-metric] canvas
//     (datasets carry hopeRun = run id)
//   #compare-diff tr[data-key] (td per run), #compare-same; #compare-summary tr[data-key]
import { $, el, num, duration } from "./util.js";
import { MetricChart, fetchSeries } from "./metric_chart.js";
import { MetricPicker } from "./metric_picker.js";
import { flatten, show as showValue } from "./run_provenance.js";

const MIN_RUNS = 2, MAX_RUNS = 5;
const PICKS_KEY = "hope.compare.metrics";

let ctx, picker;
let loadSeq = 0;
let runs = [];                // the compared runs' API objects, in URL order
let seriesNames = new Map();  // run id -> Set of its series names
const charts = new Map();     // metric -> { mc, card }

export function init(c) {
  ctx = c;
  picker = new MetricPicker($("#compare-metric-picker"), (names) => onPick(names));
  $("#compare-apply").addEventListener("click", () => {
    const ids = checkedIds();
    if (ids.length < MIN_RUNS || ids.length > MAX_RUNS) { setMessage(ids.length); return; }
    location.hash = `#compare/${ids.map(encodeURIComponent).join(",")}`;
  });
  $("#compare-runs").addEventListener("change", () => setMessage(checkedIds().length));
}

let inflight = null;           // { arg, promise } of the load under way

// app.js calls show() at login and again when the socket connects: one load serves both
export function show(arg) {
  if (inflight && inflight.arg === arg) return inflight.promise;
  const mine = { arg };
  mine.promise = load(arg).finally(() => { if (inflight === mine) inflight = null; });
  inflight = mine;
  return mine.promise;
}

async function load(arg) {
  const seq = ++loadSeq;
  const page = $("#page-compare");
  page.dataset.rendered = "0";
  const ids = [...new Set((arg || "").split(",").map((s) => s.trim()).filter(Boolean))];
  page.dataset.runs = ids.join(",");
  const list = await ctx.api("/api/runs?limit=50");
  if (seq !== loadSeq) return;
  renderPicker(list.runs, ids);
  setMessage(ids.length);
  clearCharts();
  $("#compare-body").hidden = true;
  if (ids.length < MIN_RUNS || ids.length > MAX_RUNS) return;
  const loaded = await Promise.all(ids.map(loadRun));
  if (seq !== loadSeq) return;
  runs = loaded.map((x) => x.run);
  seriesNames = new Map(loaded.map((x) => [x.run.id, new Set(x.names)]));
  $("#compare-body").hidden = false;
  renderSummary(loaded);
  renderDiff(loaded);
  const union = [];
  for (const x of loaded) for (const s of x.series) if (!union.some((u) => u.name === s.name)) union.push({ name: s.name });
  const available = new Set(union.map((u) => u.name));
  let stored = null;
  try { stored = JSON.parse(localStorage.getItem(PICKS_KEY) || "null"); } catch { /* ignore */ }
  let picks = (Array.isArray(stored) ? stored : ["loss"]).filter((n) => available.has(n));
  if (!picks.length && union.length) picks = [union[0].name];
  picker.setNames(union, picks);
  await buildCharts(picks, seq);
  if (seq === loadSeq) page.dataset.rendered = "1";
}

export const events = {};

async function loadRun(id) {
  const enc = encodeURIComponent(id);
  const [r, s, prov] = await Promise.all([ctx.api(`/api/runs/${enc}`), ctx.api(`/api/runs/${enc}/series`),
    ctx.api(`/api/runs/${enc}/provenance`).catch(() => null)]);
  return { run: r.run, series: s.series, names: s.series.map((x) => x.name),
           config: (prov && prov.config) || r.run.config || {},
           fingerprint: (prov && prov.dataset && prov.dataset.fingerprint) || r.run.dataset_fingerprint };
}

function checkedIds() {
  return [...document.querySelectorAll("#compare-runs input:checked")].map((b) => b.value);
}

function setMessage(n) {
  const msg = $("#compare-message");
  const ok = n >= MIN_RUNS && n <= MAX_RUNS;
  msg.textContent = ok ? `${n} runs picked.` : `Pick ${MIN_RUNS} to ${MAX_RUNS} runs to compare (${n} picked).`;
  msg.classList.toggle("error", !ok && n > MAX_RUNS);
  $("#compare-apply").disabled = !ok;
}

function renderPicker(list, ids) {
  const want = new Set(ids);
  $("#compare-runs tbody").replaceChildren(...list.map((r) => el("tr", { "data-run": r.id },
    el("td", {}, el("input", { type: "checkbox", value: r.id, checked: want.has(r.id), title: `compare ${r.id}` })),
    el("td", {}, el("a", { href: `#run/${encodeURIComponent(r.id)}`, text: r.id })),
    el("td", { text: r.component }), el("td", {}, el("span", { class: `state ${r.state}`, text: r.state })),
    el("td", { text: `${r.step ?? 0}/${r.total_steps ?? "?"}` }), el("td", { text: num(r.loss) }))));
  if (!list.length) $("#compare-runs tbody").append(el("tr", {}, el("td", { colSpan: 6, class: "muted", text: "No runs yet." })));
}

// a table with one column per run: rows [[key, [value per run]], ...]
function fillTable(sel, loaded, rows) {
  const table = $(sel);
  table.querySelector("thead").replaceChildren(el("tr", {}, el("th", { text: "" }),
    ...loaded.map((x) => el("th", {}, el("a", { href: `#run/${encodeURIComponent(x.run.id)}`, text: x.run.id })))));
  table.querySelector("tbody").replaceChildren(...rows.map(([key, values]) => el("tr", { "data-key": key },
    el("th", { text: key }), ...values.map((v) => el("td", { text: showValue(v) })))));
}

function renderSummary(loaded) {
  const took = (r) => (r.started_at && r.finished_at ? (new Date(r.finished_at) - new Date(r.started_at)) / 1000 : null);
  const rows = [
    ["component", loaded.map((x) => x.run.component)],
    ["state", loaded.map((x) => x.run.state)],
    ["steps", loaded.map((x) => `${x.run.step ?? 0} of ${x.run.total_steps ?? "?"}`)],
    ["final loss", loaded.map((x) => num(x.run.loss))],
    ["duration", loaded.map((x) => duration(took(x.run)))],
    ["dataset", loaded.map((x) => x.fingerprint)],
  ];
  const heldOut = [...new Set(loaded.flatMap((x) => Object.keys(x.run.validation || {})))].sort();
  for (const k of heldOut) rows.push([`held-out ${k}`, loaded.map((x) => num((x.run.validation || {})[k]))]);
  fillTable("#compare-summary", loaded, rows);
}

function renderDiff(loaded) {
  const flat = loaded.map((x) => new Map(flatten(x.config)));
  const keys = [...new Set(flat.flatMap((m) => [...m.keys()]))].sort();
  const rows = [];
  let same = 0;
  for (const k of keys) {
    const values = flat.map((m) => (m.has(k) ? m.get(k) : undefined));
    const texts = values.map((v) => (v === undefined ? "(absent)" : JSON.stringify(v)));
    if (texts.every((t) => t === texts[0])) same += 1;
    else rows.push([k, values.map((v) => (v === undefined ? "(absent)" : v))]);
  }
  fillTable("#compare-diff", loaded, rows);
  $("#compare-same").textContent = rows.length
    ? `${same} other keys are the same in all.` : `No differences: all ${same} keys are the same in all.`;
}

// -- overlay charts ---------------------------------------------------------------------------

function clearCharts() {
  for (const { mc } of charts.values()) mc.destroy();
  charts.clear();
  $("#compare-charts").replaceChildren();
}

async function buildCharts(picks, seq) {
  for (const [name, { mc, card }] of charts) {
    if (!picks.includes(name)) { mc.destroy(); card.remove(); charts.delete(name); }
  }
  const fresh = picks.filter((n) => !charts.has(n));
  const box = $("#compare-charts");
  for (const name of fresh) {
    const canvas = el("canvas", {});
    canvas.setAttribute("aria-label", `${name} of the compared runs`);
    const reset = el("button", { type: "button", class: "small secondary", text: "Reset zoom", "data-action": "reset" });
    const card = el("div", { class: "card metric-card", "data-metric": name },
      el("h3", {}, el("span", { class: "metric-name", text: name }), reset), el("div", { class: "chart-box" }, canvas));
    const mc = new MetricChart(canvas, { name, runs: runs.map((r) => ({ id: r.id, label: `${r.id} (${r.component})` })) });
    reset.addEventListener("click", () => mc.resetZoom());
    charts.set(name, { mc, card });
  }
  for (const name of picks) box.append(charts.get(name).card);
  if (!fresh.length) return;
  const perRun = await Promise.all(runs.map(async (r) => (await fetchSeries(ctx.api, r.id, fresh.filter((n) => seriesNames.get(r.id).has(n)))).series));
  if (seq !== loadSeq) return;
  for (const name of fresh) {
    const { mc, card } = charts.get(name) || {};
    if (!mc) continue;
    runs.forEach((r, i) => { if (perRun[i][name]) mc.setSeries(r.id, perRun[i][name]); });
    mc.render();
    card.dataset.points = String(mc.points());
  }
}

async function onPick(names) {
  localStorage.setItem(PICKS_KEY, JSON.stringify(names));
  $("#page-compare").dataset.rendered = "0";
  await buildCharts(names, loadSeq).catch((err) => ctx.flash(err.message, true));
  $("#page-compare").dataset.rendered = "1";
}
