"""``trustlab serve --workers N``: several processes over PostgreSQL behind nginx (issue 6, server/workers.py).

The group test runs a real group (2 workers, nginx) on PostgreSQL: a session's every request, its
teleoperation websocket and its 3D view reach one worker; the admin API and joins reach worker 0; bots
complete a study through nginx with exact rows; a worker killed with SIGKILL is started again and its
sessions go on; SIGTERM stops every process of the group. It needs ``TRUSTLAB_TEST_POSTGRES_URL`` and nginx
(CI installs both: a missing nginx fails the test there).

A group across machines (``trustlab worker`` on TCP, ``serve --workers-at``) is tested with its workers on
TCP ports of this machine: the same routing, and X-Forwarded-For believed from nginx's address only.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from sqlalchemy import create_engine, func, select
from sqlalchemy.pool import NullPool
from websockets.sync.client import connect

from experiment.iohmm import paper_params
from experiment.templates import demo_fast
from server.harness.crowd import run_remote_bots
from server.harness.live import expected_records, free_port, live_server, start_server
from server.launch import forwarded_trust
from server.models import Trial
from server.routes.viewer import SUBPROTOCOL as VIEWER_SUBPROTOCOL
from server.settings import Settings
from server.workers import (
    SESSION_PATH,
    GroupError,
    WorkerGroup,
    check_group,
    find_nginx,
    nginx_config,
    trusted_proxies,
    unix_upstream,
    worker_addresses,
)
from tests.conftest import (
    POSTGRES_URL,
    create_postgres_database,
    drop_postgres_database,
    postgres_database_url,
)

WORKER = "x-trustlab-worker"
GROUP_RESTART_TIMEOUT_S = 120
#: The group's join limit per client address: above the test's joins until it tries to get past it.
JOINS_PER_IP = 40
STICKY_SESSIONS = 24
BOTS = 8
#: The join limit per client address of the group on TCP: its sessions, each joined from an address of its own,
#: are more (all accepted: the workers count the addresses nginx forwards).
TCP_JOINS_PER_IP = 3


def _nginx() -> str:
    try:
        return find_nginx()
    except GroupError:
        if os.environ.get("CI"):
            pytest.fail("nginx is missing: .ci/run installs it")
        pytest.skip("nginx is not installed")


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


def test_nginx_accepts_the_generated_configuration_for_workers_on_unix_sockets_and_on_tcp(tmp_path: Path) -> None:
    nginx = _nginx()
    on_unix = [unix_upstream(tmp_path / f"worker-{i}.sock") for i in range(3)]
    on_tcp = worker_addresses("127.0.0.1:8001,[::1]:8002,worker-2.lan:8003")
    port = free_port()
    configs = {}
    for kind, upstreams in (("unix", on_unix), ("tcp", on_tcp)):
        configs[kind] = nginx_config(upstreams, tmp_path, "127.0.0.1", port, run_as_root=os.geteuid() == 0)
        config = tmp_path / f"nginx-{kind}.conf"
        config.write_text(configs[kind].replace("worker-2.lan", "localhost"))  # nginx -t resolves names
        checked = subprocess.run([nginx, "-t", "-p", str(tmp_path), "-c", str(config)], capture_output=True,
                                 text=True, check=False, timeout=30)
        assert checked.returncode == 0, checked.stderr
        assert "syntax is ok" in checked.stderr
    # One configuration whichever the transport: only the workers' addresses differ, in the same order.
    differ = [(a, b) for a, b in zip(configs["unix"].splitlines(), configs["tcp"].splitlines(), strict=True) if a != b]
    assert differ == [(f"        server {u};", f"        server {t};")
                      for u, t in zip(on_unix + on_unix[:1], on_tcp + on_tcp[:1], strict=True)]


def test_workers_on_tcp_refuse_what_would_break_the_group_or_its_join_limits(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from server.cli import app

    assert trusted_proxies("127.0.0.1", []) == ["127.0.0.1", "::1"], "nginx on this machine"
    assert trusted_proxies("0.0.0.0", ["10.0.0.5", "10.0.1.0/24"]) == ["10.0.0.5", "10.0.1.0/24"]
    for host, given, reason in (("0.0.0.0", [], "needs --trusted-proxy"), ("10.0.0.6", ["*"], "from anyone"),
                                ("10.0.0.6", ["nginx.lan"], "not an IP address")):
        with pytest.raises(GroupError, match=reason):
            trusted_proxies(host, given)
    assert worker_addresses(" 10.0.0.5:8001, [fd00::6]:8001 ") == ["10.0.0.5:8001", "[fd00::6]:8001"]
    for text, reason in (("10.0.0.5:8001", "at least 2"), ("10.0.0.5:8001,10.0.0.6", "not HOST:PORT"),
                         ("10.0.0.5:8001,fd00::6:8001", "not HOST:PORT"), ("a:1,a:1", "twice"),
                         ("a:1,[nope]:2", "not an IPv6")):
        with pytest.raises(GroupError, match=reason):
            worker_addresses(text)

    runner = CliRunner()
    sqlite = f"sqlite:///{tmp_path / 'x.db'}"
    for argv, reason in ((["worker", "--index", "1", "--port", "8001", "--public-url", "http://x", "--database-url",
                           sqlite], "need PostgreSQL"),
                         (["worker", "--index", "0", "--port", "8001", "--host", "0.0.0.0", "--public-url", "http://x",
                           "--database-url", "postgresql+psycopg://u@h/db"], "needs --trusted-proxy"),
                         (["worker", "--index", "0", "--port", "8001", "--database-url", "postgresql+psycopg://u@h/db"],
                          "needs --public-url"),
                         (["serve", "--workers-at", "10.0.0.5:8001,10.0.0.6:8001", "--workers", "2"], "nginx alone")):
        done = runner.invoke(app, argv, env={"TRUSTLAB_PUBLIC_URL": ""})
        assert done.exit_code == 2 and reason in " ".join(done.output.split()), (argv, done.output)
    assert not (tmp_path / "x.db").exists(), "refused before touching the database"


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


def _join(url: str, slug: str, external_id: str, *, source: str | None = None,
          headers: dict[str, str] | None = None) -> str:
    """A new session through nginx at ``url`` (from loopback address ``source``), served by the primary."""
    transport = httpx.HTTPTransport(local_address=source) if source else None
    with httpx.Client(transport=transport, timeout=30) as client:
        response = client.post(f"{url}/api/studies/{slug}/join", json={"params": {"PROLIFIC_PID": external_id}},
                               headers=headers)
    assert response.status_code == 200, response.text
    assert response.headers[WORKER] == "0", "joins are served by the primary"
    return response.json()["token"]


def _sticky_owners(url: str, slug: str, sessions: int, *, up_to: int | None = None,
                   own_addresses: bool = False) -> dict[str, str]:
    """New sessions through nginx and the one worker each is served by; they spread over both workers.

    ``sessions`` of them, or more, ``up_to`` that many, until both workers serve some. ``own_addresses``: each
    joins from a loopback address of its own (127.0.1.N), claiming another address in X-Forwarded-For, which
    nginx must replace with the real one.
    """
    owner: dict[str, str] = {}
    for i in range(max(sessions, up_to or 0)):
        if i >= sessions and set(owner.values()) == {"0", "1"}:
            break
        source = f"127.0.1.{i + 1}" if own_addresses else None
        forged = {"X-Forwarded-For": "203.0.113.1"} if own_addresses else None
        token = _join(url, slug, f"sticky-{i}", source=source, headers=forged)
        seen = _workers_of(url, token)
        assert len(seen) == 1, f"session {i} was served by workers {seen}"
        owner[token] = seen.pop()
    assert set(owner.values()) == {"0", "1"}, f"{sessions} sessions all on one worker: {owner}"
    return owner


def _workers_of(url: str, token: str) -> set[str]:
    """The workers that answered this session's HTTP requests, its 3D view page, its teleoperation socket and its
    3D view's socket."""
    seen = set()
    with httpx.Client(base_url=url, timeout=30) as client:
        for path in (f"/api/p/{token}/state", f"/p/{token}", f"/viewer/{token}/", f"/api/p/{token}/state"):
            response = client.get(path)
            assert response.status_code == 200, (path, response.text)
            seen.add(response.headers[WORKER])
    ws_url = url.replace("http://", "ws://") + f"/api/p/{token}/teleop"
    with connect(ws_url, open_timeout=30) as socket:
        seen.add(socket.response.headers[WORKER])
    # the 3D view's socket, answered by the worker's view process (handed the connection by the worker)
    with connect(url.replace("http://", "ws://") + f"/viewer/{token}", subprotocols=[VIEWER_SUBPROTOCOL],
                 open_timeout=30) as socket:
        seen.add(socket.response.headers[WORKER])
    return seen


def test_a_group_routes_each_session_to_one_worker_and_completes_a_study(group: Group) -> None:
    g = group
    assert len(g.children()) == 3, "two workers and nginx"
    config = demo_fast().model_dump(mode="json")
    created = g.admin("POST", "/api/admin/studies", json={"status": "open", "slug": "fast", "config": config})
    assert created.status_code == 201, created.text
    assert created.headers[WORKER] == "0", "the admin API is served by the primary"

    owner = _sticky_owners(g.url, "fast", STICKY_SESSIONS)

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
    assert _workers_of(g.url, token) == {"1"}
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


# -- a group across machines: workers on TCP ports of this machine ----------------------------------------------

@pytest.fixture
def postgres_url(request: pytest.FixtureRequest) -> Iterator[str]:
    """A migrated PostgreSQL database of its own (a copy of the session's template)."""
    if POSTGRES_URL is None:
        pytest.skip("TRUSTLAB_TEST_POSTGRES_URL is not set")
    name = create_postgres_database(template=request.getfixturevalue("postgres_template"))
    try:
        yield postgres_database_url(name)
    finally:
        drop_postgres_database(name)


def test_workers_on_tcp_behind_nginx_route_each_session_to_one_worker_and_believe_only_nginx(postgres_url: str) -> None:
    """``serve --workers-at`` in front of two workers on TCP as ``trustlab worker`` runs them (here in threads, with
    the uvicorn options and loopback trust it gives them; starting two more processes would cost ~10 s)."""
    nginx, proxy_port, ports = _nginx(), free_port(), [free_port(), free_port()]
    public = f"http://127.0.0.1:{proxy_port}"
    said: list[str] = []
    # nginx first, as machines may start in any order (and before this process has server threads: nginx is
    # forked with a preexec_fn, which is unsafe with threads).
    group = WorkerGroup(Settings(host="127.0.0.1", port=proxy_port), nginx,
                        remote=worker_addresses(",".join(f"127.0.0.1:{port}" for port in ports)), echo=said.append)
    group.start()
    with contextlib.ExitStack() as stack:
        stack.callback(group.stop)
        assert any("worker 0 at" in line and "does not answer yet" in line for line in said), said
        workers = [stack.enter_context(live_server(postgres_url, port=port, worker_index=index, public_url=public,
                                                   join_rate_limit_per_ip=TCP_JOINS_PER_IP,
                                                   uvicorn_options=forwarded_trust(trusted_proxies("127.0.0.1", []))))
                   for index, port in enumerate(ports)]
        token = workers[-1].admin_token  # each live server issues a new one, revoking the one before
        created = httpx.post(f"{public}/api/admin/studies", headers={"Authorization": f"Bearer {token}"}, timeout=30,
                             json={"status": "open", "slug": "fast", "config": demo_fast().model_dump(mode="json")})
        assert created.status_code == 201, created.text
        assert created.headers[WORKER] == "0", "the admin API is served by the primary"

        # More joins than the limit per address, each from an address of its own: all accepted, so the workers
        # count the address nginx forwards (not nginx's own, not the one the client claimed).
        _sticky_owners(public, "fast", TCP_JOINS_PER_IP + 2, up_to=STICKY_SESSIONS, own_addresses=True)

        # A client that reaches a worker's port directly is not nginx: its X-Forwarded-For is not believed, and its
        # joins all count against its real address, which nginx then finds spent too.
        direct_source = "127.0.0.3"
        with httpx.Client(transport=httpx.HTTPTransport(local_address=direct_source), timeout=30) as direct:
            statuses = [direct.post(f"http://127.0.0.1:{ports[0]}/api/studies/fast/join",
                                    headers={"X-Forwarded-For": f"203.0.113.{i + 10}"}).status_code
                        for i in range(TCP_JOINS_PER_IP + 2)]
            assert statuses.count(200) <= TCP_JOINS_PER_IP and statuses[-1] == 429, statuses
            through_nginx = direct.post(f"{public}/api/studies/fast/join")
        assert through_nginx.status_code == 429, "the direct joins were counted against the client's real address"
