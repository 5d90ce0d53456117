// Operator: the calls robots post when a skill cannot go on (protocol OPERATOR_CALL, SPEC §6.6),
// newest first, each with its images (the failing overlay), the skill's message, how long the
// robot has waited, and one big button per allowed choice. Polled every second; the tab's badge
// counts open calls on every page. An answer the server wants a reason for (console:
// operator_reason_for, by default "continue": accepting a failed part) opens the answer dialog:
// a preset or typed reason, then a confirmation, and only then goes to the robot. The latest
// answers are listed with who gave them and why.

import { api, ApiError } from "./api.js";
import { byId, el, formatDuration, replaceChildren } from "./dom.js";
import { Poller } from "./poll.js";

const CHOICE_TEXT = { retry: "Retry", continue: "Continue", abort: "Abort" };
const OUTCOME_TEXT = {
  expired: "nobody answered in time",
  withdrawn: "the robot withdrew it",
  stopped: "the server stopped",
};
const CHOICE_HELP = {
  retry: "the robot tries again (fix the part first)",
  continue: "accept the part and go on",
  abort: "stop the robot's task",
};

/** The number on the Operator tab: open calls, hidden at 0. */
export function setOperatorBadge(count) {
  const badge = byId("operator-badge");
  badge.textContent = String(count);
  badge.hidden = !(count > 0);
}

/** Keeps the tab's badge current while another page is shown. */
export const operatorBadge = new Poller(async () => {
  try {
    setOperatorBadge((await api.operatorCalls()).calls.length);
  } catch (exc) {
    if (!(exc instanceof ApiError)) throw exc;
  }
}, 3000);

export class OperatorPage {
  constructor() {
    this.poller = new Poller(() => this.refresh(), 1000);
    this.shown = null;    // the ids shown, so that images are not reloaded every second
    this.recentShown = "";
    this.sending = new Set();
    this.rules = { reason_for: ["continue"], reasons: [], max_reason_chars: 500 };
    this.pending = null;  // {id, choice} while the answer dialog is open
    this.wireDialog();
  }

  start() { this.poller.start(); }
  stop() { this.poller.stop(); }

  async refresh() {
    let reply;
    try {
      reply = await api.operatorCalls();
    } catch (exc) {
      if (!(exc instanceof ApiError && exc.status === 401)) this.say(exc.message, true);
      return;
    }
    setOperatorBadge(reply.calls.length);
    if (reply.answers) this.rules = reply.answers;
    this.showRecent(reply.recent ?? []);
    byId("operator-empty").hidden = reply.calls.length > 0;
    const ids = reply.calls.map((c) => c.id).join(",");
    if (ids !== this.shown) {
      this.shown = ids;
      replaceChildren(byId("operator-calls"), reply.calls.map((c) => this.card(c)));
    }
    for (const call of reply.calls) this.tick(call, reply.now);
  }

  card(call) {
    const images = call.images.map((image, i) => el("img", {
      class: "operator-image", src: image.url, alt: `${image.role} image ${i + 1} of call ${call.id}`,
      width: image.width || null, height: image.height || null,
    }));
    const buttons = call.choices.map((choice) => el("button", {
      type: "button", class: `btn btn-choice btn-${choice}`, title: CHOICE_HELP[choice] ?? "",
      dataset: { call: call.id, choice }, onclick: () => this.choose(call, choice),
    }, CHOICE_TEXT[choice] ?? choice));
    const what = [call.skill, call.inspection].filter(Boolean).join(" · ");
    return el("article", { class: "card operator-call", dataset: { call: call.id } },
      el("div", { class: "operator-media" },
        images.length ? images : el("p", { class: "muted" }, "No image was sent with this call.")),
      el("div", { class: "operator-body" },
        el("div", { class: "card-head" },
          el("span", { class: "operator-verdict" }, "FAIL"),
          el("h2", {}, what || "Operator needed"),
          el("span", { class: "tag" }, `#${call.id}`),
          call.result_id ? el("span", { class: "tag" }, `result ${call.result_id}`) : null),
        el("p", { class: "operator-message" }, call.message),
        el("p", { class: "muted" },
          "from ", el("span", { class: "mono" }, call.peer), " · waiting ",
          el("span", { class: "operator-waiting", dataset: { call: call.id } }, "—"),
          el("span", { class: "operator-expires", dataset: { call: call.id } }, "")),
        el("div", { class: "operator-choices" }, buttons)));
  }

  tick(call, now) {
    const waiting = document.querySelector(`.operator-waiting[data-call="${call.id}"]`);
    if (waiting) waiting.textContent = formatDuration(Math.max(now - call.posted_at, 0));
    const expires = document.querySelector(`.operator-expires[data-call="${call.id}"]`);
    if (expires) {
      expires.textContent = typeof call.expires_at === "number"
        ? ` · the robot gives up in ${formatDuration(Math.max(call.expires_at - now, 0))}` : "";
    }
  }

  /** A tap on a choice: at once, or through the reason and the confirmation. */
  choose(call, choice) {
    if (this.sending.has(call.id)) return;
    if ((this.rules.reason_for ?? []).includes(choice)) this.openDialog(call, choice);
    else this.answer(call.id, choice, "");
  }

  async answer(id, choice, reason) {
    if (this.sending.has(id)) return false;
    this.sending.add(id);
    for (const b of document.querySelectorAll(`.btn-choice[data-call="${id}"]`)) b.disabled = true;
    try {
      const reply = await api.answerCall(id, choice, reason);
      const who = reply.operator && reply.operator !== "console" ? ` as ${reply.operator}` : "";
      this.say(`Call #${id}: answered ${CHOICE_TEXT[choice] ?? choice}${who}.`, false);
      return true;
    } catch (exc) {
      // 409: someone else answered first, or the robot stopped waiting; the message says which.
      this.say(exc.message, true);
      return exc;
    } finally {
      this.sending.delete(id);
      // Redraw on the next round whatever it brings: also when no call is left ("" ids).
      this.shown = null;
      this.poller.kick();
    }
  }

  // -- the answer dialog: reason, then confirmation ------------------------------------------

  wireDialog() {
    const reason = byId("answer-reason");
    reason.addEventListener("input", () => this.reasonChanged());
    byId("answer-cancel").addEventListener("click", () => this.closeDialog());
    byId("answer-next").addEventListener("click", () => this.toConfirm());
    byId("answer-back").addEventListener("click", () => this.toReason());
    byId("answer-confirm").addEventListener("click", () => this.confirm());
    // Escape closes the dialog: nothing is sent.
    byId("answer-dialog").addEventListener("close", () => { this.pending = null; });
  }

  openDialog(call, choice) {
    this.pending = { id: call.id, choice };
    const text = CHOICE_TEXT[choice] ?? choice;
    byId("answer-title").textContent = `${text}: why?`;
    byId("answer-ask").textContent = choice === "continue"
      ? `Accepting the failed part of call #${call.id} needs a reason. Choose one or type it.`
      : `Answering ${text} to call #${call.id} needs a reason. Choose one or type it.`;
    const reason = byId("answer-reason");
    reason.value = "";
    reason.maxLength = this.rules.max_reason_chars ?? 500;
    replaceChildren(byId("answer-presets"), (this.rules.reasons ?? []).map((preset) => el("button", {
      type: "button", class: "btn reason-preset", "aria-pressed": "false",
      dataset: { reason: preset }, onclick: () => this.pickPreset(preset),
    }, preset)));
    byId("answer-error").textContent = "";
    this.toReason();
    const dialog = byId("answer-dialog");
    if (!dialog.open) dialog.showModal();
    reason.focus();
  }

  pickPreset(preset) {
    byId("answer-reason").value = preset;
    this.reasonChanged();
  }

  reasonChanged() {
    const value = byId("answer-reason").value.trim();
    byId("answer-next").disabled = value === "";
    for (const b of document.querySelectorAll("#answer-presets .reason-preset")) {
      b.setAttribute("aria-pressed", String(b.dataset.reason === value));
    }
  }

  toReason() {
    byId("answer-step-reason").hidden = false;
    byId("answer-step-confirm").hidden = true;
    this.reasonChanged();
  }

  toConfirm() {
    if (this.pending === null) return;
    const reason = byId("answer-reason").value.trim();
    if (reason === "") return;
    const { id, choice } = this.pending;
    const who = byId("signed-in-user").textContent;
    replaceChildren(byId("answer-summary"),
      el("strong", {}, `${CHOICE_TEXT[choice] ?? choice}`), ` call #${id}`,
      who ? ` as ${who}` : "", el("br"), "Reason: ", el("em", {}, reason));
    byId("answer-title").textContent = "Confirm";
    byId("answer-step-reason").hidden = true;
    byId("answer-step-confirm").hidden = false;
    byId("answer-confirm").focus();
  }

  async confirm() {
    if (this.pending === null) return;
    const { id, choice } = this.pending;
    const button = byId("answer-confirm");
    button.disabled = true;
    try {
      const done = await this.answer(id, choice, byId("answer-reason").value.trim());
      if (done === true) this.closeDialog();
      else byId("answer-error").textContent = done?.message ?? "The answer was not sent.";
    } finally {
      button.disabled = false;
    }
  }

  closeDialog() {
    this.pending = null;
    const dialog = byId("answer-dialog");
    if (dialog.open) dialog.close();
  }

  // -- the latest answers --------------------------------------------------------------------

  showRecent(recent) {
    const key = recent.map((r) => `${r.id}:${r.outcome}`).join(",");
    if (key === this.recentShown) return;
    this.recentShown = key;
    replaceChildren(byId("operator-recent"), recent.slice(0, 8).map((r) => el("li", {
      class: "recent-item", dataset: { call: r.id, outcome: r.outcome },
    },
    el("strong", {}, `#${r.id} `),
    r.outcome === "answered"
      ? [`${CHOICE_TEXT[r.choice] ?? r.choice} by ${r.operator ?? r.by ?? "?"}`,
        r.reason ? el("span", { class: "recent-reason" }, ` — ${r.reason}`) : null]
      : OUTCOME_TEXT[r.outcome] ?? r.outcome,
    el("span", { class: "muted" }, ` · ${r.message}`))));
  }

  say(text, isError) {
    const line = byId("operator-status");
    line.textContent = text;
    line.className = isError ? "error-text" : "ok-text";
  }
}
