// One control per schema key (GET /api/schema): a number box (and a slider when the key has a
// range), an integer box, a select for an enum, a checkbox for a boolean, a text box for a
// string (checked as you type), a regex box (compiled as you type, see pyregex.js), an
// expression box (the verdict: the server checks it on the next try), two boxes for a point,
// a text box for a file, checkboxes for symbologies and a JSON box for an opaque mapping.
// Keys whose ``when`` does not hold for the mapping being edited are not shown (another
// method's keys). Every control is found by ``#<scope>-field-<key with . as ->`` or by
// ``[data-key=KEY]`` inside its scope's container; docs/console.md lists them.

import { el, formatNumber, replaceChildren } from "./dom.js";
import { applies, getPath, prune, setPath } from "./paths.js";
import { compilePython } from "./pyregex.js";

export const INSPECTION_NAME = /^[A-Za-z0-9_.-]{1,64}$/;
export const STEP_NAME = /^[A-Za-z_][A-Za-z0-9_]*$/;

/** The id of a key's control in a scope ("step", "circle.min_radius_px" -> step-field-circle-min_radius_px). */
export function fieldId(scope, key) {
  return `${scope}-field-${key.replaceAll(".", "-")}`;
}

function numberOk(key, value) {
  if (!Number.isFinite(value)) return "not a number";
  if (key.kind === "integer" && !Number.isInteger(value)) return "a whole number";
  if (typeof key.min === "number" && key.min_exclusive && value <= key.min) return `more than ${formatNumber(key.min)}`;
  if (typeof key.min === "number" && value < key.min) return `at least ${formatNumber(key.min)}`;
  if (typeof key.max === "number" && value > key.max) return `at most ${formatNumber(key.max)}`;
  return null;
}

function describe(key) {
  const bits = [];
  if (key.unit) bits.push(key.unit);
  if (key.default !== null && key.default !== undefined && key.default !== "") bits.push(`default ${typeof key.default === "object" ? JSON.stringify(key.default) : key.default}`);
  if (key.required) bits.push("required");
  return bits.join(" · ");
}

/**
 * Render the controls of ``keys`` for the mapping ``target`` (edited in place) into
 * ``container``. ``options``: ``scope`` (id prefix), ``skip`` (keys drawn elsewhere: roi, the
 * measurement list), ``special(key, target)`` (a control of the caller's, or null),
 * ``onChange(key)`` after a value changed, ``onStructure()`` when a change may show or hide
 * keys (an enum or boolean: re-render), ``reads()`` the last reads for a regex.
 */
export function renderFields(container, keys, target, options) {
  const { scope, skip = new Set(), special = () => null } = options;
  options.keys = keys;
  const rows = [];
  for (const key of keys) {
    if (skip.has(key.key) || !applies(key, target, keys)) continue;
    const custom = special(key, target);
    const control = custom ?? makeControl(key, target, options);
    if (control === null) continue;
    const error = el("span", { class: "field-error", role: "status", "data-error-for": key.key });
    rows.push(el("div", { class: "field-row", dataset: { field: key.key, kind: key.kind } },
      el("label", { class: "field-label", for: fieldId(scope, key.key), title: key.doc ?? "" },
        el("span", { class: "field-key" }, key.key),
        el("span", { class: "muted field-meta" }, describe(key))),
      control,
      key.doc ? el("span", { class: "field-doc muted" }, key.doc) : null,
      error));
  }
  replaceChildren(container, rows.length ? rows : el("p", { class: "muted" }, "No keys to set."));
}

function setError(control, text) {
  const row = control.closest(".field-row");
  const slot = row?.querySelector(".field-error");
  if (slot) slot.textContent = text ?? "";
  row?.classList.toggle("invalid", Boolean(text));
}

function makeControl(key, target, options) {
  const { scope, onChange, onStructure } = options;
  const id = fieldId(scope, key.key);
  const current = getPath(target, key.key);
  const apply = (value, structural = false) => {
    setPath(target, key.key, value);
    // Another method or kind: its keys' values go with it.
    if (structural) prune(options.keys ?? [], target);
    if (structural) onStructure?.(key.key);
    else onChange?.(key.key);
  };
  switch (key.kind) {
    case "number":
    case "integer": {
      const attrs = {
        type: "number", id, class: "param-number", "data-key": key.key, "data-param": key.key,
        min: key.min, max: key.max, step: key.step ?? (key.kind === "integer" ? 1 : "any"),
        value: typeof current === "number" ? current : null,
        placeholder: key.default ?? "", "aria-label": key.key,
      };
      const box = el("input", attrs);
      const ranged = typeof key.min === "number" && typeof key.max === "number";
      const slider = ranged ? el("input", {
        type: "range", class: "param-range", id: `${id}-slider`, "data-key": key.key,
        min: key.min, max: key.max, step: key.step ?? "any", "aria-label": `${key.key} slider`,
        value: typeof current === "number" ? current : (key.default ?? key.min),
      }) : null;
      const changed = (source) => {
        if (source.value === "") {
          setError(box, key.required ? "required" : null);
          apply(undefined);
          return;
        }
        const value = Number(source.value);
        const problem = numberOk(key, value);
        setError(box, problem);
        if (problem) return;
        if (slider && source !== slider) slider.value = String(value);
        if (source !== box) box.value = String(value);
        apply(value);
      };
      box.addEventListener("input", () => changed(box));
      slider?.addEventListener("input", () => changed(slider));
      return el("div", { class: "param-inputs" }, slider, box);
    }
    case "boolean": {
      const box = el("input", { type: "checkbox", id, "data-key": key.key, checked: current === true || (current === undefined && key.default === true) });
      box.addEventListener("change", () => apply(box.checked === Boolean(key.default) && !key.required ? undefined : box.checked, true));
      return el("div", { class: "param-inputs" }, box);
    }
    case "enum": {
      const values = key.values ?? [];
      const select = el("select", { id, "data-key": key.key },
        el("option", { value: "" }, key.required ? "— choose —" : `— default${key.default !== null && key.default !== undefined ? ` (${key.default})` : ""} —`),
        values.map((v) => el("option", { value: String(v), selected: String(current) === String(v) }, String(v))));
      select.addEventListener("change", () => {
        const chosen = values.find((v) => String(v) === select.value);
        setError(select, select.value === "" && key.required ? "required" : null);
        apply(select.value === "" ? undefined : chosen, true);
      });
      return select;
    }
    case "symbologies": {
      const chosen = new Set(Array.isArray(current) ? current : []);
      const boxes = (key.values ?? []).map((v) => {
        const box = el("input", { type: "checkbox", value: v, "data-key": key.key, "data-value": v, checked: chosen.has(v) });
        box.addEventListener("change", () => {
          const all = boxes.filter((b) => b.checked).map((b) => b.value);
          apply(all.length ? all : undefined);
        });
        return box;
      });
      return el("div", { class: "checks", id }, boxes.map((box) => el("label", { class: "check" }, box, box.value)));
    }
    case "point": {
      const pair = Array.isArray(current) ? current : [null, null];
      const boxes = ["u", "v"].map((axis, i) => el("input", {
        type: "number", step: "any", id: `${id}-${axis}`, "data-key": key.key, "data-axis": axis,
        value: typeof pair[i] === "number" ? pair[i] : null, "aria-label": `${key.key} ${axis}`,
      }));
      const changed = () => {
        const values = boxes.map((b) => (b.value === "" ? NaN : Number(b.value)));
        if (values.every((n) => Number.isFinite(n))) {
          setError(boxes[0], null);
          apply(values);
        } else if (boxes.every((b) => b.value === "")) {
          apply(undefined);
        } else {
          setError(boxes[0], "two numbers: u v");
        }
      };
      boxes.forEach((b) => b.addEventListener("input", changed));
      return el("div", { class: "param-inputs", id }, "u", boxes[0], "v", boxes[1]);
    }
    case "mapping": {
      const box = el("textarea", { id, "data-key": key.key, rows: 2, class: "mono", spellcheck: "false",
        placeholder: "{} (JSON)" });
      box.value = current === undefined ? "" : JSON.stringify(current);
      box.addEventListener("input", () => {
        if (box.value.trim() === "") { setError(box, null); apply(undefined); return; }
        try {
          const value = JSON.parse(box.value);
          if (value === null || typeof value !== "object" || Array.isArray(value)) throw new Error("a mapping: {…}");
          setError(box, null);
          apply(value);
        } catch (exc) {
          setError(box, `not a JSON mapping: ${exc.message}`);
        }
      });
      return box;
    }
    case "list":
    case "roi":
      return null;   // drawn by the caller (the measurement list, the ROI fields)
    case "regex":
      return regexControl(key, id, current, apply, options);
    default: {
      // string, expression, file and anything newer: a text box checked as you type.
      const box = el("input", {
        type: "text", id, "data-key": key.key,
        // A mapping here (``expect: {regex: ...}``) is edited by its own key's control.
        value: typeof current === "string" || typeof current === "number" ? String(current) : null,
        class: key.kind === "expression" ? "mono wide" : "wide", spellcheck: "false",
        placeholder: key.default ?? "", "aria-label": key.key,
      });
      box.addEventListener("input", () => {
        const text = box.value;
        const problem = text === "" ? (key.required ? "required" : null) : (options.validate?.(key, text) ?? null);
        setError(box, problem);
        if (problem && text !== "") return;
        apply(text === "" ? undefined : text);
      });
      return box;
    }
  }
}

/** A regex box: compiled as you type (Python syntax, pyregex.js) and tested against the
 * inspection's last reads (``options.reads()``: [{text, step, result_id}]), each marked as
 * matching or not. */
function regexControl(key, id, current, apply, options) {
  const box = el("input", { type: "text", id, "data-key": key.key, class: "mono wide", spellcheck: "false",
    value: typeof current === "string" ? current : null, "aria-label": key.key });
  const list = el("ul", { class: "reads", id: `${id}-reads`, "data-test": "regex-reads" });
  const check = () => {
    const text = box.value;
    const row = box.closest(".field-row") ?? box.parentElement;
    if (text === "") {
      setError(box, key.required ? "required" : null);
      replaceChildren(list);
      return { ok: true, value: undefined };
    }
    const compiled = compilePython(text);
    setError(box, compiled.ok ? (compiled.note ? `note: ${compiled.note}` : null) : `does not compile: ${compiled.error}`);
    row?.classList.toggle("invalid", !compiled.ok);
    showReads(list, compiled.regexp, options.reads?.() ?? null);
    return { ok: compiled.ok, value: text };
  };
  box.addEventListener("input", () => {
    const { ok, value } = check();
    if (ok) apply(value);
  });
  // The reads arrive after the control is drawn: the caller calls refresh() when they do.
  box.refreshReads = () => check();
  queueMicrotask(() => { if (box.isConnected) check(); });
  return el("div", { class: "regex-field" }, box, list);
}

function showReads(list, regexp, reads) {
  if (reads === null) {
    replaceChildren(list, el("li", { class: "muted" }, "No reads loaded."));
    return;
  }
  if (reads.length === 0) {
    replaceChildren(list, el("li", { class: "muted" }, "No reads stored yet for this inspection."));
    return;
  }
  let matched = 0;
  const items = reads.map((read) => {
    const hit = regexp ? regexp.test(read.text) : null;
    if (hit) matched += 1;
    return el("li", { class: "read", dataset: { match: hit === null ? "unknown" : hit ? "yes" : "no", result: read.result_id ?? "" } },
      el("span", { class: "read-mark" }, hit === null ? "?" : hit ? "✓" : "✗"),
      el("code", {}, read.text),
      read.step ? el("span", { class: "muted" }, ` ${read.step}`) : null);
  });
  const head = el("li", { class: "reads-head", "data-test": "regex-summary" },
    regexp ? `${matched} of ${reads.length} last reads match` : "the server checks this pattern on the next try");
  replaceChildren(list, head, items);
}

/** Mark the control of ``key`` in ``container`` as wrong with ``text`` (a try's refusal). */
export function showFieldError(container, key, text) {
  const slot = container.querySelector(`.field-error[data-error-for="${CSS.escape(key)}"]`);
  if (!slot) return false;
  slot.textContent = text;
  slot.closest(".field-row")?.classList.add("invalid");
  return true;
}
