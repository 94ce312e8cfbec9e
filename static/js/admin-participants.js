// The live participants table: polled every 2 s while it is shown and the tab is visible,
// updated in place (rows keyed by participant, cells rewritten only when they change) so
// scroll position, focus and selections survive. Exclude/include, withdraw and delete ask for a reason.
// Above the table, how the server keeps up (GET /api/admin/server/load): a warning when the
// participants' 3D views skip frames, so the experimenter can cap concurrent participants.

import { describe } from "./admin-api.js";
import { $, ago, badge, countsText, el, number, previewText, setText, showError, sparkline } from "./admin-ui.js";

const POLL_MS = 2000;

export class ParticipantsPanel {
  constructor(app) {
    this.app = app;
    this.slug = null;
    this.rows = new Map();
    this.timer = null;
    this.active = false;
    this.inFlight = false;
    $("participants-filter").addEventListener("change", () => this.applyFilter());
    $("participants-delete-previews").addEventListener("click", () => this.deleteAllPreviews());
  }

  enter(study) {
    if (this.slug !== study.slug) {
      this.rows.clear();
      $("participants-body").replaceChildren();
      setText($("participants-summary"), "Loading…");
      setText($("participants-updated"), "");
    }
    this.slug = study.slug;
    this.active = true;
    this.poll();
  }

  leave() {
    this.active = false;
    clearTimeout(this.timer);
    this.timer = null;
  }

  visibilityChanged() {
    if (!this.active) return;
    clearTimeout(this.timer);
    this.timer = null;
    if (document.visibilityState === "visible") this.poll();
  }

  schedule() {
    clearTimeout(this.timer);
    if (this.active && document.visibilityState === "visible") this.timer = setTimeout(() => this.poll(), POLL_MS);
  }

  async poll() {
    if (this.inFlight) return;
    this.inFlight = true;
    const slug = this.slug;
    try {
      const response = await this.app.api.request("GET", `/api/admin/studies/${encodeURIComponent(slug)}/participants`,
        { raw: true });
      const rows = await response.json();
      const serverNow = Date.parse(response.headers.get("Date")) || Date.now();
      if (slug === this.slug && this.active) this.render(rows, serverNow);
      $("participants-error").textContent = "";
    } catch (err) {
      if (err.status !== 401) showError($("participants-error"), "Could not refresh the participants (retrying)", err);
    }
    await this.pollLoad();
    this.inFlight = false;
    this.schedule();
  }

  async pollLoad() {
    const line = $("server-load");
    try {
      const load = await this.app.api.request("GET", "/api/admin/server/load");
      line.hidden = false;
      line.className = `server-load small ${["busy", "overloaded"].includes(load.status) ? `load-${load.status}` : load.status === "fault" ? "load-overloaded" : "muted"}`;
      const rate = load.world_ticks_per_s === null ? "" :
        ` · world updates ${load.world_ticks_per_s.toFixed(0)}/s of ${load.world_hz.toFixed(0)}` +
        ` · 3D views skipped ${(100 * load.view_skipped_share).toFixed(0)} % of them`;
      const open = ` · ${load.viewers} 3D view${load.viewers === 1 ? "" : "s"} open now`;
      setText(line, `Server, last minute: ${load.message}${rate}${open}`);
    } catch (err) {
      line.hidden = true;  // the table's own error line says when the server does not answer
    }
  }

  render(rows, serverNow) {
    const counts = {};
    const real = rows.filter((p) => !p.preview);
    for (const p of real) counts[p.status] = (counts[p.status] || 0) + 1;
    const excluded = real.filter((p) => p.excluded && p.status !== "withdrawn").length;
    const people = `${real.length} participant${real.length === 1 ? "" : "s"}`;
    const previews = previewText(rows.length - real.length);
    setText($("participants-summary"),
      `${people}: ${countsText(counts)}${excluded ? ` · ${excluded} excluded` : ""}${previews}`);
    setText($("study-counts"), countsText(counts) + previews);
    $("participants-delete-previews").hidden = rows.length === real.length;
    for (const [id, row] of this.rows) {  // deleted previews leave the table
      if (!rows.some((p) => p.public_id === id)) {
        row.tr.remove();
        this.rows.delete(id);
      }
    }
    setText($("participants-updated"), `Updated ${new Date().toLocaleTimeString()} · refreshes every 2 s`);
    $("participants-empty").hidden = rows.length > 0;
    const body = $("participants-body");
    for (const p of rows) {
      let row = this.rows.get(p.public_id);
      if (!row) {
        row = this.createRow(p.public_id);
        this.rows.set(p.public_id, row);
        body.append(row.tr);
      }
      this.updateRow(row, p, serverNow);
    }
    this.applyFilter();
  }

  /** Hide the rows the filter leaves out (rows are never moved, so focus and scroll stay). */
  applyFilter() {
    const filter = $("participants-filter").value;
    const keep = {
      all: () => true,
      active: (p) => p.status === "active",
      completed: (p) => p.status === "completed",
      excluded: (p) => p.excluded,
      flagged: (p) => p.flags.length > 0,
      preview: (p) => p.preview,
    }[filter];
    let shown = 0;
    for (const row of this.rows.values()) {
      row.tr.hidden = !keep(row.data);
      shown += row.tr.hidden ? 0 : 1;
    }
    $("participants-none-shown").hidden = shown > 0 || this.rows.size === 0;
  }

  createRow(publicId) {
    const cells = {};
    const names = ["who", "status", "phase", "block", "trial", "score", "belief", "seen", "flags", "actions"];
    const tr = el("tr", { "data-participant": publicId });
    for (const name of names) {
      cells[name] = el(name === "who" ? "th" : "td", name === "who" ? { scope: "row" } : {});
      if (["trial", "score"].includes(name)) cells[name].className = "num";
      tr.append(cells[name]);
    }
    const exclude = el("button", { type: "button", class: "small-button", "data-action": "exclude" }, "Exclude");
    const withdraw = el("button", { type: "button", class: "small-button danger-outline", "data-action": "withdraw" },
      "Withdraw");
    // A preview session is deleted at once; a real participant's data on their request, with a reason.
    const remove = el("button", { type: "button", class: "small-button danger-outline", "data-action": "delete" },
      "Delete");
    // every trial so far, rebuilt from the database as one HTML file that plays offline (server/viewer/replay_page.py)
    const replay = el("button", { type: "button", class: "small-button", "data-action": "replay",
      title: "Download a 3D replay of this participant's trials (one HTML file, plays offline)" }, "Replay");
    exclude.addEventListener("click", () => this.askExclude(row.data));
    withdraw.addEventListener("click", () => this.askWithdraw(row.data));
    remove.addEventListener("click", () => (row.data.preview ? this.deletePreview(row.data, remove)
      : this.askDelete(row.data)));
    replay.addEventListener("click", () => this.downloadReplay(row.data, replay));
    cells.actions.append(replay, exclude, withdraw, remove);
    const row = { tr, cells, exclude, withdraw, remove, replay, keys: {}, data: null };
    return row;
  }

  /** Rewrite a cell only when what it shows changed. */
  cell(row, name, key, build) {
    if (row.keys[name] === key) return;
    row.keys[name] = key;
    row.cells[name].replaceChildren(...build().filter((child) => child !== null));
  }

  updateRow(row, p, serverNow) {
    row.data = p;
    this.cell(row, "who", `${p.public_id}|${p.external_id}`, () => [el("code", {}, p.public_id),
      p.external_id ? el("div", { class: "muted small" }, p.external_id) : null]);
    this.cell(row, "status", `${p.status}|${p.excluded}|${p.exclusion_reason}|${p.preview}`, () => [badge(p.status),
      p.preview ? el("span", { class: "badge badge-preview", title: "A preview session: not data" }, "preview") : null,
      p.excluded && p.status !== "withdrawn" ? el("span", { class: "badge badge-excluded" }, "excluded") : null,
      shownReason(p) ? el("div", { class: "muted small reason", title: shownReason(p) }, shownReason(p)) : null]);
    this.cell(row, "phase", p.phase, () => [p.phase.replace(/_/g, " ")]);
    this.cell(row, "block", `${p.block}|${p.block_name}`, () => [p.block ? `${p.block} · ${p.block_name}` : "–"]);
    this.cell(row, "trial", String(p.trial), () => [p.trial ? String(p.trial) : "–"]);
    this.cell(row, "score", String(p.score), () => [number(p.score, 0)]);
    this.cell(row, "belief", `${p.belief}|${p.belief_history.join(",")}`, () => [el("span", { class: "belief" },
      sparkline(p.belief_history), el("span", { class: "belief-value" }, number(p.belief)))]);
    const seen = ago(Math.max(0, (serverNow - Date.parse(p.last_seen_at)) / 1000));
    this.cell(row, "seen", seen, () => [el("time", { datetime: p.last_seen_at, title: p.last_seen_at }, seen)]);
    this.cell(row, "flags", JSON.stringify(p.flags), () => p.flags.length
      ? p.flags.map((f) => el("span", { class: `flag flag-${f.code}`, title: f.detail },
        f.code.replace(/_/g, " "), el("span", { class: "visually-hidden" }, `: ${f.detail}`)))
      : [el("span", { class: "muted" }, "–")]);
    const withdrawn = p.status === "withdrawn";
    setText(row.exclude, p.excluded ? "Include" : "Exclude");
    row.exclude.dataset.action = p.excluded ? "include" : "exclude";
    row.exclude.disabled = withdrawn;
    row.withdraw.disabled = withdrawn;
    row.exclude.setAttribute("aria-label", `${p.excluded ? "Include" : "Exclude"} participant ${p.public_id}`);
    row.withdraw.setAttribute("aria-label", this.withdrawalDeletes()
      ? `Withdraw participant ${p.public_id} and delete their data` : `Withdraw participant ${p.public_id}`);
    // A preview is not data: it is deleted, never excluded or withdrawn.
    row.tr.classList.toggle("is-preview", Boolean(p.preview));
    row.exclude.hidden = row.withdraw.hidden = Boolean(p.preview);
    setText(row.remove, p.preview ? "Delete" : "Delete data");
    row.remove.setAttribute("aria-label", p.preview ? `Delete preview session ${p.public_id}`
      : `Delete this participant's data (${p.public_id})`);
    row.replay.setAttribute("aria-label", `Download a 3D replay of the trials of ${p.public_id}`);
  }

  async downloadReplay(p, button) {
    button.disabled = true;
    setText(button, "Building…");
    try {
      await this.app.api.download(this.participantPath(p, "replay"), `replay-${p.public_id}.html`);
    } catch (err) {
      showError($("participants-error"), `Could not build the replay of ${p.public_id}`, err);
    } finally {
      button.disabled = false;
      setText(button, "Replay");
    }
  }

  async deletePreview(p, button) {
    button.disabled = true;
    try {
      const path = `/api/admin/studies/${encodeURIComponent(this.slug)}/participants/${encodeURIComponent(p.public_id)}`;
      await this.app.api.request("DELETE", path);
      const row = this.rows.get(p.public_id);
      if (row) {
        row.tr.remove();
        this.rows.delete(p.public_id);
      }
      this.poll();
    } catch (err) {
      button.disabled = false;
      showError($("participants-error"), `Could not delete preview session ${p.public_id}`, err);
    }
  }

  async deleteAllPreviews() {
    const button = $("participants-delete-previews");
    button.disabled = true;
    try {
      await this.app.api.request("DELETE", `/api/admin/studies/${encodeURIComponent(this.slug)}/previews`);
      this.poll();
    } catch (err) {
      showError($("participants-error"), "Could not delete the preview sessions", err);
    } finally {
      button.disabled = false;
    }
  }

  // -- actions ----------------------------------------------------------------------------
  participantPath(p, action) {
    const study = encodeURIComponent(this.slug);
    return `/api/admin/studies/${study}/participants/${encodeURIComponent(p.public_id)}/${action}`;
  }

  askExclude(p) {
    const include = p.excluded;
    reasonDialog({
      heading: `${include ? "Include" : "Exclude"} participant ${p.public_id}`,
      text: include
        ? "Their data will be used in the analysis again."
        : "Their data stay in the exports (marked excluded) but are left out of model fits and the report.",
      submit: include ? "Include" : "Exclude",
      action: (reason) => this.app.api.post(this.participantPath(p, include ? "include" : "exclude"), { reason }),
      done: () => this.poll(),
    });
  }

  /** Whether a withdrawal deletes the data in this study (its config privacy.withdrawal; "keep" by default). */
  withdrawalDeletes() {
    const config = this.app.study && this.app.study.config;
    return Boolean(config && config.privacy && config.privacy.withdrawal === "delete");
  }

  askWithdraw(p) {
    const deletes = this.withdrawalDeletes();
    reasonDialog({
      heading: `Withdraw participant ${p.public_id}`,
      text: deletes
        ? "Their session ends as withdrawn and, as this study's setting privacy.withdrawal says (delete), their "
          + "trials, answers and events are deleted for good. Only an audit line that names no one remains, with "
          + "your reason."
        : "Their session ends as withdrawn. As this study's setting privacy.withdrawal says (keep), their trials, "
          + "answers and events stay, marked withdrawn and excluded from fits and the report, and their "
          + "recruitment ID and other personal fields are erased. To delete their data, use “Delete data”.",
      submit: deletes ? "Withdraw and delete data" : "Withdraw",
      danger: true,
      confirm: deletes ? `I understand that this deletes the data of ${p.public_id} and cannot be undone.` : null,
      action: (reason) => this.app.api.post(this.participantPath(p, "withdraw"), { reason }),
      done: () => this.poll(),
    });
  }

  /** Delete a real participant's data on their request (GDPR art. 17): every row, with the reason audited. */
  askDelete(p) {
    const path = `/api/admin/studies/${encodeURIComponent(this.slug)}/participants/${encodeURIComponent(p.public_id)}`;
    reasonDialog({
      heading: `Delete the data of participant ${p.public_id}`,
      text: "Deletes every row of this participant for good: trials, answers, events, teleoperation logs, and "
        + "the participant. Only an audit line that names no one remains, with your reason (write no personal "
        + "data in it). Backups made before keep the data until they expire.",
      submit: "Delete data",
      danger: true,
      confirm: `I understand that this deletes the data of ${p.public_id} and cannot be undone.`,
      action: (reason) => this.app.api.request("DELETE", path, { body: { reason } }),
      done: () => {
        const row = this.rows.get(p.public_id);
        if (row) {
          row.tr.remove();
          this.rows.delete(p.public_id);
        }
        this.poll();
      },
    });
  }
}

/** The exclusion reason a row shows under its badges, or null. A withdrawal excludes with the reason "withdrawn",
 * which the status badge already says (the experimenter's own words are in the audit log): shown once, as the badge. */
export function shownReason(p) {
  if (!p.excluded || !p.exclusion_reason) return null;
  if (p.status === "withdrawn" && p.exclusion_reason.trim().toLowerCase() === "withdrawn") return null;
  return p.exclusion_reason;
}

/** The modal that asks for a reason (and a confirmation), runs the action and shows its error in place. */
function reasonDialog({ heading, text, submit, danger = false, confirm = null, action, done }) {
  const dialog = $("reason-dialog");
  const opener = document.activeElement;
  setText($("reason-heading"), heading);
  setText($("reason-text"), text);
  $("reason-input").value = "";
  $("reason-error").textContent = "";
  $("reason-confirm-row").hidden = !confirm;
  $("reason-confirm").checked = false;
  $("reason-confirm").required = Boolean(confirm);
  setText($("reason-confirm-text"), confirm || "");
  const button = $("reason-submit");
  setText(button, submit);
  button.classList.toggle("danger", danger);
  button.classList.toggle("primary", !danger);
  const form = $("reason-form");
  const close = () => {
    form.onsubmit = null;
    dialog.close();
    if (opener && opener.isConnected) opener.focus();
  };
  form.onsubmit = async (event) => {
    event.preventDefault();
    const reason = $("reason-input").value.trim();
    if (!reason) {
      $("reason-error").textContent = "Give a reason: it is kept in the audit log.";
      $("reason-input").focus();
      return;
    }
    if (confirm && !$("reason-confirm").checked) {
      $("reason-error").textContent = "Tick the box to confirm that the data may be deleted.";
      $("reason-confirm").focus();
      return;
    }
    button.disabled = true;
    try {
      await action(reason);
      close();
      done();
    } catch (err) {
      $("reason-error").textContent = describe(`${submit} failed`, err);
    } finally {
      button.disabled = false;
    }
  };
  $("reason-cancel").onclick = close;
  dialog.oncancel = (event) => {
    event.preventDefault();
    close();
  };
  dialog.showModal();
  $("reason-input").focus();
}
