// History: the configuration file's versions newest first (who, when, why, which inspections
// changed); a row opens the version's changes from the one before (added lines green, removed
// red) or its whole text; Revert writes that text as a new version after asking why, and the
// server reloads it. Paged with "Older"/"Newer"; the newest page follows new saves.

import { ApiError, getJson, postJson, query } from "./api.js";
import { byId, el, fillKeyValues, formatTime, replaceChildren } from "./dom.js";
import { Poller } from "./poll.js";
import { askWhy } from "./why.js";

const PAGE_SIZE = 50;

export const historyApi = {
  list: (params) => getJson(`/api/history${query(params)}`),
  version: (n) => getJson(`/api/history/${encodeURIComponent(n)}`),
  revert: (n, why) => postJson(`/api/history/${encodeURIComponent(n)}/revert`, { why }),
};

/** What a version is, for a person. */
export function kindText(version) {
  switch (version.kind) {
    case "save": return "Save";
    case "revert": return `Revert to version ${version.reverted_to}`;
    case "created_inspection": return "New inspection";
    case "edited_outside": return "Edited outside the console";
    case "original": return "The file as found";
    default: return String(version.kind);
  }
}

function changedText(version) {
  if (!version.parsed) return "the file does not parse as YAML";
  const names = version.inspections ?? [];
  return names.length ? names.join(", ") : "no inspection";
}

/** A unified diff as lines coloured by their first character. */
function diffLines(diff) {
  const out = [];
  for (const line of diff.split("\n")) {
    if (line === "") continue;
    let kind = "diff-same";
    if (line.startsWith("+++") || line.startsWith("---")) kind = "diff-file";
    else if (line.startsWith("@@")) kind = "diff-hunk";
    else if (line.startsWith("+")) kind = "diff-add";
    else if (line.startsWith("-")) kind = "diff-del";
    out.push(el("span", { class: `diff-line ${kind}` }, line), "\n");
  }
  return out;
}

export class HistoryPage {
  constructor() {
    this.before = [];        // the "before" of each newer page, for "Newer"
    this.beforeV = null;     // the page shown: null = the newest
    this.nextBefore = null;
    this.openV = null;
    this.reverting = false;
    this.wired = false;
    this.shown = "";         // what the table shows, so that a poll does not rebuild it
    this.poller = new Poller(() => (this.beforeV === null ? this.loadPage() : null), 5000);
  }

  start() {
    if (!this.wired) this.wire();
    this.poller.start();
  }

  stop() {
    this.poller.stop();
  }

  wire() {
    this.wired = true;
    byId("history-older").addEventListener("click", () => {
      if (this.nextBefore === null) return;
      this.before.push(this.beforeV);
      this.beforeV = this.nextBefore;
      this.loadPage();
    });
    byId("history-newer").addEventListener("click", () => {
      if (!this.before.length) return;
      this.beforeV = this.before.pop();
      this.loadPage();
    });
    byId("hd-close").addEventListener("click", () => this.close());
    for (const id of ["hd-view-diff", "hd-view-text"]) {
      byId(id).addEventListener("change", () => this.showView());
    }
    byId("history-revert").addEventListener("click", () => this.revert());
  }

  say(text, isError = false) {
    byId("history-status").textContent = isError ? "" : text;
    byId("history-error").textContent = isError ? text : "";
  }

  async loadPage() {
    let reply;
    try {
      reply = await historyApi.list({ before: this.beforeV, limit: PAGE_SIZE });
    } catch (exc) {
      if (!(exc instanceof ApiError && exc.status === 401)) this.say(exc.message, true);
      return;
    }
    this.nextBefore = reply.next_before;
    byId("history-older").disabled = reply.next_before === null;
    byId("history-newer").disabled = this.before.length === 0;
    byId("history-page-label").textContent =
      this.beforeV === null ? "Newest" : `Before version ${this.beforeV}`;
    byId("history-empty").hidden = reply.versions.length > 0;
    const key = JSON.stringify(reply.versions.map((v) => v.version)) + String(this.openV);
    if (key === this.shown) return;
    this.shown = key;
    replaceChildren(byId("history-body"), reply.versions.map((v) => this.row(v)));
  }

  row(version) {
    const open = () => this.open(version.version);
    const tr = el(
      "tr",
      {
        class: "history-row",
        id: `history-row-${version.version}`,
        dataset: { version: version.version, kind: version.kind },
        tabindex: "0",
        "aria-selected": version.version === this.openV ? "true" : "false",
        onclick: open,
        onkeydown: (event) => { if (event.key === "Enter") open(); },
      },
      el("td", { class: "num" }, String(version.version)),
      el("td", { class: "history-time" }, formatTime(version.time)),
      el("td", { class: "history-who" }, version.who),
      el("td", {},
        el("span", { class: "history-kind" }, kindText(version)),
        el("span", { class: "history-changed" }, changedText(version))),
      el("td", { class: "history-why" }, version.why || "—"),
    );
    return tr;
  }

  async open(number) {
    let version;
    try {
      version = await historyApi.version(number);
    } catch (exc) {
      if (!(exc instanceof ApiError && exc.status === 401)) this.say(exc.message, true);
      return;
    }
    this.openV = number;
    this.openVersion = version;
    for (const tr of byId("history-body").querySelectorAll("tr")) {
      tr.setAttribute("aria-selected", tr.dataset.version === String(number) ? "true" : "false");
    }
    byId("hd-title").textContent = `Version ${version.version}`;
    byId("hd-kind").textContent = kindText(version);
    fillKeyValues(byId("hd-meta"), [
      ["When", formatTime(version.time)],
      ["Who", version.who],
      ["Why", version.why || "—"],
      ["Inspections changed", changedText(version)],
      ["Configuration hash", version.config_hash],
      ["Compared with", version.previous === null ? "nothing (the oldest kept)" : `version ${version.previous}`],
    ]);
    replaceChildren(byId("hd-diff"), version.diff ? diffLines(version.diff) : "No change from the previous version.");
    byId("hd-text").textContent = version.text;
    byId("hd-current").hidden = !version.is_file;
    byId("history-revert").disabled = version.is_file;
    byId("history-detail").hidden = false;
    this.showView();
  }

  showView() {
    const text = byId("hd-view-text").checked;
    byId("hd-text").hidden = !text;
    byId("hd-diff").hidden = text;
  }

  close() {
    this.openV = null;
    byId("history-detail").hidden = true;
    for (const tr of byId("history-body").querySelectorAll("tr")) tr.setAttribute("aria-selected", "false");
  }

  async revert() {
    const number = this.openV;
    if (number === null || this.reverting) return;
    const why = await askWhy({
      title: `Revert to version ${number}?`,
      detail: `The configuration file gets version ${number}'s text again (as a new version) and the server reloads it.`,
      action: "Revert",
    });
    if (why === null) return;
    this.reverting = true;
    byId("history-revert").disabled = true;
    this.say(`Reverting to version ${number}…`);
    try {
      const reply = await historyApi.revert(number, why);
      if (reply.changed) {
        this.say(`Reverted to version ${number}: saved as version ${reply.version} and reloaded ` +
          `(configuration ${String(reply.config_hash).slice(0, 12)}).` +
          (reply.notes?.length ? ` Reload: ${reply.notes.join("; ")}.` : ""));
        this.before = [];
        this.beforeV = null;
        this.shown = "";
        await this.loadPage();
        await this.open(reply.version);
      } else {
        this.say(reply.message);
      }
    } catch (exc) {
      if (!(exc instanceof ApiError && exc.status === 401)) this.say(`Refused (${exc.code}): ${exc.message}`, true);
    } finally {
      this.reverting = false;
      if (this.openVersion) byId("history-revert").disabled = Boolean(this.openVersion.is_file && this.openV === this.openVersion.version);
    }
  }
}
