"""The kinds of the event log (``events.csv``): every kind the server writes, and the prefix of the clients' own.

The server writes the kinds of ``EventKind``; a page posts events of kinds of its own (camera changes, key
presses, blur/focus), stored as ``client.`` + its kind. The codebook lists the kinds from here.
"""

from __future__ import annotations

from enum import StrEnum


class EventKind(StrEnum):
    """An event the server writes (its payload: the codebook's ``events.csv`` ``kind``)."""

    JOINED = "joined"
    CONSENT = "consent"
    STEP = "step"  # the participant moved on (payload: the new step)
    TRIAL_STARTED = "trial_started"
    SCENE_SHOWN = "scene_shown"
    DECISION_WINDOW_OPENED = "decision_window_opened"
    INTERVENE = "intervene"
    TRIAL_COMPLETED = "trial_completed"
    TELEOP_LOG = "teleop_log"
    TELEOP_TIMEOUT = "teleop_timeout"
    TELEOP_RETRY = "teleop_retry"
    BLOCK_ORDER_ASSIGNED = "block_order_assigned"
    ABANDONED = "abandoned"
    ATTENTION_FAILED = "attention_failed"
    SCREENED_OUT = "screened_out"
    JOIN_REFUSED = "join_refused"  # study-level: no participant
    TELEOP_VIEW_WAIT = "teleop_view_wait"  # the time limit stood still while the page had no usable view
    CAMERA = "camera"  # the participant changed the 3D view's camera
    WITHDRAWN = "withdrawn"  # the session ended as withdrawn (payload: by = participant | researcher, the step)


#: The longest kind the event log stores (``Event.kind``).
KIND_LENGTH = 48
#: The prefix of the kinds of the events clients post (``client.`` + the page's kind).
CLIENT_KIND_PREFIX = "client."
#: The longest kind a page may post: stored with its prefix, it must fit the log's column.
CLIENT_KIND_LENGTH = KIND_LENGTH - len(CLIENT_KIND_PREFIX)


def client_kind(kind: str) -> str:
    """The stored kind of an event a page posted as ``kind``."""
    return CLIENT_KIND_PREFIX + kind
