// Jobs: the queue, starting runs, pause/resume/cancel, and one selected run in detail (a loss
// chart rebuilt from GET /api/runs/<id>/metrics, then moved by live run.progress events; the log
// tail; the convergence summary once it has finished). A run in state "starting" was sent to its
// queue but no worker has taken it; its `waiting` text (and a queued run's held behind it) is
// shown under its state, so a queue with no worker reads as waiting, not as training.
import { $, setText, fillKv, el, num, duration } from "./util.js";

const SELECTED_KEY = "hope.selectedRun";
const FINISHED = new Set(["completed", "failed", "cancelled"]);
const LOG_LINES = 200;

let ctx;
const runs = new Map();       // id -> run JSON, as the table shows it
let selected = null;           // run id in the detail view
let chart = null;
let lastStep = -1;             // the chart's newest step: older progress events are ignored
let peakRss = null;
let refreshTimer = null;
const ticked = new Set();     // run ids ticked for Compare (2-5)

export function init(c) {
  ctx = c;
  $("#start-form").addEventListener("submit", onStart);
  for (const r of document.querySelectorAll('input[name="mode"]')) r.addEventListener("change", onMode);
  $("#refresh-runs").addEventListener("click", () => loadRuns());
  $("#runs-table tbody").addEventListener("click", onTableClick);
  $("#runs-table tbody").addEventListener("change", onCompareTick);
  $("#compare-runs-button").addEventListener("click", () => {
    location.hash = `#compare/${[...ticked].map(encodeURIComponent).join(",")}`;
  });
  $("#promote-run").addEventListener("click", onPromote);
  selected = localStorage.getItem(SELECTED_KEY);
}

export async function show() {
  await loadRuns();
  if (!selected || !runs.has(selected)) {
    const first = [...runs.values()].find((r) => r.state === "running") || [...runs.values()][0];
    selected = first ? first.id : null;
  }
  if (selected) await selectRun(selected);
}

export const events = {
  "run.progress": (d) => {
    const run = runs.get(d.run_id);
    if (run) {
      Object.assign(run, { step: d.step, total_steps: d.total ?? run.total_steps, loss: d.loss,
                           steps_per_s: d.steps_per_s });
      if (run.state === "queued" || run.state === "starting") { run.state = "running"; run.waiting = null; }
      renderRow(run);
    } else {
      scheduleRefresh();
    }
    if (d.run_id === selected) {
      // how many points live events added (the browser test checks the chart moves by events)
      if (addPoint(d.step, d.loss)) {
        const detail = $("#run-detail");
        detail.dataset.livePoints = String(Number(detail.dataset.livePoints || 0) + 1);
      }
      if (typeof d.rss_mb === "number") peakRss = Math.max(peakRss ?? 0, d.rss_mb);
      renderProgress(d.step, d.total, d);
    }
  },
  "run.state": (d) => {
    stateEvents.set(d.run_id, d.state);
    const run = runs.get(d.run_id);
    // the full `waiting` text (since when, how to start a worker) comes with the refresh below
    const waiting = eventWaiting(d.state, run?.queue);
    if (run) { run.state = d.state; run.waiting = waiting; run.pause_reason = d.reason ?? run.pause_reason; renderRow(run); }
    if (d.run_id === selected) {
      appendLog(`[state] ${d.from ?? "?"} -> ${d.state}${d.message ? ": " + d.message : ""}`);
      if (FINISHED.has(d.state)) selectRun(selected, { keepLog: true });  // the final numbers and the summary
      else setState(d.state, waiting);
    }
    scheduleRefresh();  // queue order, a sequence's next member, ...
  },
  "run.log": (d) => {
    if (d.run_id !== selected) return;
    if (d.kind === "checkpoint") appendLog(`[checkpoint] step ${d.step ?? "?"} ${d.path ?? ""}`);
    else appendLog(`[${d.level ?? d.kind ?? "log"}] ${d.message ?? JSON.stringify(d)}`);
  },
};

function scheduleRefresh() {
  clearTimeout(refreshTimer);
  refreshTimer = setTimeout(() => loadRuns().catch(() => {}), 300);
}

// -- the queue --------------------------------------------------------------------------------

async function loadRuns() {
  const data = await ctx.api("/api/runs?limit=50");
  runs.clear();
  for (const r of data.runs) runs.set(r.id, r);
  const tbody = $("#runs-table tbody");
  tbody.replaceChildren();
  if (!data.runs.length) {
    tbody.append(el("tr", {}, el("td", { colSpan: 7, class: "muted", text: "No runs yet: queue one." })));
  }
  for (const r of data.runs) tbody.append(el("tr", { "data-run": r.id }));
  for (const r of data.runs) renderRow(r);
}

function controls(run) {
  const b = (action, label, cls = "small secondary") => el("button", { type: "button", class: cls, text: label,
                                                                       "data-action": action });
  const out = [];
  if (run.state === "running" || run.state === "queued" || run.state === "starting") out.push(b("pause", "Pause"));
  if (run.state === "paused" || run.state === "interrupted") out.push(b("resume", "Resume"));
  if (!FINISHED.has(run.state)) out.push(b("cancel", "Cancel", "small danger"));
  return out;
}

function renderRow(run) {
  const tr = $(`#runs-table tr[data-run="${CSS.escape(run.id)}"]`);
  if (!tr) return;
  const pct = run.total_steps ? Math.round((100 * (run.step || 0)) / run.total_steps) : 0;
  const seq = run.sequence_id ? ` (${(run.sequence_index ?? 0) + 1} of seq)` : "";
  tr.replaceChildren(
    el("td", { text: run.id }),
    el("td", { text: run.component + seq }),
    el("td", {}, el("span", { class: `state ${run.state}`, text: run.state + (run.pause_reason && run.state === "paused" ? ` (${run.pause_reason})` : "") }),
       ...(run.waiting ? [el("div", { class: "muted waiting", text: shortWaiting(run), title: run.waiting })] : [])),
    el("td", { text: `${run.step ?? 0}/${run.total_steps ?? "?"} (${pct}%)` }),
    el("td", { text: num(run.loss) }),
    el("td", {}, ...controls(run)),
    el("td", { class: "open-cell" }, el("a", { href: `#run/${encodeURIComponent(run.id)}`, text: "open", "data-open": run.id }),
       el("input", { type: "checkbox", value: run.id, checked: ticked.has(run.id), title: `compare ${run.id}`, "data-compare": run.id })));
  tr.classList.toggle("selected", run.id === selected);
  tr.dataset.state = run.state;
}

// the queue table says what a run waits for in a few words; the detail view (and the tooltip) has it all
function shortWaiting(run) {
  return run.state === "starting" ? `waiting for a worker on queue '${run.queue}'` : run.waiting.split(" (")[0];
}

function onCompareTick(event) {
  const box = event.target.closest("input[data-compare]");
  if (!box) return;
  if (box.checked) ticked.add(box.value); else ticked.delete(box.value);
  const button = $("#compare-runs-button");
  button.disabled = ticked.size < 2 || ticked.size > 5;
  button.textContent = `Compare ticked (${ticked.size})`;
}

async function onTableClick(event) {
  const tr = event.target.closest("tr[data-run]");
  if (!tr || event.target.closest("a, input")) return;  // "open" and the compare tick do their own thing
  const action = event.target.dataset.action;
  if (action) {
    event.stopPropagation();
    try {
      const data = await ctx.api(`/api/runs/${encodeURIComponent(tr.dataset.run)}/${action}`, { method: "POST" });
      runs.set(data.run.id, data.run);
      renderRow(data.run);
      // a run no child is training changes at once; a running job is asked and answers by event
      const done = { cancel: "cancelled", pause: "paused", resume: "queued" }[action] === data.run.state;
      ctx.flash(`${action}: run ${data.run.id} is ${done ? data.run.state : "asked to " + action}`);
    } catch (err) { ctx.flash(`${action} refused: ${err.message}`, true); }
    return;
  }
  await selectRun(tr.dataset.run);
}

// -- starting runs ----------------------------------------------------------------------------

function onMode() {
  const sequential = $('input[name="mode"]:checked').value === "sequential";
  $("#start-component").hidden = sequential;
  $('label[for="start-component"]').hidden = sequential;
  $("#start-components").hidden = !sequential;
  $('label[for="start-components"]').hidden = !sequential;
}

async function onStart(event) {
  event.preventDefault();
  setText("#start-error", "");
  let overrides = {};
  const raw = $("#start-overrides").value.trim();
  if (raw) {
    try { overrides = JSON.parse(raw); } catch (err) { setText("#start-error", `Config overrides: not JSON (${err.message})`); return; }
    if (typeof overrides !== "object" || overrides === null || Array.isArray(overrides)) {
      setText("#start-error", "Config overrides: expected a JSON object"); return;
    }
  }
  const body = { ...overrides, data: $("#start-data").value.trim(), steps: Number($("#start-steps").value) };
  const sequential = $('input[name="mode"]:checked').value === "sequential";
  $("#start-button").disabled = true;
  try {
    let first;
    if (sequential) {
      body.components = $("#start-components").value;
      const data = await ctx.api("/api/training/sequential", { method: "POST", body });
      first = data.runs[0];
      ctx.flash(`Queued sequence ${data.sequence_id}: ${data.runs.map((r) => r.component).join(" -> ")}`);
    } else {
      body.component = $("#start-component").value;
      first = (await ctx.api("/api/runs", { method: "POST", body })).run;
      ctx.flash(`Queued run ${first.id} (${first.component}, ${first.total_steps} steps)`);
    }
    await loadRuns();
    await selectRun(first.id);
  } catch (err) {
    setText("#start-error", err.message);
  } finally {
    $("#start-button").disabled = false;
  }
}

// -- the selected run -------------------------------------------------------------------------

function makeChart() {
  if (typeof Chart !== "function") return null;  // vendor file missing: the banner says so
  return new Chart($("#loss-chart"), {
    type: "line",
    data: { datasets: [{ label: "loss", data: [], borderColor: "#2364d2", pointRadius: 0, borderWidth: 2 }] },
    options: {
      animation: false, maintainAspectRatio: false, parsing: false, normalized: true,
      scales: { x: { type: "linear", title: { display: true, text: "step" } },
                y: { title: { display: true, text: "loss" } } },
      plugins: { legend: { display: false } },
    },
  });
}

function resetChart() {
  if (!chart) chart = makeChart();
  if (chart) { chart.data.datasets[0].data = []; chart.update(); }
  lastStep = -1;
  setText("#chart-points", "0");
}

function addPoint(step, loss, update = true) {
  if (typeof step !== "number" || step <= lastStep || typeof loss !== "number" || !isFinite(loss)) return false;
  lastStep = step;
  if (!chart) return false;
  chart.data.datasets[0].data.push({ x: step, y: loss });
  if (update) chart.update("none");
  setText("#chart-points", String(chart.data.datasets[0].data.length));
  return true;
}

function appendLog(line) {
  const pre = $("#log-tail");
  const lines = (pre.textContent ? pre.textContent.split("\n") : []).concat(line).slice(-LOG_LINES);
  pre.textContent = lines.join("\n");
  pre.scrollTop = pre.scrollHeight;
}

function setState(state, waiting = null) {
  const badge = $("#detail-state");
  badge.textContent = state;
  badge.className = `state ${state}`;
  $("#run-detail").dataset.state = state;
  setText("#detail-waiting", waiting ?? "");
  $("#detail-waiting").hidden = !waiting;
}

function renderProgress(step, total, d = {}) {
  const pct = total ? Math.min(100, (100 * step) / total) : 0;
  $("#detail-bar").style.width = `${pct}%`;
  const parts = [`step ${step ?? 0}/${total ?? "?"}`];
  if (typeof d.loss === "number") parts.push(`loss ${num(d.loss)}`);
  if (typeof d.steps_per_s === "number") parts.push(`${num(d.steps_per_s, 3)} steps/s`);
  if (typeof d.eta_s === "number") parts.push(`ETA ${duration(d.eta_s)}`);
  if (typeof d.rss_mb === "number") parts.push(`RSS ${Math.round(d.rss_mb)} MB`);
  setText("#detail-stats", parts.join(" · "));
}

async function fetchMetrics(runId) {
  // page through the whole history (records step > after)
  const records = [];
  let after = null;
  for (let i = 0; i < 50; i++) {
    const q = after === null ? "" : `&after=${after}`;
    const data = await ctx.api(`/api/runs/${encodeURIComponent(runId)}/metrics?events=1&limit=5000${q}`);
    records.push(...data.records);
    if (!data.more || data.next_after === null) break;
    after = data.next_after;
  }
  return records;
}

// What a state event lets the card say about waiting (the full text comes with the next fetch).
function eventWaiting(state, queue) {
  return state === "starting" ? `waiting for a worker on queue '${queue ?? "?"}'` : null;
}

// The last state each run's events said: a state event that arrives while selectRun still awaits
// its fetches is newer than what the fetch returned, and must not be overwritten by it.
const stateEvents = new Map();

async function selectRun(runId, { keepLog = false } = {}) {
  selected = runId;
  stateEvents.delete(runId);
  localStorage.setItem(SELECTED_KEY, runId);
  for (const tr of document.querySelectorAll("#runs-table tr[data-run]")) tr.classList.toggle("selected", tr.dataset.run === runId);
  let run;
  try {
    run = (await ctx.api(`/api/runs/${encodeURIComponent(runId)}`)).run;
  } catch (err) {
    if (err.status === 404) { localStorage.removeItem(SELECTED_KEY); selected = null; $("#run-detail").hidden = true; return; }
    throw err;
  }
  const records = await fetchMetrics(runId);
  if (selected !== runId) return;  // another run was picked meanwhile
  $("#run-detail").hidden = false;
  // the count of live points survives a reload of the same run's history (e.g. when it finishes)
  if ($("#run-detail").dataset.run !== runId) $("#run-detail").dataset.livePoints = "0";
  $("#run-detail").dataset.run = runId;
  setText("#detail-id", `${run.id} · ${run.component}`);
  const newer = stateEvents.get(runId);
  setState(newer ?? run.state, newer && newer !== run.state ? eventWaiting(newer, run.queue) : run.waiting);
  resetChart();
  peakRss = null;
  const metrics = records.filter((r) => r.type === "metric");
  for (const r of metrics) {
    addPoint(r.step, r.loss, false);
    if (typeof r.rss_mb === "number") peakRss = Math.max(peakRss ?? 0, r.rss_mb);
  }
  if (chart) chart.update("none");
  if (!keepLog) {  // the live lines of this run so far stay when it is only refreshed
    $("#log-tail").textContent = "";
    for (const r of records.filter((x) => x.type === "event")) appendLog(eventLine(r));
  }
  if (run.error) appendLog(`[error] ${run.error}`);
  const last = metrics[metrics.length - 1] || {};
  renderProgress(run.step, run.total_steps, { loss: run.loss ?? last.loss, steps_per_s: run.steps_per_s, rss_mb: last.rss_mb });
  renderSummary(run, metrics);
}

// a metrics.jsonl event record {"type": "event", "kind", "wall_time", "payload"} as one log line
function eventLine(r) {
  const p = { ...(r.payload || {}) };
  const step = r.step ?? p.step;
  delete p.step;
  const when = typeof r.wall_time === "number" ? new Date(r.wall_time * 1000).toLocaleTimeString() + " " : "";
  const text = p.message ?? p.path ?? (Object.keys(p).length ? JSON.stringify(p) : "");
  return `${when}[${r.kind}]${step !== undefined ? " step " + step : ""} ${text}`;
}

// The validation figures (result.json summary.val) a finished run reported on its held-out episodes,
// beside the baselines the promotion gate compares them with (hope_models/promote/baselines.py).
function heldOutRows(component, v) {
  if (!v) return [];
  const pct = (x) => `${(100 * x).toFixed(0)} %`;
  if (component === "vqvae" && typeof v.recon_nmse === "number") {
    const rows = [["held-out variance kept", `${(100 * (1 - v.recon_nmse)).toFixed(1)} % (normalised MSE ${num(v.recon_nmse)}; the gate asks >= 95 %)`],
      ["codebook", `perplexity ${num(v.perplexity)} per group, code usage ${pct(v.code_usage ?? NaN)}`]];
    if (typeof v.psnr_db === "number") rows.push(["held-out PSNR", `${v.psnr_db.toFixed(1)} dB`]);
    return rows;
  }
  if (component === "mid_loop") {
    const labels = Object.keys(v).filter((k) => k.startsWith("nll_")).map((k) => k.slice(4));
    const rows = labels.map((h) => {
      const mse = v[`obs_mse_${h}`], copy = v[`copy_last_obs_mse_${h}`];
      const obs = typeof mse === "number" && copy > 0
        ? `observation error ${num(mse)} vs copy-last ${num(copy)} (${pct(Math.abs(1 - mse / copy))} ${mse <= copy ? "lower" : "higher"}); ` : "";
      return [`held-out +${h}`, `${obs}nll ${num(v[`nll_${h}`])} vs copy-last ${num(v[`copy_last_nll_${h}`])}, `
        + `code frequency ${num(v[`code_freq_nll_${h}`])}`];
    });
    if (typeof v.wm_obs_mse === "number") rows.push(["world model", `observation error ${num(v.wm_obs_mse)} vs copy-last ${num(v.wm_copy_obs_mse)}`]);
    return rows;
  }
  return typeof v.loss === "number" ? [["held-out loss", num(v.loss)]] : [];
}

function renderSummary(run, metrics) {
  const box = $("#run-summary");
  box.hidden = !FINISHED.has(run.state);
  if (box.hidden) return;
  const losses = metrics.filter((r) => typeof r.loss === "number" && isFinite(r.loss));
  const first = losses[0], last = losses[losses.length - 1];
  const took = run.started_at && run.finished_at ? (new Date(run.finished_at) - new Date(run.started_at)) / 1000 : null;
  fillKv("#summary-list", [
    ["state", run.state + (run.error ? `: ${run.error}` : "")],
    ["steps", `${run.step ?? 0} of ${run.total_steps ?? "?"}`],
    ["loss", first && last ? `${num(first.loss)} (step ${first.step}) -> ${num(last.loss)} (step ${last.step})` : "–"],
    ["improvement", first && last && first.loss ? `${(100 * (1 - last.loss / first.loss)).toFixed(1)} %` : "–"],
    ["peak RSS", peakRss === null ? "–" : `${Math.round(peakRss)} MB`],
    ["time", duration(took)],
    ["checkpoint", run.last_checkpoint],
    ...heldOutRows(run.component, run.validation),
  ]);
  $("#promote-run").hidden = run.state !== "completed";
  setText("#promote-result", "");
}

async function onPromote() {
  if (!selected) return;
  const button = $("#promote-run");
  button.disabled = true;
  setText("#promote-result", "Running the promotion gate…");
  try {
    const out = await ctx.api("/api/brain/promote", { method: "POST", body: { run_id: selected } });
    setText("#promote-result", `Promoted ${out.version}${out.already ? " (it already was)" : ""}; serving ${out.serving ?? "–"}`);
  } catch (err) {
    setText("#promote-result", `Not promoted: ${err.message}`);
  } finally {
    button.disabled = false;
  }
}
