// The tools drawn on the try image beside the ROI (roi.js): a caliper line (drag from A to B:
// the band's centre, length and angle; its width from the tool bar), a circle's search ring
// (drag from the centre outwards: the radius; the ring's half-width from the tool bar) and a
// template rectangle (drag a rectangle, then "Train template"). Everything here is in image
// pixels (u = column, v = row); the page converts to a fixture's part frame (frames.js). The
// shapes are drawn on the ROI editor's canvas through its ``decorate`` hook, so one canvas
// takes every pointer and draws every shape.

const MIN_DRAG = 3;   // image pixels: a shorter drag is a tap and changes nothing
const COLOURS = { band: "#36c5f0", ring: "#ff5ad1", rect: "#7cff6b", frame: "#ffffff" };

export class ToolLayer {
  /**
   * ``roi`` the RoiEditor whose canvas and image are shared; ``onDrawn(tool, shape)`` is called
   * at the end of a drag with the shape in image pixels: band {a, b}, ring {centre, radius},
   * rect [x, y, w, h].
   */
  constructor(roi, onDrawn) {
    this.roi = roi;
    this.canvas = roi.canvas;
    this.onDrawn = onDrawn;
    this.tool = "roi";
    this.drag = null;
    // What is shown (image pixels): bands [{centre, length, width, angle}], rings
    // [{centre, radius, search}], rect [x, y, w, h] or null, frames [{u, v, angle, name}].
    this.shapes = { bands: [], rings: [], rect: null, frames: [] };
    roi.decorate = (ctx, s) => this.drawShapes(ctx, s);
    this.canvas.addEventListener("pointerdown", (e) => this.down(e));
    this.canvas.addEventListener("pointermove", (e) => this.move(e));
    this.canvas.addEventListener("pointerup", (e) => this.up(e));
    this.canvas.addEventListener("pointercancel", () => { this.drag = null; this.redraw(); });
  }

  /** Choose the tool: "roi" (the ROI editor drags), "band", "ring" or "rect". */
  use(tool) {
    this.tool = tool;
    this.drag = null;
    this.roi.enabled = tool === "roi";
    this.canvas.style.cursor = "crosshair";
    this.redraw();
  }

  show(shapes) {
    this.shapes = { ...this.shapes, ...shapes };
    this.redraw();
  }

  redraw() {
    this.roi.draw();
  }

  down(event) {
    if (this.tool === "roi" || !this.roi.image.naturalWidth) return;
    event.preventDefault();
    this.canvas.setPointerCapture(event.pointerId);
    const p = this.roi.toImage(event);
    this.drag = { start: p, end: p };
  }

  move(event) {
    if (this.drag === null) return;
    this.drag.end = this.roi.toImage(event);
    this.redraw();
  }

  up(event) {
    if (this.drag === null) return;
    this.drag.end = this.roi.toImage(event);
    const { start, end } = this.drag;
    this.drag = null;
    const length = Math.hypot(end[0] - start[0], end[1] - start[1]);
    if (length < MIN_DRAG) {
      this.redraw();
      return;
    }
    const r2 = (n) => Math.round(n * 100) / 100;
    if (this.tool === "band") {
      this.onDrawn("band", { a: start.map(r2), b: end.map(r2) });
    } else if (this.tool === "ring") {
      this.onDrawn("ring", { centre: start.map(r2), radius: r2(length) });
    } else if (this.tool === "rect") {
      const [iw, ih] = this.roi.imageSize();
      const x0 = Math.max(0, Math.round(Math.min(start[0], end[0])));
      const y0 = Math.max(0, Math.round(Math.min(start[1], end[1])));
      const x1 = Math.min(iw, Math.round(Math.max(start[0], end[0])));
      const y1 = Math.min(ih, Math.round(Math.max(start[1], end[1])));
      this.onDrawn("rect", [x0, y0, x1 - x0, y1 - y0]);
    }
    this.redraw();
  }

  drawShapes(ctx, s) {
    ctx.save();
    ctx.lineWidth = 2;
    for (const frame of this.shapes.frames) drawFrame(ctx, s, frame);
    for (const band of this.shapes.bands) drawBand(ctx, s, band);
    for (const ring of this.shapes.rings) drawRing(ctx, s, ring);
    if (this.shapes.rect) {
      const [x, y, w, h] = this.shapes.rect.map((n) => n * s);
      ctx.strokeStyle = COLOURS.rect;
      ctx.setLineDash([6, 4]);
      ctx.strokeRect(x, y, w, h);
      ctx.setLineDash([]);
    }
    if (this.drag) {
      // The shape being dragged, drawn as it will be taken.
      const [a, b] = [this.drag.start, this.drag.end];
      const length = Math.hypot(b[0] - a[0], b[1] - a[1]);
      if (this.tool === "band") {
        drawBand(ctx, s, {
          centre: [(a[0] + b[0]) / 2, (a[1] + b[1]) / 2], length,
          width: this.bandWidth ?? 5, angle: Math.atan2(b[1] - a[1], b[0] - a[0]),
        });
      } else if (this.tool === "ring") {
        drawRing(ctx, s, { centre: a, radius: length, search: this.ringSearch ?? 0 });
      } else if (this.tool === "rect") {
        ctx.strokeStyle = COLOURS.rect;
        ctx.strokeRect(Math.min(a[0], b[0]) * s, Math.min(a[1], b[1]) * s, Math.abs(b[0] - a[0]) * s, Math.abs(b[1] - a[1]) * s);
      }
    }
    ctx.restore();
  }
}

/** A caliper band: a rectangle ``length`` along the scan by ``width`` across, turned by
 * ``angle``, with an arrow head showing the scan's direction. */
function drawBand(ctx, s, { centre, length, width, angle, label }) {
  ctx.save();
  ctx.translate(centre[0] * s, centre[1] * s);
  ctx.rotate(angle);
  ctx.strokeStyle = COLOURS.band;
  const l = length * s, w = Math.max(1, width * s);
  ctx.strokeRect(-l / 2, -w / 2, l, w);
  ctx.beginPath();
  ctx.moveTo(-l / 2, 0);
  ctx.lineTo(l / 2, 0);
  ctx.lineTo(l / 2 - 8, -5);
  ctx.moveTo(l / 2, 0);
  ctx.lineTo(l / 2 - 8, 5);
  ctx.stroke();
  ctx.restore();
  if (label) text(ctx, label, centre[0] * s, centre[1] * s - w / 2 - 4, COLOURS.band);
}

/** A circle's search ring: the expected circle and its band of ± ``search``. */
function drawRing(ctx, s, { centre, radius, search, label }) {
  const [cx, cy] = [centre[0] * s, centre[1] * s];
  ctx.strokeStyle = COLOURS.ring;
  ctx.beginPath();
  ctx.arc(cx, cy, Math.max(0, radius * s), 0, 2 * Math.PI);
  ctx.stroke();
  if (search > 0) {
    ctx.setLineDash([4, 4]);
    for (const r of [radius - search, radius + search]) {
      if (r <= 0) continue;
      ctx.beginPath();
      ctx.arc(cx, cy, r * s, 0, 2 * Math.PI);
      ctx.stroke();
    }
    ctx.setLineDash([]);
  }
  ctx.beginPath();
  ctx.moveTo(cx - 5, cy);
  ctx.lineTo(cx + 5, cy);
  ctx.moveTo(cx, cy - 5);
  ctx.lineTo(cx, cy + 5);
  ctx.stroke();
  if (label) text(ctx, label, cx, cy - radius * s - 6, COLOURS.ring);
}

/** A fixture's part frame: its x axis (long) and y axis (short), named. */
function drawFrame(ctx, s, { u, v, angle, name }) {
  const [cx, cy] = [u * s, v * s];
  const c = Math.cos(angle), d = Math.sin(angle);
  ctx.save();
  ctx.lineWidth = 2;
  ctx.strokeStyle = "#ff6b3d";
  ctx.beginPath();
  ctx.moveTo(cx, cy);
  ctx.lineTo(cx + 40 * c, cy + 40 * d);
  ctx.stroke();
  ctx.strokeStyle = "#3dff8b";
  ctx.beginPath();
  ctx.moveTo(cx, cy);
  ctx.lineTo(cx - 25 * d, cy + 25 * c);
  ctx.stroke();
  ctx.restore();
  if (name) text(ctx, name, cx + 6, cy - 6, COLOURS.frame);
}

function text(ctx, label, x, y, colour) {
  ctx.save();
  ctx.font = "bold 13px system-ui, sans-serif";
  ctx.lineWidth = 3;
  ctx.strokeStyle = "rgba(0, 0, 0, 0.8)";
  ctx.strokeText(label, x, y);
  ctx.fillStyle = colour;
  ctx.fillText(label, x, y);
  ctx.restore();
}
