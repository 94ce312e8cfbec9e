// A study's config versions (who saved each, when, how many participants ran under it), the changes between
// any two side by side (path, before, after), and duplicating the study (e.g. for the next wave).

import { $, el, setText, showError, table } from "./admin-ui.js";

const KIND_WORDS = { changed: "changed", added: "added", removed: "removed" };

/** A JSON value as short text for a diff cell. */
function shown(value) {
  if (value === undefined) return "";
  return typeof value === "string" ? JSON.stringify(value) : JSON.stringify(value, null, 1);
}

export class VersionsPanel {
  constructor(app, designer) {
    this.app = app;
    this.designer = designer;
    this.list = [];
    $("diff-show").addEventListener("click", () => this.showDiff());
    $("designer-duplicate").addEventListener("click", () => this.askDuplicate());
    $("duplicate-form").addEventListener("submit", (event) => {
      event.preventDefault();
      this.duplicate();
    });
    $("duplicate-cancel").addEventListener("click", () => $("duplicate-dialog").close());
  }

  path(suffix) {
    return `/api/admin/studies/${encodeURIComponent(this.app.study.slug)}/${suffix}`;
  }

  async refresh() {
    setText($("versions-error"), "");
    try {
      this.list = await this.app.api.get(this.path("versions"));
    } catch (err) {
      showError($("versions-error"), "Could not load the versions", err);
      return;
    }
    const rows = this.list.map((v) => el("tr", {},
      el("th", { scope: "row" }, `v${v.version}`),
      el("td", {}, new Date(v.created_at).toLocaleString()),
      el("td", {}, v.author),
      el("td", { class: "num" }, String(v.participants)),
      el("td", {}, el("code", { title: v.config_hash }, v.config_hash.slice(0, 12)))));
    $("versions-table").replaceChildren(table("versions-heading",
      ["Version", "Saved", "By", ["Participants", true], "Config hash"], rows));
    const options = (select, chosen) => select.replaceChildren(...this.list.map((v) =>
      el("option", { value: String(v.version), selected: v.version === chosen }, `v${v.version} (${v.author})`)));
    const last = this.list.length ? this.list[this.list.length - 1].version : 1;
    options($("diff-from"), Math.max(1, last - 1));
    options($("diff-to"), last);
    $("diff-show").disabled = this.list.length < 2;
  }

  async showDiff() {
    setText($("versions-error"), "");
    const from = $("diff-from").value;
    const to = $("diff-to").value;
    let diff;
    try {
      diff = await this.app.api.get(`${this.path("versions/diff")}?from=${from}&to=${to}`);
    } catch (err) {
      showError($("versions-error"), "Could not compare the versions", err);
      return;
    }
    const heading = $("diff-heading");
    heading.hidden = false;
    heading.textContent = diff.changes.length
      ? `Changes from v${diff.from_version} to v${diff.to_version}: ${diff.changes.length}`
      : `v${diff.from_version} and v${diff.to_version} are the same`;
    const rows = diff.changes.map((c) => el("tr", { class: `diff-${c.kind}` },
      el("th", { scope: "row" }, el("code", {}, c.path || "(document)"),
        el("span", { class: "diff-kind" }, KIND_WORDS[c.kind])),
      el("td", {}, el("pre", { class: "diff-value" }, c.kind === "added" ? "—" : shown(c.before))),
      el("td", {}, el("pre", { class: "diff-value" }, c.kind === "removed" ? "—" : shown(c.after)))));
    $("diff-table").replaceChildren(diff.changes.length
      ? table("diff-heading", ["Field", `Before (v${diff.from_version})`, `After (v${diff.to_version})`], rows) : "");
    heading.focus();
  }

  askDuplicate() {
    const study = this.app.study;
    const wave = /^(.*)-(\d+)$/.exec(study.slug); // pilot-1 → pilot-2; pilot → pilot-2
    const next = wave ? `${wave[1]}-${Number(wave[2]) + 1}` : `${study.slug}-2`;
    $("duplicate-slug").value = next.slice(0, 63);
    $("duplicate-title").value = `${study.title} (copy)`.slice(0, 200);
    setText($("duplicate-error"), "");
    $("duplicate-dialog").showModal();
    $("duplicate-slug").select();
  }

  async duplicate() {
    if (!$("duplicate-form").reportValidity()) return;
    setText($("duplicate-error"), "");
    $("duplicate-submit").disabled = true;
    try {
      const author = $("designer-author").value.trim() || undefined;
      const copy = await this.app.api.post(this.path("duplicate"), {
        slug: $("duplicate-slug").value.trim(), title: $("duplicate-title").value.trim(), author });
      $("duplicate-dialog").close();
      this.app.go(copy.slug, "config");
    } catch (err) {
      showError($("duplicate-error"), "Could not duplicate the study", err);
    } finally {
      $("duplicate-submit").disabled = false;
    }
  }
}
