// System: memory and temperature gauges and the throttle state, from GET /api/system and then the
// daemon's system.stats samples; charts of the last hour (system_charts.js) from
// GET /api/system/history, which the daemon samples whether a run is active or not, then the live
// system.stats samples. Throttle changes (system.throttle) go in a history list. The history
// before this page was opened comes from the sampled history's level changes and the running /
// recent runs' recorded throttle events (their metrics.jsonl, through the API), so a reload does
// not empty it. #page-system[data-loaded] counts the finished loads.
import { $, setText, el, time, duration } from "./util.js";
import * as charts from "./system_charts.js";

const LEVELS = { 0: "normal", 1: "slowed", 2: "paused (too hot)" };
const HISTORY_MAX = 100;
const TEMP_SCALE_C = 90;  // the gauge's full scale; the hard limit is below it
let ctx;
let loads = 0;
const history = [];  // {when, level, text, live}

export function init(c) { ctx = c; }

export async function show() {
  const data = await ctx.api("/api/system");
  renderStats(data.stats || {});
  renderThrottle(data.throttle?.level, data.throttle?.source);
  const counts = Object.entries(data.queue?.counts || {}).map(([k, v]) => `${k} ${v}`).join(", ");
  setText("#queue-counts", counts || "no runs");
  setText("#process-text", data.process ? `webapp process ${data.process.pid}: ${data.process.rss_mb} MB RSS` : "");
  const { samples, intervalS } = await loadSamples();
  await loadHistory(data.queue, samples, intervalS);
  $("#page-system").dataset.loaded = String(++loads);
}

// The charts' hour; a failure leaves the gauges and says why under the charts.
async function loadSamples() {
  let data;
  try {
    data = await ctx.api(`/api/system/history?seconds=${charts.WINDOW_MS / 1000}`);
  } catch (err) {
    charts.load([]);
    setText("#system-sampling", `No sampled history: ${err.message}`);
    return { samples: [] };
  }
  const samples = data.samples || [];
  charts.load(samples);
  const from = data.source === "daemon" ? "the daemon's in-memory ring" : data.source === "registry"
    ? "the registry (the daemon runs in another process)" : (data.source || "?");
  const span = samples.length > 1 ? (Date.parse(samples[samples.length - 1].time) - Date.parse(samples[0].time)) / 1000 : 0;
  setText("#system-sampling", `One sample every ${duration(data.interval_s)}, from ${from}: ` +
          `${samples.length} samples over ${duration(span)}; live samples are added as they arrive.`);
  return { samples, intervalS: data.interval_s };
}

export const events = {
  "system.stats": (d) => {
    renderStats(d);
    if ("throttle_level" in d) renderThrottle(d.throttle_level, "daemon");
    if (!$("#page-system").hidden) charts.append(d);  // show() reloads the hour when it comes back
  },
  "system.throttle": (d) => {
    addHistory(d.time ? new Date(d.time) : new Date(), d.level, d.reason || d.message || "", d.run_id, true);
    renderThrottle(d.level, d.source || "event");
  },
};

function gauge(sel, pct, warnAt, badAt) {
  const fill = $(sel);
  const v = Math.max(0, Math.min(100, pct));
  fill.style.width = `${v}%`;
  fill.classList.toggle("warn", pct >= warnAt && pct < badAt);
  fill.classList.toggle("bad", pct >= badAt);
  fill.dataset.value = String(Math.round(pct));
}

function renderStats(s) {
  if (typeof s.mem_percent === "number") {
    gauge("#mem-gauge", s.mem_percent, 75, 90);
    const used = s.mem_total_mb - s.mem_available_mb;
    setText("#mem-text", `${Math.round(used)} of ${Math.round(s.mem_total_mb)} MB used (${s.mem_percent.toFixed(0)} %)`);
  }
  if (typeof s.temp_c === "number") {
    gauge("#temp-gauge", (100 * s.temp_c) / TEMP_SCALE_C, (100 * 70) / TEMP_SCALE_C, (100 * 80) / TEMP_SCALE_C);
    setText("#temp-text", `${s.temp_c.toFixed(1)} °C`);
  } else {
    gauge("#temp-gauge", 0, 100, 100);
    setText("#temp-text", "no temperature sensor configured");
  }
  const flags = s.throttled && Object.entries(s.throttled).filter(([, v]) => v === true).map(([k]) => k);
  setText("#cpu-text", `CPU ${typeof s.cpu_percent === "number" ? s.cpu_percent.toFixed(0) : "–"} %` +
          (flags && flags.length ? ` · firmware: ${flags.join(", ")}` : "") + (s.time ? ` · sampled ${time(s.time)}` : ""));
}

function renderThrottle(level, source) {
  const badge = $("#throttle-level");
  const known = level === 0 || level === 1 || level === 2;
  badge.textContent = known ? `level ${level}: ${LEVELS[level]}` : "unknown";
  badge.className = `state ${level === 2 ? "failed" : level === 1 ? "paused" : known ? "completed" : ""}`;
  badge.dataset.level = known ? String(level) : "";
  setText("#throttle-text", known ? `from ${source || "?"}` : "no running job and no daemon in this process to ask");
}

function entry(when, level, text, runId, live = false) {
  return { when, level, text: text + (runId ? ` (run ${runId})` : ""), live };
}

function addHistory(when, level, text, runId, live = false) {
  history.push(entry(when, level, text, runId, live));
  renderHistory();
}

function renderHistory() {
  history.sort((a, b) => b.when - a.when);
  history.length = Math.min(history.length, HISTORY_MAX);
  const ul = $("#throttle-history");
  ul.replaceChildren(...history.map((h) => el("li", { text: `${h.when.toLocaleString()} · level ${h.level ?? "?"} · ${h.text}` })));
  if (!history.length) ul.append(el("li", { class: "muted", text: "no throttle changes recorded" }));
}

// Built apart and swapped in at the end: a system.throttle event that arrives while this loads
// stays in the list unless what was loaded already holds it (same level, within `near`).
async function loadHistory(queue, samples, intervalS) {
  const loaded = [];
  const near = 1000 * (2 * (intervalS || 5) + 1);
  const ids = new Set([...(queue?.running || []), ...(queue?.paused || [])].map((r) => r.id));
  try {
    const recent = await ctx.api("/api/runs?limit=5");
    for (const r of recent.runs) ids.add(r.id);
  } catch { /* the live events still arrive */ }
  for (const id of ids) {
    try {
      const data = await ctx.api(`/api/runs/${encodeURIComponent(id)}/metrics?events=1&limit=5000`);
      for (const rec of data.records) {
        if (rec.type === "event" && rec.kind === "throttle") {
          const p = rec.payload || {};
          loaded.push(entry(new Date(rec.wall_time * 1000), p.level, p.reason || p.message || "", id));
        }
      }
    } catch { /* a run without metrics yet */ }
  }
  // The sampled level changes (no reason recorded, only when), unless a run's event (with its
  // reason) already says it: the sample comes within an interval or two of the event.
  const events = loaded.slice();
  let level = null;
  for (const s of samples) {
    if (typeof s.throttle_level !== "number") continue;
    const when = new Date(s.time);
    if (level !== null && s.throttle_level !== level &&
        !events.some((h) => h.level === s.throttle_level && Math.abs(h.when - when) <= near)) {
      loaded.push(entry(when, s.throttle_level, "sampled change"));
    }
    level = s.throttle_level;
  }
  const live = history.filter((h) => h.live && !loaded.some((l) => l.level === h.level && Math.abs(l.when - h.when) <= near));
  history.length = 0;
  history.push(...loaded, ...live);
  renderHistory();
}
