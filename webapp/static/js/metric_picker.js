// A metric picker: a search box over a checkbox list of series names (Run and Compare pages).
//
//   const p = new MetricPicker(rootElement, (pickedNames) => ...)
//   p.setNames([{ name, points? }], pickedNames)   each box: <input type=checkbox value=<name>>
//   p.picked()                                      the names ticked, in list order
//
// The root gets an <input type=search class="metric-search"> and a <div class="metric-list">.
import { el } from "./util.js";

export class MetricPicker {
  constructor(root, onChange) {
    this.onChange = onChange;
    this.search = el("input", { type: "search", class: "metric-search", placeholder: "filter metrics" });
    this.search.setAttribute("aria-label", "filter metrics");
    this.list = el("div", { class: "metric-list" });
    root.replaceChildren(this.search, this.list);
    this.search.addEventListener("input", () => this._filter());
    this.list.addEventListener("change", () => this.onChange(this.picked()));
  }

  setNames(names, picked) {
    const want = new Set(picked);
    this.list.replaceChildren(...names.map(({ name, points }) => {
      const box = el("input", { type: "checkbox", value: name, checked: want.has(name) });
      const label = el("label", { class: "metric-option", "data-metric": name, title: name }, box,
                       el("span", { text: name }));
      if (typeof points === "number") label.append(el("span", { class: "muted", text: ` ${points}` }));
      return label;
    }));
    if (!names.length) this.list.append(el("p", { class: "muted", text: "No numeric series recorded yet." }));
    this._filter();
  }

  picked() {
    return [...this.list.querySelectorAll("input:checked")].map((b) => b.value);
  }

  _filter() {
    const q = this.search.value.trim().toLowerCase();
    for (const label of this.list.querySelectorAll("label")) {
      label.hidden = Boolean(q) && !label.dataset.metric.toLowerCase().includes(q);
    }
  }
}
