"""A server shutting down stops its 3D view process and starts none (``server.viewer.remote``,
``server.viewer.process``).

A Ctrl-C in the terminal reached the whole foreground process group, and a service manager's SIGTERM reaches every
process of the service: the server and its view process got the signal at the same moment. The view process ended on
it first (with a KeyboardInterrupt traceback), and the server, still shutting down, logged it as a crash and started
another. Now the view process has a process group of its own and ignores both signals: its server ends it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from server.harness.live import free_port, start_server


def view_processes(parent: int) -> set[int]:
    """The view processes ``parent`` started (running, not zombies)."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            cmdline = (stat.parent / "cmdline").read_bytes()
        except OSError:
            continue
        if int(fields[1]) == parent and fields[0] != "Z" and b"server.viewer.process" in cmdline:
            found.add(int(stat.parent.name))
    return found


def ignores_stop_signals(pid: int) -> bool:
    """Whether ``pid`` ignores SIGINT and SIGTERM yet (it sets that first thing, once its imports are done)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigIgn:"):
            mask = int(line.split()[1], 16)
            return all(mask & (1 << (s - 1)) for s in (signal.SIGINT, signal.SIGTERM))
    return False


def ready_view_process(server: subprocess.Popen) -> int:
    deadline = time.monotonic() + 30
    while not (children := view_processes(server.pid)) or not all(ignores_stop_signals(c) for c in children):
        assert time.monotonic() < deadline, "no view process started"
        time.sleep(0.05)
    [child] = children
    return child


def alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_a_signal_to_the_whole_group_stops_the_view_process_and_starts_none(tmp_path, sqlite_template, signum):
    database = tmp_path / "trustlab.db"
    database.write_bytes(sqlite_template.read_bytes())
    with open(tmp_path / "serve.log", "w+") as log:
        server, _token = start_server(f"sqlite:///{database}", free_port(), log)
        try:
            child = ready_view_process(server)
            assert os.getpgid(child) == child  # a group of its own: a terminal's Ctrl-C is not sent to it
            seen = {child}
            os.kill(server.pid, signum)  # as a service manager stopping the whole group does: both at once
            os.kill(child, signum)
            deadline = time.monotonic() + 30
            while server.poll() is None:
                seen |= view_processes(server.pid)
                assert time.monotonic() < deadline, "the server did not stop"
                time.sleep(0.02)
        finally:
            if server.poll() is None:
                server.kill()
                server.wait()
        log.seek(0)
        written = log.read()
    assert seen == {child}, f"another view process was started: {seen}"
    deadline = time.monotonic() + 15
    while alive(child):
        assert time.monotonic() < deadline, "the view process outlived its server"
        time.sleep(0.05)
    shutdown = written.split("admin page:", 1)[1]
    assert "3D view process stopped (the server is shutting down)" in shutdown
    assert "starting another" not in shutdown
    assert "Traceback" not in shutdown and "KeyboardInterrupt" not in shutdown


def test_the_view_process_ignores_a_signal_meant_for_its_server(tmp_path, sqlite_template):
    """Alone, a SIGTERM or SIGINT does not end the view process (its server ends it); a crash is still restarted."""
    database = tmp_path / "trustlab.db"
    database.write_bytes(sqlite_template.read_bytes())
    with open(tmp_path / "serve.log", "w+") as log:
        server, _token = start_server(f"sqlite:///{database}", free_port(), log)
        try:
            child = ready_view_process(server)
            os.kill(child, signal.SIGTERM)
            os.kill(child, signal.SIGINT)
            time.sleep(1.5)
            assert view_processes(server.pid) == {child}
            os.kill(child, signal.SIGKILL)  # a crash: another starts
            deadline = time.monotonic() + 30
            while not view_processes(server.pid) - {child}:
                assert time.monotonic() < deadline, "no view process restarted"
                time.sleep(0.05)
            server.send_signal(signal.SIGTERM)
            server.wait(30)
        finally:
            if server.poll() is None:
                server.kill()
                server.wait()
        log.seek(0)
        written = log.read()
    assert "3D view process ended (killed by SIGKILL); starting another" in written
    assert written.rstrip().endswith("3D view process stopped (the server is shutting down)")
    assert not subprocess.run(["pgrep", "-f", "server.viewer.process", "-P", str(server.pid)],
                              capture_output=True).stdout
