// The study configuration as JSON in a text area, validated by the server on save. The
// server's 422 problems ("blocks.0.schedule.n_low: Input should be ...") are listed beside the
// editor; each one's location button selects that place in the text.

import { $, el, setText, showError } from "./admin-ui.js";

export class ConfigEditor {
  constructor(app) {
    this.app = app;
    this.saved = "";
    $("config-save").addEventListener("click", () => this.save());
    $("config-reset").addEventListener("click", () => this.load(this.app.study));
  }

  enter(study) {
    if (this.slug !== study.slug || $("config-editor").value === this.saved) this.load(study);
    this.slug = study.slug;
  }

  leave() {}

  load(study) {
    this.saved = JSON.stringify(study.config, null, 2);
    $("config-editor").value = this.saved;
    this.showProblems(null);
    setText($("config-status"), "");
  }

  async save() {
    setText($("config-status"), "");
    let config;
    try {
      config = JSON.parse($("config-editor").value);
    } catch (err) {
      this.showProblems(`The text is not valid JSON: ${err.message}`, []);
      return;
    }
    $("config-save").disabled = true;
    try {
      const before = this.app.study.version;
      const path = `/api/admin/studies/${encodeURIComponent(this.app.study.slug)}/config`;
      const study = await this.app.api.request("PUT", path, { body: { config } });
      this.app.setStudy(study);
      this.load(study);
      setText($("config-status"), study.version > before
        ? `Saved as version ${study.version} (participants keep the version they started with).`
        : `Saved (version ${study.version}).`);
    } catch (err) {
      const problems = err.body && Array.isArray(err.body.problems) ? err.body.problems : [];
      const detail = problems.length ? `The server refused the configuration (HTTP ${err.status}): `
        + `${problems.length} problem${problems.length === 1 ? "" : "s"}.` : null;
      if (detail) this.showProblems(detail, problems);
      else {
        this.showProblems(null);
        showError($("config-problems-detail"), "The server refused the configuration", err);
        $("config-problems-none").hidden = true;
      }
    } finally {
      $("config-save").disabled = false;
    }
  }

  /** detail: a sentence (or null to clear); problems: "location: message" strings from the server. */
  showProblems(detail, problems = []) {
    setText($("config-problems-detail"), detail || "");
    $("config-problems-none").hidden = Boolean(detail);
    $("config-problems").replaceChildren(...problems.map((problem) => {
      const split = problem.indexOf(": ");
      const where = split > 0 ? problem.slice(0, split) : "(document)";
      const message = split > 0 ? problem.slice(split + 2) : problem;
      const path = where.split(".").filter(Boolean);
      while (["body", "config"].includes(path[0])) path.shift(); // request-level prefixes
      const go = el("button", { type: "button", class: "link-button", title: "Show this place in the editor" },
        el("code", {}, path.join(".") || "(document)"));
      go.addEventListener("click", () => this.select(path));
      return el("li", {}, go, el("span", {}, message));
    }));
  }

  select(path) {
    const editor = $("config-editor");
    const range = locate(editor.value, path);
    editor.focus();
    if (!range) return;
    editor.setSelectionRange(range[0], range[1]);
    const line = editor.value.slice(0, range[0]).split("\n").length;
    const lineHeight = parseFloat(getComputedStyle(editor).lineHeight) || 18;
    editor.scrollTop = Math.max(0, (line - 4) * lineHeight);
  }
}

/**
 * [start, end) of the member (key and value) or array element at `path` in the JSON `text`, or of the
 * deepest one found along it. Path
 * segments that are not in the document (pydantic adds union tags such as "random_assist")
 * are skipped.
 */
export function locate(text, path) {
  let i = 0;
  let found = null;
  const space = () => {
    while (i < text.length && /\s/.test(text[i])) i += 1;
  };
  const string = () => {
    const start = i;
    for (i += 1; i < text.length && text[i] !== '"'; i += 1) if (text[i] === "\\") i += 1;
    i += 1;
    return JSON.parse(text.slice(start, i));
  };
  const skip = () => {
    space();
    if (text[i] === '"') return void string();
    if (text[i] !== "{" && text[i] !== "[") {
      while (i < text.length && !/[\s,\]}]/.test(text[i])) i += 1;
      return undefined;
    }
    let depth = 0;
    do {
      if (text[i] === '"') {
        string();
        continue;
      }
      if (text[i] === "{" || text[i] === "[") depth += 1;
      if (text[i] === "}" || text[i] === "]") depth -= 1;
      i += 1;
    } while (depth > 0 && i < text.length);
    return undefined;
  };
  const descend = (segments) => {
    space();
    const open = text[i];
    if (!segments.length || (open !== "{" && open !== "[")) return;
    const start = i;
    for (let s = 0; s < segments.length; s += 1) {
      i = start + 1;
      for (let index = 0; ; index += 1) {
        space();
        if (text[i] === "}" || text[i] === "]" || i >= text.length) break;
        const memberStart = i;
        const key = open === "{" ? string() : String(index);
        if (open === "{") {
          space();
          i += 1; // the colon
        }
        if (key === String(segments[s])) {
          space();
          const valueStart = i;
          const rest = segments.slice(s + 1);
          if (rest.length) {
            found = [open === "{" ? memberStart : valueStart, valueStart];
            return descend(rest);
          }
          skip();
          found = [open === "{" ? memberStart : valueStart, i];
          return undefined;
        }
        skip();
        space();
        if (text[i] === ",") i += 1;
      }
    }
  };
  try {
    descend(path);
  } catch (_err) {
    return found; // the text does not parse past here: the deepest place found so far
  }
  return found;
}
