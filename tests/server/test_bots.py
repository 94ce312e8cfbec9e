"""The bots' HTTP client: a connection the server closed as a request went out is retried once, where safe."""

from __future__ import annotations

import json

import httpx
import pytest

from experiment.iohmm import paper_params
from server.bots import Bot, BotStats


def flaky_transport(failures: int, seen: list[tuple[str, str, str | None]]) -> httpx.MockTransport:
    """Fails the first ``failures`` requests as a server closing a kept-alive connection does."""

    def handle(request: httpx.Request) -> httpx.Response:
        seen.append((request.method, request.url.path, request.headers.get("Idempotency-Key")))
        if len(seen) <= failures:
            raise httpx.ReadError("[Errno 104] Connection reset by peer", request=request)
        return httpx.Response(200, json={"ok": True})

    return httpx.MockTransport(handle)


def make_bot(transport: httpx.MockTransport, external_id: str | None) -> Bot:
    http = httpx.Client(transport=transport, base_url="http://server")
    bot = Bot(http, lambda path: None, "s1", paper_params(), 0, BotStats(), external_id=external_id)  # type: ignore[arg-type]
    bot.token = "t" * 32
    return bot


def test_a_reset_connection_is_retried_once_with_the_same_idempotency_key():
    seen: list = []
    bot = make_bot(flaky_transport(1, seen), "bot-1")
    assert bot.post("consent", {"agree": True}) == {"ok": True}
    assert len(seen) == 2 and seen[0] == seen[1] and seen[0][2]  # the same request, the same key
    assert len(bot.stats.latencies_ms) == 1  # one call, timed from its first attempt


def test_a_second_failure_is_an_error():
    seen: list = []
    bot = make_bot(flaky_transport(2, seen), "bot-1")
    with pytest.raises(httpx.ReadError):
        bot.state()
    assert len(seen) == 2


def test_a_join_without_an_external_id_is_not_repeated():
    seen: list = []
    bot = make_bot(flaky_transport(1, seen), None)
    with pytest.raises(httpx.ReadError):
        bot.call("POST", "/api/studies/s1/join", {"params": {}})
    assert len(seen) == 1  # a second join would make a second participant
    seen.clear()
    resuming = make_bot(flaky_transport(1, seen), "bot-2")
    assert resuming.call("POST", "/api/studies/s1/join", {"params": {"PROLIFIC_PID": "bot-2"}}) == {"ok": True}
    assert len(seen) == 2 and json.dumps(seen[0]) == json.dumps(seen[1])
