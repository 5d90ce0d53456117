// The fixture frame of a job (docs/configuration.md, "The fixture frame"): a part frame with
// its origin at (u0, v0) image pixels and its x axis at ``angle`` radians from +u towards +v.
// A part-frame point (x, y) is the image point
//   u = u0 + x cos(angle) - y sin(angle),  v = v0 + x sin(angle) + y cos(angle).
// Units are image pixels on both sides; nothing is scaled. The page draws in image pixels and
// converts what is drawn for a fixtured step into the part frame with these functions.

/** A frame from a try's ``data.steps.NAME`` (a fixture step's values), or null when it was not
 * made (a locate found nothing, or no try has run). */
export function frameFrom(values) {
  if (!values) return null;
  const { u, v, angle } = values;
  if (![u, v, angle].every((n) => typeof n === "number" && Number.isFinite(n))) return null;
  return { u, v, angle };
}

/** Part frame (x, y) -> image (u, v). */
export function toImage(frame, [x, y]) {
  const c = Math.cos(frame.angle), s = Math.sin(frame.angle);
  return [frame.u + x * c - y * s, frame.v + x * s + y * c];
}

/** Image (u, v) -> part frame (x, y). */
export function toPart(frame, [u, v]) {
  const c = Math.cos(frame.angle), s = Math.sin(frame.angle);
  const du = u - frame.u, dv = v - frame.v;
  return [du * c + dv * s, -du * s + dv * c];
}

/** The centre of an ROI [x, y, w, h] (pixel centres x .. x + w - 1, so (w - 1) / 2 in). */
function centre([x, y, w, h]) {
  return [x + (w - 1) / 2, y + (h - 1) / 2];
}

/** ``n`` rounded to hundredths of a pixel: what the page writes into a configuration. */
export function round2(n) {
  return Math.round(n * 100) / 100;
}

/**
 * An ROI drawn on the image (axis-aligned, image pixels) as the part-frame ROI of the same size
 * whose centre is the drawn one's: whole pixels, as the configuration takes them.
 */
export function roiToPart(frame, imageRoi) {
  const [, , w, h] = imageRoi;
  const [cx, cy] = toPart(frame, centre(imageRoi));
  return [Math.round(cx - (w - 1) / 2), Math.round(cy - (h - 1) / 2), w, h];
}

/** A part-frame ROI as the axis-aligned image ROI of the same size and centre (to edit). */
export function roiToImage(frame, partRoi) {
  const [, , w, h] = partRoi;
  const [cu, cv] = toImage(frame, centre(partRoi));
  return [cu - (w - 1) / 2, cv - (h - 1) / 2, w, h];
}

/** The four corners (image pixels, pixel edges) of a part-frame ROI, where the fixture puts it. */
export function roiCorners(frame, [x, y, w, h]) {
  return [[x - 0.5, y - 0.5], [x + w - 0.5, y - 0.5], [x + w - 0.5, y + h - 0.5], [x - 0.5, y + h - 0.5]]
    .map((p) => toImage(frame, p));
}

/** A point (a band's or circle's centre) image -> part, to 2 decimals. */
export function pointToPart(frame, point) {
  return toPart(frame, point).map(round2);
}

export function pointToImage(frame, point) {
  return toImage(frame, point);
}

/** An angle (radians from +u towards +v) in the image -> in the part frame, and back. */
export function angleToPart(frame, angle) {
  return normalise(angle - frame.angle);
}

export function angleToImage(frame, angle) {
  return normalise(angle + frame.angle);
}

/** An angle into (-pi, pi], to 4 decimals. */
function normalise(angle) {
  let a = angle;
  while (a <= -Math.PI) a += 2 * Math.PI;
  while (a > Math.PI) a -= 2 * Math.PI;
  return Math.round(a * 10000) / 10000;
}
