// The online view (docs/console.md, "Online view"): over each camera's live image, the graphics
// of the last production result of every inspection on that camera (ROIs, found features,
// fixture frames, caliper bands, code corners) and its verdict, drawn on a canvas in screen
// pixels so that text stays legible at any image size; below it, each inspection's running
// counts (pass, fail, yield) and its last verdicts as a strip. The data comes from
// GET /api/online, polled with If-None-Match: an unchanged board is a 304 without a body.

import { ApiError, request } from "./api.js";
import { el, replaceChildren } from "./dom.js";
import { Poller } from "./poll.js";

/** How often the board is asked for (ms): the live view's rhythm for a request camera. */
export const ONLINE_POLL_MS = 1000;

const STYLE = {
  roi: { colour: "#ffb000", width: 2 },
  search: { colour: "#ffe14d", width: 1.5, dash: [6, 4] },
  feature: { colour: "#00e5ff", width: 2.5 },
  pass: { colour: "#2fd66b", width: 2.5 },
  fail: { colour: "#ff4438", width: 3 },
  frame: { colour: "#ff4dff", width: 2.5 },
  rejected: { colour: "#ff9d2e", width: 1 },
  label: { colour: "#ffffff", width: 1 },
};
const AXIS_COLOURS = { x: "#ff4438", y: "#2fd66b", z: "#4d9dff" };
const VERDICT_COLOUR = { pass: "#2fd66b", fail: "#ff4438" };

// -- the board, polled once for every card ------------------------------------------------------

class OnlineFeed {
  constructor() {
    this.etag = null;
    this.board = null;
    this.listeners = new Set();
    this.poller = new Poller(() => this.fetch(), ONLINE_POLL_MS);
    this.users = 0;
  }

  /** ``fn(board)`` on every change; returns the function that stops the listening. */
  listen(fn) {
    this.listeners.add(fn);
    if (this.board !== null) fn(this.board);
    return () => this.listeners.delete(fn);
  }

  start() {
    this.users += 1;
    this.poller.start();
  }

  stop() {
    this.users = Math.max(0, this.users - 1);
    if (this.users === 0) this.poller.stop();
  }

  /** Ask again now (after a reset). */
  refresh() {
    this.etag = null;
    this.poller.kick();
  }

  async fetch() {
    const headers = this.etag ? { "If-None-Match": this.etag } : {};
    let response;
    try {
      response = await request("/api/online", { headers });
    } catch (exc) {
      // 304 is not "ok" to fetch: it means the board is unchanged.
      if (exc instanceof ApiError && exc.status === 304) return;
      throw exc;
    }
    if (response.status === 304) return;
    const board = await response.json();
    this.etag = response.headers.get("ETag");
    this.board = board;
    for (const fn of this.listeners) fn(board);
  }
}

export const onlineFeed = new OnlineFeed();

// -- what the viewer chose to see (kept in the browser) -----------------------------------------

const STORE_KEY = "cellvision.online.hidden";

function hiddenSet() {
  try {
    return new Set(JSON.parse(localStorage.getItem(STORE_KEY) || "[]"));
  } catch {
    return new Set();
  }
}

function setHidden(key, hidden) {
  const set = hiddenSet();
  if (hidden) set.add(key);
  else set.delete(key);
  try {
    localStorage.setItem(STORE_KEY, JSON.stringify([...set].slice(-500)));
  } catch {
    // A browser without storage forgets the choice on reload; nothing else changes.
  }
}

// -- one camera's graphics and counts ------------------------------------------------------------

/** A percentage with one decimal, "—" without a total. */
export function yieldText(value) {
  return typeof value === "number" ? `${(value * 100).toFixed(1)} %` : "—";
}

export class CameraOnline {
  /**
   * ``camera``: the camera's name; ``view``: the element holding the live image (the canvas
   * goes over it); ``image``: the <img>; ``options.wall``: the large type of the wall screen.
   */
  constructor(camera, view, image, options = {}) {
    this.camera = camera;
    this.view = view;
    this.image = image;
    this.wall = Boolean(options.wall);
    // The wall screen's copies of the controls: ids of their own (the Cameras page's stay).
    this.idPrefix = this.wall ? "wall-" : "";
    this.entry = null;       // this camera's part of the board
    this.paused = false;     // a paused card keeps the graphics of the frame it froze on
    this.pending = null;     // the board that arrived meanwhile
    this.canvas = el("canvas", {
      class: "online-canvas", "data-test": "online-canvas", "data-online-camera": camera,
      "aria-label": `Inspection graphics over camera ${camera}`,
    });
    view.append(this.canvas);
    const cardKey = `card:${camera}`;
    this.shown = !hiddenSet().has(cardKey);
    this.toggle = el("input", {
      type: "checkbox", id: `${this.idPrefix}overlay-toggle-${camera}`, "data-test": "overlay-toggle",
      "data-online-camera": camera, checked: this.shown,
      onchange: () => {
        this.shown = this.toggle.checked;
        setHidden(cardKey, !this.shown);
        this.draw();
      },
    });
    this.toggleLabel = el("label", { class: "online-toggle" }, this.toggle, "Graphics");
    this.rows = el("div", { class: "online-rows", "data-test": "online-rows", "data-online-camera": camera });
    this.panel = el("div", { class: "online-panel" }, this.rows);
    this.rowNodes = new Map();
    this.resize = new ResizeObserver(() => this.draw());
    this.resize.observe(view);
    this.unlisten = null;
  }

  start() {
    if (this.unlisten === null) this.unlisten = onlineFeed.listen((board) => this.update(board));
  }

  stop() {
    if (this.unlisten !== null) this.unlisten();
    this.unlisten = null;
  }

  /** Freeze the graphics with the card's image; on resume, show the newest board. */
  setPaused(paused) {
    this.paused = paused;
    if (!paused && this.pending !== null) {
      const board = this.pending;
      this.pending = null;
      this.update(board);
    }
  }

  update(board) {
    if (this.paused) {
      this.pending = board;
      return;
    }
    this.entry = (board.cameras || []).find((c) => c.name === this.camera) || null;
    this.renderRows();
    this.draw();
  }

  inspectionShown(name) {
    return !hiddenSet().has(`insp:${this.camera}:${name}`);
  }

  // -- counts and strips (DOM) --

  renderRows() {
    const inspections = this.entry ? this.entry.inspections : [];
    const wanted = [];
    for (const insp of inspections) {
      let row = this.rowNodes.get(insp.name);
      if (row === undefined) {
        row = this.makeRow(insp.name);
        this.rowNodes.set(insp.name, row);
      }
      this.fillRow(row, insp);
      wanted.push(row.node);
    }
    for (const [name, row] of this.rowNodes) {
      if (!inspections.some((i) => i.name === name)) this.rowNodes.delete(name);
    }
    const same = wanted.length === this.rows.children.length &&
      wanted.every((node, i) => this.rows.children[i] === node);
    if (!same) replaceChildren(this.rows, ...wanted);
    this.panel.hidden = inspections.length === 0;
  }

  makeRow(name) {
    const key = `insp:${this.camera}:${name}`;
    const show = el("input", {
      type: "checkbox", id: `${this.idPrefix}overlay-${this.camera}-${name}`, "data-test": "inspection-toggle",
      "data-online-inspection": name, checked: !hiddenSet().has(key),
      onchange: () => {
        setHidden(key, !show.checked);
        this.draw();
      },
    });
    const cell = (test, label) => {
      const value = el("span", { class: "online-count-value", "data-test": test });
      return { node: el("span", { class: `online-count online-${test}` }, el("span", { class: "online-count-label" }, label), value), value };
    };
    const pass = cell("count-pass", "pass");
    const fail = cell("count-fail", "fail");
    const yld = cell("count-yield", "yield");
    const total = cell("count-total", "total");
    const verdict = el("span", { class: "online-verdict", "data-test": "last-verdict", "data-verdict": "none" }, "—");
    const strip = el("div", { class: "online-strip", "data-test": "strip", role: "img" });
    const reset = el("button", {
      type: "button", class: "btn btn-quiet online-reset", "data-test": "reset-inspection",
      "data-online-inspection": name, title: `Reset the counts of ${name}`,
      onclick: () => resetCounts(name),
    }, "Reset");
    const node = el("div", { class: "online-row", id: `${this.idPrefix}online-${this.camera}-${name}`, "data-test": "online-row", "data-online-inspection": name },
      el("div", { class: "online-row-head" },
        el("label", { class: "online-name" }, show, el("span", {}, name)),
        reset,
        verdict),
      el("div", { class: "online-counts" }, pass.node, fail.node, yld.node, total.node),
      strip);
    return { node, show, pass: pass.value, fail: fail.value, yield: yld.value, total: total.value, verdict, strip };
  }

  fillRow(row, insp) {
    row.pass.textContent = String(insp.pass);
    row.fail.textContent = String(insp.fail);
    row.yield.textContent = yieldText(insp.yield);
    row.total.textContent = String(insp.total);
    const last = insp.last;
    const verdict = last ? (last.passed ? "pass" : "fail") : "none";
    row.verdict.dataset.verdict = verdict;
    row.verdict.textContent = last ? verdict.toUpperCase() : "—";
    const cells = (insp.strip || []).map((v) => el("span", {
      class: "strip-cell", "data-verdict": v.passed ? "pass" : "fail",
      "data-result-id": v.result_id ?? "",
      title: `${v.passed ? "PASS" : "FAIL"}${v.result_id ? ` #${v.result_id}` : ""} ${new Date(v.time * 1000).toLocaleTimeString()}`,
    }));
    replaceChildren(row.strip, ...cells);
    row.strip.setAttribute("aria-label", `last ${cells.length} verdicts of ${insp.name}, newest at the right`);
  }

  // -- graphics (canvas) --

  /** Where the image lies in the view, CSS px, and the scale from inspected-image pixels. */
  placement(imageSize) {
    const width = this.view.clientWidth;
    const height = this.view.clientHeight;
    const shown = this.image && !this.image.hidden && this.image.naturalWidth > 0;
    const nw = shown ? this.image.naturalWidth : imageSize?.[0];
    const nh = shown ? this.image.naturalHeight : imageSize?.[1];
    if (!nw || !nh || !width || !height) return null;
    const fit = Math.min(width / nw, height / nh);
    const left = (width - nw * fit) / 2;
    const top = (height - nh * fit) / 2;
    // The shapes are in the pixels of the image the inspection ran on; the frame shown may
    // have another size (a scaled view): stretch by their ratio.
    const sx = imageSize ? (nw * fit) / imageSize[0] : fit;
    const sy = imageSize ? (nh * fit) / imageSize[1] : fit;
    return { left, top, sx, sy, width, height, right: left + nw * fit, bottom: top + nh * fit };
  }

  draw() {
    const canvas = this.canvas;
    const ratio = window.devicePixelRatio || 1;
    const width = this.view.clientWidth;
    const height = this.view.clientHeight;
    if (canvas.width !== Math.round(width * ratio) || canvas.height !== Math.round(height * ratio)) {
      canvas.width = Math.round(width * ratio);
      canvas.height = Math.round(height * ratio);
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
    ctx.clearRect(0, 0, width, height);
    const drawn = [];
    let verdictBoxes = [];
    if (this.shown && this.entry) {
      const labels = [];
      const extents = [];
      const shown = [];
      let origin = null;
      for (const insp of this.entry.inspections) {
        if (!insp.last || !this.inspectionShown(insp.name)) continue;
        const place = this.placement(insp.last.image_size);
        if (place !== null) {
          const out = drawShapes(ctx, insp.last.shapes || [], place, this.wall);
          labels.push(...out.labels);
          extents.push(...out.extents);
          origin = origin ?? place;
        }
        shown.push(insp);
        drawn.push(insp.name);
      }
      // The verdicts one under the other, in the image's corner that hides the fewest of the
      // graphics; the labels last, moved off the verdict boxes they would hide under.
      const area = {
        left: Math.max(origin ? origin.left : 0, 0),
        top: Math.max(origin ? origin.top : 0, 0),
        right: Math.min(origin ? origin.right : width, width),
        bottom: Math.min(origin ? origin.bottom : height, height),
      };
      const sizes = shown.map((insp) => drawVerdict(ctx, insp, 0, 0, area.right - area.left - 16, this.wall, false));
      const stackWidth = Math.max(0, ...sizes.map((b) => b.right - b.left));
      const stackHeight = sizes.reduce((sum, b) => sum + b.bottom - b.top + 6, 0);
      const corner = bestCorner(area, stackWidth, stackHeight, extents);
      let y = corner.top;
      const boxes = [];
      for (const insp of shown) {
        const box = drawVerdict(ctx, insp, corner.left, y, area.right - area.left - 16, this.wall, true);
        boxes.push(box);
        y = box.bottom + 6;
      }
      verdictBoxes = boxes;
      const size = this.wall ? 22 : 15;
      // Each label keeps off the verdicts and the labels drawn before it (two fixture frames
      // at one origin, steps that share a corner).
      const taken = [...boxes];
      for (const item of labels) taken.push(label(ctx, item.text, item.x, item.y, size, { width, height }, taken));
    }
    // What is drawn, for a test or a screen reader: the inspections whose graphics are shown.
    canvas.dataset.drawn = drawn.join(" ");
    canvas.dataset.verdictBoxes = verdictBoxes
      .map((b) => [b.left, b.top, b.right, b.bottom].map(Math.round).join(",")).join(";");
  }
}

// -- drawing ----------------------------------------------------------------------------------

function stroke(ctx, role, path, scale = 1) {
  const style = STYLE[role] || STYLE.roi;
  ctx.save();
  ctx.setLineDash(style.dash || []);
  // A dark line under the coloured one: the shape reads on a bright and on a dark image.
  ctx.strokeStyle = "rgba(0, 0, 0, 0.8)";
  ctx.lineWidth = (style.width + 2) * scale;
  path();
  ctx.stroke();
  ctx.strokeStyle = style.colour;
  ctx.lineWidth = style.width * scale;
  path();
  ctx.stroke();
  ctx.restore();
}

/** The corner of ``area`` (top-left first) where a ``w`` x ``h`` box covers the least of the
 * graphics' ``extents``. */
function bestCorner(area, w, h, extents) {
  const lefts = [area.left + 8, Math.max(area.right - 8 - w, area.left + 8)];
  const tops = [area.top + 8, Math.max(area.bottom - 8 - h, area.top + 8)];
  let best = null;
  for (const top of tops) {
    for (const left of lefts) {
      let covered = 0;
      for (const e of extents) {
        const dx = Math.min(left + w, e.right) - Math.max(left, e.left);
        const dy = Math.min(top + h, e.bottom) - Math.max(top, e.top);
        if (dx > 0 && dy > 0) covered += dx * dy + 1000; // any overlap costs, more the more
      }
      if (best === null || covered < best.covered) best = { left, top, covered };
    }
  }
  return best;
}

/** Where a shape lies on the screen (CSS px), for placing the verdicts off it. */
function extentOf(s, x, y) {
  let points = [];
  if (s.kind === "rect") points = [[s.x, s.y], [s.x + s.w, s.y + s.h]];
  else if (s.kind === "polygon" || s.kind === "line") points = s.points;
  else if (s.kind === "circle") points = [[s.u - s.r, s.v - s.r], [s.u + s.r, s.v + s.r]];
  else if (s.kind === "point" || s.kind === "text") points = [[s.u, s.v]];
  else if (s.kind === "axes") points = [[s.u, s.v], s.x, s.y, s.z].filter(Boolean);
  if (points.length === 0) return null;
  const xs = points.map((p) => x(p[0]));
  const ys = points.map((p) => y(p[1]));
  const pad = s.kind === "text" ? 12 : 6;
  return {
    left: Math.min(...xs) - pad, right: Math.max(...xs) + pad,
    top: Math.min(...ys) - pad, bottom: Math.max(...ys) + pad,
  };
}

/** Draw the shapes' lines; answers their labels (drawn last) and their extents on screen. */
function drawShapes(ctx, shapes, place, wall) {
  const x = (u) => place.left + (u + 0.5) * place.sx;
  const y = (v) => place.top + (v + 0.5) * place.sy;
  const scale = wall ? 1.5 : 1;
  const texts = [];
  const extents = [];
  for (const s of shapes) {
    const extent = extentOf(s, x, y);
    if (extent !== null) extents.push(extent);
    switch (s.kind) {
      case "rect":
        stroke(ctx, s.role, () => {
          ctx.beginPath();
          ctx.rect(x(s.x - 0.5), y(s.y - 0.5), s.w * place.sx, s.h * place.sy);
        }, scale);
        break;
      case "polygon":
      case "line":
        stroke(ctx, s.role, () => {
          ctx.beginPath();
          s.points.forEach(([u, v], i) => (i === 0 ? ctx.moveTo(x(u), y(v)) : ctx.lineTo(x(u), y(v))));
          if (s.kind === "polygon") ctx.closePath();
        }, scale);
        break;
      case "circle":
        stroke(ctx, s.role, () => {
          ctx.beginPath();
          ctx.ellipse(x(s.u), y(s.v), Math.max(s.r * place.sx, 1), Math.max(s.r * place.sy, 1), 0, 0, 2 * Math.PI);
        }, scale);
        break;
      case "point": {
        const arm = 6 * scale;
        stroke(ctx, s.role, () => {
          ctx.beginPath();
          ctx.moveTo(x(s.u) - arm, y(s.v));
          ctx.lineTo(x(s.u) + arm, y(s.v));
          ctx.moveTo(x(s.u), y(s.v) - arm);
          ctx.lineTo(x(s.u), y(s.v) + arm);
        }, scale);
        break;
      }
      case "axes":
        for (const axis of ["x", "y", "z"]) {
          if (!s[axis]) continue;
          arrow(ctx, x(s.u), y(s.v), x(s[axis][0]), y(s[axis][1]), AXIS_COLOURS[axis], scale);
        }
        break;
      case "text":
        texts.push(s);
        break;
      default:
        break;
    }
  }
  // Labels are drawn last, over every line and verdict, each on a dark box.
  return { labels: texts.map((s) => ({ text: s.text, x: x(s.u), y: y(s.v) })), extents };
}

function arrow(ctx, x0, y0, x1, y1, colour, scale) {
  const angle = Math.atan2(y1 - y0, x1 - x0);
  const head = 8 * scale;
  for (const [style, width] of [["rgba(0, 0, 0, 0.8)", 5 * scale], [colour, 2.5 * scale]]) {
    ctx.strokeStyle = style;
    ctx.lineWidth = width;
    ctx.beginPath();
    ctx.moveTo(x0, y0);
    ctx.lineTo(x1, y1);
    ctx.moveTo(x1, y1);
    ctx.lineTo(x1 - head * Math.cos(angle - 0.45), y1 - head * Math.sin(angle - 0.45));
    ctx.moveTo(x1, y1);
    ctx.lineTo(x1 - head * Math.cos(angle + 0.45), y1 - head * Math.sin(angle + 0.45));
    ctx.stroke();
  }
}

function label(ctx, text, px, py, size, view, boxes) {
  ctx.save();
  ctx.font = `600 ${size}px system-ui, sans-serif`;
  ctx.textBaseline = "bottom";
  const width = ctx.measureText(text).width + 8;
  const height = size + 6;
  // Kept inside the view: a label at the image's edge must not be cut off.
  const left = Math.min(Math.max(px, 2), Math.max(view.width - width - 2, 2));
  const place = (b) => Math.min(Math.max(b, height + 2), view.height - 2);
  const free = (b) => !boxes.some((box) => left < box.right && left + width > box.left &&
    b - height < box.bottom && b > box.top);
  // Where it belongs, else the nearest free line above or below (within a few lines), else
  // where it belongs after all.
  let bottom = place(py);
  for (const step of [0, -1, 1, -2, 2, -3, 3]) {
    const candidate = place(py + step * (height + 1));
    if (free(candidate)) {
      bottom = candidate;
      break;
    }
  }
  ctx.fillStyle = "rgba(10, 14, 20, 0.78)";
  ctx.fillRect(left, bottom - height, width, height);
  ctx.fillStyle = "#ffffff";
  ctx.fillText(text, left + 4, bottom - 3);
  ctx.restore();
  return { left, top: bottom - height, right: left + width, bottom };
}

/** The verdict box of one inspection at ``left``, ``top``: "PASS name" in green or red on a dark
 * box with a coloured border; the result's summary below in smaller type. Returns its box
 * (CSS px); without ``paint`` only measures it. */
function drawVerdict(ctx, insp, left, top, width, wall, paint) {
  const last = insp.last;
  const verdict = last.passed ? "pass" : "fail";
  const big = wall ? 56 : 34;
  const small = wall ? 24 : 16;
  ctx.save();
  ctx.textBaseline = "top";
  ctx.font = `800 ${big}px system-ui, sans-serif`;
  const word = verdict.toUpperCase();
  const wordWidth = ctx.measureText(word).width;
  ctx.font = `700 ${small}px system-ui, sans-serif`;
  const name = insp.name;
  const detail = last.summary || "";
  const nameWidth = ctx.measureText(name).width;
  const detailWidth = ctx.measureText(detail).width;
  const pad = wall ? 14 : 10;
  const boxWidth = Math.min(Math.max(wordWidth + pad * 3 + nameWidth, detailWidth + pad * 2), width);
  const boxHeight = big + pad * 2 + (detail ? small + 4 : 0);
  if (!paint) {
    ctx.restore();
    return { left, top, right: left + boxWidth, bottom: top + boxHeight };
  }
  ctx.fillStyle = "rgba(8, 12, 18, 0.86)";
  ctx.fillRect(left, top, boxWidth, boxHeight);
  ctx.strokeStyle = VERDICT_COLOUR[verdict];
  ctx.lineWidth = wall ? 5 : 3;
  ctx.strokeRect(left, top, boxWidth, boxHeight);
  ctx.font = `800 ${big}px system-ui, sans-serif`;
  ctx.lineWidth = wall ? 6 : 4;
  ctx.strokeStyle = "#000000";
  ctx.strokeText(word, left + pad, top + pad);
  ctx.fillStyle = VERDICT_COLOUR[verdict];
  ctx.fillText(word, left + pad, top + pad);
  ctx.font = `700 ${small}px system-ui, sans-serif`;
  ctx.fillStyle = "#ffffff";
  ctx.fillText(name, left + pad * 2 + wordWidth, top + pad + (big - small) / 2, boxWidth - wordWidth - pad * 3);
  if (detail) {
    ctx.fillStyle = "#d8e0e8";
    ctx.fillText(detail, left + pad, top + pad + big + 4, boxWidth - pad * 2);
  }
  ctx.restore();
  return { left, top, right: left + boxWidth, bottom: top + boxHeight };
}

// -- reset ----------------------------------------------------------------------------------

/** Reset the counts of ``inspection`` (null: of all); the page shows a refusal's message. */
export async function resetCounts(inspection = null) {
  const status = document.getElementById("online-status");
  try {
    const response = await request("/api/online/reset", {
      method: "POST",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify(inspection === null ? {} : { inspection }),
    });
    await response.json();
    if (status) status.textContent = inspection === null ? "Counts reset." : `Counts of ${inspection} reset.`;
  } catch (exc) {
    if (status) status.textContent = `${exc.code}: ${exc.message}`;
  }
  onlineFeed.refresh();
}
