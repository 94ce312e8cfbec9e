// Fit the trust model to the study's data, follow the fit's progress, show the model (parameters
// with standard errors and how well each is determined, the policy's thresholds, the
// trust-agnostic baseline, provenance) and deploy it as a policy-evaluation study.

import { describe } from "./admin-api.js";
import { parameterLabel, STATUS_LEGEND, STATUS_TEXT } from "./admin-parameters.js";
import { ratingsSection, selectionSection } from "./admin-selection.js";
import { $, badge, el, heading, number, row, setText, showError, table } from "./admin-ui.js";

const FIT_POLL_MS = 500;

export class ModelsPanel {
  constructor(app) {
    this.app = app;
    this.slug = null;
    this.selected = null; // the model shown
    this.comparing = false; // the fit followed compares numbers of trust states
    this.timer = null;
    this.schema = null;
    $("fit-form").addEventListener("submit", (event) => {
      event.preventDefault();
      this.fit();
    });
    $("deploy-form").addEventListener("submit", (event) => {
      event.preventDefault();
      this.deploy();
    });
    $("model-download").addEventListener("click", () => this.downloadModel());
    $("model-report").addEventListener("click", () => this.downloadReport());
  }

  async enter(study) {
    if (this.slug !== study.slug) {
      this.selected = null;
      $("model-detail").hidden = true;
      setText($("fit-error"), "");
      $("fit-progress-row").hidden = true;
    }
    this.slug = study.slug;
    this.active = true;
    await Promise.all([this.loadSchema(), this.loadList()]);
    if (this.selected) this.follow(this.selected.id);
  }

  leave() {
    this.active = false;
    clearTimeout(this.timer);
  }

  /** Request defaults and the evaluation designs, from the OpenAPI schema (the server's own word). */
  async loadSchema() {
    if (this.schema) return;
    try {
      const response = await fetch("/openapi.json", { cache: "no-store" });
      this.schema = (await response.json()).components.schemas;
    } catch (_err) {
      this.schema = {};
    }
    const fit = (this.schema.FitCreate || {}).properties || {};
    if (fit.restarts && fit.restarts.default !== undefined) $("fit-restarts").value = fit.restarts.default;
    if (fit.seed && fit.seed.default !== undefined) $("fit-seed").value = fit.seed.default;
    if (fit.folds && fit.folds.default !== undefined) $("fit-folds").value = fit.folds.default;
    const template = ((this.schema.EvaluationStudyCreate || {}).properties || {}).template || {};
    const designs = template.enum || (await this.app.loadTemplates()).map((t) => t.name);
    $("deploy-template").replaceChildren(...designs.map((name) => el("option", { value: name,
      selected: name === template.default }, name)));
  }

  async loadList() {
    setText($("models-error"), "");
    try {
      this.renderList(await this.app.api.get(`/api/admin/studies/${encodeURIComponent(this.slug)}/models`));
    } catch (err) {
      showError($("models-error"), "Could not load the models", err);
    }
  }

  renderList(models) {
    $("models-empty").hidden = models.length > 0;
    $("models-list").replaceChildren(...models.map((m) => {
      const current = this.selected && this.selected.id === m.id;
      const button = el("button", { type: "button", "aria-current": current ? "true" : null },
        el("span", {}, `Model ${m.id}`, " ", badge(m.status)),
        el("span", { class: "muted small" }, m.loglik === null ? "" : `log-likelihood ${number(m.loglik, 1)}`));
      button.addEventListener("click", () => this.follow(m.id));
      return el("li", {}, button);
    }));
  }

  async fit() {
    setText($("fit-error"), "");
    if (!$("fit-form").reportValidity()) return;
    const body = { restarts: Number($("fit-restarts").value), seed: Number($("fit-seed").value) };
    if ($("fit-p-high").value !== "") body.p_high = Number($("fit-p-high").value);
    const states = [...document.querySelectorAll('input[name="fit-states"]:checked')].map((box) => Number(box.value));
    if (!states.length) {
      setText($("fit-error"), "Tick at least one number of trust states.");
      return;
    }
    if (states.length > 1 || states[0] !== 2) body.states = states;  // 2 alone: the paper's model, as before
    const withRatings = $("fit-ratings").checked;
    if (withRatings) body.with_ratings = true;
    if (states.length > 1 || withRatings) body.folds = Number($("fit-folds").value);
    this.comparing = states.length > 1 ? "numbers of trust states" : withRatings ? "with and without ratings" : null;
    $("fit-submit").disabled = true;
    try {
      const model = await this.app.api.post(`/api/admin/studies/${encodeURIComponent(this.slug)}/fits`, body);
      await this.follow(model.id, model);
    } catch (err) {
      showError($("fit-error"), "Could not start the fit", err);
    } finally {
      $("fit-submit").disabled = false;
    }
  }

  /** Show a model; while it runs, poll it and show its progress. */
  async follow(id, known = null) {
    clearTimeout(this.timer);
    let model = known;
    try {
      model = model || await this.app.api.get(`/api/admin/models/${id}`);
    } catch (err) {
      showError($("fit-error"), `Could not read model ${id}`, err);
      return;
    }
    if (!this.active) return;
    this.selected = model;
    this.showProgress(model);
    if (model.status === "running") {
      this.timer = setTimeout(() => this.follow(id), FIT_POLL_MS);
      return;
    }
    if (model.status === "failed") setText($("fit-error"), `The fit failed: ${model.error}`);
    this.renderModel(model);
    await this.loadList();
  }

  showProgress(model) {
    const running = model.status === "running";
    $("fit-progress-row").hidden = !running;
    $("fit-submit").disabled = running;
    if (!running) return;
    const { iterations_done: done, iterations_max: max } = model.progress;
    $("fit-progress").max = max || 1;
    $("fit-progress").value = done;
    setText($("fit-progress-text"), this.comparing
      ? `Fitting model ${model.id}: comparing ${this.comparing}, ${Math.round(100 * done / (max || 1))} %…`
      : `Fitting model ${model.id}: ${done} of at most ${max} EM iterations…`);
  }

  renderModel(m) {
    $("model-detail").hidden = false;
    setText($("model-heading"), `Model ${m.id}`);
    $("model-heading").append(" ", badge(m.status));
    const p = m.provenance;
    setText($("model-meta"), `Fitted on ${p.n_participants} participants and ${p.n_trials} scored trials of `
      + `${p.study} (config version ${p.study_versions.join(", ")}), ${p.restarts} restarts, seed ${p.seed}, `
      + `trustlab ${p.code_version}.`);
    const body = $("model-body");
    if (m.status !== "done") {
      body.replaceChildren(el("p", { class: "error" }, m.error || "The fit did not finish."));
      $("model-download").disabled = true;
      $("model-report").disabled = true;
      $("deploy-form").hidden = true;
      return;
    }
    $("model-download").disabled = false;
    $("model-report").disabled = false;  // a report reads a model of any number of trust states
    $("deploy-form").hidden = false;
    this.showDeployable(m);
    body.replaceChildren(this.facts(m), ...selectionSection(m.selection), ...ratingsSection(m.ratings),
      ...this.parameterTable(m.parameters),
      ...this.policyTable(m.policy),
      ...this.baselineTable(m.agnostic));
    if (!$("deploy-slug").value) $("deploy-slug").value = `${this.slug}-eval`.slice(0, 63);
    $("deploy-p-high").placeholder = number(m.policy ? m.policy.p_high : null);
  }

  /** The server says (evaluation_blocked) when this model cannot make an evaluation study: the button is off and
   * the reason is shown beside it, before anyone clicks. */
  showDeployable(m) {
    const reason = m.evaluation_blocked;
    $("deploy-submit").disabled = Boolean(reason);
    $("deploy-blocked").hidden = !reason;
    setText($("deploy-blocked"), reason
      ? `An evaluation study cannot be created from this model: ${reason.replace(/\.$/, "")}.` : "");
  }

  facts(m) {
    const link = (slug) => el("a", { href: `#/study/${encodeURIComponent(slug)}/participants` }, slug);
    const deployed = m.evaluation_studies.length
      ? m.evaluation_studies.flatMap((slug, i) => [i ? ", " : "", link(slug)])
      : ["none yet"];
    const rows = [
      ["Trust states", m.n_states === null ? "–" : m.n_states === 2 ? "2 (low, high)"
        : `${m.n_states} (state 0 the lowest trust, state ${m.n_states - 1} the highest)`],
      ["Log-likelihood", number(m.loglik, 2)],
      ["Converged", m.converged === null ? "–" : m.converged ? "yes" : "no (iteration budget reached)"],
      ["Content hash", el("code", {}, m.content_hash || "–")],
      ["Data hash", el("code", {}, m.provenance.data_hash)],
      ["Evaluation studies", el("span", {}, ...deployed)],
    ];
    const items = rows.flatMap(([term, value]) => [el("dt", {}, term), el("dd", {}, value)]);
    return el("dl", { class: "facts-list" }, ...items);
  }

  parameterTable(parameters) {
    const rows = parameters.map((p) => row({ class: `param-${p.status}` },
      [el("span", {}, parameterLabel(p.name)), el("div", { class: "muted small" }, el("code", {}, p.name))],
      [number(p.value, 3), true], [p.stderr === null ? "–" : number(p.stderr, 3), true],
      STATUS_TEXT[p.status] || p.status));
    return [heading("params-heading", "Parameters (Laplace standard errors)"),
      el("div", { class: "table-scroll params-scroll" },
        table("params-heading", ["Parameter", ["Estimate", true], ["SE", true], "Status"], rows)),
      el("p", { class: "muted small param-legend" }, STATUS_LEGEND)];
  }

  policyTable(policy) {
    const title = heading("policy-heading",
      `Trust-aware policy for P(high complexity) = ${number(policy ? policy.p_high : null)}`);
    if (!policy || policy.error) return [title, el("p", { class: "error" }, policy ? policy.error : "No policy.")];
    if (policy.ask_share) {  // K ≥ 3 states: no threshold, the share of the belief simplex where the robot asks
      const shares = ["low", "high"].map((c) => row({}, c, [`${number(100 * policy.ask_share[c], 1)} %`, true]));
      return [title, table("policy-heading", ["Complexity", ["Beliefs where the robot asks", true]], shares),
        el("p", { class: "muted small" }, `${policy.n_states} trust states: the policy acts on a belief over all `
          + `of them (${policy.grid} grid points of the belief simplex), so no single threshold describes it.`)];
    }
    const rows = ["low", "high"].map((c) => {
      const threshold = policy.threshold ? policy.threshold[c] ?? null : null;
      const action = policy.action ? policy.action[c] : null;
      const rule = threshold !== null
        ? `act autonomously when the belief of high trust exceeds ${number(threshold, 3)}, otherwise ask`
        : `always ${action === "ask" ? "ask for help" : "act autonomously"}`;
      return row({}, c, [threshold === null ? "–" : number(threshold, 3), true], rule);
    });
    return [title, table("policy-heading", ["Complexity", ["Threshold", true], "Robot"], rows)];
  }

  baselineTable(agnostic) {
    const title = heading("baseline-heading", "Trust-agnostic baseline (same data)");
    if (!agnostic) return [title, el("p", { class: "muted" }, "No baseline.")];
    const reward = (a, c) => (agnostic.expected_reward ? number(agnostic.expected_reward[a][c], 2) : "–");
    const rows = ["low", "high"].map((c) => {
      const r = agnostic.rates[c];
      return row({}, c, [`${number(r.rate, 3)} (${r.interventions} of ${r.auto_trials})`, true],
        [reward("auto", c), true], [reward("ask", c), true], agnostic.action ? agnostic.action[c] : "–");
    });
    const headers = ["Complexity", ["Intervention rate", true], ["E[R | auto]", true], ["E[R | ask]", true], "Action"];
    return [title, agnostic.error ? el("p", { class: "error" }, agnostic.error) : null,
      table("baseline-heading", headers, rows)].filter(Boolean);
  }

  async downloadModel() {
    setText($("deploy-error"), "");
    try {
      const id = this.selected.id;
      const name = await this.app.api.download(`/api/admin/models/${id}/document`, `model-${id}.json`);
      setText($("deploy-status"), `Downloaded ${name}.`);
    } catch (err) {
      showError($("deploy-error"), "Could not download the model", err);
    }
  }

  async downloadReport() {
    setText($("deploy-error"), "");
    setText($("deploy-status"), "Building the report…");
    $("model-report").disabled = true;
    try {
      const slug = encodeURIComponent(this.slug);
      const name = await this.app.api.download(`/api/admin/studies/${slug}/report?model=${this.selected.id}`,
        `${this.slug}-report.zip`);
      setText($("deploy-status"), `Downloaded ${name}.`);
    } catch (err) {
      setText($("deploy-status"), "");
      showError($("deploy-error"), "Could not build the report", err);
    } finally {
      $("model-report").disabled = false;
    }
  }

  async deploy() {
    setText($("deploy-error"), "");
    setText($("deploy-status"), "");
    if ($("deploy-submit").disabled || !$("deploy-form").reportValidity()) return;  // (Enter in a field submits too)
    const body = { slug: $("deploy-slug").value.trim(), template: $("deploy-template").value };
    if ($("deploy-title").value.trim()) body.title = $("deploy-title").value.trim();
    if ($("deploy-p-high").value !== "") body.p_high = Number($("deploy-p-high").value);
    try {
      const study = await this.app.api.post(`/api/admin/models/${this.selected.id}/evaluation-study`, body);
      $("deploy-status").replaceChildren(`Created the evaluation study “${study.title}”: `,
        el("a", { href: `#/study/${encodeURIComponent(study.slug)}/participants` }, `open ${study.slug}`),
        study.status === "draft" ? " (a draft: preview it, then open it to participants on its page)." : ".");
      await this.follow(this.selected.id);
    } catch (err) {
      setText($("deploy-error"), describe("Could not create the evaluation study", err));
    }
  }
}
