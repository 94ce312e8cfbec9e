"""Helper processes of the server: they plan the robot's autonomous attempts (``server.world.attempts``) and compute
teleoperation physics (``server.world.physics``)."""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context

#: How often a helper checks that the server that started it is still alive (s).
PARENT_CHECK_S = 1.0


def helper_pool(processes: int) -> ProcessPoolExecutor:
    """``processes`` spawned helpers (not forked: the server has threads) that end when the server ends, however
    it ends (also by kill -9, which leaves no chance to stop them)."""
    return ProcessPoolExecutor(processes, get_context("spawn"), initializer=exit_with_parent, initargs=(os.getpid(),))


def exit_with_parent(parent: int) -> None:
    """End this process (at once) when ``parent`` is no longer its parent: the server ended, however it ended."""
    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_CHECK_S)
        os._exit(0)

    threading.Thread(target=watch, name="trustlab-helper-watch", daemon=True).start()
