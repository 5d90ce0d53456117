// A Python regular expression (a code's ``expect: {regex: ...}``, matched on the server with
// Python's ``re.fullmatch``) checked in the page with JavaScript's RegExp. The two agree on the
// common syntax (classes, groups, quantifiers, anchors, \d \w \s, look-around, \xNN). Translated
// here: named groups ``(?P<name>...)`` and ``(?P=name)``, ``\A`` and ``\Z``, and leading inline
// flags ``(?i)``, ``(?s)``, ``(?m)``, ``(?x)`` (verbose: whitespace and # comments dropped).
// Not the same, said to the user as a note: Python's possessive quantifiers and atomic groups
// (3.11), conditionals ``(?(1)...)``, ``\Z`` inside a class and Unicode categories differ; the
// server's check on the next try is the one that counts.

const UNSUPPORTED = [
  [/\(\?\(/, "conditional groups (?(...)...) are Python-only"],
  [/\(\?>/, "atomic groups (?>...) are checked by the server only"],
  [/[*+?}]\+/, "possessive quantifiers (*+, ++, ?+) are checked by the server only"],
];

/**
 * ``{ok, regexp, error, note}``: ``regexp`` is the JS RegExp that full-matches as Python's
 * ``re.fullmatch`` would, ``error`` why the pattern does not compile, ``note`` a difference the
 * page cannot check.
 */
export function compilePython(pattern) {
  let source = String(pattern);
  let flags = "u";
  const inline = source.match(/^\(\?([aiLmsux]+)\)/);
  if (inline) {
    source = source.slice(inline[0].length);
    for (const f of inline[1]) {
      if (f === "i") flags += "i";
      else if (f === "s") flags += "s";
      else if (f === "m") flags += "m";
      else if (f === "x") source = stripVerbose(source);
    }
  }
  for (const [re, note] of UNSUPPORTED) {
    if (re.test(source)) return { ok: true, regexp: null, error: null, note };
  }
  source = source
    .replace(/\(\?P</g, "(?<")
    .replace(/\(\?P=([A-Za-z_][A-Za-z0-9_]*)\)/g, "\\k<$1>")
    .replace(/\\A/g, "^")
    .replace(/\\Z/g, "$");
  try {
    const regexp = new RegExp(`^(?:${source})$`, flags);
    return { ok: true, regexp, error: null, note: null };
  } catch (exc) {
    // Without the u flag a few escapes Python takes (\- outside a class) are fine: retry.
    try {
      const regexp = new RegExp(`^(?:${source})$`, flags.replace("u", ""));
      return { ok: true, regexp, error: null, note: null };
    } catch {
      return { ok: false, regexp: null, error: String(exc.message).replace(/^Invalid regular expression: /, ""), note: null };
    }
  }
}

function stripVerbose(source) {
  let out = "";
  let inClass = false;
  for (let i = 0; i < source.length; i++) {
    const c = source[i];
    if (c === "\\") { out += c + (source[i + 1] ?? ""); i++; continue; }
    if (c === "[") inClass = true;
    else if (c === "]") inClass = false;
    if (!inClass && /\s/.test(c)) continue;
    if (!inClass && c === "#") {
      while (i < source.length && source[i] !== "\n") i++;
      continue;
    }
    out += c;
  }
  return out;
}
