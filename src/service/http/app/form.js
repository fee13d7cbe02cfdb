// The options form, built from the `Options` schema of the server's OpenAPI document, so
// the form offers exactly what the API takes. Only values changed from their defaults are
// sent.

// Resolve a `$ref` (and a property's own default/description around it).
function resolve(doc, s) {
  if (s && s.$ref) {
    const target = s.$ref.split("/").slice(1).reduce((o, k) => o[k], doc);
    return { ...resolve(doc, target), ...Object.fromEntries(Object.entries(s).filter(([k]) => k !== "$ref")) };
  }
  return s;
}

const types = (s) => (Array.isArray(s.type) ? s.type : [s.type]);

let serial = 0;

function field(doc, name, s, path) {
  s = resolve(doc, s);
  const id = `opt-${path.join("-")}-${serial++}`;
  const wrap = document.createElement("div");
  wrap.className = "option";
  const label = document.createElement("label");
  label.htmlFor = id;
  label.textContent = name.replace(/_/g, " ");
  if (s.description) {
    const hint = document.createElement("span");
    hint.className = "hint";
    hint.textContent = ` ${s.description.split("\n")[0]}`;
    label.append(hint);
  }
  if (s.type === "object" && s.properties) {
    const set = document.createElement("fieldset");
    const legend = document.createElement("legend");
    legend.textContent = label.textContent;
    set.append(legend);
    for (const [k, v] of Object.entries(s.properties)) set.append(field(doc, k, v, [...path, k]));
    return set;
  }
  let input;
  if (s.enum) {
    input = document.createElement("select");
    for (const v of s.enum) {
      const o = document.createElement("option");
      o.value = o.textContent = v;
      o.selected = v === s.default;
      input.append(o);
    }
    input.dataset.kind = "enum";
  } else if (types(s).includes("array") && s.items && resolve(doc, s.items).enum) {
    // A set of names (the outputs): checkboxes, none ticked = the server's default set.
    const set = document.createElement("fieldset");
    set.className = "checks";
    set.dataset.path = path.join(".");
    set.dataset.kind = "set";
    const legend = document.createElement("legend");
    legend.textContent = `${label.textContent} (none ticked: the default set)`;
    set.append(legend);
    for (const v of resolve(doc, s.items).enum) {
      const l = document.createElement("label");
      const c = document.createElement("input");
      c.type = "checkbox";
      c.value = v;
      l.append(c, ` ${v}`);
      set.append(l);
    }
    return set;
  } else if (types(s).includes("array")) {
    input = document.createElement("input");
    input.type = "text";
    input.placeholder = (s.default || []).join(", ");
    input.dataset.kind = "numbers";
  } else if (types(s).some((t) => t === "number" || t === "integer")) {
    input = document.createElement("input");
    input.type = "number";
    input.step = types(s).includes("integer") ? "1" : "any";
    if (s.minimum != null) input.min = s.minimum;
    input.placeholder = s.default == null ? "automatic" : String(s.default);
    input.dataset.kind = types(s).includes("integer") ? "integer" : "number";
  } else {
    input = document.createElement("input");
    input.type = "text";
    input.dataset.kind = "text";
  }
  input.id = id;
  input.dataset.path = path.join(".");
  input.dataset.default = JSON.stringify(s.default ?? null);
  wrap.append(label, input);
  return wrap;
}

// Fill `root` with the form; returns the Options schema.
export function buildOptionsForm(root, doc) {
  const schema = resolve(doc, doc.components.schemas.Options);
  for (const [k, v] of Object.entries(schema.properties)) root.append(field(doc, k, v, [k]));
  return schema;
}

// The options to send: only the fields that differ from their defaults.
export function readOptions(root) {
  const out = {};
  const put = (path, v) => {
    const keys = path.split(".");
    let o = out;
    for (const k of keys.slice(0, -1)) o = o[k] ??= {};
    o[keys.at(-1)] = v;
  };
  for (const el of root.querySelectorAll("[data-path]")) {
    const path = el.dataset.path;
    const kind = el.dataset.kind;
    if (kind === "set") {
      const ticked = [...el.querySelectorAll("input:checked")].map((c) => c.value);
      if (ticked.length) put(path, ticked);
      continue;
    }
    const def = JSON.parse(el.dataset.default);
    const raw = el.value.trim();
    if (kind === "enum") {
      if (raw !== def) put(path, raw);
    } else if (raw === "") {
      continue;
    } else if (kind === "numbers") {
      const v = raw.split(/[\s,]+/).filter(Boolean).map(Number);
      if (v.some((x) => !Number.isFinite(x))) throw new Error(`${path}: "${raw}" is not a list of numbers`);
      put(path, v);
    } else if (kind === "number" || kind === "integer") {
      const v = Number(raw);
      if (!Number.isFinite(v) || (kind === "integer" && !Number.isInteger(v))) {
        throw new Error(`${path}: "${raw}" is not ${kind === "integer" ? "a whole number" : "a number"}`);
      }
      if (v !== def) put(path, v);
    } else {
      put(path, raw);
    }
  }
  return out;
}
