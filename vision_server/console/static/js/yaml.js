// A small YAML writer for the console's own display: the inspection's configuration as loaded
// and the snippet of changed keys. Values are JSON data (strings, numbers, booleans, null, lists,
// mappings); strings are quoted whenever plain YAML could read them as something else.

const PLAIN = /^[A-Za-z_][A-Za-z0-9_./-]*$/;
const RESERVED = /^(true|false|yes|no|on|off|null|~)$/i;

export function scalar(value) {
  if (value === null || value === undefined) return "null";
  if (typeof value === "number") return Number.isFinite(value) ? String(value) : (value > 0 ? ".inf" : value < 0 ? "-.inf" : ".nan");
  if (typeof value === "boolean") return value ? "true" : "false";
  const text = String(value);
  return PLAIN.test(text) && !RESERVED.test(text) ? text : JSON.stringify(text);
}

function isFlat(list) {
  return list.every((v) => v === null || typeof v !== "object");
}

/** ``value`` as YAML lines, indented by ``indent`` spaces. */
export function toYaml(value, indent = 0) {
  const pad = " ".repeat(indent);
  if (Array.isArray(value)) {
    if (isFlat(value)) return `${pad}[${value.map(scalar).join(", ")}]`;
    return value.map((item) => {
      const inner = toYaml(item, indent + 2).trimStart();
      return `${pad}- ${inner}`;
    }).join("\n");
  }
  if (value !== null && typeof value === "object") {
    const lines = [];
    for (const [key, item] of Object.entries(value)) {
      if (item !== null && typeof item === "object" && !(Array.isArray(item) && isFlat(item))) {
        if (Array.isArray(item) && item.length === 0) lines.push(`${pad}${scalar(key)}: []`);
        else if (!Array.isArray(item) && Object.keys(item).length === 0) lines.push(`${pad}${scalar(key)}: {}`);
        else lines.push(`${pad}${scalar(key)}:\n${toYaml(item, indent + 2)}`);
      } else {
        lines.push(`${pad}${scalar(key)}: ${toYaml(item, 0)}`);
      }
    }
    return lines.join("\n");
  }
  return `${pad}${scalar(value)}`;
}
