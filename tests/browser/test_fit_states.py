"""Issue 40 on the dashboard: the fit form compares numbers of trust states and the model shows the comparison.

Six simulated participants written into the database (no bots) and two restarts in two folds keep it short.
"""

from __future__ import annotations

import re
import types
import zipfile
from pathlib import Path

from playwright.sync_api import BrowserContext, expect

from experiment.iohmm import paper_params
from tests.browser.conftest import LiveServer
from tests.browser.test_admin import download, log_in
from tests.server.factories import add_simulated_participants
from tests.server.test_fits import estimation_config


def test_the_fit_form_compares_numbers_of_trust_states(live_server: LiveServer, browser: BrowserContext,
                                                       tmp_path: Path):
    live_server.create_study("s1", estimation_config())
    add_simulated_participants(types.SimpleNamespace(app=live_server.app), "s1", n=6, model=paper_params(), seed=1)
    page = browser.new_page()
    log_in(page, live_server)
    page.goto(f"{live_server.url}/admin#/study/s1/participants")
    page.get_by_role("tab", name="Model & deploy").click()
    form = page.locator("#fit-form")
    expect(form.get_by_label("2", exact=True)).to_be_checked()
    form.get_by_label("Restarts").fill("2")
    form.get_by_label("Seed", exact=True).fill("5")
    form.get_by_label("2", exact=True).uncheck()
    page.get_by_role("button", name="Fit model").click()
    expect(page.locator("#fit-error")).to_have_text("Tick at least one number of trust states.")
    for k in ("2", "3"):
        form.get_by_label(k, exact=True).check()
    form.get_by_label("Folds").fill("2")
    page.get_by_role("button", name="Fit model").click()

    detail = page.locator("#model-detail")
    expect(detail.get_by_role("heading", name=re.compile(r"^Model \d+ done$"))).to_be_visible(timeout=20_000)
    [model] = live_server.admin("GET", "/api/admin/studies/s1/models").json()
    selection = model["selection"]
    assert [c["n_states"] for c in selection["candidates"]] == [2, 3] and selection["folds"] == 2
    assert selection["chosen"] == 2  # six participants of the paper's two-state model
    table = detail.get_by_role("table", name="Which number of trust states the data support")
    chosen = table.locator("tbody tr").filter(has_text="chosen")
    expect(chosen).to_have_count(1)
    expect(chosen.locator("th")).to_have_text(str(selection["chosen"]))
    expect(detail.locator(".selection-reason")).to_have_text(f"Chosen: {selection['reason']}.")
    plot = detail.get_by_role("img", name=re.compile("^Held-out log-likelihood per trial"))
    expect(plot).to_have_attribute("aria-label", re.compile(f"Chosen: {selection['chosen']} states.$"))
    expect(plot.locator("circle")).to_have_count(2)

    # The report of this model (not of a fresh fit) has the comparison.
    report = download(page, "Report of this model (zip)", tmp_path)
    assert report.name == "s1-report.zip"
    with zipfile.ZipFile(report) as archive:
        assert "Which model the data support" in archive.read("report.html").decode("utf-8")
    expect(page.locator("#deploy-status")).to_have_text("Downloaded s1-report.zip.")


def test_the_fit_form_uses_the_trust_ratings_and_shows_what_they_add(live_server: LiveServer,
                                                                     browser: BrowserContext, tmp_path: Path):
    import numpy as np

    from experiment.trust_ratings import RatingEmission

    live_server.create_study("s1", estimation_config())
    add_simulated_participants(types.SimpleNamespace(app=live_server.app), "s1", n=6, model=paper_params(), seed=1,
                               ratings=RatingEmission(np.array([3.0, 12.0]), np.array([12.0, 3.0])))
    page = browser.new_page()
    log_in(page, live_server)
    page.goto(f"{live_server.url}/admin#/study/s1/participants")
    page.get_by_role("tab", name="Model & deploy").click()
    form = page.locator("#fit-form")
    form.get_by_label("Restarts").fill("2")
    form.get_by_label("Folds").fill("2")
    form.get_by_label("Use trust ratings").check()
    page.get_by_role("button", name="Fit model").click()

    detail = page.locator("#model-detail")
    expect(detail.get_by_role("heading", name=re.compile(r"^Model \d+ done$"))).to_be_visible(timeout=30_000)
    [model] = live_server.admin("GET", "/api/admin/studies/s1/models").json()
    ratings = model["ratings"]
    table = detail.get_by_role("table", name="What the trust ratings add")
    expect(table.locator("tbody tr")).to_have_count(2)
    expect(table.locator("tbody tr").first).to_contain_text(f"{ratings['mean_rating'][0]:.1f}")
    verdict = ratings["comparison"]["verdict"]
    expect(detail.locator(".ratings-verdict")).to_contain_text(verdict[0].upper() + verdict[1:])
    table.scroll_into_view_if_needed()
    page.screenshot(path=str(tmp_path / "fit-with-ratings.png"))
