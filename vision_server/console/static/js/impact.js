// Impact before save (docs/console.md, "Impact before save"): the Inspections page's pending
// change (pendingChange() of js/inspections.js: {name, options} or {name, config}) replayed by
// the server over the inspection's newest stored images, POST /api/inspections/{name}/impact,
// the same engine as `vision-server replay`. Shows the counts and the flipped results in two
// groups (pass → fail, fail → pass); a thumbnail opens the stored result beside the new overlay.
// Cancel (or leaving the page) aborts the request, which stops the run on the server.

import { api, ApiError, request } from "./api.js";
import { byId, countText, el, fillKeyValues, formatTime, replaceChildren } from "./dom.js";
import { pendingChange } from "./inspections.js";

const MAX_LAST = 1000;

let running = null;      // {controller, name} of the preview in flight
let shown = null;        // {name, report} of the preview shown

/** The request body for ``change`` (either shape of pendingChange()) and ``last``. */
export function impactBody(change, last) {
  if (change.config !== undefined && change.config !== null) return { config: change.config, last };
  return { options: change.options ?? {}, last };
}

function lastWanted() {
  const input = byId("impact-last");
  const value = Number(input.value);
  if (!Number.isInteger(value) || value < 1 || value > MAX_LAST) {
    throw new Error(`Enter a whole number of stored images from 1 to ${MAX_LAST}.`);
  }
  return value;
}

function setRunning(on) {
  byId("impact-run").disabled = on;
  byId("impact-cancel").hidden = !on;
  byId("impact-panel").classList.toggle("busy", on);
}

async function preview() {
  byId("impact-error").textContent = "";
  const change = pendingChange();
  if (!change) {
    byId("impact-error").textContent = "Choose an inspection first.";
    return;
  }
  let last;
  try {
    last = lastWanted();
  } catch (exc) {
    byId("impact-error").textContent = exc.message;
    return;
  }
  const empty = !change.config && Object.keys(change.options ?? {}).length === 0;
  const controller = new AbortController();
  running = { controller, name: change.name };
  setRunning(true);
  byId("impact-status").textContent = empty
    ? `No pending change: re-running ${change.name} as configured on its newest ${last} stored images…`
    : `Replaying the pending change of ${change.name} on its newest ${last} stored images…`;
  try {
    const response = await request(`/api/inspections/${encodeURIComponent(change.name)}/impact`, {
      method: "POST",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify(impactBody(change, last)),
      signal: controller.signal,
    });
    const report = await response.json();
    if (running?.controller !== controller) return;   // another preview or a page change since
    show(change.name, report, empty);
  } catch (exc) {
    if (running?.controller !== controller) return;
    if (controller.signal.aborted) {
      byId("impact-status").textContent = "Preview cancelled.";
    } else if (!(exc instanceof ApiError && exc.status === 401)) {
      byId("impact-status").textContent = "";
      byId("impact-error").textContent = exc.code === "UNKNOWN_INSPECTION"
        ? `${change.name} is not in the running configuration yet: it has no stored results to replay.`
        : `${exc.code ?? "ERROR"}: ${exc.message}`;
    }
  } finally {
    if (running?.controller === controller) {
      running = null;
      setRunning(false);
    }
  }
}

function cancel() {
  if (running) running.controller.abort();
}

/** Forget the shown preview (another inspection was chosen: its flips are not this one's). */
function clear() {
  cancel();
  shown = null;
  byId("impact-result").hidden = true;
  byId("impact-viewer").hidden = true;
  byId("impact-status").textContent = "";
  byId("impact-error").textContent = "";
}

function count(label, value, key, title = "") {
  return el("div", { class: "impact-count", dataset: { count: key }, title: title || null },
    el("span", { class: "impact-count-value" }, String(value)),
    el("span", { class: "impact-count-label" }, label));
}

function show(name, report, empty) {
  shown = { name, report };
  const flips = report.flipped ?? [];
  const toFail = flips.filter((f) => f.stored === "pass" && f.new === "fail");
  const toPass = flips.filter((f) => f.stored === "fail" && f.new === "pass");
  replaceChildren(byId("impact-counts"),
    count("results looked at", report.considered, "considered", "production results of this inspection, newest first (tries left out)"),
    count("with a stored image", report.with_image, "with_image", "replayed with the pending change"),
    count("pass → fail", toFail.length, "pass_to_fail"),
    count("fail → pass", toPass.length, "fail_to_pass"),
    count("unchanged", report.unchanged, "unchanged"),
    count("could not run", report.failed, "failed"));
  byId("impact-pass-to-fail-count").textContent = String(toFail.length);
  byId("impact-fail-to-pass-count").textContent = String(toPass.length);
  replaceChildren(byId("impact-pass-to-fail-list"), toFail.length ? toFail.map(flipItem) : el("p", { class: "muted" }, "None."));
  replaceChildren(byId("impact-fail-to-pass-list"), toPass.length ? toPass.map(flipItem) : el("p", { class: "muted" }, "None."));
  const errors = report.errors ?? [];
  const list = byId("impact-errors");
  replaceChildren(list, ...errors.map((e) =>
    el("li", { dataset: { resultId: e.result_id } }, `#${e.result_id}: ${e.code}: ${e.message}`)));
  list.hidden = errors.length === 0;
  const notes = notesFor(report, empty);
  byId("impact-note").textContent = notes.join(" ");
  byId("impact-note").hidden = notes.length === 0;
  byId("impact-result").hidden = false;
  byId("impact-viewer").hidden = true;
  byId("impact-status").textContent =
    `${name}: ${countText(flips.length, "verdict flips", "verdicts flip")} of ${report.with_image} replayed ` +
    `(${Number(report.elapsed_s ?? 0).toFixed(1)} s).`;
}

function notesFor(report, empty) {
  const notes = [];
  if (empty) notes.push("There is no pending change: every flip is a stored verdict the inspection as configured no longer reproduces.");
  if (report.with_image === 0) {
    notes.push("None of the results looked at has a stored image, so nothing was replayed.");
  } else if (report.with_image < report.considered && report.with_image < report.last) {
    notes.push(`Only ${report.with_image} of the ${report.considered} results looked at have a stored image.`);
  }
  if (report.with_image < report.last && report.store_images && report.store_images !== "all") {
    notes.push(report.store_images === "none"
      ? "This result log keeps no images (results: store_images: none)."
      : "This result log keeps the images of failed parts only (results: store_images: failures, the default): passing parts cannot be replayed, so pass → fail flips are not seen; store_images: all keeps every image.");
  }
  if (report.rows_limited) notes.push("The bound on the results looked at was reached: older images were not replayed.");
  if (report.complete === false) notes.push(`Stopped by the ${report.stopped_by ?? "deadline"}: older images were not replayed.`);
  const older = (report.flipped ?? []).filter((f) => !f.current_config).length;
  if (older > 0) notes.push(`${countText(older, "flip is", "flips are")} on results stored under another configuration (marked "older config"): the flip may come from that change, not from this one.`);
  return notes;
}

function flipItem(flip) {
  const thumb = flip.overlay
    ? el("img", { src: flip.overlay, alt: `Result ${flip.result_id} with the change`, class: "impact-thumb" })
    : el("span", { class: "impact-thumb impact-thumb-none" }, `#${flip.result_id}`);
  return el("button", {
    type: "button",
    class: "impact-flip",
    title: `Open result ${flip.result_id}`,
    dataset: {
      resultId: flip.result_id, stored: flip.stored, new: flip.new,
      currentConfig: flip.current_config ? "true" : "false",
    },
    onclick: () => openResult(flip),
  },
  thumb,
  el("span", { class: "impact-flip-caption" },
    el("span", { class: "impact-flip-id" }, `#${flip.result_id}`),
    el("span", { class: "muted" }, formatTime(flip.time)),
    flip.current_config ? null : el("span", {
      class: "impact-older", title: `stored under configuration ${String(flip.stored_config_hash).slice(0, 12)}, not the running one`,
    }, "older config")));
}

async function openResult(flip) {
  const viewer = byId("impact-viewer");
  viewer.hidden = false;
  viewer.dataset.resultId = String(flip.result_id);
  byId("impact-viewer-title").textContent =
    `Result #${flip.result_id}: stored ${flip.stored.toUpperCase()}, with the change ${flip.new.toUpperCase()}`;
  const newImage = byId("impact-viewer-new");
  if (flip.overlay) newImage.src = flip.overlay;
  else newImage.removeAttribute("src");
  newImage.hidden = !flip.overlay;
  byId("impact-viewer-new-caption").textContent = flip.overlay
    ? `with the change: ${flip.new} (around the ROI)` : "with the change: no thumbnail (past the first 24 flips)";
  byId("impact-viewer-image").href = api.resultImageUrl(flip.result_id, false);
  const stored = byId("impact-viewer-stored");
  let row;
  try {
    row = await api.result(flip.result_id);
  } catch (exc) {
    if (exc instanceof ApiError && exc.status === 401) return;
    row = { error: exc.message };
  }
  if (viewer.dataset.resultId !== String(flip.result_id)) return;
  const overlay = row.has_overlay !== false;
  stored.src = api.resultImageUrl(flip.result_id, overlay);
  byId("impact-viewer-stored-caption").textContent = `stored: ${flip.stored}${overlay ? "" : " (its input: no overlay was stored)"}`;
  fillKeyValues(byId("impact-viewer-values"), [
    ["time", formatTime(row.time ?? flip.time)],
    ["configuration", String(flip.stored_config_hash).slice(0, 12) + (flip.current_config ? " (running)" : " (older)")],
    ["peer", row.peer],
    ...Object.entries(row.data ?? {}),
    ...(row.error ? [["error", row.error]] : []),
  ]);
  viewer.scrollIntoView({ block: "nearest" });
}

function wire() {
  byId("impact-run").addEventListener("click", preview);
  byId("impact-cancel").addEventListener("click", cancel);
  byId("impact-viewer-close").addEventListener("click", () => { byId("impact-viewer").hidden = true; });
  // Another inspection chosen: the shown flips are not its flips.
  new MutationObserver(() => {
    const name = byId("insp-name").textContent;
    if ((shown && shown.name !== name) || (running && running.name !== name)) clear();
  }).observe(byId("insp-name"), { childList: true, characterData: true, subtree: true });
  // Leaving the Inspections page stops a preview in flight (the server stops with it).
  window.addEventListener("hashchange", () => {
    if (!location.hash.startsWith("#/inspections")) cancel();
  });
}

wire();
