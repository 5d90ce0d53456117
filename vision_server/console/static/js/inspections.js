// Inspections: the list, the selected inspection's configuration as loaded, and the try panel
// (source, run, overlay, verdict, values, timing, ROI editor, parameters, histogram, YAML
// snippet, save). Every change of the ROI or a parameter re-runs the inspection (debounced) with
// ``options``: the keys that differ from the configuration as loaded.

import { api, ApiError } from "./api.js";
import { histogramChart } from "./charts.js";
import { byId, debounce, el, fillKeyValues, formatNumber, replaceChildren } from "./dom.js";
import { RoiEditor } from "./roi.js";
import { askWhy } from "./why.js";
import { scalar, toYaml } from "./yaml.js";

const RERUN_DELAY_MS = 250;

function sameValue(a, b) {
  return JSON.stringify(a) === JSON.stringify(b);
}

let shownPage = null;

/** The pending change of the inspection shown, for the Impact panel: {name, options} (the try
 * panel's options: the keys that differ from the configuration as loaded), or null when no
 * inspection is open. */
export function pendingChange() {
  const page = shownPage;
  if (!page?.selected) return null;
  return { name: page.selected.name, options: { ...page.changes } };
}

export class InspectionsPage {
  constructor() {
    shownPage = this;
    this.inspections = [];
    this.selected = null;      // the inspection record from /api/inspections
    this.changes = {};         // key -> value that differs from selected (the try/save options)
    this.running = false;
    this.pending = false;
    this.started = false;
    this.rerun = debounce(() => this.run(), RERUN_DELAY_MS);
    this.paramInputs = new Map();
  }

  start() {
    if (!this.started) this.wire();
    this.load();
  }

  stop() {
    this.rerun.cancel();
  }

  wire() {
    this.started = true;
    this.roi = new RoiEditor(byId("try-image"), byId("try-canvas"), (roi) => {
      this.setChange("roi", roi);
      this.showRoiFields(roi);
      this.rerun();
    });
    byId("try-run").addEventListener("click", () => this.run());
    for (const radio of document.querySelectorAll("input[name=try-source]")) {
      radio.addEventListener("change", () => this.sourceChanged());
    }
    byId("try-file").addEventListener("change", () => this.run());
    byId("try-result-id").addEventListener("change", () => this.run());
    byId("try-recording-frame").addEventListener("change", () => this.run());
    for (const [i, id] of ["roi-x", "roi-y", "roi-w", "roi-h"].entries()) {
      byId(id).addEventListener("input", () => {
        const current = this.currentRoi() ?? [0, 0, 1, 1];
        const value = Number(byId(id).value);
        if (!Number.isFinite(value)) return;
        current[i] = value;
        this.roi.set(current);
        this.setChange("roi", current);
        this.rerun();
      });
    }
    byId("copy-yaml").addEventListener("click", () => this.copySnippet());
    byId("save-config").addEventListener("click", () => this.save());
    byId("reset-changes").addEventListener("click", () => this.reset());
  }

  async load() {
    let listing;
    try {
      listing = await api.inspections();
    } catch (exc) {
      if (!(exc instanceof ApiError && exc.status === 401)) {
        byId("inspection-none").textContent = `Inspections unavailable: ${exc.message}`;
      }
      return;
    }
    this.inspections = listing.inspections ?? [];
    const list = byId("inspection-list");
    replaceChildren(list, ...this.inspections.map((insp) =>
      el("li", {},
        el("button", {
          type: "button", class: "list-item", dataset: { inspection: insp.name },
          onclick: () => this.select(insp.name),
        },
        el("span", { class: "list-title" }, insp.name),
        el("span", { class: "list-sub" }, `${insp.type} · ${insp.camera}`)))));
    const keep = this.selected && this.inspections.find((i) => i.name === this.selected.name);
    if (keep) this.select(keep.name, { keepChanges: true });
  }

  select(name, { keepChanges = false } = {}) {
    const insp = this.inspections.find((i) => i.name === name);
    if (!insp) return;
    const switched = this.selected?.name !== name;
    this.selected = insp;
    if (switched || !keepChanges) this.changes = {};
    for (const button of document.querySelectorAll("#inspection-list .list-item")) {
      button.classList.toggle("active", button.dataset.inspection === name);
    }
    byId("inspection-none").hidden = true;
    byId("inspection-body").hidden = false;
    byId("insp-name").textContent = insp.name;
    byId("insp-type").textContent = insp.type;
    byId("insp-camera").textContent =
      `camera ${insp.camera} (${insp.camera_source}${insp.depth ? ", depth" : ""})`;
    byId("insp-config").textContent = toYaml(insp.config ?? {});
    this.buildParams(insp);
    // A recording camera's frames can be tried one by one (docs/console.md, source "recording").
    byId("try-source-recording").hidden = insp.camera_source !== "recording";
    if (switched) {
      this.clearOutcome();
      byId("try-image").removeAttribute("src");
      byId("try-hint").hidden = false;
      // A request camera has no frame of its own to grab: start from an upload. A recording
      // camera: from its recording's frames (its "camera frame" is the last one inspected).
      const first = { request: "upload", recording: "recording" };
      const source = first[insp.camera_source] ?? "camera";
      document.querySelector(`input[name=try-source][value=${source}]`).checked = true;
      this.sourceChanged({ run: false });
    }
    this.roi.set(this.currentRoi());
    this.showRoiFields(this.currentRoi());
    this.refreshSnippet();
  }

  currentRoi() {
    if (Object.hasOwn(this.changes, "roi")) return this.changes.roi ? [...this.changes.roi] : null;
    return this.selected?.roi ? [...this.selected.roi] : null;
  }

  showRoiFields(roi) {
    ["roi-x", "roi-y", "roi-w", "roi-h"].forEach((id, i) => {
      const input = byId(id);
      if (document.activeElement !== input) input.value = roi ? String(roi[i]) : "";
    });
  }

  buildParams(insp) {
    this.paramInputs.clear();
    const rows = (insp.parameters ?? []).map((param) => {
      const value = Object.hasOwn(this.changes, param.key) ? this.changes[param.key] : param.value;
      const number = el("input", {
        type: "number", class: "param-number", "aria-label": param.key,
        min: param.min, max: param.max, step: param.step ?? "any", value,
        dataset: { param: param.key },
      });
      const hasRange = typeof param.min === "number" && typeof param.max === "number";
      const range = hasRange ? el("input", {
        type: "range", class: "param-range", "aria-label": `${param.key} slider`,
        min: param.min, max: param.max, step: param.step ?? "any", value,
      }) : null;
      const changed = (source) => {
        const v = Number(source.value);
        if (!Number.isFinite(v)) return;
        if (range && source !== range) range.value = String(v);
        if (source !== number) number.value = String(v);
        this.setChange(param.key, v);
        this.rerun();
      };
      number.addEventListener("input", () => changed(number));
      if (range) range.addEventListener("input", () => changed(range));
      this.paramInputs.set(param.key, { number, range, param });
      const bounds = hasRange ? `${formatNumber(param.min)} … ${formatNumber(param.max)}` : "";
      return el("div", { class: "param" },
        el("label", { class: "param-label" }, el("span", {}, param.key), el("span", { class: "muted" }, bounds)),
        el("div", { class: "param-inputs" }, range, number));
    });
    replaceChildren(byId("param-fields"), rows.length ? rows : el("p", { class: "muted" }, "No numeric parameters."));
  }

  setChange(key, value) {
    const original = key === "roi"
      ? this.selected?.roi ?? null
      : (this.selected?.parameters ?? []).find((p) => p.key === key)?.value;
    if (sameValue(original, value)) delete this.changes[key];
    else this.changes[key] = value;
    this.refreshSnippet();
  }

  refreshSnippet() {
    const keys = Object.keys(this.changes);
    const snippet = byId("yaml-snippet");
    if (keys.length === 0) {
      snippet.textContent = "No changes.";
    } else {
      const lines = [`- name: ${scalar(this.selected.name)}`];
      for (const key of keys) lines.push(`  ${scalar(key)}: ${toYaml(this.changes[key])}`);
      snippet.textContent = lines.join("\n");
    }
    byId("save-config").disabled = keys.length === 0;
    byId("reset-changes").disabled = keys.length === 0;
  }

  reset() {
    this.changes = {};
    this.select(this.selected.name, { keepChanges: true });
    this.rerun();
  }

  source() {
    return document.querySelector("input[name=try-source]:checked").value;
  }

  sourceChanged({ run = true } = {}) {
    const source = this.source();
    byId("try-file").hidden = source !== "upload";
    byId("try-result-id").hidden = source !== "result";
    byId("try-recording-frame").hidden = source !== "recording";
    if (source === "upload" && run) byId("try-file").click();
    else if ((source === "camera" || source === "recording") && run) this.run();
  }

  clearOutcome() {
    const verdict = byId("try-verdict");
    verdict.textContent = "—";
    verdict.dataset.verdict = "none";
    replaceChildren(byId("try-values"));
    replaceChildren(byId("try-timing"));
    byId("try-error").textContent = "";
    replaceChildren(byId("try-histogram"), el("p", { class: "muted" }, "No histogram for this inspection."));
  }

  /** The try request body (docs/console.md: POST /api/inspections/{name}/try). */
  requestBody() {
    const body = { source: this.source(), options: { ...this.changes }, overlay: true };
    if (body.source === "result") body.result_id = Number(byId("try-result-id").value);
    if (body.source === "recording") body.frame = Number(byId("try-recording-frame").value);
    return body;
  }

  async run() {
    if (this.selected === null) return;
    if (this.running) {
      this.pending = true;   // one more run with the newest options when this one ends
      return;
    }
    const body = this.requestBody();
    const file = body.source === "upload" ? byId("try-file").files[0] : null;
    if (body.source === "upload" && !file) {
      byId("try-error").textContent = "Choose an image file to upload.";
      return;
    }
    if (body.source === "result" && !(body.result_id > 0)) {
      byId("try-error").textContent = "Enter the id of a stored result (see the Results page).";
      return;
    }
    if (body.source === "recording" && !(Number.isInteger(body.frame) && body.frame >= 0)) {
      byId("try-error").textContent = "Enter a frame of the recording (0 is the first).";
      return;
    }
    this.running = true;
    byId("try-run").disabled = true;
    byId("try-stage").classList.add("busy");
    const name = this.selected.name;
    try {
      const outcome = await api.tryInspection(name, body, file);
      if (this.selected?.name === name) this.show(outcome);
    } catch (exc) {
      if (!(exc instanceof ApiError && exc.status === 401)) {
        const verdict = byId("try-verdict");
        verdict.textContent = exc.code === "BUSY" ? "BUSY" : "error";
        verdict.dataset.verdict = exc.code === "BUSY" ? "busy" : "error";
        byId("try-error").textContent = `${exc.code}: ${exc.message}`;
      }
    } finally {
      this.running = false;
      byId("try-run").disabled = false;
      byId("try-stage").classList.remove("busy");
    }
    if (this.pending) {
      this.pending = false;
      this.run();
    }
  }

  show(outcome) {
    byId("try-error").textContent = "";
    const image = byId("try-image");
    const src = outcome.overlay ?? outcome.source_image;
    if (src) {
      image.src = src;
      byId("try-hint").hidden = true;
    }
    const verdict = byId("try-verdict");
    verdict.textContent = String(outcome.verdict ?? "—").toUpperCase();
    verdict.dataset.verdict = String(outcome.verdict ?? "none");
    fillKeyValues(byId("try-values"), Object.entries(outcome.data ?? {}));
    fillKeyValues(byId("try-timing"),
      Object.entries(outcome.timing ?? {}).map(([k, v]) => [k, typeof v === "number" ? `${formatNumber(v, 3)} ms` : v]));
    const hist = outcome.histogram;
    if (hist && Array.isArray(hist.bins)) {
      replaceChildren(byId("try-histogram"), histogramChart(hist.bins, hist.threshold ?? null));
    } else {
      replaceChildren(byId("try-histogram"), el("p", { class: "muted" }, "No histogram for this inspection."));
    }
    this.roi.set(this.currentRoi());
  }

  async copySnippet() {
    try {
      await navigator.clipboard.writeText(byId("yaml-snippet").textContent);
      byId("save-ok").textContent = "Snippet copied.";
    } catch {
      // Clipboard access needs a secure context; select the text instead for Ctrl+C.
      getSelection().selectAllChildren(byId("yaml-snippet"));
    }
  }

  async save() {
    const name = this.selected.name;
    const ok = byId("save-ok"), error = byId("save-error");
    ok.textContent = "";
    error.hidden = true;
    // The history keeps why with every save: no reason, no save (js/why.js).
    const why = await askWhy({ title: `Why change ${name}?`, action: "Save" });
    if (why === null) return;
    byId("save-config").disabled = true;
    try {
      const saved = await api.save(name, { ...this.changes }, why);
      // The reload applies the whole file: say what else it changed (hand edits made since
      // the last reload go live with this save) and the reload's own notes.
      const also = saved.also_changed ?? [];
      const notes = saved.notes ?? [];
      ok.textContent = `Saved and reloaded: configuration ${String(saved.config_hash).slice(0, 12)}; ` +
        `version ${saved.version} in the History.` +
        (also.length ? ` The reload also applied edits made outside the console to: ${also.join(", ")}.` : "") +
        (notes.length ? ` Reload: ${notes.join("; ")}.` : "");
      this.changes = {};
      await this.load();
    } catch (exc) {
      if (!(exc instanceof ApiError && exc.status === 401)) {
        error.textContent = `Refused (${exc.code}):\n${exc.message}`;
        error.hidden = false;
      }
    } finally {
      this.refreshSnippet();
    }
  }
}
