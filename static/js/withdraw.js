// "Withdraw from the study" (issue 41, the participant's rights): a quiet link in the top bar of every page of
// the session; it opens a confirmation that says what happens to the data (the study's own words, config
// privacy.withdrawal_text, or what privacy.withdrawal does), and confirming ends the session with
// POST /api/p/{token}/withdraw. The page then shows its end (the outcome's code and redirect, if the study gives
// them), as it shows any state: participant.js renders the answer.
//
// Every English text of this feature is in TEXT, so that the message catalogues can take them over.

export const TEXT = {
  link: "Withdraw from the study",
  heading: "Withdraw from the study?",
  intro: "You can stop taking part at any time, without giving a reason.",
  keep: "If you withdraw, your session ends now. What you have done so far is kept for the research, marked as "
    + "withdrawn and left out of the analysis; your recruitment ID and other details that could identify you are "
    + "erased.",
  delete: "If you withdraw, your session ends now and everything you have done in this study is deleted: your "
    + "choices, your answers and your recruitment ID.",
  studyText: "What happens to your data:",
  confirm: "Yes, withdraw and end my session",
  cancel: "No, continue the study",
  working: "Withdrawing…",
  failed: "Your withdrawal could not be sent. Please try again.",
  endHeading: "You have withdrawn from the study",
  endKept: "Your session has ended. What you did so far is kept for the research, marked as withdrawn, and your "
    + "recruitment ID has been erased. Thank you for your time. You can close this page.",
  endDeleted: "Your session has ended and your data have been deleted. Thank you for your time. You can close "
    + "this page.",
  endOwnText: "Your session has ended. Thank you for your time. You can close this page.",
};

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
      "aria-haspopup": "dialog" }, TEXT.link);
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
    this.confirm = element("button", { type: "button", id: "withdraw-confirm", class: "danger" }, TEXT.confirm);
    this.cancel = element("button", { type: "button", id: "withdraw-cancel", class: "primary" }, TEXT.cancel);
    dialog.append(element("h2", { id: "withdraw-heading" }, TEXT.heading), this.what,
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
    this.link.hidden = !state || NO_LINK.has(state.phase) || !state.withdrawal;
    if (!state || state.phase !== "withdrawn" || !state.withdrawal || state.withdrawal.by !== "participant") return;
    const heading = $("end-heading");
    const text = $("end-text");
    if (heading) heading.textContent = TEXT.endHeading;
    if (text) {
      text.textContent = state.withdrawal.text ? TEXT.endOwnText
        : state.withdrawal.data === "delete" ? TEXT.endDeleted : TEXT.endKept;
    }
    if (heading) document.title = `${TEXT.endHeading} – ${state.study_title}`;
  }

  open() {
    const withdrawal = this.state && this.state.withdrawal;
    if (!withdrawal) return;
    const parts = [element("p", {}, TEXT.intro)];
    if (withdrawal.text) parts.push(element("p", {}, element("strong", {}, TEXT.studyText), " ", withdrawal.text));
    else parts.push(element("p", {}, withdrawal.data === "delete" ? TEXT.delete : TEXT.keep));
    this.what.replaceChildren(...parts);
    this.error.textContent = "";
    this.confirm.disabled = this.cancel.disabled = false;
    this.confirm.textContent = TEXT.confirm;
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
    this.confirm.textContent = TEXT.working;
    await this.app.events.flush(); // what the page logged so far goes first (a kept session keeps it)
    const seq = ++this.app.issued;
    try {
      const state = await this.app.api.request("POST", `${this.app.base}/withdraw`, { body: { confirm: true } });
      this.dialog.close();
      this.app.apply(seq, state); // the end page (participant.js), then update() words it
      const redirect = state.completion && state.completion.redirect_url;
      if (redirect && !state.preview) setTimeout(() => location.assign(redirect), REDIRECT_MS);
    } catch (err) {
      this.error.textContent = TEXT.failed;
      this.confirm.disabled = this.cancel.disabled = false;
      this.confirm.textContent = TEXT.confirm;
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
