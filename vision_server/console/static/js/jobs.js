// A job's steps in the editor: the list (choose, move up or down, remove, add one of the
// schema's step types) and fixturing a step to a locate by choosing the locate. Fixturing
// computes the offsets: the step's ROI (or a caliper step's bands and circles), as drawn in the
// image, is converted into the chosen fixture's part frame with the frame the last try made
// (data.steps.NAME: u, v, angle; frames.js). Nothing is typed and nothing is guessed: without
// that frame the page says to run a try first.

import { byId, el, replaceChildren } from "./dom.js";
import {
  angleToImage, angleToPart, pointToImage, pointToPart, roiToImage, roiToPart, round2,
} from "./frames.js";
import { isMapping } from "./paths.js";

const MAX_STEPS = 32;            // docs/configuration.md: a job has 1..32 steps
const FIXTURE_KEYS = ["fixture", "origin", "x_towards", "angle_from"];
const DEFAULT_FIXTURED_ROI = [-20, -20, 40, 40];

/** A step name not yet used in ``config``: ``base``, ``base_2``, ... */
export function uniqueName(config, base) {
  const used = new Set((config.steps ?? []).map((s) => s?.name));
  const clean = base.replace(/[^A-Za-z0-9_]/g, "_").replace(/^(\d)/, "_$1") || "step";
  if (!used.has(clean)) return clean;
  for (let i = 2; ; i++) if (!used.has(`${clean}_${i}`)) return `${clean}_${i}`;
}

/** Point every reference to step ``from`` (fixture, origin, x_towards, angle_from) at ``to``. */
export function renameReferences(config, from, to) {
  for (const step of config.steps ?? []) {
    for (const key of FIXTURE_KEYS) if (step?.[key] === from) step[key] = to;
  }
}

/**
 * Move ``step``'s geometry from frame ``from`` to frame ``to`` (null: image pixels). ``from``
 * and ``to`` are frames {u, v, angle}. The ROI keeps its size and centre; a band its centre,
 * length and direction in the image; a circle its centre.
 */
export function reframe(step, from, to) {
  if (Array.isArray(step.roi) && step.roi.length === 4) {
    const image = from ? roiToImage(from, step.roi) : step.roi;
    step.roi = to ? roiToPart(to, image) : clampImageRoi(image);
  } else if (to && step.type !== "caliper" && step.type !== "fixture") {
    // A fixtured step needs an ROI: start at the frame's origin, to be dragged where it belongs.
    step.roi = [...DEFAULT_FIXTURED_ROI];
  }
  for (const m of Array.isArray(step.measurements) ? step.measurements : []) {
    if (!isMapping(m)) continue;
    if (isMapping(m.band) && Array.isArray(m.band.center)) {
      const centre = from ? pointToImage(from, m.band.center) : m.band.center;
      const angle = from ? angleToImage(from, m.band.angle_rad ?? 0) : (m.band.angle_rad ?? 0);
      m.band.center = to ? pointToPart(to, centre) : centre.map(round2);
      m.band.angle_rad = to ? angleToPart(to, angle) : Math.round(angle * 10000) / 10000;
    }
    if (Array.isArray(m.center)) {
      const centre = from ? pointToImage(from, m.center) : m.center;
      m.center = to ? pointToPart(to, centre) : centre.map(round2);
    }
  }
}

function clampImageRoi([x, y, w, h]) {
  const rx = Math.max(0, Math.round(x)), ry = Math.max(0, Math.round(y));
  return [rx, ry, Math.round(w), Math.round(h)];
}

/**
 * The steps panel of a job. ``host`` is the inspections page: ``config`` (the edited mapping),
 * ``stepIndex``, ``selectStep(i)``, ``edited({structure})``, ``frameOf(fixtureName)`` (the
 * last try's frame or null), ``stepOutcome(name)`` (the last try's values), ``runSoon()``,
 * ``stepTypes()`` (the schema's step types).
 */
export class JobPanel {
  constructor(host) {
    this.host = host;
    // A fixture chosen while its frame was not made yet: converted when a try makes it.
    this.pending = null;
    byId("step-add").addEventListener("click", () => this.add());
    byId("fixture-add").addEventListener("click", () => this.openChooser());
    byId("fixture-cancel").addEventListener("click", () => { byId("fixture-chooser").hidden = true; });
    byId("fixture-apply").addEventListener("click", () => this.applyChooser());
    byId("fixture-remove").addEventListener("click", () => this.setFixture(this.host.stepIndex, null));
  }

  steps() {
    return Array.isArray(this.host.config.steps) ? this.host.config.steps : [];
  }

  render() {
    const host = this.host;
    const steps = this.steps();
    const chosen = byId("step-add-type").value;
    replaceChildren(byId("step-add-type"), host.stepTypes().map((t) => el("option", { value: t, selected: t === chosen }, t)));
    const items = steps.map((step, i) => {
      const outcome = host.stepOutcome(step?.name);
      const verdict = outcome ? (outcome.passed ? "pass" : "fail") : "none";
      const button = (cls, label, title, fn, disabled = false) => el("button", {
        type: "button", class: `btn btn-small ${cls}`, title, "aria-label": `${title} ${step?.name}`,
        "data-test": cls, disabled, onclick: fn,
      }, label);
      return el("li", { class: `step-item${i === host.stepIndex ? " active" : ""}`, dataset: { step: step?.name ?? "", index: i } },
        el("button", { type: "button", class: "step-select", "data-test": "step-select", onclick: () => host.selectStep(i) },
          el("span", { class: "step-name" }, step?.name ?? "(no name)"),
          el("span", { class: "list-sub" }, `${step?.type ?? "?"}${step?.fixture ? ` · in ${step.fixture}` : ""}`),
          el("span", { class: "verdict-chip", dataset: { verdict } }, verdict === "none" ? "—" : verdict)),
        el("span", { class: "step-buttons" },
          button("step-up", "↑", "Move up", () => this.move(i, -1), i === 0),
          button("step-down", "↓", "Move down", () => this.move(i, 1), i === steps.length - 1),
          button("step-remove", "✕", "Remove", () => this.remove(i))));
    });
    replaceChildren(byId("job-steps"), items.length ? items : el("li", { class: "muted" }, "No steps yet: add one below."));
    byId("step-add").disabled = steps.length >= MAX_STEPS;
    this.renderFixture();
  }

  add() {
    const host = this.host;
    const type = byId("step-add-type").value;
    if (!type) return;
    if (!Array.isArray(host.config.steps)) host.config.steps = [];
    if (host.config.steps.length >= MAX_STEPS) return;
    host.config.steps.push({ name: uniqueName(host.config, type), type });
    host.selectStep(host.config.steps.length - 1, { edited: true });
  }

  move(i, by) {
    const steps = this.steps();
    const j = i + by;
    if (j < 0 || j >= steps.length) return;
    [steps[i], steps[j]] = [steps[j], steps[i]];
    this.host.stepIndex = this.host.stepIndex === i ? j : this.host.stepIndex === j ? i : this.host.stepIndex;
    this.host.edited({ structure: true });
  }

  remove(i) {
    const steps = this.steps();
    steps.splice(i, 1);
    const sel = this.host.stepIndex;
    this.host.stepIndex = steps.length === 0 ? null : sel === null ? null : Math.min(sel > i ? sel - 1 : sel, steps.length - 1);
    this.host.edited({ structure: true });
  }

  // -- fixture ---------------------------------------------------------------------------------

  renderFixture() {
    const host = this.host;
    const step = this.steps()[host.stepIndex ?? -1];
    const block = byId("fixture-block");
    block.hidden = !step || step.type === "fixture";
    if (block.hidden) return;
    const current = byId("fixture-current");
    if (step.fixture) {
      const fixture = this.steps().find((s) => s?.name === step.fixture);
      const axis = fixture?.x_towards ? `, x towards ${fixture.x_towards}` : fixture?.angle_from ? `, angle from ${fixture.angle_from}` : "";
      current.textContent = `In the part frame of ${step.fixture} (origin ${fixture?.origin ?? "?"}${axis}): ` +
        "draw in the image, the page converts.";
    } else {
      current.textContent = "In image pixels (not fixtured).";
    }
    byId("fixture-add").textContent = step.fixture ? "Change fixture" : "Add fixture";
    byId("fixture-remove").hidden = !step.fixture;
    if (this.pending && this.pending.step !== step.name) byId("fixture-status").textContent = "";
  }

  /** The earlier steps of the selected step that a fixture may use. */
  earlier(predicate) {
    const i = this.host.stepIndex ?? 0;
    return this.steps().slice(0, i).filter((s) => s && predicate(s)).map((s) => s.name);
  }

  openChooser() {
    const locates = this.earlier((s) => s.type === "locate");
    const angled = this.earlier((s) => s.type === "locate" && (s.method === "template" || s.method === "blob"));
    const status = byId("fixture-status");
    if (locates.length === 0) {
      status.textContent = "No locate step runs before this one: add a locate step above it first.";
      return;
    }
    const options = (names, none) => [el("option", { value: "" }, none), ...names.map((n) => el("option", { value: n }, n))];
    replaceChildren(byId("fixture-origin"), locates.map((n) => el("option", { value: n }, n)));
    replaceChildren(byId("fixture-x-towards"), options(locates, "— none —"));
    replaceChildren(byId("fixture-angle-from"), options(angled, "— none —"));
    byId("fixture-chooser").hidden = false;
    status.textContent = "";
  }

  applyChooser() {
    const host = this.host;
    const index = host.stepIndex;
    const step = this.steps()[index];
    const origin = byId("fixture-origin").value;
    const xTowards = byId("fixture-x-towards").value || undefined;
    const angleFrom = byId("fixture-angle-from").value || undefined;
    const status = byId("fixture-status");
    if (!step || !origin) return;
    if (xTowards && angleFrom) {
      status.textContent = "Choose x towards or angle from, not both.";
      return;
    }
    if (xTowards === origin) {
      status.textContent = "x towards must be another locate than the origin.";
      return;
    }
    // The same frame made earlier is reused; otherwise a fixture step goes just before the step.
    const steps = this.steps();
    let fixture = steps.slice(0, index).find((s) => s?.type === "fixture" && s.origin === origin &&
      (s.x_towards ?? undefined) === xTowards && (s.angle_from ?? undefined) === angleFrom);
    let at = index;
    if (!fixture) {
      const base = xTowards ? `${origin}_to_${xTowards}` : angleFrom ? `${origin}_turned` : `${origin}_frame`;
      fixture = { name: uniqueName(host.config, base), type: "fixture", origin };
      if (xTowards) fixture.x_towards = xTowards;
      if (angleFrom) fixture.angle_from = angleFrom;
      steps.splice(index, 0, fixture);
      at = index + 1;
      host.stepIndex = at;
    }
    byId("fixture-chooser").hidden = true;
    this.setFixture(at, fixture.name);
  }

  /**
   * Put step ``index`` in fixture ``name`` (null: back to image pixels), converting its
   * geometry through the image with the frames of the last try.
   */
  setFixture(index, name) {
    const host = this.host;
    const step = this.steps()[index];
    const status = byId("fixture-status");
    if (!step) return false;
    const from = step.fixture ? host.frameOf(step.fixture) : null;
    const to = name ? host.frameOf(name) : null;
    if ((step.fixture && !from) || (name && !to)) {
      const missing = step.fixture && !from ? step.fixture : name;
      // The frame is made by the next try; convert then (never guess an offset).
      this.pending = { step: step.name, fixture: name };
      status.textContent = `No try has made frame ${missing} yet: run a try first (running one now); ` +
        "the step is converted into it as soon as the frame is made.";
      host.edited({ structure: true });
      host.runSoon();
      return false;
    }
    reframe(step, from, to);
    if (name) step.fixture = name;
    else delete step.fixture;
    this.pending = null;
    status.textContent = name
      ? `${step.name} is now in frame ${name}: its offsets were computed from the last try's frame.`
      : `${step.name} is back in image pixels.`;
    host.edited({ structure: true });
    return true;
  }

  /** After a try: finish a fixture chosen before its frame was made. */
  afterTry() {
    if (!this.pending) return false;
    const index = this.steps().findIndex((s) => s?.name === this.pending.step);
    if (index < 0) {
      this.pending = null;
      return false;
    }
    const { fixture } = this.pending;
    const step = this.steps()[index];
    const from = step.fixture ? this.host.frameOf(step.fixture) : null;
    const to = fixture ? this.host.frameOf(fixture) : null;
    if ((step.fixture && !from) || (fixture && !to)) {
      byId("fixture-status").textContent = `The last try did not make frame ${fixture ?? step.fixture} ` +
        "(its locate found nothing?): fix the locate and run a try.";
      return false;
    }
    return this.setFixture(index, fixture);
  }
}
