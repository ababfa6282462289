// The Run page's Config & provenance and Downloads cards.
//
//   renderProvenance(prov)          GET /api/runs/<id>/provenance: #run-config (every config key,
//                                   nested dicts flattened to dotted keys, <tr data-key>), #run-dataset,
//                                   #run-vqvae (a link to #run/<its run id> when known), #run-code,
//                                   #run-gate (one row per gate verdict)
//   renderDownloads(ctx, data)      GET /api/runs/<id>/artifacts: one row per artifact
//                                   (<li data-artifact=<name> data-kind=<kind>>, its size and a button)
//   flatten(obj)                    [[dotted key, value], ...] sorted by key (also used by Compare)
//
// Downloads need the bearer token, which a plain <a href> cannot send: the bytes are fetched with
// it, wrapped in a Blob URL and handed to a temporary <a download>, revoked right after.
import { $, el, fillKv } from "./util.js";

export function flatten(obj, prefix = "", out = []) {
  for (const [k, v] of Object.entries(obj || {})) {
    const key = prefix ? `${prefix}.${k}` : k;
    if (v && typeof v === "object" && !Array.isArray(v)) flatten(v, key, out);
    else out.push([key, v]);
  }
  return prefix ? out : out.sort((a, b) => (a[0] < b[0] ? -1 : a[0] > b[0] ? 1 : 0));
}

export const show = (v) => (v === null || v === undefined ? "–" : typeof v === "object" ? JSON.stringify(v) : String(v));

export function bytes(n) {
  if (typeof n !== "number") return "–";
  if (n < 1024) return `${n} B`;
  if (n < 1024 ** 2) return `${(n / 1024).toFixed(1)} KiB`;
  if (n < 1024 ** 3) return `${(n / 1024 ** 2).toFixed(1)} MiB`;
  return `${(n / 1024 ** 3).toFixed(2)} GiB`;
}

export function renderProvenance(prov) {
  const rows = flatten(prov.config || {});
  $("#run-config tbody").replaceChildren(...rows.map(([k, v]) =>
    el("tr", { "data-key": k }, el("td", { text: k }), el("td", { text: show(v) }))));
  setText("#run-config-count", `${rows.length} keys`);
  const d = prov.dataset || {};
  const share = typeof d.imagined_share === "number" ? `${(100 * d.imagined_share).toFixed(1)} %` : null;
  fillKv("#run-dataset", [
    ["path", d.path], ["fingerprint", d.fingerprint], ["episodes", show(d.episodes)], ["steps", show(d.steps)],
    ["imagined", d.imagined_episodes === null || d.imagined_episodes === undefined ? null
      : `${d.imagined_episodes} episodes${share ? ` (${share})` : ""}`],
  ]);
  const vq = $("#run-vqvae");
  if (!prov.vqvae) vq.replaceChildren(el("span", { class: "muted", text: "none (this component reads no VQ-VAE)" }));
  else {
    const parts = [];
    if (prov.vqvae.run_id) parts.push(el("a", { href: `#run/${encodeURIComponent(prov.vqvae.run_id)}`, text: prov.vqvae.run_id }));
    parts.push(el("span", { text: ` ${[prov.vqvae.version, prov.vqvae.dir].filter(Boolean).join(" · ")}` }));
    vq.replaceChildren(...parts);
  }
  const c = prov.code || {};
  setText("#run-code", [c.version ? `version ${c.version}` : null,
    c.git_commit ? `commit ${c.git_commit}${c.git_dirty ? " (with uncommitted changes)" : ""}` : null].filter(Boolean).join(" · ") || "unknown");
  const gate = prov.gate || [];
  $("#run-gate tbody").replaceChildren(...(gate.length ? gate.map((g) => el("tr", { "data-verdict": show(g.verdict) },
    el("td", { text: show(g.version ?? g.model_id) }),
    el("td", { text: `${show(g.verdict)}${g.promoted && g.verdict !== "promoted" ? " · promoted" : ""}` }),
    el("td", { class: "wrap" }, checksList(g)), el("td", { text: g.at ? new Date(g.at).toLocaleString() : "–" })))
    : [el("tr", {}, el("td", { colSpan: 4, class: "muted", text: "Not gated yet (the gate runs at promotion)." }))]));
}

// one line per check ("baselines: passed (detail)"), then the reasons that are not a check's detail
function checksList(g) {
  const lines = [...(Array.isArray(g.checks) ? g.checks.map((c) => checksText([c])) : g.checks ? [checksText(g.checks)] : []),
                 ...extraReasons(g)];
  if (!lines.length) return document.createTextNode("–");
  return el("ul", { class: "checks" }, ...lines.map((line) => el("li", { text: line })));
}

// the gate's reasons repeat its failed checks' details: only the others (its notes) are added
function extraReasons(g) {
  const details = new Set(Array.isArray(g.checks) ? g.checks.map((c) => c && c.detail) : []);
  return Array.isArray(g.reasons) ? g.reasons.filter((r) => !details.has(r)) : [];
}

function setText(sel, text) { $(sel).textContent = text ?? ""; }

// the gate's checks ([{check, status, detail}], hope_models/promote/gate.py) as one line
export function checksText(checks) {
  if (!checks) return "–";
  if (Array.isArray(checks)) {
    return checks.map((c) => (c && typeof c === "object"
      ? `${c.check ?? c.name ?? "?"}: ${show(c.status ?? c.verdict ?? c.passed)}${c.detail ? ` (${c.detail})` : ""}` : show(c))).join("; ");
  }
  if (typeof checks === "object") return Object.entries(checks).map(([k, v]) => `${k}: ${show(v)}`).join("; ");
  return show(checks);
}

export function renderDownloads(ctx, data) {
  const list = $("#run-downloads");
  const items = data.artifacts || [];
  list.replaceChildren(...items.map((a) => {
    const button = el("button", { type: "button", class: "small", text: "Download" });
    button.addEventListener("click", () => download(ctx, a, button));
    const what = a.description || a.kind;
    return el("li", { "data-artifact": a.name, "data-kind": a.kind },
      el("span", { class: "artifact-name", text: a.name }),
      el("span", { class: "muted", text: ` ${bytes(a.size)}${a.step !== undefined && a.step !== null ? ` · step ${a.step}` : ""}` }),
      what ? el("div", { class: "muted small-text", text: what }) : "", button);
  }));
  if (!items.length) list.append(el("li", { class: "muted", text: "No artifacts yet." }));
}

async function download(ctx, artifact, button) {
  button.disabled = true;
  const status = $("#run-download-status");
  status.textContent = `Downloading ${artifact.name}…`;
  try {
    const response = await fetch(artifact.url, { headers: { Authorization: `Bearer ${ctx.token}` } });
    if (!response.ok) {
      let message = `HTTP ${response.status}`;
      try { message = (await response.json()).error || message; } catch { /* not JSON */ }
      throw new Error(message);
    }
    const blob = await response.blob();
    const url = URL.createObjectURL(blob);
    const a = el("a", { href: url, download: artifact.name });
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10_000);  // after the browser has started saving it
    status.textContent = `${artifact.name}: ${bytes(blob.size)} downloaded`;
  } catch (err) {
    status.textContent = `${artifact.name}: download failed (${err.message})`;
  } finally {
    button.disabled = false;
  }
}
