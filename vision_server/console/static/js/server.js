// Server: identity, health, workers and queue, connections and reloads, refreshed every 2 s.

import { api, ApiError } from "./api.js";
import { byId, countText, el, fillKeyValues, formatDuration, formatTime, replaceChildren } from "./dom.js";
import { Poller } from "./poll.js";

/** The status pill's text and level ("ok", "warn", "bad") from GET /api/server. */
export function statusText(info) {
  const health = info.health?.status ?? "unknown";
  const busy = info.pool?.busy_count ?? 0;
  if (health !== "ok") return { text: health, level: "bad" };
  if (busy > 0) return { text: `ok · ${busy} BUSY`, level: "warn" };
  return { text: "ok", level: "ok" };
}

export class ServerPage {
  constructor() {
    this.poller = new Poller(() => this.refresh(), 2000);
  }

  start() { this.poller.start(); }
  stop() { this.poller.stop(); }

  async refresh() {
    let info;
    try {
      info = await api.server();
    } catch (exc) {
      if (!(exc instanceof ApiError && exc.status === 401)) {
        fillKeyValues(byId("srv-identity"), [["error", exc.message]]);
      }
      return;
    }
    fillKeyValues(byId("srv-identity"), [
      ["name", info.name], ["version", info.version], ["protocol", info.protocol],
      ["configuration", info.config_file],
      ["hash", info.config_hash ? String(info.config_hash).slice(0, 16) : null],
      ["started", formatTime(info.started_at)], ["uptime", formatDuration(info.uptime_s)],
      ["listening", info.listen], ["sign-in", info.auth_required ? "token required" : "open"],
      ["signed in as", info.user ? `${info.user} (${info.role})` : info.role],
    ]);
    const health = info.health ?? {};
    fillKeyValues(byId("srv-health"), [
      ["status", health.status],
      ...(health.checks ?? []).map((c) => [c.name, c.ok ? "ok" : `failing: ${c.message ?? ""}`]),
    ]);
    const pool = info.pool ?? {};
    fillKeyValues(byId("srv-pool"), [
      ["workers", pool.workers], ["in flight", `${pool.in_flight ?? "—"} of ${pool.max_in_flight ?? "—"}`],
      ["queued", `${pool.queued ?? "—"} of ${pool.queue_depth ?? "—"} per lane`],
      ["waiting unread (backpressure)", pool.waiting_unread],
      ...(pool.lanes ?? []).map((l) => [`${l.lane} lane`,
        `${countText(l.threads, "thread", "threads")}, ${l.admitted} of ${l.capacity} admitted, ${l.waiting} waiting, ` +
        `expected wait ${l.expected_wait_ms} ms`]),
      ...Object.entries(pool.costs_ms ?? {}).map(([name, ms]) => [`cost of ${name}`, `${ms} ms`]),
      ["BUSY answers", pool.busy_count], ["requests answered", pool.answered],
    ]);
    const conns = info.connections ?? [];
    replaceChildren(byId("srv-connections").tBodies[0], conns.length
      ? conns.map((c) => el("tr", {},
        el("td", {}, c.peer), el("td", { class: "num" }, String(c.requests)),
        el("td", { class: "num" }, String(c.in_flight)), el("td", {}, formatTime(c.since))))
      : el("tr", {}, el("td", { colspan: 4, class: "muted" }, "No clients connected.")));
    const reloads = info.reloads ?? [];
    replaceChildren(byId("srv-reloads").tBodies[0], reloads.length
      ? reloads.map((r) => el("tr", {},
        el("td", {}, formatTime(r.time)),
        el("td", {}, el("span", { class: "verdict-chip", dataset: { verdict: r.ok ? "pass" : "fail" } }, r.ok ? "applied" : "refused")),
        el("td", { class: "mono" }, r.config_hash ? String(r.config_hash).slice(0, 12) : "—"),
        el("td", { class: "wrap" }, r.message ?? "")))
      : el("tr", {}, el("td", { colspan: 4, class: "muted" }, "No reloads since the server started.")));
  }
}
