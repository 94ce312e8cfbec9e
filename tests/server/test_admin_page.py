"""The dashboard page: ``trustlab serve`` prints a link that serves it, with the pages' security headers
(plus the hash of the report's style sheet: the report opens from a Blob URL, which inherits the page's policy)."""

from __future__ import annotations

import re

import uvicorn
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from experiment.report.html import content_security_policy as report_policy
from server.cli import app as cli
from server.http_headers import PAGE_HEADERS
from server.routes.pages import ADMIN_PAGE_HEADERS, STATIC_DIR


def test_the_admin_link_serve_prints_opens_the_dashboard(tmp_path, monkeypatch):
    served = {}
    monkeypatch.setattr(uvicorn, "run", lambda app, **kwargs: served.update(app=app, **kwargs))
    result = CliRunner().invoke(cli, ["serve", "--port", "8123", "--database-url", f"sqlite:///{tmp_path / 'a.db'}"])
    assert result.exit_code == 0, result.output
    link = re.search(r"admin page: (http://\S+)", result.stdout).group(1)
    assert link == "http://127.0.0.1:8123/admin"
    client = TestClient(served["app"])
    page = client.get(link.removeprefix("http://127.0.0.1:8123"))
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert "<title>trustlab · experimenter</title>" in page.text
    for name, value in ADMIN_PAGE_HEADERS.items():
        assert page.headers[name] == value
    policy = page.headers["Content-Security-Policy"]
    report_style = next(p for p in report_policy().split(";") if p.strip().startswith("style-src")).split()[1]
    participant_policy = PAGE_HEADERS["Content-Security-Policy"]
    assert policy == participant_policy.replace("style-src 'self'", f"style-src 'self' {report_style}")
    assert report_style.startswith("'sha256-")  # the report's one inline style sheet, nothing more
    for script in re.findall(r'src="(/static/[^"]+)"', page.text) + re.findall(r'href="(/static/[^"]+)"', page.text):
        assert client.get(script).status_code == 200, script


def test_every_dashboard_module_import_resolves():
    modules = sorted((STATIC_DIR / "js").glob("admin*.js"))
    assert modules
    for module in modules:
        for target in re.findall(r'from "(\./[^"]+)"', module.read_text()):
            assert (module.parent / target).resolve().is_file(), f"{module.name} imports missing {target}"
