"""``trustlab serve --workers N``: several processes over PostgreSQL behind nginx (issue 6, server/workers.py).

The group test runs a real group (2 workers, nginx) on PostgreSQL: a session's every request, its
teleoperation websocket and its 3D view reach one worker; the admin API and joins reach worker 0; bots
complete a study through nginx with exact rows; a worker killed with SIGKILL is started again and its
sessions go on; SIGTERM stops every process of the group. It needs ``TRUSTLAB_TEST_POSTGRES_URL`` and nginx
(CI installs both: a missing nginx fails the test there).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from sqlalchemy import create_engine, func, select
from sqlalchemy.pool import NullPool
from websockets.sync.client import connect

from experiment.iohmm import paper_params
from experiment.templates import demo_fast
from server.bots import run_remote_bots
from server.models import Trial
from server.settings import Settings
from server.workers import SESSION_PATH, GroupError, check_group, nginx_config
from tests.conftest import (
    POSTGRES_URL,
    create_postgres_database,
    drop_postgres_database,
    postgres_database_url,
)
from tests.server.live import expected_records, free_port, start_server

WORKER = "x-trustlab-worker"
GROUP_RESTART_TIMEOUT_S = 120
#: The group's join limit per client address: above the test's joins until it tries to get past it.
JOINS_PER_IP = 40
STICKY_SESSIONS = 24
BOTS = 8


def _nginx() -> str:
    nginx = shutil.which("nginx") or ("/usr/sbin/nginx" if os.access("/usr/sbin/nginx", os.X_OK) else None)
    if nginx is None:
        if os.environ.get("CI"):
            pytest.fail("nginx is missing: .ci/run installs it")
        pytest.skip("nginx is not installed")
    return nginx


# -- without a database ----------------------------------------------------------------------------------------

def test_a_group_on_sqlite_is_refused_with_the_reason(tmp_path: Path) -> None:
    with pytest.raises(GroupError, match="need PostgreSQL"):
        check_group(Settings(database_url=f"sqlite:///{tmp_path / 'x.db'}"), 2)
    done = subprocess.run([sys.executable, "-c", "from server.cli import app; app()", "serve", "--workers", "2",
                           "--database-url", f"sqlite:///{tmp_path / 'x.db'}"],
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 2
    assert "several workers need PostgreSQL" in done.stderr
    assert not (tmp_path / "x.db").exists(), "refused before touching the database"


def test_the_session_pattern_finds_the_token_of_every_participant_route() -> None:
    import re

    pattern = re.compile(SESSION_PATH.replace("(?<token>", "(?P<token>"))
    token = "Abc_def-123456789012"
    for path in (f"/p/{token}", f"/api/p/{token}/state", f"/api/p/{token}/teleop", f"/viewer/{token}",
                 f"/viewer/{token}/", f"/viewer/{token}/assets/x.js", f"/api/p/{token}/camera"):
        match = pattern.match(path)
        assert match is not None and match.group("token") == token, path
    for path in ("/api/studies/demo/join", "/join/demo", "/admin", "/api/admin/studies", "/static/app.js", "/docs"):
        assert pattern.match(path) is None, path


def test_nginx_accepts_the_generated_configuration(tmp_path: Path) -> None:
    nginx = _nginx()
    sockets = [tmp_path / f"worker-{i}.sock" for i in range(3)]
    config = tmp_path / "nginx.conf"
    config.write_text(nginx_config(sockets, tmp_path, "127.0.0.1", free_port(), run_as_root=os.geteuid() == 0))
    checked = subprocess.run([nginx, "-t", "-p", str(tmp_path), "-c", str(config)], capture_output=True, text=True,
                             check=False, timeout=30)
    assert checked.returncode == 0, checked.stderr
    assert "syntax is ok" in checked.stderr


# -- a real group on PostgreSQL ---------------------------------------------------------------------------------

@pytest.fixture
def group(tmp_path: Path):
    if POSTGRES_URL is None:
        pytest.skip("TRUSTLAB_TEST_POSTGRES_URL is not set")
    _nginx()
    name = create_postgres_database()
    url = postgres_database_url(name)
    port = free_port()
    log = (tmp_path / "group.log").open("w+")
    process, token = start_server(url, port, log, "--workers", "2",
                                  env={"TRUSTLAB_JOIN_RATE_LIMIT_PER_IP": str(JOINS_PER_IP)})
    try:
        assert token is not None, "a new database: the group prints the admin token"
        yield Group(process, f"http://127.0.0.1:{port}", token, url, Path(log.name))
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        log.close()
        drop_postgres_database(name)


class Group:
    def __init__(self, process: subprocess.Popen, url: str, token: str, database_url: str, log: Path):
        self.process, self.url, self.token, self.database_url, self.log = process, url, token, database_url, log

    def admin(self, method: str, path: str, **kwargs) -> httpx.Response:
        return httpx.request(method, self.url + path, headers={"Authorization": f"Bearer {self.token}"}, timeout=30,
                             **kwargs)

    def children(self) -> list[int]:
        return [int(pid) for pid in subprocess.run(["pgrep", "-P", str(self.process.pid)], capture_output=True,
                                                    text=True, check=False).stdout.split()]


def _join(g: Group, slug: str, external_id: str) -> str:
    response = httpx.post(f"{g.url}/api/studies/{slug}/join", json={"params": {"PROLIFIC_PID": external_id}}, timeout=30)
    assert response.status_code == 200, response.text
    assert response.headers[WORKER] == "0", "joins are served by the primary"
    return response.json()["token"]


def _workers_of(g: Group, token: str) -> set[str]:
    """The workers that answered this session's HTTP requests, its 3D view page and its teleoperation socket."""
    seen = set()
    with httpx.Client(base_url=g.url, timeout=30) as client:
        for path in (f"/api/p/{token}/state", f"/p/{token}", f"/viewer/{token}/", f"/api/p/{token}/state"):
            response = client.get(path)
            assert response.status_code == 200, (path, response.text)
            seen.add(response.headers[WORKER])
    ws_url = g.url.replace("http://", "ws://") + f"/api/p/{token}/teleop"
    with connect(ws_url, open_timeout=30) as socket:
        seen.add(socket.response.headers[WORKER])
    return seen


def test_a_group_routes_each_session_to_one_worker_and_completes_a_study(group: Group) -> None:
    g = group
    assert len(g.children()) == 3, "two workers and nginx"
    config = demo_fast().model_dump(mode="json")
    created = g.admin("POST", "/api/admin/studies", json={"slug": "fast", "config": config})
    assert created.status_code == 201, created.text
    assert created.headers[WORKER] == "0", "the admin API is served by the primary"

    # Sticky: every request of a session reaches one worker; sessions spread over both workers.
    owner: dict[str, str] = {}
    for i in range(STICKY_SESSIONS):
        token = _join(g, "fast", f"sticky-{i}")
        seen = _workers_of(g, token)
        assert len(seen) == 1, f"session {i} was served by workers {seen}"
        owner[token] = seen.pop()
    assert set(owner.values()) == {"0", "1"}, f"24 sessions all on one worker: {owner}"

    # Bots complete the study through nginx, with exactly the study's trials.
    summary = run_remote_bots(g.url, "fast", paper_params(), participants=BOTS, concurrency=BOTS, seed=3)
    assert summary.errors == [] and summary.completed == BOTS and summary.rate_limited == 0
    _, scored, _ = expected_records(demo_fast(), [block.name for block in demo_fast().blocks])
    engine = create_engine(g.database_url, poolclass=NullPool)
    try:
        with engine.connect() as connection:
            rows = connection.scalar(select(func.count()).select_from(Trial).where(Trial.practice.is_(False),
                                                                                   Trial.stage == "done"))
    finally:
        engine.dispose()
    assert rows == BOTS * scored

    # Join limits count the connecting address, which nginx passes on: joins claiming other addresses in
    # X-Forwarded-For all count against this client's allowance (were the header believed, none would be refused).
    refused = None
    for i in range(JOINS_PER_IP + 10):  # the allowance refills meanwhile, hence the slack
        response = httpx.post(f"{g.url}/api/studies/fast/join", headers={"X-Forwarded-For": f"203.0.113.{i}"},
                              timeout=30)
        if response.status_code == 429:
            refused = i
            break
        assert response.status_code == 200, response.text
    assert refused is not None, f"{JOINS_PER_IP + 10} joins with made-up addresses, none refused"

    # A worker killed with SIGKILL is started again; its sessions are served meanwhile and stick again after.
    token = next(t for t, w in owner.items() if w == "1")
    victim = _worker_pid(g, 1)
    os.kill(victim, signal.SIGKILL)
    deadline = time.monotonic() + GROUP_RESTART_TIMEOUT_S
    while True:
        response = httpx.get(f"{g.url}/api/p/{token}/state", timeout=30)
        assert response.status_code == 200, response.text  # never an error: nginx passes it to the other worker
        if response.headers[WORKER] == "1" and _worker_pid(g, 1) not in (None, victim):
            break
        assert time.monotonic() < deadline, "worker 1 did not come back"
        time.sleep(0.2)
    assert _workers_of(g, token) == {"1"}
    assert "worker 1 exited" in g.log.read_text()

    # SIGTERM stops the whole group: no process is left behind.
    children = g.children()
    g.process.send_signal(signal.SIGTERM)
    assert g.process.wait(timeout=60) == 0
    time.sleep(0.5)
    assert [pid for pid in children if Path(f"/proc/{pid}").exists()] == []


def _worker_pid(g: Group, index: int) -> int | None:
    """The pid of worker ``index`` (found by its command line among the group's children)."""
    for pid in g.children():
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except FileNotFoundError:
            continue
        if b"server.workers" in argv and str(index).encode() in argv:
            return pid
    return None
