// The reason asked before the configuration file changes (a save, a revert): an in-page dialog
// (#why-dialog) whose confirm button stays off until a reason is typed. The reason is kept in
// the configuration's history with who made the change and when (docs/console.md, "History").

import { byId } from "./dom.js";

export const MAX_WHY = 500;

let pending = null;   // the open question's resolve(), or null
let wired = false;

function finish(value) {
  const dialog = byId("why-dialog");
  if (dialog.open) dialog.close();
  const resolve = pending;
  pending = null;
  if (resolve) resolve(value);
}

function check() {
  const text = byId("why-text").value.trim();
  byId("why-ok").disabled = text === "" || text.length > MAX_WHY;
  byId("why-error").textContent = text.length > MAX_WHY ? `At most ${MAX_WHY} characters.` : "";
}

function wire() {
  wired = true;
  byId("why-text").addEventListener("input", check);
  byId("why-form").addEventListener("submit", (event) => {
    event.preventDefault();
    const text = byId("why-text").value.trim();
    if (text === "") {
      byId("why-error").textContent = "Say why: the history keeps the reason with the change.";
      return;
    }
    finish(text.slice(0, MAX_WHY));
  });
  byId("why-cancel").addEventListener("click", () => finish(null));
  // Escape closes the dialog: the question is answered "cancel".
  byId("why-dialog").addEventListener("cancel", (event) => {
    event.preventDefault();
    finish(null);
  });
}

/**
 * Ask why. Resolves to the reason (trimmed, non-empty), or null when cancelled.
 * ``title``: the question; ``detail``: what will happen; ``action``: the confirm button's text.
 */
export function askWhy({ title = "Why this change?", detail = "", action = "Save" } = {}) {
  if (!wired) wire();
  if (pending) finish(null);
  byId("why-title").textContent = title;
  byId("why-detail").textContent = detail;
  byId("why-detail").hidden = detail === "";
  byId("why-ok").textContent = action;
  byId("why-text").value = "";
  byId("why-error").textContent = "";
  check();
  const dialog = byId("why-dialog");
  const answer = new Promise((resolve) => { pending = resolve; });
  dialog.showModal();
  byId("why-text").focus();
  return answer;
}
