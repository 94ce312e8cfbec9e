"""The link between a server process and its 3D view process (``server.viewer.remote``, ``server.viewer.process``).

Two unix socket pairs, made by the server before it starts the view process:

- messages, both ways: each a 4-byte big-endian length and a pickle (both ends are this code, started by the same
  user from the same installation; nothing else can reach an unnamed socket pair);
- hand-offs, server to view process: a browser's ``/viewer/`` websocket connection as it arrived (the upgrade
  request's bytes) with the connection's file descriptor (``SCM_RIGHTS``), one datagram each (``SOCK_SEQPACKET``).

Messages, server to view process: ``("worlds", {public id: LiveWorld})`` each world tick (the teleoperations of
watched sessions), ``("playback", public id, Playback | None)`` (an attempt played back from its start, or none),
``("started", request id, participant id, Target)`` (answered with ``("reply", request id, bool)``), ``("view",
participant id, preset)``. View process to server: ``("status", ViewStatus)`` whenever it changes and every poll,
``("reply", request id, value)``.
"""

from __future__ import annotations

import asyncio
import os
import pickle
import socket
import struct
from typing import Any

_LENGTH = struct.Struct(">I")
#: The longest hand-off datagram: an upgrade request's bytes (a browser's are about 1 KB).
MAX_HANDOFF_BYTES = 64 * 1024
#: Messages buffered towards a peer that does not read, before world ticks are dropped (the views skip frames).
MAX_BUFFERED_BYTES = 4 * 1024 * 1024


def socket_pairs() -> tuple[tuple[socket.socket, socket.socket], tuple[socket.socket, socket.socket]]:
    """(messages, hand-offs): each (this end, the view process's end)."""
    return (socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM),
            socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET))


class MessageLink:
    """Framed messages over a connected stream socket, on the running event loop."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter):
        self._reader, self._writer = reader, writer

    @classmethod
    async def over(cls, sock: socket.socket) -> MessageLink:
        reader, writer = await asyncio.open_unix_connection(sock=sock, limit=MAX_BUFFERED_BYTES)
        return cls(reader, writer)

    def send(self, message: Any, *, droppable: bool = False) -> bool:
        """Queue ``message`` for the peer; False when the link is closed, or ``droppable`` and the peer lags."""
        transport = self._writer.transport
        if transport.is_closing():
            return False
        if droppable and transport.get_write_buffer_size() > MAX_BUFFERED_BYTES:
            return False
        data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        self._writer.write(_LENGTH.pack(len(data)) + data)
        return True

    async def receive(self) -> Any:
        """The next message; raises ``asyncio.IncompleteReadError`` when the peer has gone."""
        (length,) = _LENGTH.unpack(await self._reader.readexactly(_LENGTH.size))
        return pickle.loads(await self._reader.readexactly(length))

    def close(self) -> None:
        self._writer.close()


def hand_off(sock: socket.socket, request: bytes, fd: int) -> bool:
    """Send a connection (its file descriptor) and the bytes read from it; False if the peer cannot take it now."""
    try:
        socket.send_fds(sock, [request], [fd])
    except (BlockingIOError, OSError):
        return False
    return True


def take_handoffs(sock: socket.socket) -> list[tuple[socket.socket, bytes]] | None:
    """The connections handed off so far (non-blocking), as sockets of this process; None when the peer has gone."""
    taken: list[tuple[socket.socket, bytes]] = []
    while True:
        try:
            data, fds, _flags, _addr = socket.recv_fds(sock, MAX_HANDOFF_BYTES, 1)
        except BlockingIOError:
            return taken
        except OSError:
            return None
        if not data and not fds:
            return None
        for fd in fds:
            try:
                taken.append((socket.socket(fileno=fd), data))
            except OSError:
                os.close(fd)
