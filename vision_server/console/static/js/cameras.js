// Cameras: a card per configured camera with its live image. Each card fetches its own
// frame.jpg (a cache-busting query, one request at a time) at the camera's view rate, capped.
// Over the image, the online view (js/online.js) draws the last production result of every
// inspection on that camera, with running counts below; #/online is the same as a wall screen.

import { api, ApiError } from "./api.js";
import { byId, el, formatNumber, replaceChildren } from "./dom.js";
import { Poller } from "./poll.js";
import { CameraOnline, onlineFeed } from "./online.js";

/** The most frames per second one card asks for, whatever the camera offers. */
const MAX_VIEW_FPS = 15;
/** Request cameras change only when a robot sends an image: look once a second. */
const REQUEST_CAMERA_FPS = 1;

class CameraCard {
  constructor(info, options = {}) {
    this.name = info.name;
    this.info = info;
    this.tick = 0;
    this.paused = false;
    this.blob = null;         // the frame shown, for "Save frame"
    this.objectUrl = null;
    this.shown = 0;           // frames shown since the card opened
    this.since = performance.now();

    this.image = el("img", { class: "camera-image", alt: `Live image of camera ${info.name}` });
    this.placeholder = el("div", { class: "camera-placeholder" }, "waiting for the first image…");
    this.fps = el("span", { class: "metric" });
    this.size = el("span", { class: "metric" });
    this.age = el("span", { class: "metric" });
    // Cameras the console must not read (a triggered camera, a folder replay: each frame
    // belongs to the cell's next inspection) show the last frame an inspection took; say so.
    this.note = el("p", { class: "camera-note muted" });
    this.pauseButton = el("button", { type: "button", class: "btn", onclick: () => this.togglePause() }, "Pause");
    this.saveButton = el("button", { type: "button", class: "btn", disabled: true, onclick: () => this.save() }, "Save frame");
    const view = el("div", { class: "camera-view" }, this.image, this.placeholder);
    this.online = new CameraOnline(info.name, view, this.image, options);
    this.node = el("article", { class: "card camera-card", dataset: { camera: info.name } },
      el("header", { class: "card-head" },
        el("h2", { class: "camera-name" }, info.name),
        el("span", { class: "tag" }, info.source ?? "camera"),
        info.depth ? el("span", { class: "tag" }, "depth") : null,
        this.online.toggleLabel),
      el("div", { class: "camera-body" }, view, this.online.panel),
      this.note,
      el("div", { class: "card-foot" },
        el("div", { class: "metrics" }, this.fps, this.size, this.age),
        el("div", { class: "actions" }, this.pauseButton, this.saveButton)));
    this.update(info);
    this.poller = new Poller(() => this.fetchFrame(), this.intervalMs());
  }

  intervalMs() {
    const rate = this.info.source === "request"
      ? REQUEST_CAMERA_FPS
      : Math.min(MAX_VIEW_FPS, this.info.view_fps || this.info.fps || 5);
    return Math.max(1000 / Math.max(rate, 0.1), 1000 / MAX_VIEW_FPS);
  }

  update(info) {
    this.info = info;
    const rate = typeof info.fps === "number" ? `${formatNumber(info.fps, 3)} fps` : "— fps";
    this.fps.textContent = rate;
    this.size.textContent = info.width && info.height ? `${info.width} × ${info.height}` : "size —";
    this.age.textContent = typeof info.frame_age_s === "number"
      ? `frame ${formatNumber(info.frame_age_s, 2)} s old` : "";
    this.note.textContent = info.view === "last_taken"
      ? "Shows the last frame an inspection took: watching takes no frame of this camera." : "";
    this.note.hidden = info.view !== "last_taken";
    if (this.poller) this.poller.intervalMs = this.intervalMs();
  }

  async fetchFrame() {
    if (this.paused) return;
    this.tick += 1;
    let response;
    try {
      response = await fetch(api.frameUrl(this.name, this.tick), { credentials: "same-origin", cache: "no-store" });
    } catch {
      this.showMessage("the server does not answer");
      return;
    }
    if (response.status === 404) {
      this.showMessage(this.info.source === "request"
        ? "no image yet: a robot has not sent one"
        : this.info.view === "last_taken" ? "no frame yet: no inspection has taken one" : "no frame yet");
      return;
    }
    if (response.status === 401) {
      // The console's own 401 handling runs through api.request: let it see this.
      await api.cameras().catch(() => {});
      return;
    }
    if (!response.ok) {
      const err = await response.json().catch(() => null);
      this.showMessage(err?.error?.message ?? `error ${response.status}`);
      return;
    }
    const blob = await response.blob();
    if (this.paused) return;
    this.blob = blob;
    const url = URL.createObjectURL(blob);
    await new Promise((resolve) => {
      this.image.onload = resolve;
      this.image.onerror = resolve;
      this.image.src = url;
    });
    if (this.objectUrl) URL.revokeObjectURL(this.objectUrl);
    this.objectUrl = url;
    this.placeholder.hidden = true;
    this.image.hidden = false;
    this.saveButton.disabled = false;
    this.shown += 1;
    // The graphics follow the image's size (the first frame, a camera that changed it).
    if (this.image.naturalWidth !== this.drawnWidth) {
      this.drawnWidth = this.image.naturalWidth;
      this.online.draw();
    }
    if (!this.info.width && this.image.naturalWidth) {
      this.size.textContent = `${this.image.naturalWidth} × ${this.image.naturalHeight}`;
    }
  }

  showMessage(text) {
    if (this.blob === null) {
      this.placeholder.textContent = text;
      this.placeholder.hidden = false;
      this.image.hidden = true;
    }
  }

  togglePause() {
    this.paused = !this.paused;
    this.pauseButton.textContent = this.paused ? "Resume" : "Pause";
    this.pauseButton.classList.toggle("btn-active", this.paused);
    this.node.classList.toggle("paused", this.paused);
    this.online.setPaused(this.paused);
    if (!this.paused) this.poller.kick();
  }

  save() {
    if (this.blob === null) return;
    const stamp = new Date().toISOString().replace(/[:.]/g, "-");
    const link = el("a", { href: URL.createObjectURL(this.blob), download: `${this.name}-${stamp}.jpg` });
    document.body.append(link);
    link.click();
    link.remove();
    setTimeout(() => URL.revokeObjectURL(link.href), 10000);
  }

  start() {
    this.poller.start();
    this.online.start();
  }

  stop() {
    this.poller.stop();
    this.online.stop();
  }
}

export class CamerasPage {
  /**
   * ``options.wall``: the wall screen (#/online, #/online/CAMERA): large type, no top bar, one
   * camera or all; ``grid`` and ``empty``: the ids of its card grid and its "no cameras" line.
   */
  constructor(options = {}) {
    this.wall = Boolean(options.wall);
    this.gridId = options.grid ?? "camera-cards";
    this.emptyId = options.empty ?? "cameras-empty";
    this.cards = new Map();
    this.allNames = [];
    // The list (rates, frame ages, cameras added by a reload) refreshes every 2 s.
    this.listPoller = new Poller(() => this.refresh(), 2000);
    this.active = false;
  }

  start() {
    this.active = true;
    onlineFeed.start();
    this.listPoller.start();
    for (const card of this.cards.values()) card.start();
  }

  stop() {
    this.active = false;
    onlineFeed.stop();
    this.listPoller.stop();
    for (const card of this.cards.values()) card.stop();
  }

  /** The wall's choice: the camera named after #/online/, or null for every camera. */
  chosenCamera() {
    if (!this.wall) return null;
    const parts = location.hash.replace(/^#\/?/, "").split("/");
    return parts.length > 1 && parts[1] ? decodeURIComponent(parts[1]) : null;
  }

  async refresh() {
    let listing;
    try {
      listing = await api.cameras();
    } catch (exc) {
      if (!(exc instanceof ApiError && exc.status === 401)) {
        byId(this.emptyId).textContent = `Cameras unavailable: ${exc.message}`;
        byId(this.emptyId).hidden = false;
      }
      return;
    }
    const chosen = this.chosenCamera();
    const all = listing.cameras ?? [];
    this.allNames = all.map((c) => c.name);
    const cameras = chosen === null ? all : all.filter((c) => c.name === chosen);
    const names = new Set(cameras.map((c) => c.name));
    for (const [name, card] of this.cards) {
      if (!names.has(name)) {
        card.stop();
        card.node.remove();
        this.cards.delete(name);
      }
    }
    for (const info of cameras) {
      let card = this.cards.get(info.name);
      if (card === undefined) {
        card = new CameraCard(info, { wall: this.wall });
        this.cards.set(info.name, card);
        if (this.active) card.start();
      } else {
        card.update(info);
      }
    }
    // Re-append only when the set or order changed: moving an <img> makes it flicker.
    const grid = byId(this.gridId);
    grid.dataset.count = String(cameras.length);
    const wanted = cameras.map((c) => this.cards.get(c.name).node);
    const same = wanted.length === grid.children.length &&
      wanted.every((node, i) => grid.children[i] === node);
    if (!same) replaceChildren(grid, ...wanted);
    byId(this.emptyId).textContent = chosen === null
      ? "No cameras are configured." : `No camera named ${chosen}.`;
    byId(this.emptyId).hidden = cameras.length > 0;
  }
}
