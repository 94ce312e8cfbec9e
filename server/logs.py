"""Keep credentials out of the server's logs.

A participant's token is in the paths they request (``/api/p/{token}/...``,
``/p/{token}``, ``/viewer/{token}``) and recruitment ids such as ``PROLIFIC_PID``
are in join query strings (an external id resumes its session, so it is a key
too). uvicorn's access log and its websocket lines name both; this filter
rewrites them before any handler sees the record.
"""

from __future__ import annotations

import logging
import re

_TOKEN_IN_PATH = re.compile(r"(/(?:p|viewer)/)[^/?#\s\"]+")
_QUERY = re.compile(r"\?[^\s\"]*")
#: The loggers that name request paths (uvicorn: access lines; "WebSocket /path" [accepted] lines).
REDACTED_LOGGERS = ("uvicorn.access", "uvicorn.error")


def redact(text: str) -> str:
    return _QUERY.sub("?…", _TOKEN_IN_PATH.sub(r"\1…", text))


class RedactCredentials(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redact(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(redact(a) if isinstance(a, str) else a for a in record.args)
        return True


def redact_server_logs() -> None:
    """Install the filter on uvicorn's loggers (once, however many apps are created)."""
    for name in REDACTED_LOGGERS:
        logger = logging.getLogger(name)
        if not any(isinstance(f, RedactCredentials) for f in logger.filters):
            logger.addFilter(RedactCredentials())
