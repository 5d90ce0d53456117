// The console's entry point: the router between pages (#/cameras, #/inspections, #/results,
// #/server, #/operator, #/history, #/online: the wall screen), the login page shown whenever
// the API answers 401, and the status pill.

import { api, ApiError, onUnauthorized } from "./js/api.js";
import { byId } from "./js/dom.js";
import { Poller } from "./js/poll.js";
import { CamerasPage } from "./js/cameras.js";
import { InspectionsPage } from "./js/inspections.js";
import { ResultsPage } from "./js/results.js";
import { ServerPage, statusText } from "./js/server.js";
import { OperatorPage, operatorBadge } from "./js/operator.js";
import { HistoryPage } from "./js/history.js";
import { WallPage } from "./js/wall.js";
import { resetCounts } from "./js/online.js";

const pages = {
  cameras: new CamerasPage(),
  inspections: new InspectionsPage(),
  results: new ResultsPage(),
  server: new ServerPage(),
  operator: new OperatorPage(),
  history: new HistoryPage(),
  online: new WallPage(),
};
const DEFAULT_PAGE = "cameras";

let current = null;     // the name of the page shown
let locked = false;     // the login page is up

function pageFromHash() {
  const name = location.hash.replace(/^#\/?/, "").split("/")[0];
  return Object.hasOwn(pages, name) ? name : DEFAULT_PAGE;
}

function show(name) {
  if (locked) return;
  if (current !== null && current !== name) pages[current].stop();
  for (const section of document.querySelectorAll("section.page[data-page]")) {
    section.hidden = section.dataset.page !== name;
  }
  for (const link of document.querySelectorAll(".nav-link")) {
    const active = link.dataset.page === name;
    link.classList.toggle("active", active);
    if (active) link.setAttribute("aria-current", "page");
    else link.removeAttribute("aria-current");
  }
  if (current !== name) {
    current = name;
    pages[name].start();
  }
}

// -- status pill and banner ------------------------------------------------------------------

const statusPoller = new Poller(async () => {
  const pill = byId("status-pill");
  try {
    const info = await api.server();
    const { text, level } = statusText(info);
    pill.textContent = text;
    pill.dataset.level = level;
    byId("server-name").textContent = info.name ?? "";
    byId("logout").hidden = !info.auth_required;
    showSignedIn(info);
    // The session's role (operator, integrator, admin): an operator's page hides what it
    // may not do (the server refuses it anyway: 403).
    document.body.dataset.role = info.role ?? "admin";
    setBanner("");
  } catch (exc) {
    if (exc instanceof ApiError && exc.status === 401) return;
    pill.textContent = "unreachable";
    pill.dataset.level = "bad";
    setBanner(`The server does not answer: ${exc.message}`);
  }
}, 3000);

/** Who is signed in, in the header: the user's name and role, or the role of a token. */
function showSignedIn(info) {
  const who = byId("signed-in");
  who.hidden = !info.auth_required || !info.role;
  byId("signed-in-user").textContent = info.user ?? "";
  byId("signed-in-role").textContent = info.role ?? "";
}

export function setBanner(text) {
  const banner = byId("banner");
  banner.textContent = text;
  banner.hidden = text === "";
}

// -- login -----------------------------------------------------------------------------------

function lock() {
  if (locked) return;
  locked = true;
  if (current !== null) pages[current].stop();
  current = null;
  statusPoller.stop();
  operatorBadge.stop();
  for (const section of document.querySelectorAll("section.page")) section.hidden = true;
  byId("page-login").hidden = false;
  byId("nav").hidden = true;
  byId("logout").hidden = true;
  byId("signed-in").hidden = true;
  byId("signed-in-user").textContent = "";
  byId("status-pill").textContent = "signed out";
  byId("status-pill").dataset.level = "idle";
  byId("login-token").focus();
}

function unlock() {
  locked = false;
  byId("page-login").hidden = true;
  byId("nav").hidden = false;
  byId("login-error").textContent = "";
  for (const id of ["login-token", "login-user", "login-pin"]) byId(id).value = "";
  statusPoller.start();
  operatorBadge.start();
  show(pageFromHash());
}

async function submitLogin(event) {
  event.preventDefault();
  const button = byId("login-submit");
  button.disabled = true;
  byId("login-error").textContent = "";
  // Name and PIN, or a badge or token. A badge reader types into whichever field has the
  // focus: a name without a PIN and no token is taken as a badge.
  const user = byId("login-user").value.trim();
  const pin = byId("login-pin").value;
  let token = byId("login-token").value;
  const byName = user !== "" && pin !== "";
  if (!byName && token === "") token = user || pin;
  if (!byName && token === "") {
    byId("login-error").textContent = "Enter your name and PIN, or scan your badge.";
    button.disabled = false;
    return;
  }
  try {
    await api.login(byName ? { user, pin } : token);
    unlock();
  } catch (exc) {
    byId("login-error").textContent = exc instanceof ApiError && exc.status === 401
      ? (byName ? "That name and PIN do not match." : "That badge or token is not valid.")
      : exc.message;
    byId("login-pin").value = "";
  } finally {
    button.disabled = false;
  }
}

async function logout() {
  try {
    await api.logout();
  } finally {
    lock();
  }
}

// -- start -----------------------------------------------------------------------------------

onUnauthorized(lock);
byId("login-form").addEventListener("submit", submitLogin);
byId("logout").addEventListener("click", logout);
byId("online-reset-all").addEventListener("click", () => resetCounts(null));
window.addEventListener("hashchange", () => show(pageFromHash()));
// Polling stops while the tab is hidden: a console left open in a background tab costs nothing.
document.addEventListener("visibilitychange", () => {
  if (locked || current === null) return;
  if (document.hidden) {
    pages[current].stop();
    statusPoller.stop();
    operatorBadge.stop();
  } else {
    pages[current].start();
    statusPoller.start();
    operatorBadge.start();
  }
});
statusPoller.start();
operatorBadge.start();
show(pageFromHash());
