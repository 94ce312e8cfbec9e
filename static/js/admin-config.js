// The study designer: the configuration as a form generated from its JSON Schema (admin-designer-form.js) or,
// in the advanced view, as raw JSON text, with the same working document behind both (switching loses
// nothing); a debounced live check shows the server's problems beside their fields and the study's summary;
// saving adds a version (admin-versions.js lists them, diffs any two and duplicates the study).

import { DesignerForm } from "./admin-designer-form.js";
import { $, el, setText, showError } from "./admin-ui.js";
import { VersionsPanel } from "./admin-versions.js";

const AUTHOR_KEY = "trustlab.designer-author";
const CHECK_DELAY_MS = 400;
const VIEWS = ["form", "raw", "versions"];

export class ConfigEditor {
  constructor(app) {
    this.app = app;
    this.saved = "";
    this.view = "form";
    this.editView = "form"; // where the working document lives: the form or the raw text
    this.schema = null;
    this.checkTimer = null;
    this.checkSeq = 0;
    this.lastProblems = [];
    this.form = new DesignerForm($("designer-form"), () => this.edited());
    this.versions = new VersionsPanel(app, this);
    $("config-save").addEventListener("click", () => this.save());
    $("config-reset").addEventListener("click", () => this.load(this.app.study));
    $("config-editor").addEventListener("input", () => this.edited());
    for (const view of VIEWS) $(`view-${view}`).addEventListener("click", () => this.switchTo(view));
    const author = $("designer-author");
    author.value = localStorage.getItem(AUTHOR_KEY) || "";
    author.addEventListener("change", () => localStorage.setItem(AUTHOR_KEY, author.value.trim()));
  }

  enter(study) {
    const fresh = this.slug !== study.slug || !this.dirty();
    this.slug = study.slug;
    if (fresh) this.load(study);
    if (this.view === "versions") this.versions.refresh();
  }

  leave() {
    clearTimeout(this.checkTimer);
  }

  /** The working document (from the form or the text); throws SyntaxError when the text is not JSON. */
  document() {
    if (this.editView === "form" && this.form.ready) return this.form.getValue();
    return JSON.parse($("config-editor").value);
  }

  dirty() {
    try {
      return JSON.stringify(this.document()) !== JSON.stringify(JSON.parse(this.saved || "null"));
    } catch (_err) {
      return true;
    }
  }

  async load(study) {
    this.saved = JSON.stringify(study.config, null, 2);
    $("config-editor").value = this.saved;
    this.showProblems(null);
    setText($("config-problems-none"), "Checking…"); // not "no problems" before the server has looked
    setText($("config-status"), "");
    await this.fillForm(study.config);
    this.check();
  }

  async fillForm(config) {
    try {
      if (!this.schema) this.schema = await this.app.api.get("/api/admin/study-config-schema");
      if (!this.form.editor) {
        await this.form.build(this.schema, config);
        $("designer-form-loading").hidden = true;
      } else {
        this.form.setValue(config);
      }
    } catch (err) {
      showError($("designer-form-loading"), "The form could not be built; use the raw JSON view", err);
    }
  }

  // -- views ----------------------------------------------------------------------------
  /** Show the form, the raw JSON or the versions; the working document moves with it and loses nothing. */
  async switchTo(view) {
    if (view === this.view) return;
    if (view === "form" && this.editView === "raw") {
      let value;
      try {
        value = JSON.parse($("config-editor").value);
      } catch (err) {
        this.showProblems(`The text is not valid JSON (${err.message}): fix it before switching to the form.`);
        return;
      }
      this.form.setValue(value);
    }
    if (view === "raw" && this.editView === "form" && this.form.ready) {
      $("config-editor").value = JSON.stringify(this.form.getValue(), null, 2);
    }
    this.view = view;
    if (view !== "versions") this.editView = view;
    for (const name of VIEWS) {
      $(`view-${name}`).setAttribute("aria-pressed", String(name === view));
      $(`designer-${name}-view`).hidden = name !== view;
    }
    if (view === "versions") await this.versions.refresh();
    else this.placeProblems();
  }

  // -- live validation ------------------------------------------------------------------
  edited() {
    setText($("config-status"), "");
    clearTimeout(this.checkTimer);
    this.checkTimer = setTimeout(() => this.check(), CHECK_DELAY_MS);
  }

  /** Ask the server what is wrong with the working document (nothing is saved) and show it with the summary. */
  async check() {
    let config;
    try {
      config = this.document();
    } catch (err) {
      this.showProblems(`The text is not valid JSON: ${err.message}`);
      return null;
    }
    const seq = ++this.checkSeq;
    try {
      const result = await this.app.api.post("/api/admin/study-config/check", { config });
      if (seq !== this.checkSeq) return null; // a later edit's check is on its way
      this.showProblems(result.valid ? null : problemCount(result.problems.length), result.problems);
      this.showWarnings(result.warnings || []);
      setText($("config-problems-none"), "No problems found.");
      if (result.summary) renderSummary(result.summary);
      setText($("summary-note"), result.valid ? "" : "The summary is of the last valid configuration.");
      return result;
    } catch (err) {
      if (seq === this.checkSeq) showError($("config-problems-detail"), "Could not check the configuration", err);
      return null;
    }
  }

  async save() {
    clearTimeout(this.checkTimer); // saving checks too; a pending live check would only repeat it
    setText($("config-status"), "");
    let config;
    try {
      config = this.document();
    } catch (err) {
      this.showProblems(`The text is not valid JSON: ${err.message}`);
      return;
    }
    $("config-save").disabled = true;
    try {
      const before = this.app.study.version;
      const path = `/api/admin/studies/${encodeURIComponent(this.app.study.slug)}/config`;
      const author = $("designer-author").value.trim() || undefined;
      const study = await this.app.api.request("PUT", path, { body: { config, author } });
      this.app.setStudy(study);
      await this.load(study);
      setText($("config-status"), study.version > before
        ? `Saved as version ${study.version}.`
        : `No changes to save (version ${study.version}).`);
    } catch (err) {
      const problems = err.body && Array.isArray(err.body.problems) ? err.body.problems : [];
      if (problems.length) {
        const result = await this.check(); // the same problems, with their places in the document
        const count = result && result.problems.length ? result.problems.length : problems.length;
        setText($("config-problems-detail"), `The server refused the configuration (HTTP ${err.status}): `
          + `${problemCount(count).toLowerCase()}`);
        if (!result || !result.problems.length) this.listProblems(problems.map(fromString));
      } else {
        this.showProblems(null);
        showError($("config-problems-detail"), "The server refused the configuration", err);
        $("config-problems-none").hidden = true;
      }
    } finally {
      $("config-save").disabled = false;
    }
  }

  // -- problems -------------------------------------------------------------------------
  /** detail: a sentence (or null to clear); problems: {path, loc, message} from the server. */
  showProblems(detail, problems = []) {
    setText($("config-problems-detail"), detail || "");
    $("config-problems-none").hidden = Boolean(detail);
    this.listProblems(problems);
  }

  listProblems(problems) {
    this.lastProblems = problems;
    $("config-problems").replaceChildren(...problems.map((problem) => this.problemItem(problem)));
    this.placeProblems();
  }

  /** Warnings (e.g. a questionnaire without a language the study offers): the study can run, but should it? */
  showWarnings(warnings) {
    setText($("config-warnings-detail"), warnings.length
      ? `${warnings.length} warning${warnings.length === 1 ? "" : "s"} (the study can still be saved and run):` : "");
    $("config-warnings").replaceChildren(...warnings.map((warning) => this.problemItem(warning)));
  }

  problemItem(problem) {
    const go = el("button", { type: "button", class: "link-button", title: "Show this place" },
      el("code", {}, problem.path || "(document)"));
    go.addEventListener("click", () => this.goTo(problem.loc));
    return el("li", {}, go, el("span", {}, problem.message));
  }

  placeProblems() {
    if (this.form.ready) this.form.showProblems(this.editView === "form" ? this.lastProblems : []);
  }

  goTo(loc) {
    if (this.view === "form") this.form.focus(loc);
    else if (this.view === "raw") this.select(loc);
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

/** "1 problem to fix." / "3 problems to fix." */
function problemCount(n) {
  return `${n} problem${n === 1 ? "" : "s"} to fix.`;
}

/** A 422's "body.config.blocks.0.name: message" as {path, loc, message} (when no check could place it). */
function fromString(problem) {
  const split = problem.indexOf(": ");
  const where = split > 0 ? problem.slice(0, split) : "";
  const loc = where.split(".").filter(Boolean).map((s) => (/^\d+$/.test(s) ? Number(s) : s));
  while (["body", "config"].includes(loc[0])) loc.shift();
  return { path: loc.join("."), loc, message: split > 0 ? problem.slice(split + 2) : problem };
}

/** The summary panel: what a researcher checks before launch. */
function renderSummary(summary) {
  const blocks = summary.blocks.map((b) => el("li", {},
    el("strong", {}, b.name), ` — ${b.trials} trials (${b.schedule}; ${b.shelves} shel${b.shelves === 1 ? "f" : "ves"})`,
    el("div", { class: "policy-words" }, b.policy)));
  const orders = summary.orders.map((o) => el("li", {}, o.join(" → ")));
  const questionnaires = summary.questionnaires.map((q) => el("li", {}, `${q.title} (${q.items} items): ${q.when}`));
  const fact = (term, ...value) => [el("dt", {}, term), el("dd", {}, ...value)];
  $("designer-summary").replaceChildren(el("dl", { class: "facts-list summary-facts" },
    ...fact("Trials", `${summary.scored_trials} scored`,
      summary.practice_trials ? ` + ${summary.practice_trials} practice` : " (no practice)"),
    ...fact("Duration", summary.duration),
    ...fact("Payment", summary.payment),
    ...fact("Block orders", summary.counterbalance, el("ul", { class: "plain-list" }, ...orders)),
    ...fact("Blocks", el("ul", { class: "plain-list" }, ...blocks)),
    ...fact("Questionnaires", questionnaires.length ? el("ul", { class: "plain-list" }, ...questionnaires) : "none")));
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
