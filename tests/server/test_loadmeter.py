"""The server's own load report (``server.loadmeter``, ``GET /api/admin/server/load``)."""

from __future__ import annotations

import time

import httpx
import pytest

from server.harness.live import live_server
from server.loadmeter import LoadFigures, LoadHistory, LoadSample, load_status


def _samples(seconds: int, *, late_from: int, skip_from: int) -> list[LoadSample]:
    """One sample a second: 30 ticks a second, from ``late_from`` 3 of them late a second, from ``skip_from`` 6 of
    them skipped by the views a second; a 2 s hold-up before the window and a 0.25 s one inside it."""
    out, late, skipped = [], 0, 0
    for s in range(seconds + 1):
        late += 3 if s > late_from else 0
        skipped += 6 if s > skip_from else 0
        latest = {5: 2.0, seconds - 10: 0.25}.get(s, 0.004)
        out.append(LoadSample(at=100.0 + s, ticks=30 * s, late_ticks=late, view_ticks=30 * s,
                              view_ticks_skipped=skipped, latest_start_s=latest))
    return out


def test_the_load_figures_cover_the_last_minute_only():
    history = LoadHistory(window_s=60.0)
    assert history.figures() is None
    for sample in _samples(90, late_from=30, skip_from=60):
        history.record(sample)
    figures = history.figures()
    assert figures is not None
    assert figures.window_s == pytest.approx(60.0)
    assert figures.ticks_per_s == pytest.approx(30.0)
    assert figures.late_share == pytest.approx(3 / 30)  # late all through the window
    assert figures.skipped_share == pytest.approx(0.5 * 6 / 30)  # skipping in its second half
    assert figures.latest_start_s == pytest.approx(0.25)  # the 2 s hold-up was before the window


@pytest.mark.parametrize(("figures", "world_loop", "status"), [
    (None, True, "starting"),
    (None, False, "off"),
    (LoadFigures(60.0, 30.0, 0.01, 0.02, 0.0), True, "ok"),
    (LoadFigures(60.0, 30.0, 0.01, 0.02, 0.05), True, "busy"),
    (LoadFigures(60.0, 30.0, 0.20, 0.08, 0.0), True, "busy"),
    (LoadFigures(60.0, 30.0, 0.50, 0.30, 0.30), True, "overloaded"),
    (LoadFigures(60.0, 20.0, 0.50, 0.30, 0.0), True, "overloaded"),  # the loop itself runs slow
])
def test_the_load_status_says_what_the_figures_mean(figures, world_loop, status):
    said, message = load_status(figures, 30.0, world_loop=world_loop)
    assert said == status
    assert message.endswith(".")
    if status == "overloaded":
        assert "max_active_participants" in message and "--workers" in message
    if status == "busy":  # says why: frames skipped, or updates late
        assert ("5 %" in message) if figures.skipped_share else ("20 %" in message and "80 ms" in message)


def test_the_server_reports_how_long_its_event_loop_was_held_up(database_url):
    with live_server(database_url) as live:
        assert httpx.get(live.url + "/api/admin/server/load", timeout=10).status_code == 401

        def report() -> dict:
            response = live.admin("GET", "/api/admin/server/load")
            assert response.status_code == 200, response.text
            return response.json()

        deadline = time.monotonic() + 20
        while (first := report())["status"] == "starting":
            assert time.monotonic() < deadline, first
            time.sleep(0.2)
        assert first["world_hz"] == 30.0
        assert 0 < first["world_ticks_per_s"] <= 31
        assert first["viewers"] == first["attempts_playing"] == first["arms_teleoperated"] == 0

        hub, held = live.app.state.services.hub, []

        def hold_the_loop_once(worlds) -> None:  # a tick listener runs on the event loop
            if not held:
                held.append(time.monotonic())
                time.sleep(0.3)

        hub.add_tick_listener(hold_the_loop_once)
        deadline = time.monotonic() + 20
        while not held or (after := report())["longest_tick_delay_ms"] < 250:
            assert time.monotonic() < deadline, "the held-up loop was not reported"
            time.sleep(0.3)
        hub.remove_tick_listener(hold_the_loop_once)
        assert after["late_tick_share"] > 0
        assert after["longest_tick_delay_ms"] < 2000
