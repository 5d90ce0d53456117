// The ROI editor: a canvas laid over the image. The ROI is kept in image pixel coordinates,
// [x, y, w, h] with x = column (u) and y = row (v) of the top-left corner (docs/conventions.md);
// the canvas only converts to and from its displayed size. Pointer events, so fingers work too.

const HANDLE_PX = 14;   // how close (in screen pixels) to a corner a drag resizes instead of moves
const MIN_SIZE = 2;     // the smallest ROI side, in image pixels

export class RoiEditor {
  /**
   * ``image`` the <img> under ``canvas``; ``onChange(roi)`` is called while dragging and at the
   * end of a drag with the ROI rounded to whole image pixels.
   */
  constructor(image, canvas, onChange) {
    this.image = image;
    this.canvas = canvas;
    this.onChange = onChange;
    this.roi = null;
    this.drag = null;
    // Off while another tool of the tool bar (tools.js) draws on the same canvas.
    this.enabled = true;
    // A fixtured step's ROI is edited as the axis-aligned rectangle of its size around its
    // centre and shown turned by its part frame's angle (radians, +u towards +v).
    this.angle = 0;
    // Called after each drawing with (context, displayed px per image px): the other tools'
    // shapes go on the same canvas.
    this.decorate = null;
    canvas.addEventListener("pointerdown", (e) => this.down(e));
    canvas.addEventListener("pointermove", (e) => this.move(e));
    canvas.addEventListener("pointerup", (e) => this.up(e));
    canvas.addEventListener("pointercancel", (e) => this.up(e));
    new ResizeObserver(() => this.draw()).observe(image);
    image.addEventListener("load", () => this.draw());
  }

  /** Image pixels per displayed pixel (1 until the image has loaded). */
  scale() {
    const shown = this.image.clientWidth;
    return shown > 0 && this.image.naturalWidth > 0 ? this.image.naturalWidth / shown : 1;
  }

  imageSize() {
    return [this.image.naturalWidth || 0, this.image.naturalHeight || 0];
  }

  set(roi) {
    this.roi = roi === null || roi === undefined ? null : roi.map(Number);
    this.draw();
  }

  toImage(event) {
    const rect = this.canvas.getBoundingClientRect();
    const s = this.scale();
    return [(event.clientX - rect.left) * s, (event.clientY - rect.top) * s];
  }

  hit([px, py]) {
    if (this.roi === null) return null;
    const [x, y, w, h] = this.roi;
    const tol = HANDLE_PX * this.scale();
    const corners = { nw: [x, y], ne: [x + w, y], sw: [x, y + h], se: [x + w, y + h] };
    for (const [name, [cx, cy]] of Object.entries(corners)) {
      if (Math.abs(px - cx) <= tol && Math.abs(py - cy) <= tol) return name;
    }
    if (px >= x && px <= x + w && py >= y && py <= y + h) return "move";
    return null;
  }

  down(event) {
    if (!this.enabled || !this.image.naturalWidth) return;
    event.preventDefault();
    this.canvas.setPointerCapture(event.pointerId);
    const p = this.toImage(event);
    const mode = this.hit(p) ?? "draw";
    this.drag = {
      mode, start: p, previous: this.roi, roi: this.roi ? [...this.roi] : [p[0], p[1], 0, 0],
    };
  }

  move(event) {
    if (this.drag === null) {
      if (!this.enabled) return;
      const mode = this.hit(this.toImage(event));
      this.canvas.style.cursor = mode === "move" ? "move" : mode ? `${mode}-resize` : "crosshair";
      return;
    }
    const [px, py] = this.toImage(event);
    const [sx, sy] = this.drag.start;
    const [x, y, w, h] = this.drag.roi;
    let a, b;   // two opposite corners
    switch (this.drag.mode) {
      case "move": {
        const [iw, ih] = this.imageSize();
        const nx = Math.min(Math.max(0, x + px - sx), Math.max(0, iw - w));
        const ny = Math.min(Math.max(0, y + py - sy), Math.max(0, ih - h));
        this.roi = [nx, ny, w, h];
        this.changed(false);
        return;
      }
      case "draw": a = [sx, sy]; b = [px, py]; break;
      case "nw": a = [px, py]; b = [x + w, y + h]; break;
      case "ne": a = [x, py]; b = [px, y + h]; break;
      case "sw": a = [px, y]; b = [x + w, py]; break;
      default: a = [x, y]; b = [px, py]; break;   // "se"
    }
    this.roi = this.clamp(a, b);
    this.changed(false);
  }

  up(event) {
    if (this.drag === null) return;
    this.move(event);
    const { previous } = this.drag;
    this.drag = null;
    if (this.roi !== null && (this.roi[2] < MIN_SIZE || this.roi[3] < MIN_SIZE)) {
      // A tap without a drag: keep the ROI that was there, and re-run nothing.
      this.roi = previous;
      this.draw();
      return;
    }
    this.changed(true);
  }

  clamp([ax, ay], [bx, by]) {
    const [iw, ih] = this.imageSize();
    const x0 = Math.max(0, Math.min(ax, bx)), y0 = Math.max(0, Math.min(ay, by));
    const x1 = Math.min(iw, Math.max(ax, bx)), y1 = Math.min(ih, Math.max(ay, by));
    return [x0, y0, Math.max(0, x1 - x0), Math.max(0, y1 - y0)];
  }

  rounded() {
    return this.roi === null ? null : this.roi.map((v) => Math.round(v));
  }

  changed(final) {
    this.draw();
    if (this.roi !== null) this.onChange(this.rounded(), final);
    else if (final) this.onChange(null, true);
  }

  draw() {
    const canvas = this.canvas;
    const w = this.image.clientWidth, h = this.image.clientHeight;
    const ratio = window.devicePixelRatio || 1;
    if (canvas.width !== Math.round(w * ratio) || canvas.height !== Math.round(h * ratio)) {
      canvas.width = Math.round(w * ratio);
      canvas.height = Math.round(h * ratio);
      canvas.style.width = `${w}px`;
      canvas.style.height = `${h}px`;
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
    ctx.clearRect(0, 0, w, h);
    if (!this.image.naturalWidth) return;
    const s = 1 / this.scale();
    if (this.roi !== null) this.drawRoi(ctx, s, w, h);
    this.decorate?.(ctx, s);
  }

  drawRoi(ctx, s, w, h) {
    const [x, y, rw, rh] = this.roi.map((v) => v * s);
    if (this.angle) {
      // Turned about its centre, where the fixture puts it: outline only.
      const cx = x + rw / 2, cy = y + rh / 2;
      ctx.save();
      ctx.translate(cx, cy);
      ctx.rotate(this.angle);
      ctx.strokeStyle = "#ffb000";
      ctx.lineWidth = this.enabled ? 2 : 1;
      ctx.strokeRect(-rw / 2, -rh / 2, rw, rh);
      ctx.beginPath();
      ctx.moveTo(0, 0);
      ctx.lineTo(rw / 2, 0);
      ctx.stroke();
      ctx.restore();
      return;
    }
    if (!this.enabled) {
      ctx.strokeStyle = "rgba(255, 176, 0, 0.7)";
      ctx.lineWidth = 1;
      ctx.strokeRect(x, y, rw, rh);
      return;
    }
    // Dim everything outside the ROI, then outline it with its corner handles.
    ctx.fillStyle = "rgba(10, 20, 30, 0.35)";
    ctx.fillRect(0, 0, w, y);
    ctx.fillRect(0, y + rh, w, h - y - rh);
    ctx.fillRect(0, y, x, rh);
    ctx.fillRect(x + rw, y, w - x - rw, rh);
    ctx.strokeStyle = "#ffb000";
    ctx.lineWidth = 2;
    ctx.strokeRect(x, y, rw, rh);
    ctx.fillStyle = "#ffb000";
    for (const [cx, cy] of [[x, y], [x + rw, y], [x, y + rh], [x + rw, y + rh]]) {
      ctx.fillRect(cx - 5, cy - 5, 10, 10);
    }
  }
}
