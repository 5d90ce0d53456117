// Small inline SVG charts drawn from numbers (no library): the ROI histogram with its threshold,
// bar series (pass rate) and line series (timing percentiles).

import { formatNumber, svg } from "./dom.js";

/**
 * A 256-bin histogram as bars, with a vertical line at ``threshold`` (a grey level) when given.
 * Heights are square-root scaled so that a small dark mode beside a large background still shows.
 */
export function histogramChart(bins, threshold, { width = 320, height = 120 } = {}) {
  const peak = Math.max(1, ...bins);
  const barW = width / bins.length;
  const bars = [];
  for (let i = 0; i < bins.length; i += 1) {
    if (bins[i] <= 0) continue;
    const h = Math.max(1, Math.sqrt(bins[i] / peak) * (height - 14));
    const below = threshold !== null && threshold !== undefined && i < threshold;
    bars.push(svg("rect", {
      x: (i * barW).toFixed(2), y: (height - 12 - h).toFixed(2),
      width: Math.max(barW, 1).toFixed(2), height: h.toFixed(2),
      class: below ? "bar bar-below" : "bar",
    }));
  }
  const parts = [
    svg("rect", { x: 0, y: 0, width, height: height - 12, class: "chart-bg" }),
    ...bars,
    svg("text", { x: 0, y: height - 1, class: "axis" }, "0"),
    svg("text", { x: width, y: height - 1, class: "axis", "text-anchor": "end" }, "255"),
  ];
  if (threshold !== null && threshold !== undefined) {
    const x = (threshold / bins.length) * width;
    parts.push(
      svg("line", { x1: x, x2: x, y1: 0, y2: height - 12, class: "threshold" }),
      svg("text", { x: Math.min(Math.max(x + 4, 4), width - 40), y: 11, class: "threshold-label" },
        `threshold ${formatNumber(threshold)}`),
    );
  }
  return svg("svg", {
    viewBox: `0 0 ${width} ${height}`, class: "chart chart-histogram", role: "img",
    "aria-label": `Histogram of the ROI${threshold !== null && threshold !== undefined ? `, threshold ${threshold}` : ""}`,
  }, parts);
}

/** Bars of values in 0..1 (pass rate per bucket); empty buckets (null) leave a gap. */
export function rateBars(values, { width = 280, height = 64, label = "" } = {}) {
  const n = Math.max(values.length, 1);
  const slot = width / n;
  const bars = values.map((v, i) => {
    if (v === null || v === undefined) return null;
    const h = Math.max(1, v * (height - 4));
    return svg("rect", {
      x: (i * slot + slot * 0.1).toFixed(2), y: (height - h).toFixed(2),
      width: Math.max(slot * 0.8, 1).toFixed(2), height: h.toFixed(2),
      class: v >= 0.99 ? "bar bar-good" : v >= 0.9 ? "bar bar-warn" : "bar bar-bad",
    }, svg("title", {}, `${formatNumber(v * 100, 3)} %`));
  });
  return svg("svg", {
    viewBox: `0 0 ${width} ${height}`, preserveAspectRatio: "none", class: "chart", role: "img", "aria-label": label,
  }, svg("rect", { x: 0, y: 0, width, height, class: "chart-bg" }), bars);
}

/** Lines for several series of equal length ({values, cls}); nulls break the line. */
export function lines(series, { width = 280, height = 64, label = "" } = {}) {
  const all = series.flatMap((s) => s.values).filter((v) => typeof v === "number");
  const top = Math.max(1e-9, ...all) * 1.1;
  const n = Math.max(...series.map((s) => s.values.length), 2);
  const step = width / (n - 1);
  const paths = series.map(({ values, cls }) => {
    let d = "";
    let pen = false;
    values.forEach((v, i) => {
      if (typeof v !== "number") { pen = false; return; }
      const x = (i * step).toFixed(2), y = (height - 2 - (v / top) * (height - 14)).toFixed(2);
      d += `${pen ? "L" : "M"}${x} ${y} `;
      pen = true;
    });
    return d ? svg("path", { d: d.trim(), class: `line ${cls}` }) : null;
  });
  // No text inside: the chart stretches to its card; the scale goes into the tooltip instead.
  return svg("svg", {
    viewBox: `0 0 ${width} ${height}`, preserveAspectRatio: "none", class: "chart", role: "img",
    "aria-label": `${label} (top of the chart: ${formatNumber(top, 2)} ms)`,
  }, svg("title", {}, `top of the chart: ${formatNumber(top, 2)} ms`),
  svg("rect", { x: 0, y: 0, width, height, class: "chart-bg" }), paths);
}
