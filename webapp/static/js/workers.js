// Workers: which workers are connected (the Pi's own, a remote GPU box's), the queues they serve,
// how they report (registry db or redis), their last heartbeat and the job they are running; and
// each queue's runs by state with the number of workers online for it. What Flower would show,
// for this product's queues. From GET /api/workers:
//   {"heartbeat_s", "workers": [{"name", "host", "pid", "queues", "report", "started_at",
//    "last_seen", "stopped_at", "state": "online"|"offline"|"stopped", "current": {"run_id", "component",
//    "state", "step", "total_steps"} | null}],
//    "queues": [{"name", "queued", "starting", "running", "paused", "workers_online"}]}
// Reloaded every heartbeat_s while the page is visible (the timer stops when it is hidden) and on
// run.state / run.progress events; the "N s ago" texts tick every second in between.
//
// DOM contract: #workers-table tbody tr[data-worker=<name>][data-state=<state>], its
// td[data-key=current] holds a.run-link[href="#run/<run id>"] (empty without a job);
// #queues-table tbody tr[data-queue=<name>], .stalled (data-stalled="1") when the queue has runs
// waiting and no worker online; #page-workers[data-loaded] counts the loads.
import { $, el, setText } from "./util.js";

const EVENT_MIN_GAP_MS = 1000;  // run.progress comes up to 5/s: one reload a second is plenty
let ctx;
let timer = null;
let ticker = null;
let lastLoad = 0;
let pendingEvent = null;
let loads = 0;

export function init(c) {
  ctx = c;
  $("#workers-refresh").addEventListener("click", () => load().catch((err) => ctx.flash(err.message, true)));
}

export async function show() {
  await load();
  if (!ticker) ticker = setInterval(tick, 1000);
}

// "3 s ago", "4 min ago" from an ISO time (this browser's clock; a future time reads "just now")
function agoText(iso) {
  const t = Date.parse(iso || "");
  if (!isFinite(t)) return "never";
  const s = Math.max(0, (Date.now() - t) / 1000);
  if (s < 2) return "just now";
  if (s < 90) return `${Math.round(s)} s ago`;
  if (s < 5400) return `${Math.round(s / 60)} min ago`;
  if (s < 172800) return `${Math.round(s / 3600)} h ago`;
  return `${Math.round(s / 86400)} days ago`;
}

const visible = () => !$("#page-workers").hidden;

function onRunEvent() {
  if (!visible() || pendingEvent) return;
  const wait = Math.max(0, lastLoad + EVENT_MIN_GAP_MS - Date.now());
  pendingEvent = setTimeout(() => { pendingEvent = null; if (visible()) load().catch(() => {}); }, wait);
}

export const events = { "run.state": onRunEvent, "run.progress": onRunEvent };

async function load() {
  lastLoad = Date.now();
  const data = await ctx.api("/api/workers");
  renderWorkers(data.workers || [], data.heartbeat_s);
  renderQueues(data.queues || []);
  loads += 1;
  $("#page-workers").dataset.loaded = String(loads);
  schedule(data.heartbeat_s);
}

function schedule(heartbeatS) {
  clearTimeout(timer);
  const ms = 1000 * (typeof heartbeatS === "number" && heartbeatS > 0 ? heartbeatS : 10);
  timer = setTimeout(() => {
    timer = null;
    if (visible()) load().catch((err) => ctx.flash(err.message, true));
  }, ms);
}

// the "N s ago" texts; the ticker stops itself once the page is hidden (show() starts it again)
function tick() {
  if (!visible()) { clearInterval(ticker); ticker = null; return; }
  for (const span of document.querySelectorAll("#workers-table .ago")) span.textContent = agoText(span.dataset.time);
}

function cell(key, label, ...children) {
  return el("td", { "data-key": key, "data-label": label }, ...children);
}

function currentJob(cur) {
  if (!cur) return [el("span", { class: "muted", text: "idle" })];
  const link = el("a", { class: "run-link", href: `#run/${encodeURIComponent(cur.run_id)}`, text: cur.run_id });
  const steps = typeof cur.step === "number" ? ` step ${cur.step}${cur.total_steps ? ` of ${cur.total_steps}` : ""}` : "";
  return [link, el("span", { text: ` ${cur.component || ""} ${cur.state || ""}${steps}` })];
}

function renderWorkers(workers, heartbeatS) {
  const online = workers.filter((w) => w.state === "online").length;
  setText("#workers-summary", `${workers.length} worker${workers.length === 1 ? "" : "s"} known, ${online} online; ` +
          `a worker reports a heartbeat every ${heartbeatS ?? "?"} s and is offline when it has missed a few.`);
  const rows = workers.map((w) => {
    const seen = el("span", { class: "ago", "data-time": w.last_seen || "", text: agoText(w.last_seen) });
    seen.title = w.last_seen ? `last heartbeat ${new Date(w.last_seen).toLocaleString()}` +
      (w.started_at ? `; started ${new Date(w.started_at).toLocaleString()}` : "") +
      (w.stopped_at ? `; stopped ${new Date(w.stopped_at).toLocaleString()}` : "") : "";
    const tr = el("tr", { "data-worker": w.name, "data-state": w.state || "" },
      cell("name", "Name", el("span", { class: "worker-name", text: w.name })),
      cell("host", "Host", el("span", { text: w.host + (w.pid ? ` (pid ${w.pid})` : "") })),
      cell("queues", "Queues", ...(w.queues || []).map((q) => el("span", { class: "tag", text: q }))),
      cell("report", "Reports by", el("span", { text: w.report || "–" })),
      cell("state", "State", el("span", { class: `state worker-${w.state}`, text: w.state || "?" })),
      cell("last_seen", "Last heartbeat", seen),
      cell("current", "Current job", ...currentJob(w.current)));
    return tr;
  });
  if (!rows.length) rows.push(el("tr", {}, el("td", { colSpan: 7, class: "muted", text: "no worker has reported yet" })));
  $("#workers-table tbody").replaceChildren(...rows);
}

function renderQueues(queues) {
  const hints = [];
  const rows = queues.map((q) => {
    const waiting = (q.queued || 0) + (q.starting || 0);
    const stalled = waiting > 0 && !q.workers_online;
    const tr = el("tr", { "data-queue": q.name, "data-stalled": stalled ? "1" : "0" },
      cell("name", "Queue", el("span", { class: "tag", text: q.name })),
      ...["queued", "starting", "running", "paused", "workers_online"].map((k) =>
        cell(k, k === "workers_online" ? "Workers online" : k[0].toUpperCase() + k.slice(1),
             el("span", { text: String(q[k] ?? 0) }))));
    tr.classList.toggle("stalled", stalled);
    if (stalled) {
      hints.push(el("li", {}, el("span", { text: `${waiting} run${waiting === 1 ? " waits" : "s wait"} on queue "${q.name}" ` +
                                                  "and no worker serves it: start one with " }),
                    el("code", { text: `run_trainer.py worker --queue ${q.name}` })));
    }
    return tr;
  });
  if (!rows.length) rows.push(el("tr", {}, el("td", { colSpan: 6, class: "muted", text: "no queues" })));
  $("#queues-table tbody").replaceChildren(...rows);
  const hint = $("#queues-hint");
  hint.replaceChildren(...(hints.length ? [el("ul", { class: "why" }, ...hints)] : []));
}
