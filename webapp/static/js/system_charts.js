// The System page's charts of the last hour: memory (% used; MB in the tooltip), temperature (°C),
// CPU % and the throttle level (a stepped line 0..2), one sample per point.
//
// Samples are the shape of GET /api/system/history's "samples" and of the live system.stats event:
//   {"time": ISO-8601 UTC, "mem_percent", "mem_used_mb"?, "mem_available_mb", "mem_total_mb",
//    "temp_c" (null without a sensor), "cpu_percent", "throttle_level"}
// x is wall-clock milliseconds on a linear scale (Chart.js "time" scales need a date adapter we do
// not ship), labelled as local hh:mm (hh:mm:ss while the span is under ten minutes).
//
// DOM contract: #system-charts carries data-samples (points held, live ones included) and
// data-live-samples (points appended from system.stats since the page was last loaded);
// #system-temp-none is shown while no held sample has a temperature.
import { $ } from "./util.js";

export const WINDOW_MS = 3600 * 1000;
const SERIES = {  // canvas id -> how a sample becomes a point, and the y axis
  mem: { canvas: "#system-mem-chart", color: "#2364d2", label: "memory used (%)", y: { min: 0, max: 100 },
         point: (s, x) => (num(s.mem_percent) ? { x, y: s.mem_percent, used: usedMb(s), total: s.mem_total_mb } : null) },
  temp: { canvas: "#system-temp-chart", color: "#d2552a", label: "temperature (°C)", y: {},
          point: (s, x) => (num(s.temp_c) ? { x, y: s.temp_c } : null) },
  cpu: { canvas: "#system-cpu-chart", color: "#2a9d5c", label: "CPU (%)", y: { min: 0, max: 100 },
         point: (s, x) => (num(s.cpu_percent) ? { x, y: s.cpu_percent } : null) },
  throttle: { canvas: "#system-throttle-chart", color: "#b7791f", label: "throttle level", stepped: true,
              y: { min: 0, max: 2, ticks: { stepSize: 1 } },
              point: (s, x) => (num(s.throttle_level) ? { x, y: s.throttle_level } : null) },
};

const charts = {};
let lastX = -Infinity;
let held = 0;
let live = 0;

function num(v) { return typeof v === "number" && isFinite(v); }

function usedMb(s) {
  if (num(s.mem_used_mb)) return s.mem_used_mb;
  return num(s.mem_total_mb) && num(s.mem_available_mb) ? s.mem_total_mb - s.mem_available_mb : null;
}

function clock(ms, spanMs) {
  const opts = spanMs < 600_000 ? { hour: "2-digit", minute: "2-digit", second: "2-digit" }
                                : { hour: "2-digit", minute: "2-digit" };
  return new Date(ms).toLocaleTimeString([], opts);
}

function tooltipLabel(key) {
  return (item) => {
    const p = item.raw;
    if (key === "mem") {
      const mb = num(p.used) && num(p.total) ? ` (${Math.round(p.used)} of ${Math.round(p.total)} MB)` : "";
      return `${p.y.toFixed(1)} % used${mb}`;
    }
    if (key === "temp") return `${p.y.toFixed(1)} °C`;
    if (key === "cpu") return `CPU ${p.y.toFixed(0)} %`;
    return `throttle level ${p.y}`;
  };
}

function make(key) {
  const spec = SERIES[key];
  return new Chart($(spec.canvas), {
    type: "line",
    data: { datasets: [{ label: spec.label, data: [], borderColor: spec.color, pointRadius: 0, borderWidth: 2,
                         stepped: spec.stepped ? "before" : false }] },
    options: {
      animation: false, maintainAspectRatio: false, parsing: false, normalized: true,
      interaction: { mode: "nearest", axis: "x", intersect: false },
      scales: {
        x: { type: "linear", bounds: "data",
             ticks: { maxTicksLimit: 6, maxRotation: 0,
                      callback(value) { return clock(value, this.max - this.min); } } },
        y: { ...spec.y },  // the figure caption names it
      },
      plugins: { legend: { display: false },
                 tooltip: { callbacks: { title: (items) => (items.length ? new Date(items[0].raw.x).toLocaleString() : ""),
                                         label: tooltipLabel(key) } } },
    },
  });
}

function ensure() {
  if (typeof Chart !== "function") return false;  // vendor file missing: the banner says so
  for (const key of Object.keys(SERIES)) if (!charts[key]) charts[key] = make(key);
  return true;
}

function push(sample) {
  const x = Date.parse(sample.time);
  if (!isFinite(x) || x <= lastX) return false;  // a live sample the history already had
  lastX = x;
  for (const [key, spec] of Object.entries(SERIES)) {
    const p = spec.point(sample, x);
    if (p) charts[key].data.datasets[0].data.push(p);
  }
  held += 1;
  return true;
}

// Points older than an hour before the newest go (the newest, not this browser's clock: the
// server's clock is the one the samples carry).
function trim() {
  const cutoff = lastX - WINDOW_MS;
  for (const chart of Object.values(charts)) {
    const data = chart.data.datasets[0].data;
    let cut = 0;
    while (cut < data.length && data[cut].x < cutoff) cut += 1;
    if (cut) data.splice(0, cut);
  }
  held = Math.max(...Object.values(charts).map((c) => c.data.datasets[0].data.length), 0);
}

function render() {
  for (const chart of Object.values(charts)) chart.update("none");
  const box = $("#system-charts");
  box.dataset.samples = String(held);
  box.dataset.liveSamples = String(live);
  $("#system-temp-none").hidden = charts.temp.data.datasets[0].data.length > 0;
}

// The history replaces whatever the charts held.
export function load(samples) {
  if (!ensure()) return;
  for (const chart of Object.values(charts)) chart.data.datasets[0].data = [];
  lastX = -Infinity;
  held = 0;
  live = 0;
  for (const s of samples) push(s);
  trim();
  render();
}

// One live system.stats sample; its throttle level comes as throttle_level.
export function append(sample) {
  if (!ensure() || !sample || !push(sample)) return;
  live += 1;
  trim();
  render();
}
