// The API calls of building inspections on the image (docs/console.md, "Building
// inspections"): the schema of every key, a whole inspection saved (created or replaced), a
// template trained from a rectangle of the image and the inspection's last reads. Through
// api.js's request(): the session, the 401 page and the X-Cellvision header as every call.

import { getJson, postJson, request } from "./api.js";

const enc = encodeURIComponent;
let schemaPromise = null;

export const buildApi = {
  /** GET /api/schema, asked once per page load (it changes only with the server's version). */
  schema() {
    if (schemaPromise === null) {
      schemaPromise = getJson("/api/schema").catch((exc) => {
        schemaPromise = null;   // asked again next time (a 401 before signing in)
        throw exc;
      });
    }
    return schemaPromise;
  },
  /** PUT /api/inspections/{name}: {config, why} -> {config_hash, backup, also_changed, notes, created}. */
  async putInspection(name, config, why) {
    const response = await request(`/api/inspections/${enc(name)}`, {
      method: "PUT",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ config, why }),
    });
    return response.json();
  },
  /** POST /api/inspections/{name}/save with the changed numeric keys (written in place). */
  saveOptions: (name, options, why) =>
    postJson(`/api/inspections/${enc(name)}/save`, { options, why }),
  /** POST /api/inspections/{name}/template -> {path, width, height, image}. */
  trainTemplate: (name, body) => postJson(`/api/inspections/${enc(name)}/template`, body),
  /** GET /api/inspections/{name}/reads?last=N -> {reads: [{result_id, time, text, step}]}. */
  reads: (name, last = 20) => getJson(`/api/inspections/${enc(name)}/reads?last=${last}`),
};
