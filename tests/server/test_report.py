"""The analysis report from a study in the database: ``trustlab report`` and the admin routes."""

from __future__ import annotations

import base64
import io
import json
import re
import shutil
import tempfile
import time
import zipfile
from contextlib import nullcontext
from pathlib import Path

import pytest
from sqlalchemy import select
from typer.testing import CliRunner

from experiment.codebook import columns
from experiment.iohmm import paper_params
from experiment.records import MODEL_COLUMNS
from experiment.report.data import PARTICIPANT_COLUMNS, SURVEY_COLUMNS
from experiment.report.html import content_security_policy
from server.cli import app
from server.errors import Unauthorized
from server.harness.crowd import run_bots
from server.models import AdminCredential, utcnow
from server.services import report as reports
from server.services.admin import rotate_admin_token
from server.services.sessions import hash_token
from tests.server.factories import auth, join, make_client, make_study

runner = CliRunner()
RESTARTS = "2"


def test_the_report_reads_columns_the_export_writes():
    assert set(SURVEY_COLUMNS) <= set(columns("surveys.csv"))
    assert set(PARTICIPANT_COLUMNS) <= set(columns("participants.csv"))
    assert {"block_name", "policy", "reward", "study"} | set(MODEL_COLUMNS) <= set(columns("trials.csv"))


@pytest.fixture(scope="module")
def bot_study(sqlite_template, tmp_path_factory):
    """A demo study on SQLite (the backend where a long request transaction would block the export) after
    one bot completed it: consent, practice, both blocks, shelf surveys and Schaefer questionnaires."""
    path = tmp_path_factory.mktemp("report-db") / "trustlab.db"
    shutil.copy(sqlite_template, path)
    url = f"sqlite:///{path}"
    client, admin = make_client(database_url=url)
    make_study(client, admin)
    summary = run_bots(lambda: nullcontext(client), client.websocket_connect, "s1", paper_params(),
                       participants=1, concurrency=1)
    assert summary.errors == [] and summary.completed == 1
    return client, admin, url


def test_report_command_exports_the_study_and_writes_the_report(bot_study, tmp_path):
    _, _, url = bot_study
    out = tmp_path / "report"
    result = runner.invoke(app, ["report", "s1", "--out", str(out), "--database-url", url, "--restarts", RESTARTS,
                                 "--json"])
    assert result.exit_code == 0, result.output
    printed = json.loads(result.stdout)
    assert printed["report"] == str(out / "report.html") and (out / "data" / "trials.csv").is_file()
    assert printed["figures"] and all(Path(f).is_file() for f in printed["figures"])
    assert printed["key_figures"]["flow"]["flow"]["completed"] == 1
    assert printed["key_figures"] == json.loads((out / "report.json").read_text())
    page = (out / "report.html").read_text(encoding="utf-8")
    assert "Analysis report: trustlab demo (s1)" in page and "Schaefer items per condition" in page

    again = runner.invoke(app, ["report", str(out / "data"), "--out", str(tmp_path / "from-dir"),
                                "--restarts", RESTARTS, "--json"])  # an export directory instead of a slug
    assert again.exit_code == 0, again.output
    assert json.loads(again.stdout)["key_figures"]["model"] == printed["key_figures"]["model"]


def test_report_zip_holds_the_page_its_figures_and_the_data(bot_study):
    client, admin, _ = bot_study
    response = client.get("/api/admin/studies/s1/report", params={"restarts": RESTARTS}, headers=auth(admin))
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/zip"
    assert response.headers["content-disposition"] == 'attachment; filename="s1-report.zip"'
    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        names = set(archive.namelist())
        assert {"report.html", "report.json", "model.json", "data/trials.csv", "data/surveys.csv",
                "data/participants.csv", "data/manifest.json"} <= names
        figures = sorted(n for n in names if n.startswith("figures/"))
        assert "figures/fig4_emissions.png" in figures
        page = archive.read("report.html").decode()
        assert sorted(re.findall(r"<img src='([^']+)'", page)) == figures
        for name in names - set(figures):  # no server path anywhere (the zip is built in a temporary directory)
            text = archive.read(name).decode()
            assert tempfile.gettempdir() + "/" not in text and "trustlab-report-" not in text, name
        assert json.loads(archive.read("model.json"))["fitted_on"]["source"] == "data/trials.csv"
        assert archive.read(figures[0]).startswith(b"\x89PNG")


def test_report_page_is_self_contained(bot_study):
    client, admin, _ = bot_study
    response = client.get("/api/admin/studies/s1/report.html", params={"restarts": RESTARTS}, headers=auth(admin))
    assert response.status_code == 200, response.text
    assert response.headers["content-type"].startswith("text/html")
    assert response.headers["content-security-policy"] == content_security_policy()
    sources = re.findall(r"<img src='([^']+)'", response.text)
    assert sources and all(s.startswith("data:image/png;base64,") for s in sources)
    assert all(base64.b64decode(s.split(",", 1)[1]).startswith(b"\x89PNG") for s in sources)


def test_report_routes_need_the_admin_token_and_an_analysable_study(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    for path in ("/api/admin/studies/s1/report", "/api/admin/studies/s1/report.html"):
        assert client.get(path).status_code == 401
        assert client.get(path, headers=auth("tla_wrong")).status_code == 401
        missing = client.get(path.replace("s1", "nope"), headers=auth(admin))
        assert missing.status_code == 404 and "nope" in missing.json()["detail"]
        join(client, PROLIFIC_PID="p1")  # joined, no trial yet
        empty = client.get(path, headers=auth(admin))
        assert empty.status_code == 409
        assert empty.json()["detail"] == ("no report for study 's1' yet: trials.csv: no trials left after removing "
                                          "practice and excluded rows")
        assert client.get(path, params={"restarts": 0}, headers=auth(admin)).status_code == 422


def test_report_command_errors_are_one_line(database_url, tmp_path):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    for study, message in (("nope", "no study 'nope'"), ("s1", "no trials left"),
                           (str(tmp_path / "no-such-dir"), "neither a study slug nor an export directory")):
        result = runner.invoke(app, ["report", study, "--out", str(tmp_path / "out"), "--database-url", database_url])
        assert result.exit_code == 2 and message in result.output, result.output
        assert "Traceback" not in result.output


def test_report_page_has_a_stable_address_a_browser_opens_with_the_report_cookie(bot_study):
    """The admin page trades its bearer token for a cookie that lets a tab open (reload, bookmark) report.html;
    the cookie opens nothing else, expires, and dies with the token."""
    client, admin, _ = bot_study
    page_url = "/api/admin/studies/s1/report.html"
    client.cookies.clear()
    try:
        refused = client.get(page_url, headers={"Accept": "text/html"})
        assert refused.status_code == 401 and refused.headers["content-type"].startswith("text/html")
        assert "sign in on the admin page" in refused.text and "href='/admin'" in refused.text
        assert client.get(page_url).json()["code"] == "unauthorized"  # an API client still gets JSON

        assert client.post("/api/admin/report-access").status_code == 401
        granted = client.post("/api/admin/report-access", headers=auth(admin))
        assert granted.status_code == 200, granted.text
        cookie = granted.headers["set-cookie"]
        assert f"{reports.REPORT_COOKIE}=" in cookie and "HttpOnly" in cookie and "SameSite=strict" in cookie
        assert "Path=/api/admin/studies/" in cookie and granted.json()["path"] == "/api/admin/studies/"

        page = client.get(page_url, params={"restarts": RESTARTS}, headers={"Accept": "text/html"})
        assert page.status_code == 200, page.text
        assert "Analysis report: trustlab demo (s1)" in page.text
        assert "an export of study s1 taken for this report" in page.text
        assert tempfile.gettempdir() + "/" not in page.text and "trustlab-report-" not in page.text
        nothing = client.get(page_url.replace("s1", "nope"), headers={"Accept": "text/html"})
        assert nothing.status_code == 404 and nothing.headers["content-type"].startswith("text/html")
        assert "No study &#x27;nope&#x27;" in nothing.text

        # The cookie reads report pages only.
        assert client.get("/api/admin/studies").status_code == 401
        assert client.get("/api/admin/studies/s1/report").status_code == 401
        assert client.get("/api/admin/studies/s1/export/trials.csv").status_code == 401

        factory = client.app.state.services.sessionmaker
        value = client.cookies[reports.REPORT_COOKIE]
        with factory() as session:
            reports.verify_report_access(session, value)  # valid now ...
            with pytest.raises(Unauthorized, match="expired"):  # ... not after its lifetime
                reports.verify_report_access(session, value, now_s=time.time() + reports.REPORT_ACCESS_S + 1)
            for forged in ("", "x", value.split(".")[0] + ".00", str(int(value.split(".")[0]) + 1) + "." +
                           value.split(".")[1]):
                with pytest.raises(Unauthorized):
                    reports.verify_report_access(session, forged)
        with factory.begin() as session:
            rotate_admin_token(session, utcnow())
        try:
            with factory() as session, pytest.raises(Unauthorized):
                reports.verify_report_access(session, value)
            assert client.get(page_url, headers={"Accept": "text/html"}).status_code == 401
        finally:  # the module's other tests keep using ``admin``
            with factory.begin() as session:
                for credential in session.scalars(select(AdminCredential)):
                    credential.active = credential.token_hash == hash_token(admin)
    finally:
        client.cookies.clear()
