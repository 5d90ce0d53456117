// Training an anomaly inspection (docs/console.md, "Training an anomaly inspection"): the
// Inspections page's Train panel, shown for an anomaly inspection and a job with an anomaly
// step. Good images are picked from the inspection's stored results (passing ones checked by
// default) or grabbed from its camera; POST /api/inspections/{name}/train trains, writes the
// model beside the configuration, points model: at it (in the History) and reloads the server.
// While it runs, GET /api/training says how far it is. The model in force comes from
// GET /api/inspections/{name}/model.

import { ApiError, api, getJson, request } from "./api.js";
import { byId, el, formatNumber, formatTime, replaceChildren } from "./dom.js";
import { reloadInspections } from "./inspections.js";

const PAGE = 48;          // stored results listed per page
const POLL_MS = 1000;     // how often the progress is asked while a training runs
const TRAINABLE_TYPES = new Set(["anomaly", "job"]);

let shown = null;         // {name, info}: the inspection the panel shows, its GET .../model answer
let nextBefore = null;    // before_id of the next page of stored results (null: none)
let running = null;       // {controller, name} of the training in flight
let poller = null;
let loading = null;       // the name whose model is being asked for
let listToken = 0;
let lastName = null;      // the inspection the panel last showed        // the newest list load: an older one's answer is dropped

const path = (name, rest) => `/api/inspections/${encodeURIComponent(name)}/${rest}`;

function currentName() {
  const draft = !byId("insp-draft").hidden;
  const type = byId("insp-type").textContent;
  const name = byId("insp-name").textContent;
  return !name || draft || !TRAINABLE_TYPES.has(type) ? null : name;
}

/** Show the panel for the inspection on the page (hidden when it cannot be trained). */
async function refresh() {
  const name = currentName();
  if (name === null) {
    hide();
    return;
  }
  if (shown?.name === name || loading === name) return;
  loading = name;
  let info;
  try {
    info = await getJson(path(name, "model"));
  } catch {
    if (currentName() === name) hide();   // NOT_TRAINABLE (a job without an anomaly step), gone
    return;
  } finally {
    loading = null;
  }
  if (currentName() !== name) return;
  shown = { name, info };
  byId("train-panel").hidden = false;
  byId("train-title").textContent = `Train ${name}`;
  if (name !== lastName) {
    // Another inspection: the last one's report and messages go (they stay while the page
    // re-reads the same inspection after a training).
    lastName = name;
    byId("train-report").hidden = true;
    byId("train-error").textContent = "";
    if (!running) byId("train-status").textContent = "";
  }
  const steps = info.models.map((m) => m.step).filter((s) => s !== null);
  byId("train-step-field").hidden = steps.length < 2;
  replaceChildren(byId("train-step"), steps.map((s) => el("option", { value: s }, s)));
  const camera = byId("train-source-camera");
  camera.disabled = !info.camera_grabs;
  camera.parentElement.title = info.camera_grabs ? ""
    : `camera ${info.camera} gives no frames of its own to the console (its images come from robots, a trigger or a sequence): pick stored results`;
  if (!info.camera_grabs) byId("train-source-results").checked = true;
  sourceChanged();
  showModel();
  await loadList(name, false);
}

function hide() {
  shown = null;
  byId("train-panel").hidden = true;
}

/** The model in force of the step chosen (or of the inspection). */
function showModel() {
  if (!shown) return;
  const step = byId("train-step-field").hidden ? null : byId("train-step").value;
  const model = shown.info.models.find((m) => step === null || m.step === step) ?? shown.info.models[0];
  const trained = Boolean(model?.trained);
  byId("train-model-none").hidden = trained;
  byId("train-model-facts").hidden = !trained;
  byId("train-model").dataset.trained = trained ? "true" : "false";
  if (!trained) {
    byId("train-model-none").textContent = model?.file
      ? `Not trained: ${model.file} is missing. The inspection cannot judge a part until it is trained.`
      : "Not trained yet: the inspection cannot judge a part until it is.";
    return;
  }
  byId("train-model-file").textContent = model.file;
  byId("train-model-version").textContent = String(model.version);
  byId("train-model-method").textContent = model.method;
  byId("train-model-threshold").textContent = formatNumber(model.threshold) +
    (model.threshold_override !== null ? " (set in the configuration)" : "");
  byId("train-model-false-reject").textContent = percent(model.model_false_reject ?? model.false_reject);
  byId("train-model-trained-at").textContent = model.trained_at ?? "";
  byId("train-model-images").textContent = String(model.images);
}

function percent(rate) {
  return `${(Number(rate) * 100).toFixed(1)} %`;
}

// -- the stored results ---------------------------------------------------------------------

async function loadList(name, more) {
  const list = byId("train-list");
  const note = byId("train-list-note");
  const token = ++listToken;
  if (!more) {
    replaceChildren(list);
    nextBefore = null;
    note.textContent = "Loading the stored results…";
  }
  let answer;
  try {
    answer = await getJson(path(name, "train/images") +
      `?limit=${PAGE}${more && nextBefore ? `&before_id=${nextBefore}` : ""}`);
  } catch (exc) {
    if (shown?.name === name) note.textContent = exc.code === "NO_RESULT_LOG"
      ? "This server keeps no result log: grab frames from the camera instead."
      : `Stored results unavailable: ${exc.message}`;
    return;
  }
  if (shown?.name !== name || token !== listToken) return;
  nextBefore = answer.next_before_id;
  list.append(...answer.results.map(item));
  byId("train-older").hidden = nextBefore === null;
  const count = list.children.length;
  const passing = list.querySelectorAll('.train-item[data-verdict="pass"]').length;
  note.textContent = count === 0
    ? `No stored result of ${name} has an input image` +
      (answer.store_images && answer.store_images !== "all" ? ` (results: store_images: ${answer.store_images}; "all" keeps every part's image).` : ".")
    : passing === 0
      ? "No passing result yet (an untrained inspection ends every run in an error): check the images of good parts."
      : "Passing results are checked: uncheck any that is not a good part.";
  updateCount();
}

function item(row) {
  const verdict = row.error ? "error" : row.passed ? "pass" : "fail";
  const pick = el("input", {
    type: "checkbox", class: "train-pick", value: String(row.id),
    "aria-label": `use result ${row.id}`, onchange: updateCount,
  });
  pick.checked = verdict === "pass";
  return el("label", {
    class: "train-item",
    title: row.error ? `${row.error}` : `result ${row.id}`,
    dataset: { resultId: row.id, verdict, try: row.try ? "true" : "false" },
  },
  el("img", { src: api.resultImageUrl(row.id, false), alt: `Stored input of result ${row.id}`, loading: "lazy" }),
  el("span", { class: "train-item-caption" },
    pick,
    el("span", { class: "train-item-id" }, `#${row.id}`),
    el("span", { class: "train-item-verdict" }, verdict),
    row.try ? el("span", { class: "muted" }, "try") : null,
    typeof row.score === "number" ? el("span", { class: "muted" }, `score ${formatNumber(row.score, 3)}`) : null),
  el("span", { class: "muted" }, formatTime(row.time)));
}

function picks() {
  return [...byId("train-list").querySelectorAll(".train-pick")];
}

function select(which) {
  for (const box of picks()) {
    const verdict = box.closest(".train-item").dataset.verdict;
    box.checked = which === "all" || (which === "passing" && verdict === "pass");
  }
  updateCount();
}

function updateCount() {
  const chosen = picks().filter((b) => b.checked).length;
  byId("train-selected-count").textContent = `${chosen} selected`;
}

function sourceChanged() {
  const camera = byId("train-source-camera").checked;
  byId("train-results-block").hidden = camera;
  byId("train-camera-block").hidden = !camera;
}

// -- training -------------------------------------------------------------------------------

function body() {
  const out = {};
  if (byId("train-source-camera").checked) {
    out.source = "camera";
    out.frames = Number(byId("train-frames").value);
    out.interval_ms = Number(byId("train-interval").value);
    if (!Number.isInteger(out.frames) || out.frames < 1) throw new Error("Enter a whole number of frames (at least 8).");
    if (!Number.isInteger(out.interval_ms) || out.interval_ms < 0) throw new Error("Enter the wait between frames in whole milliseconds.");
  } else {
    out.source = "results";
    out.ids = picks().filter((b) => b.checked).map((b) => Number(b.value));
    if (out.ids.length === 0) throw new Error("Check the stored results of good parts to train on.");
  }
  if (!byId("train-step-field").hidden) out.step = byId("train-step").value;
  const method = byId("train-method").value;
  if (method) out.method = method;
  const rate = byId("train-false-reject").value.trim();
  if (rate !== "") out.false_reject = Number(rate);
  return out;
}

function setRunning(on) {
  byId("train-run").disabled = on;
  byId("train-cancel").hidden = !on;
  byId("train-spinner").hidden = !on;
  byId("train-panel").classList.toggle("busy", on);
  if (poller !== null) clearInterval(poller);
  poller = on ? setInterval(pollProgress, POLL_MS) : null;
}

async function pollProgress() {
  if (!running) return;
  try {
    const state = await getJson("/api/training");
    if (!running || !state.running || state.inspection !== running.name) return;
    const count = state.stage === "reading images" ? `${state.images} of ${state.wanted} images read` : `${state.images} images`;
    byId("train-status").textContent = `Training ${running.name}… ${state.stage}: ${count} (${Math.round(state.elapsed_s)} s)`;
  } catch {
    // The progress is a courtesy: the training's own answer says how it ended.
  }
}

async function train() {
  if (!shown || running) return;
  const name = shown.name;
  byId("train-error").textContent = "";
  let ask;
  try {
    ask = body();
  } catch (exc) {
    byId("train-error").textContent = exc.message;
    return;
  }
  const count = ask.source === "camera" ? ask.frames : ask.ids.length;
  const controller = new AbortController();
  running = { controller, name };
  setRunning(true);
  byId("train-report").hidden = true;
  byId("train-status").textContent = `Training ${name}… ${count} images`;
  try {
    const response = await request(path(name, "train"), {
      method: "POST",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify(ask),
      signal: controller.signal,
    });
    const report = await response.json();
    showReport(name, report);
    // The configuration changed (model:): the page reads it again, and the model in force
    // (the stored results listed and the ones checked stay).
    await reloadInspections();
    if (shown?.name === name) {
      shown.info = await getJson(path(name, "model"));
      showModel();
    }
    byId("train-status").textContent =
      `Trained ${name} on ${report.images} images and reloaded: model version ${report.version}, configuration ${String(report.config_hash).slice(0, 12)}.`;
  } catch (exc) {
    if (controller.signal.aborted) {
      byId("train-status").textContent = "Training cancelled: nothing was written.";
    } else if (!(exc instanceof ApiError && exc.status === 401)) {
      byId("train-status").textContent = "";
      byId("train-error").textContent = `${exc.code ?? "ERROR"}: ${exc.message}`;
    }
  } finally {
    running = null;
    setRunning(false);
  }
}

function showReport(name, report) {
  const panel = byId("train-report");
  panel.dataset.inspection = name;
  panel.dataset.version = String(report.version);
  panel.dataset.configHash = String(report.config_hash);
  byId("train-report-threshold").textContent = formatNumber(report.threshold);
  byId("train-report-false-reject").textContent = percent(report.false_reject);
  byId("train-report-held-out").textContent =
    `${percent(report.held_out_rejected)} of ${report.held_out_scores?.length ?? "?"} (scored by a model that had not seen them)`;
  byId("train-report-images").textContent = String(report.images);
  byId("train-report-method").textContent = report.method;
  byId("train-report-model").textContent = report.model;
  byId("train-report-version").textContent = String(report.version);
  byId("train-report-config").textContent =
    `${String(report.config_hash).slice(0, 12)} (version ${report.config_version} in the History)`;
  byId("train-report-seconds").textContent = `${Number(report.seconds).toFixed(1)} s`;
  const skipped = byId("train-skipped");
  replaceChildren(skipped, (report.skipped ?? []).map((s) => el("li", {}, `left out: ${s}`)));
  skipped.hidden = (report.skipped ?? []).length === 0;
  panel.hidden = false;
}

function wire() {
  byId("train-run").addEventListener("click", train);
  byId("train-cancel").addEventListener("click", () => running?.controller.abort());
  byId("train-select-passing").addEventListener("click", () => select("passing"));
  byId("train-select-all").addEventListener("click", () => select("all"));
  byId("train-select-none").addEventListener("click", () => select("none"));
  byId("train-older").addEventListener("click", () => shown && loadList(shown.name, true));
  byId("train-step").addEventListener("change", showModel);
  for (const radio of document.querySelectorAll("input[name=train-source]")) {
    radio.addEventListener("change", sourceChanged);
  }
  // Another inspection chosen (or a draft, or another type): the panel follows it. A training
  // in flight goes on (leaving the page does not stop it; Cancel does).
  const observer = new MutationObserver(() => { refresh(); });
  for (const id of ["insp-name", "insp-type"]) {
    observer.observe(byId(id), { childList: true, characterData: true, subtree: true });
  }
  observer.observe(byId("insp-draft"), { attributes: true, attributeFilter: ["hidden"] });
  refresh();
}

wire();
