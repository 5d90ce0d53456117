// Results: the result log newest first with filters and paging; a row opens the stored image
// with its overlay, the values and the timing. Above the table, per inspection: pass rate, count
// and timing p50/p99 over a chosen window, as small charts.

import { api, ApiError } from "./api.js";
import { lines, rateBars } from "./charts.js";
import { byId, countText, el, fillKeyValues, formatNumber, formatTime, replaceChildren } from "./dom.js";
import { Poller } from "./poll.js";

const PAGE_SIZE = 50;

/** A duration for a person: "3.6 ms", or "—" when there is none (no results in the window). */
function msText(value) {
  return typeof value === "number" ? `${formatNumber(value, 3)} ms` : "—";
}

export class ResultsPage {
  constructor() {
    this.filters = {};
    this.before = [];          // before_id of each page shown, for "Newer"
    this.beforeId = null;      // the page shown: null = the newest
    this.nextBeforeId = null;
    this.openId = null;
    this.openRow = null;       // the open result's answer, to switch overlay/input
    this.wired = false;
    // The newest page follows the log; an older page stays put until the user moves.
    this.poller = new Poller(() => (this.beforeId === null ? this.loadPage() : null), 3000);
    this.statsPoller = new Poller(() => this.loadStats(), 10000);
  }

  start() {
    if (!this.wired) this.wire();
    this.fillInspections();
    this.poller.start();
    this.statsPoller.start();
  }

  stop() {
    this.poller.stop();
    this.statsPoller.stop();
  }

  wire() {
    this.wired = true;
    byId("results-filters").addEventListener("submit", (event) => {
      event.preventDefault();
      this.applyFilters();
    });
    for (const id of ["f-inspection", "f-verdict"]) {
      byId(id).addEventListener("change", () => this.applyFilters());
    }
    byId("f-clear").addEventListener("click", () => {
      byId("results-filters").reset();
      this.applyFilters();
    });
    byId("page-older").addEventListener("click", () => {
      if (this.nextBeforeId === null) return;
      this.before.push(this.beforeId);
      this.beforeId = this.nextBeforeId;
      this.loadPage();
    });
    byId("page-newer").addEventListener("click", () => {
      if (this.before.length === 0) return;
      this.beforeId = this.before.pop();
      this.loadPage();
    });
    byId("rd-close").addEventListener("click", () => this.closeDetail());
    for (const id of ["rd-view-overlay", "rd-view-input"]) {
      byId(id).addEventListener("change", () => this.showImage());
    }
    byId("stats-window").addEventListener("change", () => this.statsPoller.kick());
    byId("rd-try").addEventListener("click", () => {
      const r = this.openRow;
      if (r === null || !r.inspection) return;
      // The Inspections page reads this route: open the inspection, source "Stored result".
      location.hash = `#/inspections/${encodeURIComponent(r.inspection)}?result=${r.id}`;
    });
    this.exportLink();
  }

  /** The CSV export of exactly the rows the filters select. */
  exportLink() {
    const query = new URLSearchParams(Object.entries(this.filters).filter(([, v]) => v));
    const text = query.toString();
    byId("results-export").href = `/api/results.csv${text ? `?${text}` : ""}`;
  }

  async fillInspections() {
    try {
      const listing = await api.inspections();
      const select = byId("f-inspection");
      const chosen = select.value;
      replaceChildren(select, el("option", { value: "" }, "all"),
        ...(listing.inspections ?? []).map((i) => el("option", { value: i.name }, i.name)));
      select.value = chosen;
    } catch {
      // The table still works without the list; the filter then offers "all" only.
    }
  }

  /** The filter form as API query parameters; ``since`` in Unix seconds. */
  readFilters() {
    const since = byId("f-since").value;
    return {
      inspection: byId("f-inspection").value,
      verdict: byId("f-verdict").value,
      since: since ? String(Math.floor(new Date(since).getTime() / 1000)) : "",
      peer: byId("f-peer").value.trim(),
      operator: byId("f-operator").value.trim(),
    };
  }

  applyFilters() {
    this.filters = this.readFilters();
    this.exportLink();
    this.before = [];
    this.beforeId = null;
    this.loadPage();
    this.statsPoller.kick();
  }

  async loadPage() {
    const params = { ...this.filters, limit: PAGE_SIZE, before_id: this.beforeId };
    let page;
    try {
      page = await api.results(params);
    } catch (exc) {
      if (!(exc instanceof ApiError && exc.status === 401)) {
        byId("results-empty").textContent = `Results unavailable: ${exc.message}`;
        byId("results-empty").hidden = false;
      }
      return;
    }
    const rows = page.results ?? [];
    this.nextBeforeId = page.next_before_id ?? null;
    replaceChildren(byId("results-body"), ...rows.map((r) => this.row(r)));
    byId("results-empty").textContent = "No results match.";
    byId("results-empty").hidden = rows.length > 0;
    byId("page-older").disabled = this.nextBeforeId === null;
    byId("page-newer").disabled = this.before.length === 0;
    byId("page-label").textContent = this.beforeId === null ? "Newest" : `Before #${this.beforeId}`;
  }

  row(r) {
    const verdict = r.passed === undefined ? String(r.verdict ?? "") : r.passed ? "pass" : "fail";
    const tr = el("tr", {
      class: `result-row${r.id === this.openId ? " active" : ""}`, tabindex: 0,
      dataset: { id: r.id },
      onclick: () => this.open(r.id),
      onkeydown: (e) => { if (e.key === "Enter") this.open(r.id); },
    },
    el("td", { class: "num" }, String(r.id)),
    el("td", {}, formatTime(r.time)),
    el("td", {}, r.inspection),
    el("td", {}, el("span", { class: "verdict-chip", dataset: { verdict } }, verdict),
      // A console try is not a production result (docs/console.md): say so on its row.
      r.try ? el("span", { class: "try-chip", title: "a console try, not counted in the statistics" }, "try") : ""),
    el("td", {}, r.camera ?? ""),
    el("td", {}, r.peer ?? ""),
    el("td", { class: "num" }, typeof r.duration_ms === "number" ? formatNumber(r.duration_ms, 3) : "—"));
    return tr;
  }

  async open(id) {
    this.openId = id;
    for (const tr of document.querySelectorAll("#results-body tr")) {
      tr.classList.toggle("active", Number(tr.dataset.id) === id);
    }
    let r;
    try {
      r = await api.result(id);
    } catch (exc) {
      if (exc instanceof ApiError && exc.status === 401) return;
      r = { id, error: exc.message };
    }
    if (this.openId !== id) return;
    const verdict = r.passed === undefined ? String(r.verdict ?? "") : r.passed ? "pass" : "fail";
    byId("result-detail").hidden = false;
    byId("rd-title").textContent = `#${id} ${r.inspection ?? ""}`;
    const chip = byId("rd-verdict");
    chip.textContent = verdict.toUpperCase();
    chip.dataset.verdict = verdict || "none";
    this.openRow = r;
    // Only a stored input can be tried again (the try's source "result").
    byId("rd-try").hidden = !r.has_image;
    // A row opens on its overlay when it has one (older rows and failed requests have none).
    byId(r.has_overlay === false ? "rd-view-input" : "rd-view-overlay").checked = true;
    this.showImage();
    fillKeyValues(byId("rd-values"), [
      ["time", formatTime(r.time)], ["camera", r.camera], ["peer", r.peer],
      ["request id", r.request_id], ["configuration", r.config_hash ? String(r.config_hash).slice(0, 12) : null],
      ...Object.entries(r.data ?? {}),
      ...(r.error ? [["error", r.error]] : []),
    ]);
    fillKeyValues(byId("rd-timing"), Object.entries(r.timing ?? { total: r.duration_ms })
      .map(([k, v]) => [k, typeof v === "number" ? `${formatNumber(v, 3)} ms` : v]));
  }

  /** The open row's stored overlay or input, as the toggle says; a note when one is missing. */
  showImage() {
    const r = this.openRow;
    if (r === null) return;
    const image = byId("rd-image");
    const wantOverlay = byId("rd-view-overlay").checked;
    const hasOverlay = r.has_overlay !== false;
    const overlay = wantOverlay && hasOverlay;
    const shown = overlay || Boolean(r.has_image);
    byId("rd-views").hidden = !r.has_image;
    byId("rd-view-overlay").disabled = !hasOverlay;
    byId("rd-nooverlay").hidden = !(r.has_image && !hasOverlay);
    byId("rd-noimage").hidden = shown;
    image.hidden = !shown;
    image.dataset.view = overlay ? "overlay" : "input";
    if (shown) image.src = api.resultImageUrl(r.id, overlay);
    else image.removeAttribute("src");
    image.alt = overlay ? "Stored image with its overlay" : "Stored input image";
  }

  closeDetail() {
    this.openId = null;
    this.openRow = null;
    byId("result-detail").hidden = true;
    for (const tr of document.querySelectorAll("#results-body tr.active")) tr.classList.remove("active");
  }

  async loadStats() {
    const windowS = byId("stats-window").value;
    let stats;
    try {
      stats = await api.stats({ inspection: this.filters.inspection, window_s: windowS });
    } catch (exc) {
      if (!(exc instanceof ApiError && exc.status === 401)) {
        replaceChildren(byId("stats-cards"), el("p", { class: "muted" }, `Statistics unavailable: ${exc.message}`));
      }
      return;
    }
    const cards = (stats.inspections ?? []).map((s) => {
      const series = s.series ?? [];
      const rate = typeof s.pass_rate === "number" ? `${formatNumber(s.pass_rate * 100, 3)} %` : "—";
      return el("article", { class: "card stat-card", dataset: { inspection: s.name } },
        el("header", { class: "card-head" }, el("h3", {}, s.name),
          el("span", { class: "stat-big" }, rate), el("span", { class: "muted" }, countText(s.count, "result", "results"))),
        el("div", { class: "stat-row" },
          el("span", { class: "stat-label" }, "pass rate"),
          rateBars(series.map((b) => (b.count > 0 ? b.pass_rate : null)), { label: `Pass rate of ${s.name}` })),
        el("div", { class: "stat-row" },
          el("span", { class: "stat-label" },
            el("span", { class: "key key-p50" }, `p50 ${msText(s.p50_ms)}`),
            el("span", { class: "key key-p99" }, `p99 ${msText(s.p99_ms)}`)),
          lines([
            { values: series.map((b) => b.p99_ms ?? null), cls: "line-p99" },
            { values: series.map((b) => b.p50_ms ?? null), cls: "line-p50" },
          ], { label: `Timing p50 and p99 of ${s.name}` })));
    });
    replaceChildren(byId("stats-cards"), cards.length ? cards : el("p", { class: "muted" }, "No results in this window."));
  }
}
