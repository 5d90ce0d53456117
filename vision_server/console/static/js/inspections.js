// Inspections: the list, a new inspection (a draft), and the editor of the inspection shown:
// the try panel (source, run, overlay, verdict, values, timing), the tools drawn on the image
// (ROI, caliper line, circle ring, template: tools.js), a control for every key of its type from
// GET /api/schema (fields.js), a job's steps and fixtures (jobs.js), the histogram, the YAML
// snippet and the save. The page holds the whole edited mapping (``config``); every change
// re-runs the inspection (debounced) in the try lane. A configured inspection whose changes are
// only numeric keys and its ROI is tried with ``options`` and saved in place (POST .../save:
// comments and layout kept); anything else, and every draft, is tried with ``config`` and saved
// whole (PUT /api/inspections/{name}). Both saves ask why.

import { api, ApiError } from "./api.js";
import { buildApi } from "./buildapi.js";
import { histogramChart } from "./charts.js";
import { byId, debounce, el, fillKeyValues, formatNumber, replaceChildren } from "./dom.js";
import { INSPECTION_NAME, STEP_NAME, fieldId, renderFields, showFieldError } from "./fields.js";
import { angleToImage, angleToPart, frameFrom, pointToImage, pointToPart, roiToImage, roiToPart, round2 } from "./frames.js";
import { JobPanel, renameReferences } from "./jobs.js";
import { clone, flatten, getPath, isMapping, sameValue, setPath } from "./paths.js";
import { RoiEditor } from "./roi.js";
import { ToolLayer } from "./tools.js";
import { askWhy } from "./why.js";
import { scalar, toYaml } from "./yaml.js";

const RERUN_DELAY_MS = 250;
const TYPES_WITHOUT_SCHEMA = ["presence", "locate", "qr", "code", "qr_pose", "caliper", "calibration_board", "job"];
const BAND_KINDS = new Set(["edge", "width", "line"]);
// Keys drawn by the editor itself, not as one control each.
const INSPECTION_SKIP = new Set(["name", "type", "roi", "steps", "measurements"]);
const STEP_SKIP = new Set(["type", "roi", "measurements"]);

/** The page shown (for pendingChange()). */
let page = null;

/**
 * The pending change of the inspection being edited, as a save would write it: ``{name,
 * options}`` when only tuned keys changed (the keys that differ, ``{}`` when none: the
 * inspection as configured), else ``{name, config}`` with the whole edited mapping (a copy);
 * null when none is open. The impact preview (js/impact.js) re-runs it over stored images.
 */
export function pendingChange() {
  if (page === null || page.selected === null || page.config === null) return null;
  const options = page.optionsDiff();
  if (options !== null) return { name: page.selected.name, options };
  return { name: page.selected.name, config: clone(page.config) };
}

/**
 * Read the inspections again after the configuration changed from another panel of the page
 * (the Train panel wrote ``model:``), keeping the inspection shown; its pending changes stay
 * when it has any, else it shows the configuration as now loaded.
 */
export async function reloadInspections() {
  if (page === null) return;
  if (page.selected !== null && !page.selected.draft && !page.isDirty()) page.config = null;
  await page.load();
  const name = page.selected?.name;
  if (name && page.config === null) page.select(name);
}

const STAGE_MARGIN_PX = 300;   // the window's height less this is the image's at most

function fitImage(image, stage) {
  if (!image.naturalWidth) return;
  const room = stage.clientWidth;
  const tall = Math.max(200, window.innerHeight - STAGE_MARGIN_PX);
  const width = Math.min(room, tall * image.naturalWidth / image.naturalHeight);
  image.style.width = `${Math.floor(width)}px`;
}

/** A try's values as table rows: a job's steps one row each (its verdict and numbers; lists
 * as their length), everything else as it is. */
function summaryRows(data) {
  const rows = [];
  for (const [key, value] of Object.entries(data)) {
    if (key === "steps" && isMapping(value)) {
      for (const [name, step] of Object.entries(value)) {
        if (!isMapping(step)) continue;
        const bits = [step.passed ? "pass" : "FAIL"];
        for (const [k, v] of Object.entries(step)) {
          if (k === "passed" || k === "type") continue;
          if (typeof v === "number") bits.push(`${k} ${formatNumber(v)}`);
          else if (typeof v === "string" || typeof v === "boolean") bits.push(`${k} ${v}`);
          else if (Array.isArray(v)) bits.push(`${k} ×${v.length}`);
        }
        rows.push([`${name} (${step.type ?? "step"})`, bits.join(" · ")]);
      }
    } else {
      rows.push([key, value]);
    }
  }
  return rows;
}

export class InspectionsPage {
  constructor() {
    this.inspections = [];
    this.drafts = new Map();   // name -> draft record, until saved
    this.selected = null;      // the record from /api/inspections (or a draft)
    this.original = null;      // its config as loaded (null for a draft)
    this.config = null;        // the edited mapping
    this.stepIndex = null;     // a job's selected step
    this.measIndex = null;     // the selected caliper measurement
    this.lastData = null;      // the last try's data (fixture frames, step outcomes)
    this.reads = null;         // the inspection's last reads (for a regex)
    this.templateRect = null;  // the rectangle drawn with the template tool, image pixels
    this.schema = null;
    this.cameras = [];
    this.running = false;
    this.pending = false;
    this.started = false;
    // Each edit is numbered; the stage says which edit the outcome shown was tried with
    // (``#try-stage[data-edit]`` and ``[data-tried]``: equal once the try of the last edit
    // answered), so that a person or a test can tell a stale verdict from a current one.
    this.editSeq = 0;
    const later = debounce(() => this.run(), RERUN_DELAY_MS);
    this.rerun = () => {
      this.editSeq += 1;
      byId("try-stage").dataset.edit = String(this.editSeq);
      later();
    };
    this.rerun.cancel = () => later.cancel();
    page = this;
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
    this.roi = new RoiEditor(byId("try-image"), byId("try-canvas"), (roi, final) => this.roiDrawn(roi, final));
    // A small image (320 x 240) is shown enlarged, a large one shrunk, always whole: as wide as
    // the panel and no taller than the window leaves beside the verdict.
    const fit = () => fitImage(byId("try-image"), byId("try-stage"));
    byId("try-image").addEventListener("load", fit);
    window.addEventListener("resize", fit);
    this.tools = new ToolLayer(this.roi, (tool, shape) => this.toolDrawn(tool, shape));
    this.jobs = new JobPanel(this);
    this.hintText = byId("try-hint").textContent;
    byId("try-run").addEventListener("click", () => this.run());
    for (const radio of document.querySelectorAll("input[name=try-source]")) {
      radio.addEventListener("change", () => this.sourceChanged());
    }
    byId("try-file").addEventListener("change", () => this.run());
    byId("try-result-id").addEventListener("change", () => this.run());
    byId("try-recording-frame").addEventListener("change", () => this.run());
    for (const [i, id] of ["roi-x", "roi-y", "roi-w", "roi-h"].entries()) {
      byId(id).addEventListener("input", () => this.roiTyped(i, id));
    }
    for (const button of document.querySelectorAll("#tool-bar [data-tool]")) {
      button.addEventListener("click", () => this.useTool(button.dataset.tool));
    }
    byId("tool-band-width").addEventListener("input", () => this.bandWidthTyped());
    byId("tool-ring-search").addEventListener("input", () => { this.tools.ringSearch = Number(byId("tool-ring-search").value) || 0; });
    byId("train-template").addEventListener("click", () => this.trainTemplate());
    byId("meas-add").addEventListener("click", () => this.addMeasurement());
    byId("copy-yaml").addEventListener("click", () => this.copySnippet());
    byId("save-config").addEventListener("click", () => this.save());
    byId("reset-changes").addEventListener("click", () => this.reset());
    byId("new-inspection").addEventListener("click", () => this.openNew());
    byId("new-cancel").addEventListener("click", () => { byId("new-form").hidden = true; });
    byId("new-form").addEventListener("submit", (event) => { event.preventDefault(); this.createDraft(); });
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
    try {
      this.schema = await buildApi.schema();
    } catch {
      this.schema = null;   // an older server: numeric keys and the ROI only, as before
    }
    this.inspections = listing.inspections ?? [];
    for (const insp of this.inspections) this.drafts.delete(insp.name);
    this.renderList();
    if (this.followRoute()) return;
    const name = this.selected?.name;
    if (name && this.inspections.some((i) => i.name === name)) this.select(name, { keepChanges: true });
  }

  /** The routes `#/inspections/NAME` (the inspection open: a bookmark, a reload) and
   * `#/inspections/NAME?result=ID` (the Results page's "Try this image": NAME tried on the
   * stored input of result ID). The result is taken once: the hash then names the inspection
   * only, so that a reload or a return does not try it again. */
  followRoute() {
    const match = /^#\/inspections\/([^?]+)(?:\?result=(\d{1,18}))?$/.exec(location.hash);
    if (match === null) return false;
    const name = decodeURIComponent(match[1]);
    if (!this.inspections.some((i) => i.name === name)) {
      history.replaceState(null, "", "#/inspections");
      return false;
    }
    if (this.selected?.name !== name || match[2]) this.select(name);
    else this.select(name, { keepChanges: true });
    if (match[2]) {
      document.querySelector("input[name=try-source][value=result]").checked = true;
      byId("try-result-id").value = match[2];
      this.sourceChanged({ run: false });
      this.run();
    }
    return true;
  }

  renderList() {
    const entries = [...this.inspections, ...this.drafts.values()];
    replaceChildren(byId("inspection-list"), ...entries.map((insp) =>
      el("li", {},
        el("button", {
          type: "button", class: `list-item${insp.draft ? " draft" : ""}${insp.name === this.selected?.name ? " active" : ""}`,
          dataset: { inspection: insp.name }, onclick: () => this.select(insp.name),
        },
        el("span", { class: "list-title" }, insp.name),
        el("span", { class: "list-sub" }, `${insp.type} · ${insp.camera}${insp.draft ? " · draft" : ""}`)))));
  }

  // -- a new inspection -----------------------------------------------------------------------

  async openNew() {
    const form = byId("new-form");
    form.hidden = !form.hidden;
    if (form.hidden) return;
    byId("new-error").textContent = "";
    const types = this.schema ? Object.keys(this.schema.types ?? {}) : TYPES_WITHOUT_SCHEMA;
    replaceChildren(byId("new-type"), types.map((t) => el("option", { value: t }, t)));
    try {
      this.cameras = (await api.cameras()).cameras ?? [];
    } catch (exc) {
      byId("new-error").textContent = `Cameras unavailable: ${exc.message}`;
    }
    replaceChildren(byId("new-camera"), this.cameras.map((c) => el("option", { value: c.name }, `${c.name} (${c.source})`)));
    if (!this.schema) byId("new-error").textContent = "This server gives no schema (GET /api/schema): a draft cannot be edited here.";
    byId("new-name").focus();
  }

  createDraft() {
    const name = byId("new-name").value.trim();
    const type = byId("new-type").value;
    const camera = byId("new-camera").value;
    const error = byId("new-error");
    if (!INSPECTION_NAME.test(name)) {
      error.textContent = "A name of letters, digits and _ - . (at most 64).";
      return;
    }
    if (this.inspections.some((i) => i.name === name) || this.drafts.has(name)) {
      error.textContent = `An inspection named ${name} exists: choose it in the list, or another name.`;
      return;
    }
    if (!type || !camera) {
      error.textContent = "Choose a type and a camera.";
      return;
    }
    const source = this.cameras.find((c) => c.name === camera)?.source ?? "sim";
    const config = { name, type, camera };
    if (type === "job") config.steps = [];
    // A draft's ``config`` is the page's working copy (kept while another inspection is
    // shown); ``initial`` is what Reset goes back to.
    this.drafts.set(name, {
      name, type, camera, camera_source: source, depth: false, config, initial: clone(config),
      parameters: [], roi: null, draft: true,
    });
    byId("new-form").hidden = true;
    byId("new-name").value = "";
    this.renderList();
    this.select(name);
    // The editor opens on the camera's live frame, so that tools can be drawn before a try.
    if (source !== "request") {
      const image = byId("try-image");
      const failed = () => {
        // A triggered or folder camera has no frame until an inspection took one.
        image.removeAttribute("src");
        byId("try-hint").textContent = `No frame of camera ${camera} yet: press Run, or upload an image.`;
        byId("try-hint").hidden = false;
      };
      image.addEventListener("error", failed, { once: true });
      image.addEventListener("load", () => image.removeEventListener("error", failed), { once: true });
      image.src = api.frameUrl(camera, Date.now());
      byId("try-hint").hidden = true;
    }
  }

  // -- choosing an inspection -----------------------------------------------------------------

  record(name) {
    return this.inspections.find((i) => i.name === name) ?? this.drafts.get(name) ?? null;
  }

  select(name, { keepChanges = false } = {}) {
    const insp = this.record(name);
    if (!insp) return;
    const switched = this.selected?.name !== name;
    const keep = keepChanges && !switched && this.config !== null;
    this.selected = insp;
    this.original = insp.draft ? null : clone(insp.config ?? {});
    if (!keep) {
      this.config = insp.draft ? insp.config : clone(insp.config ?? { name: insp.name, type: insp.type, camera: insp.camera });
      this.stepIndex = insp.type === "job" && (this.config.steps ?? []).length ? 0 : null;
      this.measIndex = null;
    }
    if (switched) {
      this.lastData = null;
      this.templateRect = null;
      this.reads = null;
      this.jobs.pending = null;
      byId("fixture-status").textContent = "";
      byId("template-preview").hidden = true;
      if (!insp.draft) this.loadReads(insp.name);
    }
    for (const button of document.querySelectorAll("#inspection-list .list-item")) {
      button.classList.toggle("active", button.dataset.inspection === name);
    }
    // The address names the inspection shown (a draft has none to name: not in the server's list).
    const route = insp.draft ? "#/inspections" : `#/inspections/${encodeURIComponent(name)}`;
    if (location.hash.startsWith("#/inspections") && location.hash !== route) {
      history.replaceState(null, "", route);
    }
    byId("inspection-none").hidden = true;
    byId("inspection-body").hidden = false;
    byId("insp-name").textContent = insp.name;
    byId("insp-type").textContent = insp.type;
    byId("insp-draft").hidden = !insp.draft;
    byId("insp-camera").textContent =
      `camera ${insp.camera} (${insp.camera_source}${insp.depth ? ", depth" : ""})`;
    byId("insp-config").textContent = insp.draft ? "(a draft: not in the configuration until saved)" : toYaml(insp.config ?? {});
    byId("try-source-recording").hidden = insp.camera_source !== "recording";
    if (switched) {
      this.clearOutcome();
      byId("try-image").removeAttribute("src");
      byId("try-hint").textContent = this.hintText;
      byId("try-hint").hidden = false;
      byId("save-ok").textContent = "";
      byId("save-error").hidden = true;
      // A request camera has no frame of its own to grab: start from an upload. A recording
      // camera: from its recording's frames (its "camera frame" is the last one inspected).
      const first = { request: "upload", recording: "recording" };
      const source = first[insp.camera_source] ?? "camera";
      document.querySelector(`input[name=try-source][value=${source}]`).checked = true;
      this.sourceChanged({ run: false });
      this.useTool("roi");
    }
    this.renderEditor();
  }

  async loadReads(name) {
    try {
      const answer = await buildApi.reads(name);
      if (this.selected?.name !== name) return;
      this.reads = Array.isArray(answer.reads) ? answer.reads : [];
    } catch {
      this.reads = null;
    }
    for (const box of document.querySelectorAll("#inspection-body input[data-key]")) box.refreshReads?.();
  }

  // -- what is edited: the inspection, a job's step, a caliper's measurement ------------------

  isJob() {
    return this.config?.type === "job";
  }

  /** The mapping the tools and the ROI edit: the inspection, or the job's selected step. */
  target() {
    if (!this.isJob()) return this.config;
    const steps = Array.isArray(this.config.steps) ? this.config.steps : [];
    return isMapping(steps[this.stepIndex ?? -1]) ? steps[this.stepIndex] : null;
  }

  measurement() {
    const target = this.target();
    const list = target?.measurements;
    return Array.isArray(list) && isMapping(list[this.measIndex ?? -1]) ? list[this.measIndex] : null;
  }

  /** The fixture frame of the target: null when it is in image pixels, undefined when it is
   * fixtured but no try has made that frame yet. */
  targetFrame() {
    const target = this.target();
    if (!this.isJob() || !target?.fixture) return null;
    return this.frameOf(target.fixture) ?? undefined;
  }

  frameOf(name) {
    return frameFrom(this.lastData?.steps?.[name]);
  }

  stepOutcome(name) {
    const values = this.lastData?.steps?.[name];
    return isMapping(values) ? values : null;
  }

  stepTypes() {
    return this.schema ? Object.keys(this.schema.steps ?? {}) : [];
  }

  keysFor(kind, type) {
    const s = this.schema;
    if (!s) return [];
    if (kind === "step") {
      const keys = [...(s.steps?.[type]?.keys ?? [])];
      if (!keys.some((k) => k.key === "name")) keys.unshift({ key: "name", kind: "string", required: true, doc: "what later steps and the verdict call it" });
      return keys;
    }
    // The common keys less those the type does not take (a job's or a caliper's roi).
    const without = new Set(s.types?.[type]?.without_common ?? []);
    // The type's own keys first (what is tuned), then the ones every inspection has.
    const merged = new Map();
    for (const key of [...(s.types?.[type]?.keys ?? []), ...(s.common ?? [])]) {
      if (!without.has(key.key) && !merged.has(key.key)) merged.set(key.key, key);
    }
    return [...merged.values()];
  }

  /** A presence's min and max take the range of its measure (a slider where it is bounded). */
  ranged(keys, scope) {
    const range = scope?.type === "presence" ? this.schema?.presence_ranges?.[scope.measure] : null;
    if (!Array.isArray(range)) return keys;
    return keys.map((k) => (k.key === "min" || k.key === "max" ? { ...k, min: range[0] ?? k.min, max: range[1] ?? k.max } : k));
  }

  measurementKeys(targetKeys) {
    const list = targetKeys.find((k) => k.key === "measurements");
    return list?.items?.keys ?? [];
  }

  targetKeys() {
    const target = this.target();
    if (!target) return [];
    return this.isJob() ? this.keysFor("step", target.type) : this.keysFor("inspection", target.type);
  }

  targetHasRoi() {
    const target = this.target();
    if (!target) return false;
    if (!this.schema) return !this.isJob();
    return this.targetKeys().some((k) => k.key === "roi");
  }

  /** The key a trained template goes to in the target (null: the target takes none now). */
  templateKey() {
    const target = this.target();
    if (target?.type === "locate" && target.method === "template") return "template.image";
    if (target?.type === "presence" && target.measure === "template_score") return "template";
    return null;
  }

  // -- the editor -----------------------------------------------------------------------------

  renderEditor() {
    const job = this.isJob();
    const target = this.target();
    byId("job-block").hidden = !job;
    if (job) this.jobs.render();
    else byId("fixture-block").hidden = true;
    // The inspection's own keys.
    byId("param-title").textContent = this.schema ? (job ? "Job" : "Settings") : "Parameters";
    if (this.schema) {
      renderFields(byId("param-fields"), this.ranged(this.keysFor("inspection", this.config.type), this.config), this.config, {
        scope: "insp", skip: INSPECTION_SKIP,
        special: (key) => (key.key === "camera" ? this.cameraControl() : null),
        validate: (key, text) => this.validateText("insp", key, text),
        onChange: () => this.edited(),
        onStructure: () => this.edited({ structure: true }),
        reads: () => this.reads,
      });
    } else {
      this.buildParams();
    }
    // A job's selected step.
    const stepBlock = byId("step-block");
    stepBlock.hidden = !(job && target && this.schema);
    if (!stepBlock.hidden) {
      byId("step-title").textContent = `Step ${target.name ?? ""} (${target.type ?? "?"})`;
      renderFields(byId("step-fields"), this.ranged(this.keysFor("step", target.type), target), target, {
        scope: "step", skip: STEP_SKIP,
        special: (key) => this.stepControl(key, target),
        validate: (key, text) => this.validateText("step", key, text),
        onChange: () => this.edited(),
        onStructure: () => this.edited({ structure: true }),
        reads: () => this.reads,
      });
    }
    this.renderMeasurements();
    // The ROI and the tools.
    byId("roi-block").hidden = !this.targetHasRoi();
    const frame = this.targetFrame();
    byId("target-title").textContent = !job ? "Region of interest"
      : `ROI of ${target?.name ?? "the step"}${target?.fixture ? ` (part frame of ${target.fixture}, px)` : " (image px)"}`;
    this.syncTools(frame);
    this.refreshSnippet();
  }

  cameraControl() {
    const names = new Set(this.cameras.map((c) => c.name));
    names.add(this.config.camera);
    const select = el("select", { id: fieldId("insp", "camera"), "data-key": "camera" },
      [...names].filter(Boolean).map((n) => el("option", { value: n, selected: n === this.config.camera }, n)));
    select.addEventListener("change", () => {
      this.config.camera = select.value;
      this.edited();
    });
    if (this.cameras.length === 0) {
      api.cameras().then((answer) => {
        this.cameras = answer.cameras ?? [];
        for (const c of this.cameras) {
          if (![...select.options].some((o) => o.value === c.name)) select.append(el("option", { value: c.name }, c.name));
        }
      }).catch(() => {});
    }
    return select;
  }

  /** A step's references to earlier steps are chosen, never typed; its name renames them. */
  stepControl(key, step) {
    const index = this.stepIndex ?? 0;
    const earlier = (this.config.steps ?? []).slice(0, index).filter(isMapping);
    const choices = {
      fixture: earlier.filter((s) => s.type === "fixture"),
      origin: earlier.filter((s) => s.type === "locate"),
      x_towards: earlier.filter((s) => s.type === "locate"),
      angle_from: earlier.filter((s) => s.type === "locate" && (s.method === "template" || s.method === "blob")),
    }[key.key];
    if (choices) {
      const select = el("select", { id: fieldId("step", key.key), "data-key": key.key },
        el("option", { value: "" }, key.key === "origin" ? "— choose a locate —" : "— none —"),
        choices.map((s) => el("option", { value: s.name, selected: step[key.key] === s.name }, s.name)));
      select.addEventListener("change", () => {
        if (key.key === "fixture") {
          this.jobs.setFixture(index, select.value || null);
          return;
        }
        setPath(step, key.key, select.value || undefined);
        this.edited({ structure: true });
      });
      return select;
    }
    if (key.key === "name") {
      const box = el("input", { type: "text", id: fieldId("step", "name"), "data-key": "name", value: step.name ?? "", spellcheck: "false", class: "wide" });
      let current = step.name;
      box.addEventListener("input", () => {
        const text = box.value;
        const taken = (this.config.steps ?? []).some((s, i) => i !== index && s?.name === text);
        const problem = !STEP_NAME.test(text) ? "letters, digits and _, not starting with a digit" : taken ? "another step has this name" : null;
        const slot = box.closest(".field-row")?.querySelector(".field-error");
        if (slot) slot.textContent = problem ?? "";
        if (problem) return;
        renameReferences(this.config, current, text);
        step.name = text;
        current = text;
        byId("step-title").textContent = `Step ${text} (${step.type})`;
        this.edited();
      });
      return box;
    }
    return null;
  }

  validateText(scope, key, text) {
    if (key.key === "name" && scope === "meas") {
      return this.isJob() && !STEP_NAME.test(text) ? "letters, digits and _, not starting with a digit" : null;
    }
    if (key.kind === "expression" && /[\n\r]/.test(text)) return "one line";
    if (text.length > 500) return "at most 500 characters";
    return null;
  }

  renderMeasurements() {
    const target = this.target();
    const block = byId("meas-block");
    const keys = this.measurementKeys(this.targetKeys());
    block.hidden = !(target && target.type === "caliper" && keys.length);
    if (block.hidden) return;
    const list = Array.isArray(target.measurements) ? target.measurements : [];
    if (this.measIndex === null && list.length) this.measIndex = 0;
    if (this.measIndex !== null && this.measIndex >= list.length) this.measIndex = list.length ? list.length - 1 : null;
    const kinds = keys.find((k) => k.key === "kind")?.values ?? [];
    // A caliper's most common measurement first: the width between an edge pair.
    const keep = byId("meas-add-kind").value || (kinds.includes("width") ? "width" : kinds[0]);
    replaceChildren(byId("meas-add-kind"), kinds.map((k) => el("option", { value: k, selected: k === keep }, k)));
    replaceChildren(byId("meas-list"), list.length ? list.map((m, i) => el("li", {
      class: `step-item${i === this.measIndex ? " active" : ""}`, dataset: { measurement: m?.name ?? "", index: i },
    },
    el("button", { type: "button", class: "step-select", "data-test": "measurement-select", onclick: () => { this.measIndex = i; this.renderEditor(); } },
      el("span", { class: "step-name" }, m?.name ?? "(no name)"), el("span", { class: "list-sub" }, m?.kind ?? "?")),
    el("span", { class: "step-buttons" },
      el("button", { type: "button", class: "btn btn-small measurement-remove", "data-test": "measurement-remove", "aria-label": `Remove ${m?.name}`,
        onclick: () => { list.splice(i, 1); if (list.length === 0) delete target.measurements; this.edited({ structure: true }); } }, "✕"))))
      : el("li", { class: "muted" }, "No measurements yet: add one, or draw a caliper line or a circle ring."));
    const m = this.measurement();
    if (m) {
      renderFields(byId("meas-fields"), keys, m, {
        scope: "meas",
        validate: (key, text) => this.validateText("meas", key, text),
        onChange: () => this.edited(),
        onStructure: () => this.edited({ structure: true }),
        reads: () => this.reads,
      });
    } else {
      replaceChildren(byId("meas-fields"));
    }
  }

  addMeasurement(kind = byId("meas-add-kind").value, values = {}) {
    const target = this.target();
    if (!target || !kind) return null;
    if (!Array.isArray(target.measurements)) target.measurements = [];
    if (target.measurements.length >= 64) return null;
    const used = new Set(target.measurements.map((m) => m?.name));
    let n = target.measurements.length + 1;
    while (used.has(`${kind}_${n}`)) n += 1;
    const m = { name: `${kind}_${n}`, kind, ...values };
    target.measurements.push(m);
    this.measIndex = target.measurements.length - 1;
    this.edited({ structure: true });
    return m;
  }

  /** The old numeric parameters (GET /api/inspections), for a server without a schema. */
  buildParams() {
    const insp = this.selected;
    const rows = (insp.parameters ?? []).map((param) => {
      const value = getPath(this.config, param.key) ?? param.value;
      const number = el("input", {
        type: "number", class: "param-number", "aria-label": param.key,
        min: param.min, max: param.max, step: param.step ?? "any", value,
        dataset: { param: param.key, key: param.key },
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
        setPath(this.config, param.key, v);
        this.edited();
      };
      number.addEventListener("input", () => changed(number));
      if (range) range.addEventListener("input", () => changed(range));
      const bounds = hasRange ? `${formatNumber(param.min)} … ${formatNumber(param.max)}` : "";
      return el("div", { class: "param" },
        el("label", { class: "param-label" }, el("span", {}, param.key), el("span", { class: "muted" }, bounds)),
        el("div", { class: "param-inputs" }, range, number));
    });
    replaceChildren(byId("param-fields"), rows.length ? rows : el("p", { class: "muted" }, "No numeric parameters."));
  }

  /** After any edit: the snippet, the tools, the step list; a structural one redraws the
   * controls (another method's keys, a step added). Then a try. */
  edited({ structure = false } = {}) {
    if (structure) this.renderEditor();
    else {
      if (this.isJob()) this.jobs.render();
      this.syncTools(this.targetFrame());
      this.refreshSnippet();
    }
    byId("save-ok").textContent = "";
    this.rerun();
  }

  runSoon() {
    this.rerun();
  }

  selectStep(i, { edited = false } = {}) {
    this.stepIndex = i;
    this.measIndex = null;
    this.templateRect = null;
    this.lastRing = null;
    byId("fixture-chooser").hidden = true;
    // Another step may not take the tool in hand: back to the ROI where it does not.
    if (!this.toolsAllowed()[this.tools.tool]) this.useTool("roi");
    if (edited) this.edited({ structure: true });
    else this.renderEditor();
  }

  // -- the ROI and the tools ------------------------------------------------------------------

  useTool(tool) {
    this.tools.use(tool);
    for (const button of document.querySelectorAll("#tool-bar [data-tool]")) {
      button.setAttribute("aria-pressed", String(button.dataset.tool === tool));
    }
    byId("tool-band-options").hidden = tool !== "band";
    byId("tool-ring-options").hidden = tool !== "ring";
    byId("train-template").hidden = tool !== "rect";
    this.tools.bandWidth = Number(byId("tool-band-width").value) || 5;
    this.tools.ringSearch = Number(byId("tool-ring-search").value) || 0;
    this.syncTools(this.targetFrame());
  }

  /** Which tools the target takes, what is drawn, and the ROI editor on the target's ROI. */
  /** Which tools apply to what is edited now. */
  toolsAllowed() {
    const target = this.target();
    const type = target?.type;
    return {
      roi: this.targetHasRoi(),
      band: type === "caliper",
      ring: type === "caliper" || (type === "locate" && target?.method === "circle"),
      rect: this.templateKey() !== null,
    };
  }

  syncTools(frame) {
    if (!this.tools) return;
    const target = this.target();
    const type = target?.type;
    const circleLocate = type === "locate" && target?.method === "circle";
    const can = this.toolsAllowed();
    for (const button of document.querySelectorAll("#tool-bar [data-tool]")) {
      button.disabled = !can[button.dataset.tool];
    }
    const status = byId("tool-status");
    let say = "";
    if (frame === undefined) say = `This step is in frame ${target.fixture}: run a try first (no try has made that frame yet).`;
    else if (this.tools.tool !== "roi" && !can[this.tools.tool]) say = "This tool does not apply to what is edited now.";
    status.textContent = say;
    // The ROI: a fixtured one is edited around its centre and shown turned by the frame.
    const roiValue = Array.isArray(target?.roi) ? target.roi.map(Number) : null;
    if (!can.roi || frame === undefined) {
      this.roi.angle = 0;
      this.roi.set(null);
    } else if (frame) {
      this.roi.angle = frame.angle;
      this.roi.set(roiValue ? roiToImage(frame, roiValue) : null);
    } else {
      this.roi.angle = 0;
      this.roi.set(roiValue);
    }
    this.showRoiFields(roiValue);
    // The caliper's bands and circles, in the image.
    const bands = [], rings = [];
    if (type === "caliper" && frame !== undefined) {
      for (const m of Array.isArray(target.measurements) ? target.measurements : []) {
        if (!isMapping(m)) continue;
        const b = m.band;
        if (isMapping(b) && Array.isArray(b.center) && typeof b.length === "number") {
          bands.push({
            centre: frame ? pointToImage(frame, b.center) : b.center, length: b.length, width: b.width ?? 1,
            angle: frame ? angleToImage(frame, b.angle_rad ?? 0) : (b.angle_rad ?? 0), label: m.name,
          });
        }
        if (Array.isArray(m.center) && typeof m.radius === "number") {
          rings.push({ centre: frame ? pointToImage(frame, m.center) : m.center, radius: m.radius, search: m.search ?? 10, label: m.name });
        }
      }
    }
    if (circleLocate && this.lastRing) rings.push(this.lastRing);
    const frames = [];
    for (const step of this.isJob() ? this.config.steps ?? [] : []) {
      if (step?.type !== "fixture") continue;
      const f = this.frameOf(step.name);
      if (f) frames.push({ ...f, name: step.name });
    }
    this.tools.show({ bands, rings, rect: can.rect ? this.templateRect : null, frames });
    byId("template-block").hidden = !can.rect;
    if (can.rect) {
      const path = getPath(target, this.templateKey());
      byId("template-path").textContent = path ? `${this.templateKey()}: ${path}` : "No template yet: drag a rectangle on the image, then Train template.";
    }
    byId("train-template").disabled = !(can.rect && this.templateRect);
  }

  showRoiFields(roi) {
    ["roi-x", "roi-y", "roi-w", "roi-h"].forEach((id, i) => {
      const input = byId(id);
      if (document.activeElement !== input) input.value = roi ? String(roi[i]) : "";
    });
  }

  /** The ROI editor moved or drew the ROI (image pixels). */
  roiDrawn(imageRoi, final = true) {
    const target = this.target();
    if (!target) return;
    const frame = this.targetFrame();
    if (frame === undefined) {
      if (!final) return;
      byId("tool-status").textContent = `Run a try first: no try has made frame ${target.fixture} yet, so the ROI cannot be put in it.`;
      this.roi.set(null);
      this.runSoon();
      return;
    }
    target.roi = imageRoi === null ? undefined : frame ? roiToPart(frame, imageRoi) : imageRoi;
    if (target.roi === undefined) delete target.roi;
    this.showRoiFields(target.roi ?? null);
    this.refreshSnippet();
    if (this.isJob()) this.jobs.render();
    this.rerun();
  }

  roiTyped(i, id) {
    const target = this.target();
    if (!target) return;
    const value = Number(byId(id).value);
    if (!Number.isFinite(value) || byId(id).value === "") return;
    const current = Array.isArray(target.roi) ? [...target.roi] : [0, 0, 1, 1];
    current[i] = value;
    target.roi = current;
    this.edited();
  }

  bandWidthTyped() {
    const width = Number(byId("tool-band-width").value);
    if (!(width >= 1)) return;
    this.tools.bandWidth = width;
    const m = this.measurement();
    if (m && isMapping(m.band)) {
      m.band.width = width;
      this.edited({ structure: true });
    }
  }

  /** A caliper line, a ring or a template rectangle was drawn (image pixels). */
  toolDrawn(tool, shape) {
    const target = this.target();
    if (!target || !this.toolsAllowed()[tool]) return;
    if (tool === "rect") {
      this.templateRect = shape;
      this.syncTools(this.targetFrame());
      byId("tool-status").textContent = `Template rectangle ${shape.join(", ")}: press Train template.`;
      return;
    }
    const frame = this.targetFrame();
    if (frame === undefined) {
      if (!final) return;
      byId("tool-status").textContent = `Run a try first: no try has made frame ${target.fixture} yet.`;
      return;
    }
    if (tool === "band") {
      const { a, b } = shape;
      const centre = [(a[0] + b[0]) / 2, (a[1] + b[1]) / 2];
      const angle = Math.atan2(b[1] - a[1], b[0] - a[0]);
      const band = {
        center: frame ? pointToPart(frame, centre) : centre.map(round2),
        length: Math.max(3, round2(Math.hypot(b[0] - a[0], b[1] - a[1]))),
        width: Number(byId("tool-band-width").value) || 5,
        angle_rad: frame ? angleToPart(frame, angle) : Math.round(angle * 10000) / 10000,
      };
      let m = this.measurement();
      if (m && BAND_KINDS.has(m.kind)) {
        m.band = band;
        this.edited({ structure: true });
      } else {
        const wanted = byId("meas-add-kind").value;
        m = this.addMeasurement(BAND_KINDS.has(wanted) ? wanted : "width", { band });
      }
      byId("tool-status").textContent = `Band of ${m?.name}: centre ${band.center.join(", ")}, length ${band.length}, angle ${band.angle_rad} rad` +
        (frame ? ` (in frame ${target.fixture})` : "") + ".";
      return;
    }
    if (tool === "ring") {
      const search = Number(byId("tool-ring-search").value) || 10;
      if (target.type === "locate") {
        setPath(target, "circle.min_radius_px", Math.max(1, Math.round(shape.radius - search)));
        setPath(target, "circle.max_radius_px", Math.round(shape.radius + search));
        this.lastRing = { centre: shape.centre, radius: shape.radius, search, label: "radius" };
        byId("tool-status").textContent = `Circle radius ${Math.round(shape.radius - search)} … ${Math.round(shape.radius + search)} px.`;
        this.edited({ structure: true });
        return;
      }
      const centre = frame ? pointToPart(frame, shape.centre) : shape.centre;
      let m = this.measurement();
      if (m && m.kind === "circle") {
        Object.assign(m, { center: centre, radius: shape.radius, search });
        this.edited({ structure: true });
      } else {
        m = this.addMeasurement("circle", { center: centre, radius: shape.radius, search });
      }
      byId("tool-status").textContent = `Circle ${m?.name}: centre ${centre.join(", ")}, radius ${shape.radius}, search ± ${search} px.`;
    }
  }

  async trainTemplate() {
    const key = this.templateKey();
    const rect = this.templateRect;
    const status = byId("tool-status");
    if (!key || !rect) return;
    const body = { source: this.source(), rect };
    if (body.source === "upload") {
      status.textContent = "A template is cut from the camera frame, a stored result or a recording frame, not an upload.";
      return;
    }
    if (body.source === "result") body.result_id = Number(byId("try-result-id").value);
    if (body.source === "recording") body.frame = Number(byId("try-recording-frame").value);
    if (this.selected.draft || this.isDirty()) body.config = clone(this.config);
    const target = this.target();
    byId("train-template").disabled = true;
    try {
      const answer = await buildApi.trainTemplate(this.selected.name, body);
      setPath(target, key, answer.path);
      const preview = byId("template-preview");
      preview.src = answer.image;
      preview.hidden = false;
      status.textContent = `Trained ${answer.path} (${answer.width} × ${answer.height} px).`;
      this.edited({ structure: true });
    } catch (exc) {
      if (!(exc instanceof ApiError && exc.status === 401)) status.textContent = `Template refused (${exc.code}): ${exc.message}`;
    } finally {
      byId("train-template").disabled = !(this.templateKey() && this.templateRect);
    }
  }

  // -- changes, the snippet -------------------------------------------------------------------

  /** The changed keys of a configured inspection as a try's ``options`` (numeric keys and the
   * ROI only), or null when the change needs the whole mapping (``config``). */
  optionsDiff() {
    if (this.selected?.draft || this.original === null) return null;
    const allowed = new Set(["roi", ...(this.selected.parameters ?? []).map((p) => p.key)]);
    const before = flatten(this.original), after = flatten(this.config);
    const options = {};
    for (const key of new Set([...before.keys(), ...after.keys()])) {
      if (sameValue(before.get(key), after.get(key))) continue;
      if (!allowed.has(key) || !after.has(key)) return null;
      options[key] = after.get(key);
    }
    return options;
  }

  isDirty() {
    if (this.selected?.draft) return true;
    return !sameValue(this.original, this.config);
  }

  refreshSnippet() {
    const snippet = byId("yaml-snippet");
    const dirty = this.isDirty();
    const options = this.optionsDiff();
    if (!dirty) {
      snippet.textContent = "No changes.";
    } else if (options !== null) {
      const lines = [`- name: ${scalar(this.selected.name)}`];
      for (const [key, value] of Object.entries(options)) lines.push(`  ${scalar(key)}: ${toYaml(value)}`);
      snippet.textContent = lines.join("\n");
    } else {
      snippet.textContent = toYaml([this.config]);
    }
    byId("save-config").disabled = !dirty;
    byId("reset-changes").disabled = !dirty || (this.selected?.draft === true && sameValue(this.config, this.selected.initial));
  }

  reset() {
    if (this.selected.draft) {
      this.selected.config = clone(this.selected.initial);
      this.config = this.selected.config;
    } else {
      this.config = clone(this.selected.config);
    }
    this.stepIndex = this.isJob() && (this.config.steps ?? []).length ? 0 : null;
    this.measIndex = null;
    this.renderEditor();
    this.rerun();
  }

  // -- the try --------------------------------------------------------------------------------

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
    const body = { source: this.source(), overlay: true };
    const options = this.optionsDiff();
    if (options !== null) body.options = options;
    else body.config = clone(this.config);
    if (body.source === "result") body.result_id = Number(byId("try-result-id").value);
    if (body.source === "recording") body.frame = Number(byId("try-recording-frame").value);
    return body;
  }

  async run() {
    if (this.selected === null) return;
    if (this.running) {
      this.pending = true;   // one more run with the newest edits when this one ends
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
    const seq = this.editSeq;
    try {
      const outcome = await api.tryInspection(name, body, file);
      if (this.selected?.name === name) this.show(outcome);
    } catch (exc) {
      if (!(exc instanceof ApiError && exc.status === 401) && this.selected?.name === name) {
        this.showRefusal(exc);
        if (exc.code !== "BUSY") this.showSourceImage(body, file);
      }
    } finally {
      byId("try-stage").dataset.tried = String(seq);
      this.running = false;
      byId("try-run").disabled = false;
      byId("try-stage").classList.remove("busy");
    }
    if (this.pending) {
      this.pending = false;
      this.run();
    }
  }

  /** The image a refused try would have run on, so that the tools can be drawn on it: a new
   * inspection is refused until its required keys are set, and some of them (a circle's radii,
   * an ROI) are set by drawing. An upload is shown from the file itself, a stored result from
   * the log, a camera's frame when the live view has one (a folder camera nothing has read
   * yet has none: upload its image instead). */
  showSourceImage(body, file) {
    const image = byId("try-image");
    let src = null;
    if (body.source === "upload" && file) {
      if (this.uploadUrl) URL.revokeObjectURL(this.uploadUrl);
      this.uploadUrl = URL.createObjectURL(file);
      src = this.uploadUrl;
    } else if (body.source === "result" && body.result_id > 0) {
      src = api.resultImageUrl(body.result_id, false);
    } else if (body.source === "camera" && !image.getAttribute("src")) {
      src = `/api/cameras/${encodeURIComponent(this.config?.camera ?? this.selected.camera)}/frame.jpg?t=${Date.now()}`;
    }
    if (src === null) return;
    image.addEventListener("load", () => { byId("try-hint").hidden = true; }, { once: true });
    image.src = src;
  }

  showRefusal(exc) {
    const verdict = byId("try-verdict");
    verdict.textContent = exc.code === "BUSY" ? "BUSY" : "ERROR";
    verdict.dataset.verdict = exc.code === "BUSY" ? "busy" : "error";
    byId("try-error").textContent = `${exc.code}: ${exc.message}`;
    for (const slot of document.querySelectorAll("#inspection-body .field-error[data-from-try]")) {
      slot.textContent = "";
      delete slot.dataset.fromTry;
    }
    // The refusal names a key path ("steps[2] (name='magnet') -> roi: ...", "verdict: ... (column
    // 7)"): say it beside that key's control too.
    const segments = String(exc.message).split(" -> ");
    const last = segments[segments.length - 1];
    const key = last.match(/^([A-Za-z_][\w.]*)/)?.[1];
    if (!key) return;
    for (const id of ["param-fields", "step-fields", "meas-fields"]) {
      if (showFieldError(byId(id), key, last)) {
        byId(id).querySelector(`.field-error[data-error-for="${CSS.escape(key)}"]`).dataset.fromTry = "1";
        break;
      }
    }
  }

  show(outcome) {
    byId("try-error").textContent = "";
    for (const slot of document.querySelectorAll("#inspection-body .field-error[data-from-try]")) {
      slot.textContent = "";
      slot.closest(".field-row")?.classList.remove("invalid");
      delete slot.dataset.fromTry;
    }
    const image = byId("try-image");
    const src = outcome.overlay ?? outcome.source_image;
    if (src) {
      image.src = src;
      byId("try-hint").hidden = true;
    }
    const verdict = byId("try-verdict");
    verdict.textContent = String(outcome.verdict ?? "—").toUpperCase();
    verdict.dataset.verdict = String(outcome.verdict ?? "none");
    this.lastData = isMapping(outcome.data) ? outcome.data : {};
    fillKeyValues(byId("try-values"), summaryRows(this.lastData));
    fillKeyValues(byId("try-timing"),
      Object.entries(outcome.timing ?? {}).map(([k, v]) => [k, typeof v === "number" ? `${formatNumber(v, 3)} ms` : v]));
    const hist = outcome.histogram;
    if (hist && Array.isArray(hist.bins)) {
      replaceChildren(byId("try-histogram"), histogramChart(hist.bins, hist.threshold ?? null));
    } else {
      replaceChildren(byId("try-histogram"), el("p", { class: "muted" }, "No histogram for this inspection."));
    }
    // A fixture chosen before its frame was made is converted now (and tried again).
    if (this.isJob() && this.jobs.afterTry()) return;
    if (this.isJob()) this.jobs.render();
    const target = this.target();
    if (this.isJob() && target?.fixture) byId("target-title").textContent = `ROI of ${target.name} (part frame of ${target.fixture}, px)`;
    this.syncTools(this.targetFrame());
  }

  // -- saving ---------------------------------------------------------------------------------

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
    const options = this.optionsDiff();
    try {
      const saved = options !== null && Object.keys(options).length
        ? await buildApi.saveOptions(name, options, why)
        : await buildApi.putInspection(name, clone(this.config), why);
      // The reload applies the whole file: say what else it changed (hand edits made since
      // the last reload go live with this save) and the reload's own notes.
      const also = saved.also_changed ?? [];
      const notes = saved.notes ?? [];
      ok.textContent = `Saved and reloaded${saved.created ? `: ${name} created` : ""}: configuration ${String(saved.config_hash).slice(0, 12)}; ` +
        `version ${saved.version} in the History.` +
        (also.length ? ` The reload also applied edits made outside the console to: ${also.join(", ")}.` : "") +
        (notes.length ? ` Reload: ${notes.join("; ")}.` : "");
      this.drafts.delete(name);
      this.config = null;
      await this.load();
      if (this.selected?.name === name && this.config === null) this.select(name);
    } catch (exc) {
      if (!(exc instanceof ApiError && exc.status === 401)) {
        error.textContent = `Refused (${exc.code}):\n${exc.message}`;
        error.hidden = false;
      }
    } finally {
      if (this.config !== null) this.refreshSnippet();
    }
  }
}

