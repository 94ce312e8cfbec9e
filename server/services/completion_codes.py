"""Completion codes of a study's own: the defaults in ``experiment.outcomes`` are public.

A recruitment site pays whoever enters a study's completion code. ``TRUSTLAB-DONE`` and the other defaults are
in this source code, so a study that kept them could be "completed" by anyone who reads it. A study saved with a
default code gets a random code of its own for that outcome instead (shown on the admin page, to enter on the
recruitment site), and keeps it in later versions: a version saved again with the default (from a template, say)
keeps the study's code rather than changing what the recruitment site was told. A code the lab set is kept.
"""

from __future__ import annotations

import secrets
from typing import Any

from experiment.config import StudyConfig
from experiment.outcomes import CompletionConfig

#: The completion codes a config has when it sets none (public).
PUBLIC_DEFAULT_CODES = {name: CompletionConfig.model_fields[name].default
                        for name in ("code_completed", "code_declined", "code_screened_out")}
#: Upper-case letters and digits without the look-alikes (0/O, 1/I/L): a participant copies the code by hand.
CODE_ALPHABET = "ABCDEFGHJKMNPQRSTUVWXYZ23456789"
#: 10 characters of 31: about 50 bits, far beyond guessing at the join rate limit, short enough to type.
CODE_LENGTH = 10


def random_code() -> str:
    return "".join(secrets.choice(CODE_ALPHABET) for _ in range(CODE_LENGTH))


def with_private_codes(config: StudyConfig, previous: dict[str, Any] | None = None) -> StudyConfig:
    """``config`` with each public default code replaced: by the previous version's code for that outcome when it
    had one of its own (``previous``: that version's stored document), else by a new random code."""
    earlier = (previous or {}).get("completion") or {}
    codes = {}
    for name, public in PUBLIC_DEFAULT_CODES.items():
        if getattr(config.completion, name) != public:
            continue
        kept = earlier.get(name)
        codes[name] = kept if isinstance(kept, str) and kept not in PUBLIC_DEFAULT_CODES.values() else random_code()
    if not codes:
        return config
    return config.model_copy(update={"completion": config.completion.model_copy(update=codes)})
