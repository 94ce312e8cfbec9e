// The study config as a form, generated from the server's JSON Schema (GET /api/admin/study-config-schema) by
// json-editor (static/vendor/json-editor, MIT): every field with its description, bounds and allowed values.
// The server's validation messages are put beside the field they concern (by the problem's `loc`).

import { el } from "./admin-ui.js";

const OPTIONS = {
  theme: "trustlab", // json-editor's plain "html" theme without inline styles (cspTheme)
  iconlib: null,
  disable_edit_json: true,
  disable_properties: true,
  disable_array_delete_all_rows: true,
  disable_array_delete_last_row: true,
  prompt_before_delete: false,
  show_errors: "never", // the server's messages are shown instead (one source of truth)
  show_opt_in: true, // fields a document may leave out (e.g. a questionnaire's DOI) stay out unless ticked
  no_additional_properties: true,
  keep_oneof_values: false, // a policy of another kind starts from that kind's defaults
  use_name_attributes: false,
  disable_theme_rules: true, // its rules go in an inline style sheet, which the page's CSP refuses; admin.css styles it
};

const shown = (element) => element.offsetParent !== null;

/** json-editor's path of a problem's loc (["blocks", 1, "policy"] → "root.blocks.1.policy"). */
const editorPath = (loc) => ["root", ...loc].join(".");

export class DesignerForm {
  /** holder: the element the form goes in; onChange(): after every edit (not after setValue). */
  constructor(holder, onChange) {
    this.holder = holder;
    this.onChange = onChange;
    this.editor = null;
    this.settingValue = false;
    this.marks = [];
  }

  /** Build the form for `schema` filled with `value`; resolves once it is drawn. */
  build(schema, value) {
    if (this.editor) this.editor.destroy();
    registerExtensions(window.JSONEditor);
    this.editor = new window.JSONEditor(this.holder, { ...OPTIONS, schema, startval: value });
    return new Promise((resolve) => {
      this.editor.on("ready", () => {
        this.editor.on("change", () => {
          labelControls(this.holder); // a policy of another kind brings its own controls
          if (!this.settingValue) this.onChange();
        });
        labelControls(this.holder);
        resolve();
      });
    });
  }

  get ready() {
    return Boolean(this.editor && this.editor.ready);
  }

  getValue() {
    return this.editor.getValue();
  }

  setValue(value) {
    this.settingValue = true;
    try {
      this.editor.setValue(value);
      labelControls(this.holder);
    } finally {
      // json-editor reports the change asynchronously: ignore it, it is not the user's edit
      setTimeout(() => {
        this.settingValue = false;
      }, 0);
    }
  }

  /** Put each problem's message beside its field (or the nearest enclosing one that is shown). */
  showProblems(problems) {
    this.clearProblems();
    problems.forEach((problem, index) => {
      const target = this.fieldFor(problem.loc);
      if (!target) return;
      const id = `field-problem-${index}`;
      const note = el("p", { class: "field-problem", id }, problem.message);
      // a field's own input; a section's message (e.g. a collapsed one's) goes at the section's end
      const control = target.input && shown(target.input) ? target.input : null;
      if (control) {
        control.setAttribute("aria-invalid", "true");
        const described = control.getAttribute("aria-describedby");
        control.setAttribute("aria-describedby", described ? `${described} ${id}` : id);
        const bounds = control.nextElementSibling; // a number's bounds stay beside it, the message below both
        (bounds && bounds.classList.contains("je-bounds") ? bounds : control).insertAdjacentElement("afterend", note);
      } else {
        target.container.append(note);
      }
      target.container.classList.add("has-problem");
      this.marks.push({ note, control, container: target.container, id });
    });
    labelControls(this.holder);
  }

  clearProblems() {
    for (const { note, control, container, id } of this.marks) {
      note.remove();
      container.classList.remove("has-problem");
      if (!control) continue;
      control.removeAttribute("aria-invalid");
      const rest = (control.getAttribute("aria-describedby") || "").split(" ").filter((x) => x && x !== id);
      if (rest.length) control.setAttribute("aria-describedby", rest.join(" "));
      else control.removeAttribute("aria-describedby");
    }
    this.marks = [];
  }

  /** The editor of `loc`, or of the nearest enclosing place that has a visible editor. */
  fieldFor(loc) {
    if (!this.editor) return null;
    for (let n = loc.length; n >= 0; n -= 1) {
      const editor = this.editor.getEditor(editorPath(loc.slice(0, n)));
      if (editor && editor.container && shown(editor.container)) return editor;
    }
    return this.editor.root;
  }

  /** Move the keyboard focus to the field of `loc` (from the problems list). */
  focus(loc) {
    const target = this.fieldFor(loc);
    if (!target) return;
    const controls = [target.input, ...target.container.querySelectorAll("input, select, textarea, button")];
    const control = controls.find((c) => c && shown(c));
    target.container.scrollIntoView({ block: "center" });
    if (control) control.focus();
  }
}

/** "root.blocks.1.policy" → "blocks[1].policy", as the server's problems name places. */
function readablePath(schemaPath) {
  return schemaPath.replace(/^root\.?/, "").replace(/\.(\d+)(?=\.|$)/g, "[$1]") || "configuration";
}

/** Name json-editor's choice of a union's option ("Kind of blocks[1].policy") by its place, and each section's
 * collapse button by its section ("Collapse Timing"). */
function labelControls(holder) {
  for (const select of holder.querySelectorAll("select.je-switcher:not([aria-label])")) {
    const place = select.closest("[data-schemapath]");
    if (place) select.setAttribute("aria-label", `Kind of ${readablePath(place.getAttribute("data-schemapath"))}`);
  }
  for (const button of holder.querySelectorAll("button.json-editor-btntype-toggle")) nameToggle(button);
}

/** A collapse button says what it collapses: json-editor gives them all the same text ("Collapse"/"Expand"),
 * and its section's title is the header text beside it. */
function nameToggle(button) {
  const header = button.nextElementSibling ? button.nextElementSibling.textContent.trim() : "";
  const place = button.closest("[data-schemapath]");
  if (!header && !place) return;
  // a union's option has no header of its own (its choice is titled above it): its place names it
  const section = header || readablePath(place.getAttribute("data-schemapath"));
  const action = button.textContent.trim();
  button.setAttribute("aria-label", `${action} ${section}`);
  button.setAttribute("aria-expanded", String(action !== "Expand"));
}

/** "0 to 1", "whole number ≥ 1", "> 0, ≤ 60": a number field's bounds from its schema, shown beside it. */
export function boundsText(schema) {
  const huge = (x) => Math.abs(x) >= 1e15; // a bound that only says "fits in 64 bits" is not worth reading
  const bound = (value, sign) => (value === undefined || huge(value) ? null : { value, sign });
  const low = bound(schema.minimum, "≥") || bound(schema.exclusiveMinimum, ">");
  const high = bound(schema.maximum, "≤") || bound(schema.exclusiveMaximum, "<");
  const whole = schema.type === "integer" ? "whole number" : "";
  if (low && high && low.sign === "≥" && high.sign === "≤") return [whole, `${low.value} to ${high.value}`].join(" ").trim();
  const limits = [low, high].filter(Boolean).map((b) => `${b.sign} ${b.value}`).join(", ");
  return [whole, limits].filter(Boolean).join(" ");
}

/** This page's additions to json-editor (once): the CSP-safe theme and the JSON document editor. */
function registerExtensions(JSONEditor) {
  if (JSONEditor.defaults.themes.trustlab) return;
  // json-editor "cleans" every string value and title by writing it into an element's innerHTML: that loads an
  // <img> in a config string (and runs its handlers where no CSP forbids them), and drops a text's markup from the
  // saved value. A config string is text: kept as written, and json-editor shows it through textContent.
  JSONEditor.AbstractEditor.prototype.cleanText = asText;
  JSONEditor.AbstractTheme.prototype.cleanText = asText;
  JSONEditor.defaults.themes.trustlab = cspTheme(JSONEditor.defaults.themes.html);
  JSONEditor.defaults.editors.jsonDocument = jsonDocumentEditor(JSONEditor.defaults.editors.string);
  JSONEditor.defaults.editors.number = boundedNumberEditor(JSONEditor.defaults.editors.number);
  JSONEditor.defaults.editors.integer = boundedNumberEditor(JSONEditor.defaults.editors.integer);
  JSONEditor.defaults.resolvers.unshift((schema) => (schema.options && schema.options.json_document
    ? "jsonDocument" : undefined));
}

/** A value as the text json-editor shows through textContent (its cleanText, without ever parsing it as HTML). */
const asText = (value) => (value == null ? "" : String(value));

/** A free-form JSON document (a model JSON) as text in a text area: its value is the parsed document, or the
 * text itself while it does not parse (the server's check then says so beside it). */
function jsonDocumentEditor(StringEditor) {
  return class extends StringEditor {
    setValue(value, initial, fromTemplate) {
      const text = typeof value === "string" ? value : JSON.stringify(value ?? {}, null, 2);
      return super.setValue(text, initial, fromTemplate);
    }

    getValue() {
      const text = super.getValue();
      try {
        return JSON.parse(text);
      } catch (_err) {
        return text;
      }
    }
  };
}

/** A number field with its bounds written beside the input (the input's min/max only show on a spinner). */
function boundedNumberEditor(NumberEditor) {
  return class extends NumberEditor {
    build() {
      super.build();
      const text = boundsText(this.schema);
      if (!text || !this.input) return;
      const id = `${this.input.id || this.formname}-bounds`;
      this.input.insertAdjacentElement("afterend", el("span", { class: "je-bounds", id }, text));
      const described = this.input.getAttribute("aria-describedby");
      this.input.setAttribute("aria-describedby", described ? `${described} ${id}` : id);
    }
  };
}

/** json-editor's "html" theme minus its inline style attributes, which the page's Content-Security-Policy
 * (style-src 'self') refuses: hidden labels use the page's .visually-hidden class instead. */
function cspTheme(Base) {
  const hidden = (tag, text) => el(tag, { class: "visually-hidden" }, text);
  return class extends Base {
    getHiddenLabel(text) {
      return hidden("label", text);
    }

    getHiddenText(text) {
      return hidden("span", text);
    }

    visuallyHidden(element) {
      if (element) element.classList.add("visually-hidden");
    }

    setButtonText(button, text, icon, title) {
      super.setButtonText(button, text, icon, title);
      if (button.classList.contains("json-editor-btntype-toggle")) nameToggle(button); // on every collapse/expand
    }

    getFormControl(label, input, description, infoText, formName) {
      const control = super.getFormControl(label, input, description, infoText, formName);
      if (description && input && input.id && !formName) { // a check box's description got the id "undefined-…"
        description.id = `${input.id}-description`;
        input.setAttribute("aria-describedby", description.id);
      }
      return control;
    }

    getOptInCheckbox(name) {
      const label = hidden("label", `Include ${name.replace(/^root\[?/, "").replace(/\]\[/g, ".").replace(/\]$/, "")}`);
      label.setAttribute("for", `${name}-opt-in`);
      const checkbox = el("input", { type: "checkbox", id: `${name}-opt-in`, class: "json-editor-opt-in" });
      return { label, checkbox, container: el("span", { class: "opt-in" }, checkbox, label) };
    }
  };
}
