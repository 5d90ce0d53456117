// Building the page from data. Every text that comes from the server or the user goes in through
// textContent or an attribute, never through innerHTML: a camera named "<img onerror=...>" must
// show as those characters, not run.

/**
 * Create an element: el("td", {class: "num", title: "x"}, "text", childNode, ...).
 * Attribute values are set with setAttribute (quoted by the DOM); children that are strings
 * become text nodes.
 */
export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (value === null || value === undefined || value === false) continue;
    if (key === "dataset") {
      for (const [k, v] of Object.entries(value)) node.dataset[k] = String(v);
    } else if (key.startsWith("on") && typeof value === "function") {
      node.addEventListener(key.slice(2), value);
    } else {
      node.setAttribute(key, value === true ? "" : String(value));
    }
  }
  append(node, children);
  return node;
}

const SVG_NS = "http://www.w3.org/2000/svg";

/** Create an SVG element with attributes (numbers are written as they are). */
export function svg(tag, attrs = {}, ...children) {
  const node = document.createElementNS(SVG_NS, tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (value === null || value === undefined) continue;
    node.setAttribute(key, String(value));
  }
  append(node, children);
  return node;
}

function append(node, children) {
  for (const child of children.flat()) {
    if (child === null || child === undefined || child === false) continue;
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
}

/** Replace all children of ``node``. */
export function replaceChildren(node, ...children) {
  node.replaceChildren();
  append(node, children);
}

export function byId(id) {
  const node = document.getElementById(id);
  if (node === null) throw new Error(`console: no element #${id}`);
  return node;
}

/** Fill a two-column table from [[label, value], ...]; values are formatted as text. */
export function fillKeyValues(table, rows) {
  const body = rows.map(([label, value]) =>
    el("tr", {}, el("th", { scope: "row" }, label), el("td", {}, formatValue(value))));
  replaceChildren(table, el("tbody", {}, body));
}

/** A value as a person reads it: numbers rounded, lists and mappings as compact JSON. */
export function formatValue(value) {
  if (value === null || value === undefined) return "—";
  if (typeof value === "number") return formatNumber(value);
  if (typeof value === "boolean") return value ? "yes" : "no";
  if (typeof value === "string") return value;
  return JSON.stringify(value, (_, v) => (typeof v === "number" ? roundForShow(v) : v));
}

function roundForShow(v) {
  return Number.isInteger(v) ? v : Number(v.toPrecision(4));
}

export function formatNumber(v, digits = 4) {
  if (!Number.isFinite(v)) return String(v);
  if (Number.isInteger(v)) return String(v);
  return String(Number(v.toPrecision(digits)));
}

/** Unix seconds as local date and time, "2024-05-01 13:04:05". */
export function formatTime(unixS) {
  if (typeof unixS !== "number") return "—";
  const d = new Date(unixS * 1000);
  const pad = (n) => String(n).padStart(2, "0");
  return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ` +
    `${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
}

/** A duration in seconds as "3 d 4 h", "5 h 2 min", "42 s". */
export function formatDuration(seconds) {
  if (typeof seconds !== "number" || !Number.isFinite(seconds)) return "—";
  const s = Math.floor(seconds);
  const d = Math.floor(s / 86400), h = Math.floor((s % 86400) / 3600), m = Math.floor((s % 3600) / 60);
  if (d > 0) return `${d} d ${h} h`;
  if (h > 0) return `${h} h ${m} min`;
  if (m > 0) return `${m} min ${s % 60} s`;
  return `${s} s`;
}

/** Call ``fn`` ``waitMs`` after the last of a burst of calls. */
export function debounce(fn, waitMs) {
  let timer = null;
  const debounced = (...args) => {
    clearTimeout(timer);
    timer = setTimeout(() => fn(...args), waitMs);
  };
  debounced.cancel = () => clearTimeout(timer);
  return debounced;
}

/** "1 result", "0 results", "2 results": a count with the noun in the number it takes. */
export function countText(n, one, many) {
  return `${n} ${n === 1 ? one : many}`;
}
