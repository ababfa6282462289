// Inference: one observation -> fast_loop's action (with the version that answered and the
// latency), with a camera frame when one is chosen (#infer-frame: a JPEG or PNG file, sent as the
// request's `frame`, a data:image/...;base64 URL; the server decodes and resizes it to the served
// model's frame, hope_models/runtime/brain_frame.py, and answers 400 saying what is wrong with it,
// shown in #infer-error), and the sim reflex: an eval-reflex job with the promoted fast_loop, polled until it
// finishes (POST /api/sim/reflex, GET /api/sim/reflex/<job>). The first episode's frames arrive as
// sim.frame events {job_id, step, image, return_so_far} while it runs and are drawn on the canvas;
// if the server could not render, the result says why ("frames").
// Beside the frames, the promoted Mid Loop's surprise at each of its grid points of that episode
// (job.surprise.records, computed by the eval-reflex child as BrainService defines it) is plotted
// against time as the polls bring it, with a dashed marker at the target jump if one was asked for.
// Without a promoted mid_loop the chart gives way to the reason ("no mid_loop promoted").
import { $, setText, fillKv, num, duration } from "./util.js";

const POLL_MS = 1000;
const EPISODE_S = 20;  // the reacher's episode: 1000 control steps of 20 ms
let ctx;
let job = null;  // the reflex job this page follows
let surpriseChart = null;
let lastRecordStep = -1;  // the newest grid point already on the chart

const FRAME_TYPES = ["image/jpeg", "image/png"];

export function init(c) {
  ctx = c;
  $("#infer-form").addEventListener("submit", onInfer);
  $("#infer-frame").addEventListener("change", showFrame);
  $("#infer-frame-clear").addEventListener("click", () => { $("#infer-frame").value = ""; showFrame(); });
  $("#reflex-form").addEventListener("submit", onReflex);
}

export async function show() {
  // prefill an observation of the size the served fast_loop reads
  const obs = $("#infer-observation");
  const brain = await ctx.api("/api/brain?history=0");
  const served = brain.components.fast_loop?.serving;
  if (served?.obs_dim && !obs.value.trim()) obs.value = Array(served.obs_dim).fill("0").join(", ");
  obs.placeholder = served?.observation_fields ? served.observation_fields.join(", ") : "no fast_loop is served yet";
  setText("#reflex-status", served?.version ? `promoted fast_loop: ${served.version}` : "no fast_loop promoted yet");
}

export const events = {
  "sim.frame": (d) => {
    if (!job || (d.job_id && d.job_id !== job)) return;
    const src = d.image || d.frame;  // a data: URL (PNG / JPEG)
    if (typeof src === "string" && src.startsWith("data:image/")) {
      const canvas = $("#reflex-frame");
      const img = new Image();
      img.onload = () => {
        canvas.hidden = false;
        canvas.getContext("2d").drawImage(img, 0, 0, canvas.width, canvas.height);
        canvas.dataset.frames = String(Number(canvas.dataset.frames || 0) + 1);  // drawn frames (tests read it)
        canvas.dataset.step = String(d.step ?? "");
      };
      img.src = src;
    }
    const ret = d.return_so_far ?? d.return ?? d.reward;
    if (typeof ret === "number") {
      setText("#reflex-status", `step ${d.step ?? "?"} · return so far ${num(ret)}`);
    }
  },
};

async function onInfer(event) {
  event.preventDefault();
  setText("#infer-error", "");
  const parts = $("#infer-observation").value.split(/[\s,]+/).filter((x) => x !== "");
  const observation = parts.map(Number);
  const bad = parts.findIndex((x, i) => !isFinite(observation[i]));
  if (!parts.length || bad >= 0) {
    setText("#infer-error", parts.length ? `observation: "${parts[bad]}" is not a number` : "observation: type some numbers");
    return;
  }
  const file = $("#infer-frame").files[0] || null;
  if (file && !FRAME_TYPES.includes(file.type)) {
    setText("#infer-error", `frame: ${file.name} is ${file.type || "of an unknown type"}, not a JPEG or PNG`);
    return;
  }
  $("#infer-button").disabled = true;
  try {
    const body = { component: "fast_loop", observation, session: "robot-editor", reset: $("#infer-reset").checked };
    if (file) body.frame = await frameForRequest(file);
    const out = await ctx.api("/api/brain/infer", { method: "POST", body });
    const rows = [["action", out.action.map((v) => num(v)).join(", ")], ["version", out.model_version],
                  ["latency", `${num(out.latency_ms, 3)} ms`]];
    if (file) rows.push(["frame", file.name]);
    fillKv("#infer-result", rows);
  } catch (err) {
    $("#infer-result").replaceChildren();
    // the server's own words (a 400 names what is wrong: the observation, or the frame and why)
    setText("#infer-error", err.status ? `The server answered HTTP ${err.status}: ${err.message}` : err.message);
  } finally {
    $("#infer-button").disabled = false;
  }
}

// A phone photo is several MB and the API takes 1 MiB bodies (base64 adds a third): a large file
// is drawn at most FRAME_SEND_SIDE pixels on its long side and sent as a JPEG. The served model
// reads 64-128 pixels, so nothing it could use is lost; a small file goes byte for byte.
const FRAME_SEND_BYTES = 512 * 1024;
const FRAME_SEND_SIDE = 640;

async function frameForRequest(file) {
  const url = await dataUrl(file);
  if (file.size <= FRAME_SEND_BYTES) return url;
  const img = new Image();
  await new Promise((resolve, reject) => {
    img.onload = resolve;
    img.onerror = () => reject(new Error(`frame: ${file.name} is not an image the browser can read`));
    img.src = url;
  });
  const scale = Math.min(1, FRAME_SEND_SIDE / Math.max(img.naturalWidth, img.naturalHeight));
  const canvas = document.createElement("canvas");
  canvas.width = Math.max(1, Math.round(img.naturalWidth * scale));
  canvas.height = Math.max(1, Math.round(img.naturalHeight * scale));
  canvas.getContext("2d").drawImage(img, 0, 0, canvas.width, canvas.height);
  return canvas.toDataURL("image/jpeg", 0.92);
}

// the chosen file as a data: URL, what the request's `frame` carries
function dataUrl(file) {
  return new Promise((resolve, reject) => {
    const reader = new FileReader();
    reader.onload = () => resolve(reader.result);
    reader.onerror = () => reject(new Error(`frame: cannot read ${file.name}: ${reader.error?.message || "read error"}`));
    reader.readAsDataURL(file);
  });
}

let previewUrl = null;

function showFrame() {
  const file = $("#infer-frame").files[0] || null;
  const img = $("#infer-frame-preview");
  if (previewUrl) URL.revokeObjectURL(previewUrl);
  previewUrl = file ? URL.createObjectURL(file) : null;
  $("#infer-frame-box").hidden = !file;
  img.hidden = true;  // until it has loaded: a file that is no image shows no broken one
  img.onload = () => { img.hidden = false; };
  if (previewUrl) img.src = previewUrl;
  else img.removeAttribute("src");
  setText("#infer-error", file && !FRAME_TYPES.includes(file.type)
    ? `frame: ${file.name} is ${file.type || "of an unknown type"}, not a JPEG or PNG` : "");
}

async function onReflex(event) {
  event.preventDefault();
  $("#reflex-button").disabled = true;
  $("#reflex-result").replaceChildren();
  const canvas = $("#reflex-frame");
  canvas.hidden = true;
  canvas.dataset.frames = "0";
  const jumpS = $("#reflex-jump").checked ? Number($("#reflex-jump-s").value) : null;
  resetSurprise(jumpS);
  try {
    const body = { episodes: Number($("#reflex-episodes").value), seed: Number($("#reflex-seed").value), task: "reach" };
    if (jumpS !== null) body.target_jump_s = jumpS;
    const started = await ctx.api("/api/sim/reflex", { method: "POST", body });
    job = started.job.id;
    setText("#reflex-status", `job ${job} running (the sim runs in a child process)…`);
    await poll(job);
  } catch (err) {
    setText("#reflex-status", `Reflex refused: ${err.message}`);
  } finally {
    $("#reflex-button").disabled = false;
  }
}

async function poll(id) {
  for (;;) {
    const j = (await ctx.api(`/api/sim/reflex/${encodeURIComponent(id)}`)).job;
    showSurprise(j.surprise);
    if (j.state !== "running") return renderReflex(j);
    await new Promise((r) => setTimeout(r, POLL_MS));
  }
}

function renderReflex(j) {
  $("#reflex-result").dataset.state = j.state;
  if (j.state !== "completed") {
    setText("#reflex-status", `Reflex ${j.state}: ${j.error ?? "no result"}`);
    return;
  }
  const r = j.result || {};
  const mean = r.mean_return ?? r.candidate?.mean_return ?? r.policy?.mean_return;
  setText("#reflex-status", `Reflex done in ${duration(j.elapsed_s)}`);
  const pairs = [["mean return", num(mean, 5)]];
  for (const key of ["success_rate", "expert_mean_return", "random_mean_return", "version", "checkpoint"]) {
    if (r[key] !== undefined) pairs.push([key.replace(/_/g, " "), Array.isArray(r[key]) ? r[key].map((v) => num(v, 5)).join(", ") : String(r[key])]);
  }
  const f = j.frames;
  if (f) pairs.push(["frames", f.error ? `none: ${f.error}` : `${f.emitted} streamed`]);
  fillKv("#reflex-result", pairs);
}

// -- the Mid Loop's surprise beside the frames ---------------------------------------------------

// A dashed vertical line at the target jump (no annotation plugin is vendored: a few lines do it)
const jumpMarker = {
  id: "jumpMarker",
  afterDatasetsDraw(chart, _args, opts) {
    if (typeof opts.t !== "number") return;
    const x = chart.scales.x.getPixelForValue(opts.t);
    const { top, bottom } = chart.chartArea;
    const g = chart.ctx;
    g.save();
    g.strokeStyle = "#c0392b";
    g.setLineDash([5, 4]);
    g.beginPath(); g.moveTo(x, top); g.lineTo(x, bottom); g.stroke();
    g.fillStyle = "#c0392b";
    g.fillText(`target jump ${opts.t} s`, Math.min(x + 4, chart.chartArea.right - 90), top + 10);
    g.restore();
  },
};

function makeSurpriseChart() {
  if (typeof Chart !== "function") return null;  // vendor file missing: the banner says so
  return new Chart($("#reflex-surprise-chart"), {
    type: "line",
    data: { datasets: [{ label: "surprise", data: [], borderColor: "#8e44ad", pointRadius: 1.5, borderWidth: 2 }] },
    options: {
      animation: false, maintainAspectRatio: false, parsing: false, normalized: true,
      scales: { x: { type: "linear", min: 0, max: EPISODE_S, title: { display: true, text: "time (s)" } },
                y: { beginAtZero: true, title: { display: true, text: "surprise (nats)" } } },
      plugins: { legend: { display: false }, jumpMarker: { t: null } },
    },
    plugins: [jumpMarker],
  });
}

function resetSurprise(jumpS) {
  lastRecordStep = -1;
  $("#reflex-surprise").hidden = true;
  $("#reflex-surprise").dataset.records = "0";
  setText("#reflex-surprise-latest", "–");
  if (!surpriseChart) surpriseChart = makeSurpriseChart();
  if (surpriseChart) {
    surpriseChart.data.datasets[0].data = [];
    surpriseChart.options.plugins.jumpMarker.t = jumpS;
    surpriseChart.update("none");
  }
}

function showSurprise(s) {
  if (!s) return;  // the child has not said yet (or streams no frames)
  const box = $("#reflex-surprise");
  box.hidden = false;
  const none = !s.mid_loop;
  $("#reflex-surprise-none").hidden = !none;
  box.querySelector(".chart-box").hidden = none;
  if (none) {
    setText("#reflex-surprise-none", s.reason || "no mid_loop promoted");
    return;
  }
  const horizon = s.horizons?.length ? ` at ${s.horizons[0]}` : "";
  for (const r of s.records || []) {
    if (typeof r.step !== "number" || r.step <= lastRecordStep) continue;
    lastRecordStep = r.step;
    box.dataset.records = String(Number(box.dataset.records) + 1);  // grid points received (tests read it)
    if (typeof r.surprise !== "number") continue;  // null until the first prediction that far back
    surpriseChart?.data.datasets[0].data.push({ x: r.t, y: r.surprise });
    setText("#reflex-surprise-latest", `${num(r.surprise, 3)} at ${num(r.t, 3)} s (${s.mid_loop}${horizon})`);
  }
  surpriseChart?.update("none");
}
