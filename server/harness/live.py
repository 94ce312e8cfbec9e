"""A real uvicorn server in a thread or a `trustlab serve` subprocess, and bots driving it over HTTP and websockets."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import closing, contextmanager
from dataclasses import dataclass
from typing import Any, TextIO

import httpx
import uvicorn
from fastapi import FastAPI

from experiment.config import StudyConfig
from experiment.flow import all_steps
from experiment.iohmm import paper_params
from server.harness.bots import Bot
from server.harness.client import BotStats, remote_sockets
from server.harness.crowd import BotRunSummary, run_remote_bots
from server.launch import websocket_protocol
from server.main import create_app
from server.models import utcnow
from server.services.admin import ensure_admin_token, rotate_admin_token
from server.settings import Settings

#: Test servers that bots teleoperate on push the teleoperation world 60 times a second (15 in production) and take
#: 120 messages a second (60): the bots' scripted controller closes its loop through the socket, and its teleoperation
#: of a sped-up study takes ~1.7 s instead of ~4 s. Browser tests keep the production settings (the page is tested as
#: deployed); so do the benchmarks.
BOT_TELEOP_SETTINGS: dict[str, Any] = {"teleop_world_hz": 60.0, "teleop_rate_limit_hz": 120.0}
BOT_TELEOP_ENV = {f"TRUSTLAB_{name.upper()}": str(value) for name, value in BOT_TELEOP_SETTINGS.items()}
#: Server subprocesses that should run the production default (a helper process plans attempts) get this
#: environment (``start_server``); the tests' own apps plan attempts in process (``tests/conftest.py``).
PRODUCTION_ENV = {"TRUSTLAB_PLANNER_PROCESSES": "1"}


@dataclass
class Live:
    app: FastAPI
    url: str
    admin_token: str

    def admin(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        return httpx.request(method, self.url + path, headers={"Authorization": f"Bearer {self.admin_token}"},
                             timeout=30, **kwargs)

    def bots(self, slug: str, participants: int, seed: int = 0) -> BotRunSummary:
        """``participants`` bots through the whole study, two at a time (as ``trustlab bots`` runs them)."""
        return run_remote_bots(self.url, slug, paper_params(), participants=participants, concurrency=2, seed=seed)


@contextmanager
def live_server(database_url: str, *, log_level: str = "warning", port: int = 0,
                uvicorn_options: dict[str, Any] | None = None, **settings: Any) -> Iterator[Live]:
    """The app on a loopback port (a free one unless given) with its world loop, uvicorn's logging left to the
    root logger (``BOT_TELEOP_SETTINGS`` unless given); ``uvicorn_options`` add to uvicorn's configuration."""
    settings = BOT_TELEOP_SETTINGS | settings
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", port))
    port = sock.getsockname()[1]
    app = create_app(Settings(database_url=database_url, port=port, **settings))
    with app.state.services.sessionmaker.begin() as session:  # a restart on the same database gets a new token
        token = ensure_admin_token(session) or rotate_admin_token(session, utcnow())
    server = uvicorn.Server(uvicorn.Config(app, log_config=None, log_level=log_level, lifespan="on",
                                           ws=websocket_protocol(app), **(uvicorn_options or {})))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, name="uvicorn", daemon=True)
    thread.start()
    deadline = time.monotonic() + 15
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "the server did not start"
        time.sleep(0.02)
    try:
        yield Live(app, f"http://127.0.0.1:{port}", token)
    finally:
        server.should_exit = True
        thread.join(timeout=15)
        sock.close()
        assert not thread.is_alive(), "the server did not stop"


# -- a real `trustlab serve` in a subprocess, to be killed with SIGKILL -----------------------------------------------

#: Longest a server subprocess may take to answer its first request (imports and migrations on a busy machine).
SERVER_START_TIMEOUT_S = 60.0


def free_port() -> int:
    with closing(socket.socket()) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(database_url: str, port: int, log: TextIO, *options: str,
                 env: dict[str, str] | None = None) -> tuple[subprocess.Popen, str | None]:
    """``trustlab serve [options]`` in a subprocess, once it answers and has printed its links; returns it and the
    admin token it printed (first run only). ``env`` adds to the production settings (and ``BOT_TELEOP_ENV``)."""
    offset = log.tell()
    process = subprocess.Popen([sys.executable, "-c", "from server.cli import app; app()", "serve", "--port", str(port),
                                "--database-url", database_url, *options], stdout=log, stderr=subprocess.STDOUT,
                               text=True, env=os.environ | PRODUCTION_ENV | BOT_TELEOP_ENV | (env or {}))
    deadline = time.monotonic() + SERVER_START_TIMEOUT_S
    while True:
        try:  # any answer (a 404 too) means the app is serving; the OpenAPI schema would cost a build
            httpx.get(f"http://127.0.0.1:{port}/api/ready-check", timeout=1)
            if "admin page:" in _written(log, offset):  # a group prints its links once it answers
                break
        except httpx.TransportError:
            pass
        if process.poll() is not None or time.monotonic() > deadline:
            process.kill()
            process.wait()
            raise RuntimeError(f"the server did not start:\n{_written(log, offset)[-2000:]}") from None
        time.sleep(0.05)
    token = None
    for line in _written(log, offset).splitlines():
        if "admin token (shown once" in line:
            token = line.rsplit(" ", 1)[-1].strip()
    return process, token


def _written(log: TextIO, offset: int) -> str:
    """What the server wrote to ``log`` since ``offset``."""
    log.flush()
    with open(log.name, encoding="utf-8") as text_log:
        text_log.seek(offset)
        return text_log.read()


def kill_server(process: subprocess.Popen) -> None:
    """kill -9: no shutdown code runs, open transactions die with the process."""
    process.send_signal(signal.SIGKILL)
    process.wait()


def make_bots(port: int, stats: BotStats, n: int, *, slug: str = "fast", prefix: str = "durable",
              bot_class: type[Bot] = Bot) -> list[Bot]:
    """``n`` bots against the server on ``port``, with fixed external ids (so a rerun resumes their sessions)."""
    url = f"http://127.0.0.1:{port}"
    sockets = remote_sockets(url)
    return [bot_class(httpx.Client(base_url=url, timeout=10), sockets, slug, paper_params(), 7, stats,
                      external_id=f"{prefix}-{i}") for i in range(n)]


def expected_records(config: StudyConfig, block_order: list[str]) -> tuple[int, int, int]:
    """(practice trials, scored trials, answers) of one participant who finishes a study of ``config``."""
    steps = all_steps(config, block_order)
    phases = [s.phase for s in steps]
    answers = sum(len(config.questionnaire(page.questionnaire).items)
                  for page in (s.questionnaire_page(config) for s in steps) if page is not None)
    return phases.count("practice"), phases.count("trial"), answers


def run_all(bots: list[Bot]) -> tuple[list[BaseException | None], list[threading.Thread]]:
    """Each bot's ``run`` in a thread of its own; a bot's exception (the server died under it) lands in the list."""
    results: list[BaseException | None] = [None] * len(bots)

    def one(i: int) -> None:
        try:
            bots[i].run()
        except BaseException as exc:  # noqa: BLE001 -- the server died under the bot
            results[i] = exc

    threads = [threading.Thread(target=one, args=(i,), name=f"bot-{i}") for i in range(len(bots))]
    for t in threads:
        t.start()
    return results, threads
