"""The experimenter's dashboard in the real browser, with bots as the participants.

An experimenter logs in, creates a study from a template, watches bots fill the live
participants table, excludes one, fails to save an invalid config, downloads the export, fits
the model, deploys the evaluation study, runs bots on it, withdraws one and opens the report.
"""

from __future__ import annotations

import csv
import io
import json
import re
import threading
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from playwright.sync_api import Page, expect

from experiment.iohmm import paper_params
from server.cli.server import bots
from server.harness.bots import Bot
from server.harness.client import BotStats, remote_sockets
from server.harness.live import BOT_TELEOP_SETTINGS
from tests.browser.conftest import LiveServer, serving

BOTS = 5  # four are fitted (one is excluded): with three, an input the policy needs went unexercised in ~5 % of runs
SCORED_TRIALS = 12  # the pilot's one block, and demo-fast's two blocks of 6
PRACTICE_TRIALS = 4
BOTS_TIMEOUT_MS = 180_000
STATUS_TEXT = {"estimated": "estimated", "boundary": "at a bound", "unidentified": "not identified",
               "not_exercised": "not exercised"}


@pytest.fixture
def live_server(sqlite_template: Path, tmp_path: Path) -> Iterator[LiveServer]:
    """The app as deployed, but for the teleoperation socket's pace, which is the bots' test setting
    (``BOT_TELEOP_SETTINGS``: world 60/s, 120 messages/s): the participants here are bots, never the page, and their
    scripted teleoperations take about half as long. The dashboard is served exactly as deployed."""
    with serving(sqlite_template, tmp_path, **BOT_TELEOP_SETTINGS) as live:
        yield live


class BotRun:
    """``trustlab bots`` against the live server, in a thread (the page is driven meanwhile), all of them at once."""

    def __init__(self, url: str, slug: str, participants: int, seed: int):
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, args=(url, slug, participants, seed), daemon=True)
        self.thread.start()

    def _run(self, url: str, slug: str, participants: int, seed: int) -> None:
        try:
            bots(url, study=slug, participants=participants, concurrency=participants, model="paper", seed=seed,
                 as_json=True)
        except Exception as exc:  # noqa: BLE001 -- typer.Exit too (a bot failed): reported by join()
            self.error = exc

    def join(self) -> None:
        self.thread.join(timeout=BOTS_TIMEOUT_MS / 1000)
        assert not self.thread.is_alive(), "the bots did not finish"
        assert self.error is None, f"the bots failed: {self.error!r}"


def log_in(page: Page, server: LiveServer) -> None:
    page.goto(f"{server.url}/admin")
    page.get_by_label("Admin token").fill("tla_not-the-token")
    page.get_by_role("button", name="Log in").click()
    expect(page.locator("#login-error")).to_contain_text("Not logged in: this admin token is not (or no longer) valid")
    expect(page.get_by_label("Admin token")).to_have_value("tla_not-the-token")
    expect(page.get_by_role("heading", name="Studies")).to_be_hidden()
    page.get_by_label("Admin token").fill(server.admin_token)
    page.keyboard.press("Enter")
    expect(page.get_by_role("heading", name="Studies")).to_be_visible()


def rows(page: Page):
    return page.locator("#participants-body tr")


def row_of(page: Page, public_id: str):
    return page.locator(f'#participants-body tr[data-participant="{public_id}"]')


def api_participants(server: LiveServer, slug: str) -> list[dict[str, Any]]:
    response = server.admin("GET", f"/api/admin/studies/{slug}/participants")
    assert response.status_code == 200, response.text
    return response.json()


def download(page: Page, button_name: str, tmp_path: Path) -> Path:
    with page.expect_download() as info:
        page.get_by_role("button", name=button_name, exact=True).click()
    target = tmp_path / info.value.suggested_filename
    info.value.save_as(target)
    return target


def create_study(page: Page, template: str, slug: str) -> None:
    page.get_by_label("Template", exact=True).select_option(template)
    page.get_by_label("Slug (used in the join link)").fill(slug)
    page.get_by_role("button", name="Create study").click()
    expect(page.get_by_role("tab", name="Configuration")).to_have_attribute("aria-selected", "true")


def check_invalid_config_is_explained(page: Page) -> None:
    page.get_by_role("button", name="Advanced: raw JSON").click()
    editor = page.get_by_label("Study configuration (JSON)")
    text = editor.input_value()
    assert '"shelf_size": 3' in text
    editor.fill(text.replace('"shelf_size": 3', '"shelf_size": -2', 1))
    page.get_by_role("button", name="Validate and save").click()
    problems = page.locator("#config-problems li")
    expect(problems).to_have_count(1)
    expect(problems.first).to_contain_text("shelf_size")
    expect(problems.first).to_contain_text("greater than or equal to 1")
    expect(page.locator("#config-problems-detail")).to_contain_text("HTTP 422")
    problems.first.get_by_role("button").click()  # selects the offending member in the editor
    selected = editor.evaluate("e => e.value.slice(e.selectionStart, e.selectionEnd)")
    assert selected == '"shelf_size": -2'
    editor.fill("{ not json")
    page.get_by_role("button", name="Validate and save").click()
    expect(page.locator("#config-problems-detail")).to_contain_text("not valid JSON")
    page.get_by_role("button", name="Discard changes").click()
    assert '"shelf_size": 3' in editor.input_value()
    expect(page.locator("#config-problems li")).to_have_count(0)


def make_it_a_pilot(page: Page) -> None:
    """Through the editor: one block where the robot asks at random and fails often, so that a few bots exercise
    every model input the trust-aware policy needs (the demo's policies never ask in low complexity)."""
    editor = page.get_by_label("Study configuration (JSON)")
    config = json.loads(editor.input_value())
    schedule = {**config["blocks"][0]["schedule"], "n_low": SCORED_TRIALS // 2, "n_high": SCORED_TRIALS // 2}
    config["blocks"] = [{"name": "estimation", "label": "Main task", "schedule": schedule,
                         "policy": {"kind": "random_assist", "p_ask_low": 0.3, "p_ask_high": 0.3}}]
    config.update(title="Pilot", counterbalance="none")
    config["task"].update(p_success_low=0.55, p_success_high=0.65)
    editor.fill(json.dumps(config, indent=2))
    page.get_by_role("button", name="Validate and save").click()
    expect(page.locator("#config-status")).to_have_text("Saved as version 2.")  # every changed save is a version
    expect(page.get_by_role("heading", name="Pilot", exact=True)).to_be_visible()


def open_from_the_page(page: Page, server: LiveServer, slug: str) -> None:
    """A new study is a draft: the experimenter opens it before anyone can join."""
    expect(page.locator("#study-status")).to_have_text("draft")
    page.get_by_role("button", name="Open study").click()
    expect(page.locator("#study-status")).to_have_text("open")
    assert server.admin("GET", f"/api/admin/studies/{slug}").json()["status"] == "open"


def watch_the_table_fill(page: Page, run: BotRun) -> None:
    """Rows appear and change while the bots run, without a reload (the marker survives)."""
    page.evaluate("window.__notReloaded = true")
    expect(rows(page).first).to_be_visible(timeout=60_000)
    phase = rows(page).first.locator("td").nth(1)
    expect(phase).not_to_have_text(phase.inner_text(), timeout=60_000)
    expect(rows(page)).to_have_count(BOTS, timeout=BOTS_TIMEOUT_MS)
    # how the server keeps up, above the table (GET /api/admin/server/load): its world loop measured by now
    expect(page.locator("#server-load")).to_contain_text("Server, last minute: The server")
    expect(page.locator("#server-load")).to_contain_text("world updates", timeout=30_000)
    run.join()
    expect(page.locator("#participants-summary")).to_have_text(f"{BOTS} participants: {BOTS} completed",
                                                               timeout=10_000)
    expect(page.locator("#participants-body svg.sparkline polyline")).to_have_count(BOTS)
    assert page.evaluate("window.__notReloaded") is True
    for p in api_participants_from_page(page):
        points = page.locator(f'tr[data-participant="{p}"] svg.sparkline polyline').get_attribute("points")
        assert len(points.split()) == SCORED_TRIALS


def api_participants_from_page(page: Page) -> list[str]:
    return rows(page).evaluate_all("rs => rs.map(r => r.dataset.participant)")


def polls(page: Page) -> int:
    return page.evaluate(
        "() => performance.getEntriesByType('resource').filter(e => e.name.endsWith('/participants')).length")


def check_polling_pauses_while_hidden(page: Page) -> None:
    page.evaluate("""() => {
        Object.defineProperty(document, "visibilityState", { value: "hidden", configurable: true });
        document.dispatchEvent(new Event("visibilitychange"));
    }""")
    page.wait_for_timeout(500)  # a request already under way may still land
    page.evaluate("performance.clearResourceTimings()")
    page.wait_for_timeout(5000)  # two and a half polling periods
    assert polls(page) == 0
    page.evaluate("""() => {
        delete document.visibilityState;  // back to the real (visible) state
        document.dispatchEvent(new Event("visibilitychange"));
    }""")
    page.wait_for_function("() => performance.getEntriesByType('resource').some(e => e.name.endsWith('/participants'))")


def check_focus_survives_polls(page: Page) -> None:
    button = rows(page).first.get_by_role("button", name=re.compile("^Exclude"))
    button.focus()
    page.evaluate("performance.clearResourceTimings()")
    page.wait_for_function("() => performance.getEntriesByType('resource')"
                           ".filter(e => e.name.endsWith('/participants')).length >= 2")
    expect(button).to_be_focused()


def exclude_one(page: Page, server: LiveServer, slug: str) -> str:
    public_id = api_participants_from_page(page)[0]
    row = row_of(page, public_id)
    button = row.get_by_role("button", name=f"Exclude participant {public_id}")
    button.click()
    dialog = page.get_by_role("dialog")
    expect(dialog).to_be_visible()
    expect(dialog.get_by_label("Reason (kept in the audit log)")).to_be_focused()
    page.keyboard.press("Escape")
    expect(dialog).to_be_hidden()
    expect(button).to_be_focused()
    page.keyboard.press("Enter")  # the focused button opens it again
    expect(dialog).to_be_visible()
    dialog.get_by_role("button", name="Exclude").click()
    expect(dialog.locator("#reason-error")).to_have_text("Give a reason: it is kept in the audit log.")
    dialog.get_by_label("Reason (kept in the audit log)").fill("did not follow the instructions")
    dialog.get_by_role("button", name="Exclude").click()
    expect(dialog).to_be_hidden()
    expect(row.locator(".badge-excluded")).to_be_visible()
    expect(row).to_contain_text("did not follow the instructions")
    expect(row.get_by_role("button", name=f"Include participant {public_id}")).to_be_visible()
    [excluded] = [p for p in api_participants(server, slug) if p["excluded"]]
    assert excluded["public_id"] == public_id and excluded["exclusion_reason"] == "did not follow the instructions"
    return public_id


def check_export_zip(page: Page, tmp_path: Path, slug: str, excluded: str) -> None:
    page.get_by_role("tab", name="Data & report").click()
    path = download(page, "All files (zip)", tmp_path)
    assert path.name == f"{slug}-export.zip"
    with zipfile.ZipFile(path) as archive:
        names = set(archive.namelist())
        assert {"trials.csv", "surveys.csv", "participants.csv", "events.csv", "codebook.csv", "manifest.json"} <= names
        manifest = json.loads(archive.read("manifest.json"))
        trials = list(csv.DictReader(io.StringIO(archive.read("trials.csv").decode("utf-8"))))
        people = list(csv.DictReader(io.StringIO(archive.read("participants.csv").decode("utf-8"))))
    assert manifest["files"]["trials.csv"]["rows"] == len(trials) == BOTS * (SCORED_TRIALS + PRACTICE_TRIALS)
    assert {p["participant_id"]: p["excluded"] for p in people} == {
        p["participant_id"]: "1" if p["participant_id"] == excluded else "0" for p in people}
    assert {t["excluded"] for t in trials if t["participant_id"] == excluded} == {"1"}
    expect(page.locator("#data-status")).to_have_text(f"Downloaded {slug}-export.zip.")
    single = download(page, "trials.csv", tmp_path)
    assert single.name == f"{slug}-trials.csv"
    assert single.read_text(encoding="utf-8").splitlines()[0].startswith("participant_id,block,trial,complexity")
    dataset = download(page, "Psych-DS dataset (zip)", tmp_path)
    assert dataset.name == f"{slug}-psych-ds.zip"
    with zipfile.ZipFile(dataset) as archive:
        assert json.loads(archive.read("dataset_description.json"))["@type"] == "Dataset"
        rows = archive.read(f"data/study-{slug}_description-trials_data.csv").decode("utf-8")
    assert list(csv.DictReader(io.StringIO(rows))) == trials  # the same rows as the CSV export's


def fit_a_model(page: Page, server: LiveServer, tmp_path: Path) -> dict[str, Any]:
    page.get_by_role("tab", name="Model & deploy").click()
    page.locator("#fit-form").get_by_label("Restarts").fill("10")
    page.locator("#fit-form").get_by_label("Seed", exact=True).fill("3")  # the designer's form has a Seed too
    page.evaluate("""() => {  // every text the progress line shows (the fit may be over before a poll could look)
        const line = document.getElementById("fit-progress-text");
        window.__progressTexts = [];
        new MutationObserver(() => window.__progressTexts.push(line.textContent))
            .observe(line, { childList: true, characterData: true, subtree: true });
    }""")
    page.get_by_role("button", name="Fit model").click()
    detail = page.locator("#model-detail")
    expect(detail.get_by_role("heading", name=re.compile(r"^Model \d+ done$"))).to_be_visible(timeout=60_000)
    assert any(t.startswith("Fitting model") for t in page.evaluate("window.__progressTexts"))
    [model] = server.admin("GET", "/api/admin/studies/pilot/models").json()
    assert model["status"] == "done" and model["provenance"]["n_participants"] == BOTS - 1  # one is excluded
    table = detail.get_by_role("table", name="Parameters (Laplace standard errors)")
    shown = table.locator("tbody tr").evaluate_all(
        "rows => rows.map(r => [r.querySelector('code').textContent, ...[...r.cells].map(c => c.textContent)])")
    assert len(shown) == len(model["parameters"]) == 21
    for (name, _label, value, stderr, status), p in zip(shown, model["parameters"], strict=True):
        assert name == p["name"] and value == ("–" if p["value"] is None else f"{p['value']:.3f}")
        assert stderr == ("–" if p["stderr"] is None else f"{p['stderr']:.3f}")
        assert status == STATUS_TEXT[p["status"]]
    policy = model["policy"]
    assert policy["error"] is None, policy["error"]
    table = detail.get_by_role("table", name=re.compile("^Trust-aware policy"))
    for row, complexity in enumerate(("low", "high")):
        threshold, action = policy["threshold"][complexity], policy["action"][complexity]
        expect(table.locator("tbody tr").nth(row)).to_contain_text(
            f"exceeds {threshold:.3f}" if threshold is not None
            else {"ask": "always ask for help", "auto": "always act autonomously"}[action])
    baseline = detail.get_by_role("table", name="Trust-agnostic baseline (same data)")
    high = model["agnostic"]["rates"]["high"]
    expect(baseline.locator("tbody tr").nth(1)).to_contain_text(f"({high['interventions']} of {high['auto_trials']})")
    document = json.loads(download(page, "Download model JSON", tmp_path).read_text())
    assert document["format"] == "trustlab-iohmm"
    expect(page.locator("#deploy-status")).to_have_text(
        f"Downloaded model-{model['id']}-{model['content_hash'][:12]}.json.")
    return model


def deploy(page: Page, server: LiveServer, model: dict[str, Any]) -> None:
    page.get_by_label("Slug", exact=True).fill("pilot-eval")
    page.get_by_label("Title (optional)").fill("Pilot evaluation")
    page.get_by_label("Design").select_option("demo-fast")
    page.get_by_role("button", name="Create evaluation study").click()
    expect(page.locator("#deploy-status")).to_contain_text("Created the evaluation study")
    deployed = server.admin("GET", f"/api/admin/models/{model['id']}").json()
    assert deployed["evaluation_studies"] == ["pilot-eval"]
    expect(page.locator("#model-detail dd").filter(has_text="pilot-eval")).to_be_visible()
    page.get_by_role("link", name="open pilot-eval").click()
    expect(page.get_by_role("tab", name="Participants")).to_have_attribute("aria-selected", "true")
    expect(page.locator("#study-slug")).to_have_text("pilot-eval")
    config = server.admin("GET", "/api/admin/studies/pilot-eval").json()["config"]
    policies = {b["name"]: b["policy"]["kind"] for b in config["blocks"]}
    assert sorted(policies.values()) == ["trust_agnostic", "trust_aware"]


def withdraw_one(page: Page, server: LiveServer, slug: str) -> None:
    public_id = api_participants_from_page(page)[-1]
    row = row_of(page, public_id)
    row.get_by_role("button", name=f"Withdraw participant {public_id}", exact=True).click()
    dialog = page.get_by_role("dialog")  # the study keeps a withdrawal's data (privacy.withdrawal: keep, the default)
    expect(dialog).to_contain_text("their trials, answers and events stay")
    dialog.get_by_role("button", name="Withdraw", exact=True).click()
    expect(dialog.locator("#reason-error")).to_have_text("Give a reason: it is kept in the audit log.")
    dialog.get_by_label("Reason (kept in the audit log)").fill("asked to withdraw")
    dialog.get_by_role("button", name="Withdraw", exact=True).click()
    expect(dialog).to_be_hidden()
    expect(row.locator(".badge-withdrawn")).to_be_visible()
    expect(row.get_by_role("button", name=re.compile("^Withdraw"))).to_be_disabled()
    [withdrawn] = [p for p in api_participants(server, slug) if p["status"] == "withdrawn"]
    assert withdrawn["public_id"] == public_id and withdrawn["excluded"] and withdrawn["external_id"] is None


def preview_to_the_end(page: Page, browser, server: LiveServer, slug: str) -> str:
    """The experimenter previews the open study from the page, and the preview session is played to its debrief (by
    a bot, through the session the button started); it is marked in the table. Returns its public id."""
    page.get_by_role("tab", name="Participants").click()
    with browser.expect_page() as opened:
        page.get_by_role("button", name="Preview as participant").click()
    tab = opened.value
    tab.wait_for_url(re.compile(r"/p/[A-Za-z0-9_-]+$"))
    token = tab.url.rsplit("/", 1)[1]
    tab.close()
    with httpx.Client(base_url=server.url, timeout=30) as http:
        final = Bot(http, remote_sockets(server.url), slug, paper_params(), 7, BotStats()).run(token=token)
    assert final["phase"] == "debrief" and final["preview"] is True
    [preview] = [p for p in api_participants(server, slug) if p["preview"]]
    expect(row_of(page, preview["public_id"]).locator(".badge-preview")).to_have_text("preview")
    return preview["public_id"]


def open_the_report(page: Page, browser, tmp_path: Path, slug: str, left_out: str) -> None:
    """The report of the study's data, in its page and as a zip; ``left_out``: a preview session's id, in neither
    (nor in the exports) unless previews are asked for."""
    page.get_by_role("tab", name="Data & report").click()
    link = page.get_by_role("link", name="Open the report")
    address = f"/api/admin/studies/{slug}/report.html"
    expect(link).to_have_attribute("href", address)  # once the panel holds the report cookie
    with browser.expect_page() as info:
        link.click()
    report = info.value
    console: list[str] = []
    report.on("console", lambda message: console.append(message.text))
    report.wait_for_url(re.compile(re.escape(address) + "$"), timeout=120_000)  # its own address, not a blob:
    expect(report.get_by_role("heading", name=f"Analysis report: Pilot evaluation ({slug})")).to_be_visible(
        timeout=120_000)
    images = report.evaluate("() => [...document.images].map(i => i.complete && i.naturalWidth > 0)")
    assert len(images) >= 4 and all(images)
    assert report.evaluate("() => getComputedStyle(document.body).maxWidth") == "1200px"  # its style sheet applies
    assert not [m for m in console if "Content Security Policy" in m]
    text = report.locator("body").inner_text()
    assert "exported to" not in text and "/tmp/" not in text  # no server paths
    expect(page.locator("#data-status")).to_have_text("The report opens in a new tab; building it takes a few seconds.")
    report.close()
    archive = download(page, "Download the report (zip)", tmp_path)
    with zipfile.ZipFile(archive) as files:
        names = files.namelist()
        people = files.read("data/participants.csv").decode("utf-8")
        trials = files.read("data/trials.csv").decode("utf-8")
        html = files.read("report.html").decode("utf-8")
    assert "report.html" in names and any(n.startswith("figures/") and n.endswith(".png") for n in names)
    assert left_out not in people and left_out not in trials and "preview session" not in html


def test_dashboard_from_study_to_report(live_server: LiveServer, browser, tmp_path):
    page = browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    log_in(page, live_server)
    create_study(page, "demo-fast", "pilot")
    expect(page.get_by_role("heading", name="trustlab demo (fast, for bots)")).to_be_visible()
    check_invalid_config_is_explained(page)
    make_it_a_pilot(page)

    page.get_by_role("tab", name="Configuration").focus()
    page.keyboard.press("ArrowLeft")  # tabs follow the arrow keys
    expect(page.get_by_role("tab", name="Participants")).to_be_focused()
    expect(page.get_by_role("tab", name="Participants")).to_have_attribute("aria-selected", "true")
    expect(page.locator("#participants-empty")).to_be_visible()
    open_from_the_page(page, live_server, "pilot")
    run = BotRun(live_server.url, "pilot", BOTS, seed=1)
    watch_the_table_fill(page, run)
    check_polling_pauses_while_hidden(page)
    check_focus_survives_polls(page)
    excluded = exclude_one(page, live_server, "pilot")
    check_export_zip(page, tmp_path, "pilot", excluded)

    model = fit_a_model(page, live_server, tmp_path)
    deploy(page, live_server, model)
    open_from_the_page(page, live_server, "pilot-eval")
    run = BotRun(live_server.url, "pilot-eval", BOTS, seed=2)
    watch_the_table_fill(page, run)
    withdraw_one(page, live_server, "pilot-eval")
    preview = preview_to_the_end(page, browser, live_server, "pilot-eval")
    open_the_report(page, browser, tmp_path, "pilot-eval", left_out=preview)
    asked = live_server.admin("GET", "/api/admin/studies/pilot-eval/export/participants.csv",
                              params={"include_preview": "true"})
    assert preview in asked.text  # in the data, and left out of the report's only because it is a preview
    page.get_by_role("button", name="Close study").click()
    expect(page.locator("#study-status")).to_have_text("closed")
    assert live_server.admin("GET", "/api/admin/studies/pilot-eval").json()["status"] == "closed"
    page.get_by_role("tab", name="Configuration").click()
    assert json.loads(page.get_by_label("Study configuration (JSON)").input_value())["title"] == "Pilot evaluation"
    page.get_by_role("link", name="← All studies").click()
    listed = page.locator('#studies-body tr[data-slug="pilot-eval"]')
    expect(listed).to_contain_text(f"{BOTS - 1} completed · 1 withdrawn")
    expect(listed.locator(".badge")).to_have_text("closed")
    assert errors == []
