// Downloads of the study's exports and report (fetched with the bearer header, saved from a
// Blob), and the HTML report opened in a new tab from a Blob URL.

import { describe } from "./admin-api.js";
import { $, setText } from "./admin-ui.js";

const REPORT_URL_LIFETIME_MS = 10 * 60 * 1000;

export class DataPanel {
  constructor(app) {
    this.app = app;
    for (const button of document.querySelectorAll("[data-download]")) {
      button.addEventListener("click", () => this.download(button, button.dataset.download));
    }
    $("report-open").addEventListener("click", () => this.openReport());
  }

  enter() {
    setText($("data-status"), "");
    setText($("data-error"), "");
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
    const path = what === "report" ? `${this.base()}/report` : `${this.base()}/${what}`;
    const fallback = `${this.app.study.slug}-${what.replace("export/", "")}${what === "report" ? ".zip" : ""}`;
    const working = what === "report" ? "Building the report…" : `Preparing ${what.replace("export/", "")}…`;
    return this.run(button, working, async () => `Downloaded ${await this.app.api.download(path, fallback)}.`);
  }

  openReport() {
    // Open the tab now, while the click still counts as a user gesture, and fill it when the report is ready.
    const tab = window.open("", "_blank");
    return this.run($("report-open"), "Building the report…", async () => {
      let file;
      try {
        file = await this.app.api.fetchFile(`${this.base()}/report.html`, "report.html");
      } catch (err) {
        if (tab) tab.close();
        throw err;
      }
      const url = URL.createObjectURL(new Blob([file.blob], { type: "text/html" }));
      setTimeout(() => URL.revokeObjectURL(url), REPORT_URL_LIFETIME_MS);
      if (!tab) throw new Error("the browser blocked the new tab: allow pop-ups for this page, or download the zip");
      tab.location.href = url;
      return "The report opened in a new tab.";
    });
  }
}
