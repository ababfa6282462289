// Small DOM and formatting helpers shared by the pages.
export const $ = (sel, root = document) => root.querySelector(sel);

export function setText(sel, text) { $(sel).textContent = text ?? ""; }

// <dl> from [[label, value], ...]; values go in as text, never HTML
export function fillKv(sel, pairs) {
  const dl = $(sel);
  dl.replaceChildren();
  for (const [k, v] of pairs) {
    const dt = document.createElement("dt"); dt.textContent = k;
    const dd = document.createElement("dd"); dd.textContent = v ?? "–";
    dd.dataset.key = k;
    dl.append(dt, dd);
  }
}

export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") node.className = v;
    else if (k.startsWith("data-")) node.dataset[k.slice(5)] = v;
    else if (k === "text") node.textContent = v;
    else node[k] = v;
  }
  node.append(...children);
  return node;
}

export const num = (v, digits = 4) => (typeof v === "number" && isFinite(v) ? Number(v.toPrecision(digits)).toString() : "–");

export function duration(seconds) {
  if (typeof seconds !== "number" || !isFinite(seconds)) return "–";
  if (seconds < 90) return `${seconds.toFixed(1)} s`;
  if (seconds < 5400) return `${(seconds / 60).toFixed(1)} min`;
  return `${(seconds / 3600).toFixed(1)} h`;
}

export const time = (iso) => (iso ? new Date(iso).toLocaleTimeString() : "–");
