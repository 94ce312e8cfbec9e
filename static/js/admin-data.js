// Downloads of the study's exports and report zip (fetched with the bearer header, saved from a
// Blob), and the link to the report page at its own address (/api/admin/studies/{slug}/report.html):
// a tab cannot send the bearer header, so entering the panel trades the token for the server's
// report-reading cookie (HttpOnly, for report pages only) and only then enables the link.

import { describe } from "./admin-api.js";
import { $, setText } from "./admin-ui.js";

export class DataPanel {
  constructor(app) {
    this.app = app;
    for (const button of document.querySelectorAll("[data-download]")) {
      button.addEventListener("click", () => this.download(button, button.dataset.download));
    }
    $("report-open").addEventListener("click", () => {
      setText($("data-status"), "The report opens in a new tab; building it takes a few seconds.");
    });
    $("data-include-preview").addEventListener("change", () => this.linkReport());
  }

  enter() {
    $("data-include-preview").checked = false; // previews are not data: included only when asked, each time
    setText($("data-status"), "");
    setText($("data-error"), "");
    return this.allowReportPage();
  }

  async allowReportPage() {
    const link = $("report-open");
    this.reportAllowed = false;
    link.setAttribute("aria-disabled", "true");
    link.removeAttribute("href");
    try {
      const access = await this.app.api.request("POST", "/api/admin/report-access", { credentials: "same-origin" });
      const hours = Math.round((Date.parse(access.expires_at) - Date.now()) / 3600000);
      if (hours > 0) setText($("report-access-hours"), String(hours));
    } catch (err) {
      setText($("data-error"), describe("The report page cannot be opened from here", err));
      return;
    }
    this.reportAllowed = true;
    this.linkReport();
    link.removeAttribute("aria-disabled");
  }

  /** "?include_preview=true" when the experimenter asked for their preview sessions too, else "". */
  previewQuery() {
    return $("data-include-preview").checked ? "?include_preview=true" : "";
  }

  /** Point the report link at the page (with or without previews), once this browser may open report pages. */
  linkReport() {
    if (this.reportAllowed) $("report-open").href = `${this.base()}/report.html${this.previewQuery()}`;
  }

  leave() {}

  base() {
    return `/api/admin/studies/${encodeURIComponent(this.app.study.slug)}`;
  }

  async run(button, working, work) {
    setText($("data-error"), "");
    setText($("data-status"), working);
    button.disabled = true;
    try {
      setText($("data-status"), await work());
    } catch (err) {
      setText($("data-status"), "");
      setText($("data-error"), describe(working.replace(/…$/, " failed"), err));
    } finally {
      button.disabled = false;
    }
  }

  download(button, what) {
    const path = (what === "report" ? `${this.base()}/report` : `${this.base()}/${what}`)
      + (what.endsWith("codebook.csv") ? "" : this.previewQuery());
    const fallback = `${this.app.study.slug}-${what.replace("export/", "")}${what === "report" ? ".zip" : ""}`;
    const working = what === "report" ? "Building the report…" : `Preparing ${what.replace("export/", "")}…`;
    return this.run(button, working, async () => `Downloaded ${await this.app.api.download(path, fallback)}.`);
  }
}
