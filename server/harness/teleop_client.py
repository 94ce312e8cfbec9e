"""A teleoperation socket for tests that checks every message, both ways, against the published JSON Schema.

``CheckedSocket`` wraps a TestClient websocket or a ``websockets`` sync connection: every text frame
sent or received is validated against ``/api/schema/teleop.json`` (the document the app serves), so a
test that uses it fails when the server sends something its contract does not describe.
"""

from __future__ import annotations

import json
from functools import cache
from typing import TYPE_CHECKING, Any

from server.teleop_messages import json_schema

if TYPE_CHECKING:
    import jsonschema


@cache
def _validators() -> tuple[jsonschema.Draft202012Validator, jsonschema.Draft202012Validator]:
    import jsonschema  # a test dependency

    schema = json_schema()
    defs = schema["$defs"]
    client = {**schema["properties"]["client_to_server"], "$defs": defs}
    server = {**schema["properties"]["server_to_client"], "$defs": defs}
    jsonschema.Draft202012Validator.check_schema(client)
    return jsonschema.Draft202012Validator(client), jsonschema.Draft202012Validator(server)


def check_server_message(message: dict[str, Any]) -> dict[str, Any]:
    _validators()[1].validate(message)
    return message


def check_client_message(message: dict[str, Any]) -> dict[str, Any]:
    _validators()[0].validate(message)
    return message


class CheckedSocket:
    """Sends and receives teleoperation messages as dicts, validating each against the schema."""

    def __init__(self, socket: Any, *, check_sent: bool = True):
        self.socket, self.check_sent = socket, check_sent
        self.received: list[dict[str, Any]] = []

    def send(self, message: dict[str, Any]) -> None:
        if self.check_sent:
            check_client_message(message)
        self.send_raw(json.dumps(message))

    def send_raw(self, text: str) -> None:
        send = getattr(self.socket, "send_text", None) or self.socket.send
        send(text)

    def receive(self, **kwargs: Any) -> dict[str, Any]:
        receive = getattr(self.socket, "receive_text", None) or self.socket.recv
        message = json.loads(receive(**kwargs))
        self.received.append(message)
        return check_server_message(message)

    def receive_until(self, kind: str, **kwargs: Any) -> dict[str, Any]:
        """The next message of type ``kind`` (world messages in between are checked and kept)."""
        while (message := self.receive(**kwargs))["type"] != kind:
            if message["type"] == "over" and kind != "over":
                raise AssertionError(f"teleoperation over while waiting for {kind}: {message}")
        return message

    def input(self, seq: int, **fields: Any) -> dict[str, Any]:
        """Send an input message and return its ack."""
        self.send({"type": "input", "seq": seq, **fields})
        return self.receive_until("ack")
