// Models: what each component serves and what is promoted (with the gate's verdict and the
// history), promote a completed run, roll a component back. brain.reloaded refreshes it.
import { $, setText, el, time } from "./util.js";

let ctx;

export function init(c) {
  ctx = c;
  $("#refresh-models").addEventListener("click", () => show());
  $("#promote-form").addEventListener("submit", onPromote);
  $("#models-list").addEventListener("click", onRollback);
}

export async function show() {
  const [brain, completed] = await Promise.all([ctx.api("/api/brain?history=5"),
                                                ctx.api("/api/runs?state=completed&limit=50")]);
  setText("#brain-state", `BrainService: ${brain.brain}`);
  const list = $("#models-list");
  list.replaceChildren(...Object.entries(brain.components).map(([name, c]) => card(name, c)));
  const select = $("#promote-run-select");
  const keep = select.value;
  select.replaceChildren(...completed.runs.map((r) => el("option", { value: r.id, text: `${r.id} · ${r.component} · ${r.step} steps` })));
  if (!completed.runs.length) select.append(el("option", { value: "", text: "no completed runs yet" }));
  if (keep && completed.runs.some((r) => r.id === keep)) select.value = keep;
}

export const events = {
  "brain.reloaded": (d) => {
    ctx.flash(`${d.component} now serves ${d.version}`);
    if (!$("#page-models").hidden) show().catch(() => {});
  },
};

function gateText(gate) {
  if (!gate) return "–";
  const verdict = gate.passed === false ? "refused" : gate.passed ? "passed" : "?";
  const reasons = (gate.reasons || []).join("; ");
  return reasons ? `${verdict}: ${reasons}` : verdict;
}

function card(name, c) {
  const promoted = c.promoted;
  const rows = [
    ["serving", c.serving?.version || (c.serving?.last_error ? `not served: ${c.serving.last_error}` : "nothing")],
    ["promoted", promoted ? `${promoted.version} (run ${promoted.run_id ?? "–"}) at ${time(promoted.promoted_at)}` : "nothing yet"],
    ["gate", gateText(promoted?.gate_result)],
  ];
  if (c.pointer_error) rows.push(["pointer", c.pointer_error]);
  const dl = el("dl", { class: "kv" });
  for (const [k, v] of rows) dl.append(el("dt", { text: k }), el("dd", { text: v, "data-key": k }));
  const hist = el("ul", { class: "history" },
    ...(c.history || []).map((m) => el("li", { text: `${m.version ?? m.checkpoint_path} · ${m.promoted ? "promoted" : m.demoted_at ? "demoted" : "candidate"} · gate ${gateText(m.gate_result)}` })));
  const rollback = el("button", { type: "button", class: "small secondary", text: "Roll back", "data-rollback": name });
  rollback.disabled = !promoted || !promoted.previous_model_id;
  return el("div", { class: "card", "data-component": name },
            el("h3", { text: name }), dl, rollback, el("h3", { text: "History" }), hist);
}

async function onPromote(event) {
  event.preventDefault();
  const runId = $("#promote-run-select").value;
  if (!runId) { setText("#promote-form-result", "Pick a completed run."); return; }
  $("#promote-button").disabled = true;
  setText("#promote-form-result", "Running the promotion gate…");
  try {
    const force = $("#promote-force").checked;
    const admin = $("#promote-admin").value.trim();  // forcing over HTTP needs the second credential
    const headers = force && admin ? { "X-Hope-Admin": admin } : undefined;
    const out = await ctx.api("/api/brain/promote", { method: "POST", body: { run_id: runId, force }, headers });
    setText("#promote-form-result", `Promoted ${out.version}; serving ${out.serving ?? "–"}`);
    await show();
  } catch (err) {
    setText("#promote-form-result", `Not promoted: ${err.message}`);
  } finally {
    $("#promote-button").disabled = false;
  }
}

async function onRollback(event) {
  const component = event.target.dataset.rollback;
  if (!component) return;
  try {
    const out = await ctx.api("/api/brain/rollback", { method: "POST", body: { component } });
    ctx.flash(`${component} rolled back to ${out.version}; serving ${out.serving ?? "–"}`);
    await show();
  } catch (err) { ctx.flash(`Rollback refused: ${err.message}`, true); }
}
