"""A thread that runs commands in the order they are posted: the viewer thread (``trustlab-viewers``).

A trial's scene is (re)built in its viser server by this one thread, with commands from the event loop: tens of
viser messages, a few times a minute per session. While the thread is not running, commands run inline.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import queue
import threading
from collections.abc import Callable
from typing import Any

log = logging.getLogger("trustlab.viewer")

#: The thread's longest sleep (s): it wakes for every command anyway.
IDLE_WAKE_S = 1.0
_STOP = object()  # tells the thread to end


class Mailbox:
    """Commands (callables) run in order on one daemon thread, started and stopped by its owner."""

    def __init__(self, name: str):
        self.name = name
        self._thread: threading.Thread | None = None
        self._running = False
        self._inbox: queue.SimpleQueue[Any] = queue.SimpleQueue()  # commands and _STOP, in order

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        self._running = True
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Run the commands already posted, then end the thread (blocks: call it from a worker thread)."""
        self._running = False
        self._inbox.put(_STOP)
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None

    def post(self, command: Callable[[], Any]) -> None:
        """Run ``command`` on the thread (inline if it is not running)."""
        if self._running:
            self._inbox.put(command)
        else:
            command()

    async def call(self, command: Callable[[], Any]) -> Any:
        """Run ``command`` on the thread and wait for it."""
        if not self._running:
            return command()
        done: concurrent.futures.Future = concurrent.futures.Future()

        def run() -> None:
            if not done.set_running_or_notify_cancel():  # the caller is gone (cancelled at shutdown)
                return
            try:
                done.set_result(command())
            except Exception as exc:  # noqa: BLE001 -- handed to the awaiting caller
                done.set_exception(exc)

        self.post(run)
        return await asyncio.wrap_future(done)

    def _run(self) -> None:
        """Run commands in order until told to stop."""
        while True:
            try:
                item = self._inbox.get(timeout=IDLE_WAKE_S)
            except queue.Empty:
                continue
            if item is _STOP:
                return
            try:
                item()
            except Exception:
                log.exception("viewer command failed")
