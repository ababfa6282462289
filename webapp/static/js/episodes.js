// Episodes: packages dropped (or picked) are uploaded to POST /api/episodes/upload with a progress
// bar; the answer's verdict per episode is listed; the inbox table (GET /api/episodes) shows each
// episode's validation verdict (its errors and warnings readable), what it can train and why not,
// and its tags, with a tag action (POST /api/v1/data/tag). The upload goes through
// XMLHttpRequest, not fetch: only XHR reports upload progress.
import { $, setText, el } from "./util.js";

let ctx;
let uploading = false;

export function init(c) {
  ctx = c;
  const zone = $("#drop-zone");
  zone.addEventListener("dragover", (event) => { event.preventDefault(); zone.classList.add("over"); });
  zone.addEventListener("dragleave", () => zone.classList.remove("over"));
  zone.addEventListener("drop", onDrop);
  zone.addEventListener("keydown", (event) => {
    if (event.key === "Enter" || event.key === " ") { event.preventDefault(); $("#upload-input").click(); }
  });
  $("#upload-input").addEventListener("change", (event) => {
    const files = [...event.target.files];
    event.target.value = "";
    upload(files);
  });
  // a package dropped just beside the zone must not make the browser open (or download) it
  for (const name of ["dragover", "drop"]) {
    window.addEventListener(name, (event) => { if (!zone.contains(event.target)) event.preventDefault(); });
  }
  $("#refresh-episodes").addEventListener("click", () => show().catch((err) => ctx.flash(err.message, true)));
  $("#episodes-table tbody").addEventListener("submit", onTag);
}

export async function show() {
  const inbox = await ctx.api("/api/episodes");
  setText("#inbox-info", `${inbox.episodes.length} episode(s) in ${inbox.inbox}; uploads up to ${inbox.upload_max_mb} MB`);
  $("#drop-zone").dataset.maxBytes = String(inbox.upload_max_mb * 1024 * 1024);
  $("#episodes-table tbody").replaceChildren(...inbox.episodes.map(row));
  if (!inbox.episodes.length) {
    $("#episodes-table tbody").append(el("tr", {}, el("td", { colSpan: 6, class: "muted", text: "No episodes yet: drop a package above." })));
  }
}

export const events = {};

function onDrop(event) {
  event.preventDefault();
  $("#drop-zone").classList.remove("over");
  upload([...(event.dataTransfer?.files || [])]);
}

function send(files, tags, onProgress) {
  // resolves to {status, data}; the body is multipart with one "file" part per package
  const form = new FormData();
  for (const f of files) form.append("file", f, f.name);
  if (tags) form.append("tags", tags);
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open("POST", "/api/episodes/upload");
    xhr.setRequestHeader("Authorization", `Bearer ${ctx.token}`);
    xhr.responseType = "json";
    xhr.upload.addEventListener("progress", (e) => { if (e.lengthComputable) onProgress(e.loaded / e.total); });
    xhr.addEventListener("load", () => resolve({ status: xhr.status, data: xhr.response }));
    xhr.addEventListener("error", () => reject(new Error("the upload did not reach the server")));
    xhr.send(form);
  });
}

async function upload(files) {
  if (!files.length || uploading) return;
  const max = Number($("#drop-zone").dataset.maxBytes || 0);
  const total = files.reduce((n, f) => n + f.size, 0);
  if (max && total > max) {
    setText("#upload-status", `Too large: ${files.length} file(s) of ${total} bytes; the limit is ${max} bytes.`);
    return;
  }
  uploading = true;
  const bar = $("#upload-bar");
  bar.style.width = "0%";
  $("#upload-result").replaceChildren();
  $("#upload-panel").dataset.state = "uploading";
  setText("#upload-status", `Uploading ${files.map((f) => f.name).join(", ")}…`);
  try {
    const { status, data } = await send(files, $("#upload-tags").value.trim(),
                                        (p) => { bar.style.width = `${Math.round(p * 100)}%`; });
    bar.style.width = "100%";
    if (status === 401) throw new Error("the server refused the token: log in again");
    if (status !== 200) throw new Error((data && data.error) || `HTTP ${status}`);
    const episodes = data.packages.flatMap((p) => p.episodes);
    setText("#upload-status", `Done: ${data.summary.written} new, ${data.summary.unchanged + data.summary.duplicate} already there, ${data.summary.rejected} rejected.`);
    $("#upload-result").replaceChildren(...episodes.map((e) => el("li", {
      "data-episode": e.episode_id ?? "",
      text: `${e.episode_id ?? e.source}: ${e.action}, ${e.status}; trains ${e.trainable.join(", ") || "nothing"}`,
    })));
    $("#upload-panel").dataset.state = "done";
    await show();
  } catch (err) {
    $("#upload-panel").dataset.state = "refused";
    setText("#upload-status", `Refused: ${err.message}`);
  } finally {
    uploading = false;
  }
}

function messages(kind, list) {
  if (!list.length) return null;
  return el("details", { class: kind },
            el("summary", { text: `${list.length} ${kind === "errors" ? "error" : "warning"}(s)` }),
            el("ul", {}, ...list.map((m) => el("li", { text: m }))));
}

function verdictCell(e) {
  const cell = el("td", { class: "wrap verdict", "data-status": e.status },
                  el("span", { class: `state ${e.status}`, text: e.status }));
  for (const part of [messages("errors", e.errors || []), messages("warnings", e.warnings || [])]) {
    if (part) cell.append(part);
  }
  return cell;
}

function trainCell(e) {
  const cell = el("td", { class: "wrap trainable", "data-trainable": (e.trainable || []).join(",") },
                  el("strong", { text: (e.trainable || []).join(", ") || "nothing" }));
  const why = Object.entries(e.not_trainable || {});
  if (why.length) cell.append(el("ul", { class: "why" }, ...why.map(([c, r]) => el("li", { text: `not ${c}: ${r}` }))));
  return cell;
}

function row(e) {
  const tags = el("td", { class: "wrap tags" }, ...(e.tags || []).map((t) => el("span", { class: "tag", text: t })));
  const form = el("form", { class: "tag-form", "data-episode": e.episode_id ?? "" },
                  el("input", { name: "tag", placeholder: "tag", maxLength: 64, ariaLabel: `tag for ${e.episode_id}` }),
                  el("button", { type: "submit", class: "small", text: "Tag" }));
  if (e.status === "rejected") for (const c of form.elements) c.disabled = true;
  return el("tr", { "data-episode": e.episode_id ?? "" },
            el("td", { class: "wrap", text: e.episode_id ?? "–", title: `${e.origin ?? ""} ${e.source ?? ""}`.trim() }),
            el("td", { text: String(e.steps ?? 0) }), verdictCell(e), trainCell(e), tags, el("td", {}, form));
}

async function onTag(event) {
  event.preventDefault();
  const form = event.target;
  const tag = form.elements.tag.value.trim();
  if (!tag) return;
  try {
    const out = await ctx.api("/api/v1/data/tag", { method: "POST", body: { episode_id: form.dataset.episode, tag } });
    ctx.flash(`Tagged ${out.episode.episode_id}: ${out.episode.tags.join(", ")}`);
    await show();
  } catch (err) { ctx.flash(`Not tagged: ${err.message}`, true); }
}
