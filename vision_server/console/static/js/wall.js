// The wall screen (#/online: every camera; #/online/CAMERA: one): the online view of the Cameras
// page for a 1920x1080 screen on the floor, large type and no top bar. Once open it needs no
// mouse: it follows the cell by itself; keys 1-9 show the n-th camera alone, 0 every camera,
// Escape goes back to the Cameras page.

import { CamerasPage } from "./cameras.js";

export class WallPage {
  constructor() {
    this.page = new CamerasPage({ wall: true, grid: "online-cards", empty: "online-empty" });
    this.onKey = (event) => this.key(event);
    this.onHash = () => {
      if (location.hash.startsWith("#/online")) this.page.refresh();
    };
  }

  start() {
    document.body.classList.add("wall");
    document.addEventListener("keydown", this.onKey);
    window.addEventListener("hashchange", this.onHash);
    this.page.start();
  }

  stop() {
    document.body.classList.remove("wall");
    document.removeEventListener("keydown", this.onKey);
    window.removeEventListener("hashchange", this.onHash);
    this.page.stop();
  }

  key(event) {
    // Typing in a field is not a command; a checkbox (the graphics toggles) takes no keys.
    const typing = event.target instanceof HTMLInputElement && event.target.type !== "checkbox";
    if (typing || event.altKey || event.ctrlKey || event.metaKey) return;
    if (event.key === "Escape") {
      location.hash = "#/cameras";
    } else if (event.key === "0") {
      location.hash = "#/online";
    } else if (/^[1-9]$/.test(event.key)) {
      const names = [...this.page.allNames];
      const name = names[Number(event.key) - 1];
      if (name !== undefined) location.hash = `#/online/${encodeURIComponent(name)}`;
    }
  }
}
