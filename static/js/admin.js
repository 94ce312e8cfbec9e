// The experimenter's dashboard /admin: log in with the admin token, list and create studies,
// and per study the participants (live), the configuration, the data and the model. The
// location hash says where we are (#/ or #/study/SLUG/TAB), so a reload stays there.

import { AdminApi, loggedOutBecause, token } from "./admin-api.js";
import { ConfigEditor } from "./admin-config.js";
import { DataPanel } from "./admin-data.js";
import { ModelsPanel } from "./admin-models.js";
import { ParticipantsPanel } from "./admin-participants.js";
import { $, badge, countsText, el, focusHeading, previewText, showError } from "./admin-ui.js";
import { connectionNotice } from "./api.js";
import { copyText } from "./views.js";

const TABS = ["participants", "config", "data", "models"];
/** Why the server refused a token (a 401), in the experimenter's words: the server's own reason is for API clients. */
const TOKEN_REFUSED = "this admin token is not (or no longer) valid. Use the token 'trustlab serve' printed on "
  + "its first run, or the newest one 'trustlab admin-token --rotate' printed (a rotation revokes the older ones).";

/** What the log-in field says when a token could not be tried or was refused: words, no status code or JSON. */
function loginProblem(err) {
  if (err && err.status === 401) return `Not logged in: ${TOKEN_REFUSED}`;
  if (err && err.status === 0) return `Could not log in: ${err.detail}.`;  // the server could not be reached
  if (err && err.status === 429) return "Could not log in: too many attempts just now. Wait a minute and try again.";
  if (err && err.status >= 500) return "Could not log in: the server had a problem. Try again in a moment.";
  const detail = err && typeof err.detail === "string" ? err.detail : "";
  return `Could not log in${detail ? `: ${detail}` : ". Try again in a moment."}`;
}

/** Withdrawal and retention of the participants' personal data (config privacy) and what was erased: one line. */
function personalDataText(study) {
  const data = study.personal_data;
  if (!data) return "";
  const day = (iso) => iso.slice(0, 10);
  const today = new Date().toISOString().slice(0, 10);
  const parts = [`Withdrawal ${data.withdrawal === "delete" ? "deletes the data" : "keeps the data (excluded)"}`];
  if (data.erase_on && data.erase_on <= today) parts.push(`personal data erased on ${data.erase_on}`);
  else parts.push(`personal data ${data.retention}`);
  if (data.erased_sessions) {
    parts.push(`erased for ${data.erased_sessions} session${data.erased_sessions === 1 ? "" : "s"}, last on `
      + day(data.last_erased_at));
  }
  if (data.deleted_participants) {
    parts.push(`${data.deleted_participants} participant${data.deleted_participants === 1 ? "'s" : "s'"} data deleted`);
  }
  return parts.join(" · ");
}

/** The study's cap on active participants and the joins it refused (as of loading the study); "" when neither. */
function admissionText(study) {
  const parts = [];
  if (study.max_active_participants != null) parts.push(`at most ${study.max_active_participants} active at once`);
  const refused = study.refused_joins;
  if (refused) parts.push(`${refused} join${refused === 1 ? "" : "s"} refused (study full)`);
  return parts.join(" · ");
}

class Dashboard {
  constructor() {
    this.api = new AdminApi({
      onUnauthorized: () => this.logout(`You were logged out: ${TOKEN_REFUSED}`),
      onTrouble: connectionNotice($("connection")),
    });
    this.study = null;
    this.tab = null;
    this.templates = [];
    this.panels = {
      participants: new ParticipantsPanel(this),
      config: new ConfigEditor(this),
      data: new DataPanel(this),
      models: new ModelsPanel(this),
    };
    this.wire();
  }

  wire() {
    $("login-form").addEventListener("submit", (event) => {
      event.preventDefault();
      this.login($("login-token").value.trim());
    });
    $("logout").addEventListener("click", () => this.logout());
    $("create-form").addEventListener("submit", (event) => {
      event.preventDefault();
      this.createStudy();
    });
    $("study-toggle").addEventListener("click", () => this.toggleOpen());
    $("study-preview").addEventListener("click", () => this.preview());
    $("study-copy-join").addEventListener("click", () => copyText($("study-join"), $("study-copy-status")));
    const tabs = [...document.querySelectorAll('[role="tab"]')];
    for (const tab of tabs) {
      tab.addEventListener("click", () => this.go(this.study.slug, tab.dataset.tab));
      tab.addEventListener("keydown", (event) => this.tabKey(event, tabs));
    }
    window.addEventListener("hashchange", () => this.route());
    document.addEventListener("visibilitychange", () => this.panels.participants.visibilityChanged());
  }

  start() {
    if (token.get()) this.route();
    else this.showLogin();
  }

  // -- log-in ---------------------------------------------------------------------------
  // (a message of the last log-out stays until a log-in, across reloads: another refused request, a route to the
  // log-in page or a reload would otherwise wipe it before it was read)
  showLogin(message = loggedOutBecause.get()) {
    this.show("login");
    $("logout").hidden = true;
    $("login-error").textContent = message;
    $("login-token").value = "";
    $("login-token").focus();
  }

  /** Try the token typed; on failure say why in words and keep what was typed (selected, to paste over). */
  async login(value) {
    const error = $("login-error");
    error.textContent = "";
    if (!value) {
      error.textContent = "Enter the admin token.";
      return;
    }
    if (!/^[\x21-\x7e]+$/.test(value)) {  // a header cannot carry it: the request would fail before the server
      error.textContent = "This is not an admin token: it has spaces or characters an admin token never has "
        + "(letters, digits, '-' and '_', starting with tla_). Copy it again from where trustlab printed it.";
      $("login-token").select();
      return;
    }
    try {
      await this.api.request("GET", "/api/admin/studies", { bearer: value, loggingIn: true });
    } catch (err) {
      error.textContent = loginProblem(err);
      $("login-token").select();
      return;
    }
    token.set(value);
    loggedOutBecause.set("");
    this.route();
  }

  logout(message = "") {
    loggedOutBecause.set(message);
    token.clear();
    this.leaveStudy();
    this.study = null;
    if (location.hash && location.hash !== "#/") history.replaceState(null, "", "#/");
    this.showLogin(message);
  }

  show(view) {
    for (const name of ["login", "studies", "study"]) $(`view-${name}`).hidden = name !== view;
  }

  // -- routing --------------------------------------------------------------------------
  go(slug, tab = "participants") {
    location.hash = slug ? `#/study/${encodeURIComponent(slug)}/${tab}` : "#/";
  }

  async route() {
    if (!token.get()) return this.showLogin();
    $("logout").hidden = false;
    const match = /^#\/study\/([^/]+)(?:\/([a-z]+))?/.exec(location.hash);
    if (!match) {
      this.leaveStudy();
      return this.showStudies();
    }
    const slug = decodeURIComponent(match[1]);
    const tab = TABS.includes(match[2]) ? match[2] : "participants";
    if (!this.study || this.study.slug !== slug) {
      this.leaveStudy();
      if (!(await this.loadStudy(slug))) return undefined;
      this.show("study");
      focusHeading($("study-title"));
    }
    return this.selectTab(tab);
  }

  // -- studies list ---------------------------------------------------------------------
  async showStudies() {
    this.show("studies");
    focusHeading($("studies-heading"));
    $("studies-error").textContent = "";
    try {
      const [studies, templates] = await Promise.all([this.api.get("/api/admin/studies"), this.loadTemplates()]);
      this.renderStudies(studies);
      this.fillTemplates($("create-template"), templates);
    } catch (err) {
      showError($("studies-error"), "Could not load the studies", err);
    }
  }

  async loadTemplates() {
    if (!this.templates.length) this.templates = await this.api.get("/api/admin/templates");
    return this.templates;
  }

  fillTemplates(select, templates) {
    if (select.options.length) return;
    for (const t of templates) select.append(el("option", { value: t.name }, `${t.name} — ${t.config.title}`));
  }

  renderStudies(studies) {
    $("studies-empty").hidden = studies.length > 0;
    $("studies-table").hidden = studies.length === 0;
    $("studies-body").replaceChildren(...studies.map((s) => {
      const link = el("output", { class: "join-url" }, s.join_url);
      const status = el("span", { class: "muted small", role: "status" });
      const label = `Copy the join link of ${s.slug}`;
      const copy = el("button", { type: "button", class: "small-button", "aria-label": label }, "Copy");
      copy.addEventListener("click", () => copyText(link, status));
      return el("tr", { "data-slug": s.slug },
        el("td", {}, el("a", { href: `#/study/${encodeURIComponent(s.slug)}/participants` }, s.title),
          el("div", { class: "muted small" }, s.slug)),
        el("td", { class: "status-cell" }, badge(s.status), " ", this.statusButton(s)),
        el("td", {}, `v${s.version}`),
        el("td", {}, countsText(s.participants), previewText(s.preview_sessions)),
        el("td", { class: "join-cell" }, link, " ", copy, " ", status));
    }));
  }

  /** The Open / Close / Reopen button of a study in the list (it moves the study along draft → open ⇄ closed). */
  statusButton(s) {
    const action = s.status === "open" ? "close" : "open";
    const label = { draft: "Open", open: "Close", closed: "Reopen" }[s.status] || "Open";
    const button = el("button", { type: "button", class: "small-button", "aria-label": `${label} study ${s.slug}` },
      label);
    button.addEventListener("click", async () => {
      button.disabled = true;
      try {
        await this.api.post(`/api/admin/studies/${encodeURIComponent(s.slug)}/${action}`);
        await this.showStudies();
      } catch (err) {
        button.disabled = false;
        showError($("studies-error"), `Could not ${action} study ${s.slug}`, err);
      }
    });
    return button;
  }

  async createStudy() {
    const slug = $("create-slug").value.trim();
    $("create-error").textContent = "";
    if (!$("create-form").reportValidity()) return;
    try {
      const study = await this.api.post("/api/admin/studies", { template: $("create-template").value, slug });
      $("create-slug").value = "";
      this.go(study.slug, "config");
    } catch (err) {
      showError($("create-error"), "Could not create the study", err);
    }
  }

  // -- one study ------------------------------------------------------------------------
  async loadStudy(slug) {
    try {
      this.setStudy(await this.api.get(`/api/admin/studies/${encodeURIComponent(slug)}`));
      return true;
    } catch (err) {
      if (err.status === 401) return false;
      this.show("studies");
      showError($("studies-error"), `Could not open study ${slug}`, err);
      return false;
    }
  }

  /** Show a study's head (after loading it, saving its config or opening/closing it). */
  setStudy(study) {
    this.study = study;
    $("study-title").textContent = study.title;
    $("study-slug").textContent = study.slug;
    $("study-status").replaceWith(badge(study.status, "study-status"));
    $("study-version").textContent = `config version ${study.version}`;
    $("study-counts").textContent = countsText(study.participants) + previewText(study.preview_sessions);
    const admission = admissionText(study);
    $("study-admission").hidden = !admission;
    $("study-admission").textContent = admission ? ` · ${admission}` : "";
    $("study-join").textContent = study.join_url;
    const personal = personalDataText(study);
    $("study-personal-data").hidden = !personal;
    $("study-personal-data").textContent = personal;
    $("study-toggle").textContent = { open: "Close study", closed: "Reopen study" }[study.status] || "Open study";
    $("study-draft-note").hidden = study.status !== "draft";
    $("study-closed-note").hidden = study.status !== "closed";
    $("participants-empty").textContent = {
      draft: "Nobody can join a draft. Try it with “Preview as participant”, then open the study and share the join link.",
      closed: "Nobody joined before the study was closed. Reopen it to let participants join.",
    }[study.status] || "Nobody has joined yet. Share the join link above.";
    $("study-error").textContent = "";
  }

  async toggleOpen() {
    const action = this.study.status === "open" ? "close" : "open";
    try {
      const study = await this.api.post(`/api/admin/studies/${encodeURIComponent(this.study.slug)}/${action}`);
      this.setStudy({ ...this.study, ...study }); // the answer has no config: keep the one we have
    } catch (err) {
      showError($("study-error"), `Could not ${action} the study`, err);
    }
  }

  /** Open the participant's pages as a new preview session in a new tab (opened at the click, so that no popup
   * blocker stops it, and pointed at the session once the server made it). */
  async preview() {
    const tab = window.open("about:blank", "_blank");
    if (tab) tab.opener = null;
    $("study-error").textContent = "";
    try {
      const started = await this.api.post(`/api/admin/studies/${encodeURIComponent(this.study.slug)}/preview`);
      const url = `/p/${encodeURIComponent(started.token)}`;
      if (tab) tab.location.replace(url);
      else window.location.assign(url); // popups blocked: go there in this tab
      if (this.tab === "participants") this.panels.participants.poll();
    } catch (err) {
      if (tab) tab.close();
      showError($("study-error"), "Could not start a preview session", err);
    }
  }

  selectTab(name) {
    if (this.tab && this.tab !== name) this.panels[this.tab].leave();
    for (const tab of TABS) {
      const button = $(`tab-${tab}`);
      button.setAttribute("aria-selected", String(tab === name));
      button.tabIndex = tab === name ? 0 : -1;
      $(`panel-${tab}`).hidden = tab !== name;
    }
    const entering = this.tab !== name;
    this.tab = name;
    if (entering) this.panels[name].enter(this.study);
  }

  tabKey(event, tabs) {
    const index = tabs.indexOf(event.currentTarget);
    const moves = { ArrowRight: index + 1, ArrowLeft: index - 1, Home: 0, End: tabs.length - 1 };
    if (!(event.key in moves)) return;
    event.preventDefault();
    const next = tabs[(moves[event.key] + tabs.length) % tabs.length];
    next.focus();
    this.go(this.study.slug, next.dataset.tab);
  }

  leaveStudy() {
    if (this.tab) this.panels[this.tab].leave();
    this.tab = null;
    this.study = null;
  }
}

const dashboard = new Dashboard();
dashboard.start();
