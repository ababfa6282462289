// The Robot Editor's core: the token login, the API client, the Socket.IO connection and the
// page switcher. Each page is a small module (jobs.js, run.js, compare.js, episodes.js, system.js,
// workers.js, models.js, inference.js) with
//   init(ctx)    once, after login: wire its forms
//   show(arg)    each time it becomes visible: reload its state from the API (so a reload of the
//                browser or a missed event never leaves it stale); `arg` is what follows the page
//                name in the hash (#run/<run id>, #compare/<id>,<id>), or null
//   events       {socket event name: handler}, live updates while logged in.
// No framework and no build step: the vendor globals `io` and `Chart` come from
// webapp/static/vendor/ (npm, copied at setup).
import * as jobs from "./jobs.js";
import * as run from "./run.js";
import * as compare from "./compare.js";
import * as episodes from "./episodes.js";
import * as system from "./system.js";
import * as workers from "./workers.js";
import * as models from "./models.js";
import * as inference from "./inference.js";
import { $, setText } from "./util.js";

const TOKEN_KEY = "hope.token";
const PAGES = { jobs, run, compare, episodes, system, workers, models, inference };
const EVENTS = ["run.state", "run.progress", "run.log", "system.stats", "system.throttle",
                "brain.reloaded", "sim.frame"];

class AuthError extends Error {}

const ctx = {
  token: null,
  socket: null,
  // fetch with the bearer token; resolves to the JSON body, throws Error(message) on a 4xx/5xx
  async api(path, { method = "GET", body, headers: extra } = {}) {
    const headers = { Authorization: `Bearer ${ctx.token}`, ...(extra || {}) };
    if (body !== undefined) headers["Content-Type"] = "application/json";
    const response = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
    let data = null;
    try { data = await response.json(); } catch { /* an empty or non-JSON body: reported below */ }
    if (response.status === 401) {
      logout("The server refused the token: " + ((data && data.error) || "unauthorized"));
      throw new AuthError("unauthorized");
    }
    if (!response.ok) {
      const err = new Error((data && data.error) || `${method} ${path}: HTTP ${response.status}`);
      err.status = response.status;
      err.data = data;
      throw err;
    }
    return data;
  },
  flash(message, bad = false) {
    const el = $("#flash");
    el.textContent = message;
    el.classList.toggle("bad", bad);
  },
};

// -- login ------------------------------------------------------------------------------------

async function tokenAccepted(token) {
  // any cheap authenticated GET tells a good token from a bad one
  const response = await fetch("/api/runs?limit=1", { headers: { Authorization: `Bearer ${token}` } });
  if (response.status === 401) {
    let message = "invalid token";
    try { message = (await response.json()).error || message; } catch { /* keep the default */ }
    return { ok: false, message };
  }
  if (!response.ok) return { ok: false, message: `the server answered HTTP ${response.status}` };
  return { ok: true };
}

function showLogin(message = "") {
  $("#app").hidden = true;
  $("#login").hidden = false;
  setText("#login-error", message);
  $("#token-input").focus();
}

function logout(message = "") {
  localStorage.removeItem(TOKEN_KEY);
  ctx.token = null;
  if (ctx.socket) { ctx.socket.disconnect(); ctx.socket = null; }
  showLogin(message);
}

let initialised = false;

async function enter(token) {
  ctx.token = token;
  $("#login").hidden = true;
  $("#app").hidden = false;
  if (!initialised) {
    for (const page of Object.values(PAGES)) page.init(ctx);
    initialised = true;
  }
  connectSocket();
  route();
}

async function onLogin(event) {
  event.preventDefault();
  const token = $("#token-input").value.trim();
  setText("#login-error", "");
  $("#login-button").disabled = true;
  try {
    const verdict = await tokenAccepted(token);
    if (!verdict.ok) { setText("#login-error", `Token refused: ${verdict.message}`); return; }
    localStorage.setItem(TOKEN_KEY, token);
    $("#token-input").value = "";
    await enter(token);
  } catch (err) {
    setText("#login-error", `Cannot reach the server: ${err.message}`);
  } finally {
    $("#login-button").disabled = false;
  }
}

// -- live events ------------------------------------------------------------------------------

function connectSocket() {
  if (typeof io !== "function") {
    ctx.flash("Live updates are off: socket.io-client is not installed (run make setup)", true);
    return;
  }
  // WebSocket first: one connection for the session's life. Long-polling only when a WebSocket
  // cannot open (a proxy that strips Upgrade); the server allows it one waiting request per session.
  const socket = io({ auth: { token: ctx.token }, reconnectionDelayMax: 5000,
                      transports: ["websocket", "polling"], tryAllTransports: true });
  ctx.socket = socket;
  const conn = $("#conn");
  socket.on("connect", () => {
    conn.textContent = "live"; conn.classList.add("live");
    // events sent while we were away are in the API: reload what is on screen
    const [hashName, arg] = hashParts();
    current()?.show(hashName === pageName() ? arg : null);
  });
  socket.on("disconnect", () => { conn.textContent = "offline"; conn.classList.remove("live"); });
  socket.on("connect_error", (err) => {
    conn.textContent = "offline"; conn.classList.remove("live");
    if (String(err && err.message).startsWith("unauthorized")) logout("The server refused the token for live updates.");
  });
  for (const name of EVENTS) {
    socket.on(name, (data) => {
      for (const page of Object.values(PAGES)) {
        const handler = page.events && page.events[name];
        if (handler) {
          try { handler(data); } catch (err) { console.error(name, err); }
        }
      }
    });
  }
}

// -- pages ------------------------------------------------------------------------------------

// "#run/r-123" -> ["run", "r-123"]; a bare "#system" -> ["system", null]
function hashParts() {
  const hash = location.hash.replace(/^#/, "");
  const cut = hash.indexOf("/");
  return cut < 0 ? [hash, null] : [hash.slice(0, cut), decodeURIComponent(hash.slice(cut + 1)) || null];
}

function pageName() {
  const [name] = hashParts();
  if (name in PAGES) return name;
  const path = location.pathname.replace(/^\//, "");
  return path in PAGES ? path : "jobs";
}

function current() { return ctx.token ? PAGES[pageName()] : null; }

function route() {
  if (!ctx.token) return;
  const name = pageName();
  for (const p of Object.keys(PAGES)) $(`#page-${p}`).hidden = p !== name;
  for (const a of document.querySelectorAll("#nav a")) a.classList.toggle("active", a.dataset.page === name);
  ctx.flash("");
  const [hashName, arg] = hashParts();
  PAGES[name].show(hashName === name ? arg : null).catch((err) => { if (!(err instanceof AuthError)) ctx.flash(err.message, true); });
}

window.addEventListener("hashchange", route);
$("#login-form").addEventListener("submit", onLogin);
$("#logout").addEventListener("click", () => logout("Logged out."));

const saved = localStorage.getItem(TOKEN_KEY);
if (saved) {
  // check it again: the deployment may have a new token since
  tokenAccepted(saved).then(
    (v) => (v.ok ? enter(saved) : logout(`Token refused: ${v.message}`)),
    (err) => showLogin(`Cannot reach the server: ${err.message}`));
} else {
  showLogin();
}
