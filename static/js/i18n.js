// The participant pages' words: the catalogue of the session's language, loaded as JSON from GET
// /api/messages/{language} (the server's gettext catalogues, server/i18n.py; the pages carry no texts of their own).
// t("key", {name: value}) fills {name} placeholders; a plural text is picked by the count's CLDR plural category
// (Intl.PluralRules). Elements marked data-i18n="key" get the text, data-i18n-<attribute>="key" an attribute. A text
// may hold <kbd>, <strong>, <em> and <span id="..."> markup, built as elements (never parsed as HTML).

const RETRY_MS = [300, 1000, 3000, 5000];
const RICH = /<(kbd|strong|em|span)(?: id="([a-z0-9-]+)")?>(.*?)<\/\1>/gs;

let catalogue = { language: "en", direction: "ltr", messages: {}, fallback: [] };
let fallback = new Set();
let rules = new Intl.PluralRules("en");
let numbers = new Intl.NumberFormat("en", { maximumFractionDigits: 2, useGrouping: false });
const loading = new Map();

/** The catalogue's language ("de"); "en" until one is loaded. */
export function language() {
  return catalogue.language;
}

/** A number with exactly `digits` decimals, as the language writes it ("1,8" in German). */
export function decimal(value, digits) {
  return new Intl.NumberFormat(catalogue.language, { minimumFractionDigits: digits, maximumFractionDigits: digits })
    .format(value);
}

/** Marks a key used by name elsewhere (a table of keys), so that extraction finds it. */
export function N_(key) {
  return key;
}

function fill(text, params) {
  return text.replace(/\{(\w+)\}/g, (whole, name) => {
    if (!(name in params)) return whole;
    const value = params[name];
    return typeof value === "number" ? numbers.format(value) : String(value);
  });
}

/** The text of `key` with its placeholders filled (the key itself when the catalogue has no such text). */
export function t(key, params = {}) {
  const entry = catalogue.messages[key];
  if (entry === undefined) return key;
  const text = typeof entry === "string" ? entry : entry[rules.select(Number(params.count ?? 0))] ?? entry.other;
  const filled = fill(text, params);
  // An English text on a right-to-left page: isolated, so that its words and punctuation keep their order.
  return catalogue.direction === "rtl" && fallback.has(key) ? `\u2068${filled}\u2069` : filled;
}

/** A plural text: the form for `count` (also {count} in it). */
export function tn(key, count, params = {}) {
  return t(key, { ...params, count });
}

/** Put a text with its markup (kbd, strong, em, span with an id) into `element` as elements. */
export function setRich(element, text) {
  const nodes = [];
  let at = 0;
  for (const match of text.matchAll(RICH)) {
    if (match.index > at) nodes.push(text.slice(at, match.index));
    const inner = document.createElement(match[1]);
    if (match[2]) inner.id = match[2];
    inner.textContent = match[3];
    nodes.push(inner);
    at = match.index + match[0].length;
  }
  if (at < text.length) nodes.push(text.slice(at));
  element.replaceChildren(...nodes);
}

/** Fill every element under `root` marked data-i18n (text) or data-i18n-<attribute> (that attribute). */
export function translatePage(root = document) {
  for (const element of root.querySelectorAll("*")) {
    for (const name of element.getAttributeNames()) {
      if (!name.startsWith("data-i18n")) continue;
      const key = element.getAttribute(name);
      if (name === "data-i18n") setRich(element, t(key));
      else element.setAttribute(name.slice("data-i18n-".length), t(key));
    }
  }
}

async function fetchCatalogue(wanted) {
  for (let attempt = 0; ; attempt += 1) {
    try {
      const response = await fetch(`/api/messages/${encodeURIComponent(wanted)}`,
        { headers: { Accept: "application/json" }, credentials: "same-origin" });
      if (response.ok) return await response.json();
      if (response.status < 500 && response.status !== 429) wanted = "en"; // a tag the server refuses: English
    } catch (_err) {
      // offline for a moment: try again
    }
    await new Promise((resolve) => setTimeout(resolve, RETRY_MS[Math.min(attempt, RETRY_MS.length - 1)]));
  }
}

/** Load the catalogue of `wanted` (once per language), set <html lang dir> and translate the page. */
export function loadMessages(wanted) {
  if (!loading.has(wanted)) {
    loading.set(wanted, fetchCatalogue(wanted).then((loaded) => {
      catalogue = loaded;
      fallback = new Set(loaded.fallback || []);
      rules = new Intl.PluralRules(loaded.language);
      numbers = new Intl.NumberFormat(loaded.language, { maximumFractionDigits: 2, useGrouping: false });
      document.documentElement.lang = loaded.language;
      document.documentElement.dir = loaded.direction;
      translatePage(document);
      return loaded.language;
    }));
  }
  return loading.get(wanted);
}
