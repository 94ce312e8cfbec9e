// "Withdraw from the study" (issue 41, the participant's rights): a quiet link in the top bar of every page of
// the session; it opens a confirmation that says what happens to the data (the study's own words, config
// privacy.withdrawal_text, or what privacy.withdrawal does), and confirming ends the session with
// POST /api/p/{token}/withdraw. The page then shows its end (the outcome's code and redirect, if the study gives
// them), as it shows any state: participant.js renders the answer.
//
// Its words are the catalogue's (withdraw.*, static/js/i18n.js), set when the link is shown and the dialog opens:
// the catalogue of the session's language is loaded by then.

import { t } from "./i18n.js";

/** How long the end page shows before the study's redirect for a withdrawal (config completion) takes over. */
const REDIRECT_MS = 3000;

/** Phases in which the session is over for good: no link (withdrawing again would change nothing). */
const NO_LINK = new Set(["withdrawn"]);

const $ = (id) => document.getElementById(id);

/**
 * The link and its dialog, for participant.js's App (`app`: its `api`, `base`, `apply`, `issued`, `events`).
 * `update(state)` after each render: the link is shown while there is a session that has not withdrawn, and a
 * withdrawal by the participant gets its own end text.
 */
export class WithdrawLink {
  constructor(app, slot = $("withdraw-slot")) {
    this.app = app;
    this.slot = slot;
    this.state = null;
    this.sending = false;
    this.link = element("button", { type: "button", class: "withdraw-link", id: "withdraw-open",
      "aria-haspopup": "dialog" });
    this.dialog = this.buildDialog();
    this.link.addEventListener("click", () => this.open());
    if (slot) slot.append(this.link);
    document.body.append(this.dialog);
    // Registered before the trial screen's own (capture, on window): while the dialog is open its keys are the
    // dialog's (Space and Enter press its buttons, Tab moves between them, Escape closes it), never the robot's,
    // the arm's or the camera's.
    for (const type of ["keydown", "keyup"]) {
      window.addEventListener(type, (event) => {
        if (this.dialog.open) event.stopImmediatePropagation();
      }, true);
    }
    this.update(null);
  }

  buildDialog() {
    const dialog = element("dialog", { id: "withdraw-dialog", class: "withdraw-dialog",
      "aria-labelledby": "withdraw-heading", "aria-describedby": "withdraw-what" });
    this.what = element("div", { id: "withdraw-what" });
    this.error = element("p", { id: "withdraw-error", class: "error", role: "alert" });
    this.confirm = element("button", { type: "button", id: "withdraw-confirm", class: "danger" });
    this.cancel = element("button", { type: "button", id: "withdraw-cancel", class: "primary" });
    this.heading = element("h2", { id: "withdraw-heading" });
    dialog.append(this.heading, this.what,
      element("div", { class: "actions" }, this.cancel, this.confirm), this.error);
    this.cancel.addEventListener("click", () => this.close());
    this.confirm.addEventListener("click", () => this.send());
    dialog.addEventListener("cancel", (event) => { // Escape
      event.preventDefault();
      if (!this.sending) this.close();
    });
    return dialog;
  }

  /** Show or hide the link for `state` (null: no session, e.g. an invalid link), and word a withdrawal's end. */
  update(state) {
    this.state = state;
    this.link.textContent = t("withdraw.link");
    this.link.hidden = !state || NO_LINK.has(state.phase) || !state.withdrawal;
    if (!state || state.phase !== "withdrawn" || !state.withdrawal || state.withdrawal.by !== "participant") return;
    const heading = $("end-heading");
    const text = $("end-text");
    if (heading) heading.textContent = t("withdraw.end_heading");
    if (text) {
      text.textContent = state.withdrawal.text ? t("withdraw.end_own_text")
        : state.withdrawal.data === "delete" ? t("withdraw.end_deleted") : t("withdraw.end_kept");
    }
    if (heading) document.title = `${t("withdraw.end_heading")} – ${state.study_title}`;
  }

  open() {
    const withdrawal = this.state && this.state.withdrawal;
    if (!withdrawal) return;
    const parts = [element("p", {}, t("withdraw.intro"))];
    if (withdrawal.text) {
      parts.push(element("p", {}, element("strong", {}, t("withdraw.study_text")), " ", withdrawal.text));
    } else {
      parts.push(element("p", {}, withdrawal.data === "delete" ? t("withdraw.delete") : t("withdraw.keep")));
    }
    this.heading.textContent = t("withdraw.heading");
    this.cancel.textContent = t("withdraw.cancel");
    this.what.replaceChildren(...parts);
    this.error.textContent = "";
    this.confirm.disabled = this.cancel.disabled = false;
    this.confirm.textContent = t("withdraw.confirm");
    this.app.events.log("withdraw_asked", { phase: this.state.phase });
    this.dialog.showModal();
    this.cancel.focus(); // the safe choice has the focus: Enter never withdraws by accident
  }

  close() {
    if (this.dialog.open) this.dialog.close();
    this.app.events.log("withdraw_cancelled", { phase: this.state ? this.state.phase : null });
    this.link.focus();
  }

  async send() {
    if (this.sending) return;
    this.sending = true;
    this.confirm.disabled = this.cancel.disabled = true;
    this.confirm.textContent = t("withdraw.working");
    await this.app.events.flush(); // what the page logged so far goes first (a kept session keeps it)
    const seq = ++this.app.issued;
    try {
      const state = await this.app.api.request("POST", `${this.app.base}/withdraw`, { body: { confirm: true } });
      this.dialog.close();
      this.app.apply(seq, state); // the end page (participant.js), then update() words it
      const redirect = state.completion && state.completion.redirect_url;
      if (redirect && !state.preview) setTimeout(() => location.assign(redirect), REDIRECT_MS);
    } catch (err) {
      this.error.textContent = t("withdraw.failed");
      this.confirm.disabled = this.cancel.disabled = false;
      this.confirm.textContent = t("withdraw.confirm");
      this.confirm.focus();
    } finally {
      this.sending = false;
    }
  }
}

function element(tag, attributes = {}, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(attributes)) node.setAttribute(name, value);
  node.append(...children);
  return node;
}
