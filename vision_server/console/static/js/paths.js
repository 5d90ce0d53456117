// Dotted key paths into a configuration mapping ("circle.min_radius_px", "band.center"), as the
// schema (GET /api/schema) names keys, and the small data helpers the inspection editor needs.
// Values are JSON data: what GET /api/inspections gives as ``config`` and a try's ``config`` takes.

/** A deep copy of JSON data (undefined stays undefined). */
export function clone(value) {
  return value === undefined ? undefined : JSON.parse(JSON.stringify(value));
}

export function isMapping(value) {
  return value !== null && typeof value === "object" && !Array.isArray(value);
}

/** The value at ``dotted`` in ``obj``, or undefined when a part of the path is missing. */
export function getPath(obj, dotted) {
  let current = obj;
  for (const part of dotted.split(".")) {
    if (!isMapping(current) || !Object.hasOwn(current, part)) return undefined;
    current = current[part];
  }
  return current;
}

/**
 * Set ``dotted`` in ``obj`` to ``value``, making the mappings on the way; ``undefined`` deletes
 * the key, and a mapping left empty by that is deleted too (``circle: {}`` means nothing).
 */
export function setPath(obj, dotted, value) {
  const parts = dotted.split(".");
  const chain = [obj];
  let current = obj;
  for (const part of parts.slice(0, -1)) {
    if (!isMapping(current[part])) {
      if (value === undefined) return;
      current[part] = {};
    }
    current = current[part];
    chain.push(current);
  }
  const last = parts[parts.length - 1];
  if (value === undefined) delete current[last];
  else current[last] = value;
  // Drop the mappings the deletion emptied, innermost first.
  for (let i = parts.length - 1; i > 0 && value === undefined; i--) {
    if (Object.keys(chain[i]).length > 0) break;
    delete chain[i - 1][parts[i - 1]];
  }
}

/** Every leaf of ``obj`` by its dotted path (lists are leaves). */
export function flatten(obj, prefix = "", into = new Map()) {
  for (const [key, value] of Object.entries(obj ?? {})) {
    const path = prefix ? `${prefix}.${key}` : key;
    if (isMapping(value) && Object.keys(value).length > 0) flatten(value, path, into);
    else into.set(path, value);
  }
  return into;
}

export function sameValue(a, b) {
  return JSON.stringify(a) === JSON.stringify(b);
}

/**
 * Whether a schema key applies to ``scope`` (the mapping that holds it): its ``when`` names
 * sibling keys and the value (or list of values) each must have; no ``when``: always.
 */
export function applies(key, scope, keys = []) {
  const when = key.when;
  if (!isMapping(when)) return true;
  for (const [sibling, wanted] of Object.entries(when)) {
    // A sibling not given has its default (units: px).
    const actual = getPath(scope, sibling) ?? keys.find((k) => k.key === sibling)?.default ?? undefined;
    const allowed = Array.isArray(wanted) ? wanted : [wanted];
    if (!allowed.some((w) => sameValue(w, actual))) return false;
  }
  return true;
}

/**
 * Drop from ``scope`` the values of ``keys`` whose ``when`` no longer holds (the keys of the
 * method or kind chosen before): the loader refuses them beside another method.
 */
export function prune(keys, scope) {
  for (const key of keys) {
    if (!applies(key, scope, keys) && getPath(scope, key.key) !== undefined) setPath(scope, key.key, undefined);
  }
}
