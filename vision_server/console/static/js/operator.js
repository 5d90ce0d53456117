// Operator: the calls robots post when a skill cannot go on (protocol OPERATOR_CALL, SPEC §6.6),
// newest first, each with its images (the failing overlay), the skill's message, how long the
// robot has waited, and one big button per allowed choice. Polled every second; the tab's badge
// counts open calls on every page.

import { api, ApiError } from "./api.js";
import { byId, el, formatDuration, replaceChildren } from "./dom.js";
import { Poller } from "./poll.js";

const CHOICE_TEXT = { retry: "Retry", continue: "Continue", abort: "Abort" };
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
    this.shown = "";      // the ids shown, so that images are not reloaded every second
    this.sending = new Set();
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
      dataset: { call: call.id, choice }, onclick: () => this.answer(call.id, choice),
    }, CHOICE_TEXT[choice] ?? choice));
    const what = [call.skill, call.inspection].filter(Boolean).join(" · ");
    return el("article", { class: "card operator-call", dataset: { call: call.id } },
      el("div", { class: "operator-media" },
        images.length ? images : el("p", { class: "muted" }, "No image was sent with this call.")),
      el("div", { class: "operator-body" },
        el("div", { class: "card-head" },
          el("h2", {}, what || "Operator needed"),
          el("span", { class: "tag" }, `#${call.id}`)),
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

  async answer(id, choice) {
    if (this.sending.has(id)) return;
    this.sending.add(id);
    for (const b of document.querySelectorAll(`.btn-choice[data-call="${id}"]`)) b.disabled = true;
    try {
      await api.answerCall(id, choice);
      this.say(`Call #${id}: answered ${CHOICE_TEXT[choice] ?? choice}.`, false);
    } catch (exc) {
      // 409: someone else answered first, or the robot stopped waiting; the message says which.
      this.say(exc.message, true);
    } finally {
      this.sending.delete(id);
      this.shown = "";
      this.poller.kick();
    }
  }

  say(text, isError) {
    const line = byId("operator-status");
    line.textContent = text;
    line.className = isError ? "error-text" : "ok-text";
  }
}
