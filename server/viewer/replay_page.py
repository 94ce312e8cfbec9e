"""Replay files: one self-contained HTML page with viser's player beside the trial's timeline (``static/replay.html``).

A page holds one or more trials of one participant: viser's client page once (``client/build/index.html``, the 0.8 MB
that ``StateSerializer.as_html`` inlines in every file it writes), each trial's recording (``server.viewer.recording``)
and its timeline. The page's script puts the chosen trial's recording into the client page as ``as_html`` does and
shows it in an iframe (``srcdoc``: the same origin as the file). So a whole participant is one file, and each trial
after the first costs only its recording and timeline. Nothing is fetched: it plays from disk with no network.
"""

from __future__ import annotations

import base64
import html
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import viser

from experiment.flow import TrialRef
from experiment.replay import Replay, reconstruct
from server.db.units import SessionOpener
from server.errors import NotFound
from server.services.replay import ParticipantTrials, TrialToReplay, load_trials
from server.viewer.recording import record
from server.world.processes import helper_pool

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"
CLIENT_PAGE = Path(viser.__file__).parent / "client" / "build" / "index.html"


@dataclass(frozen=True)
class ReplayedTrial:
    trial: TrialToReplay
    replay: Replay
    recording: bytes  # viser's serialised recording

    @property
    def reproduced(self) -> bool:
        return self.replay.reproduced


def participant_replay(factory: SessionOpener, slug: str, public_id: str,
                       refs: Sequence[TrialRef] | None = None) -> tuple[str, str]:
    """(file name, HTML) of the participant's trials (all of them, or ``refs``): read in one unit, then rebuilt,
    recorded and written in a helper process (pure-Python CPU, a few hundred milliseconds a trial, that in a thread
    of the server would hold the interpreter lock against its event loop)."""
    with factory() as session:
        loaded = load_trials(session, slug, public_id, refs)
    if not loaded.trials:
        raise NotFound(f"participant {public_id!r} has no trials yet")
    name = (f"replay-{public_id}-{file_label(loaded.trials[0].ref)}.html" if len(loaded.trials) == 1 and refs
            else f"replay-{public_id}.html")
    with helper_pool(1) as pool:
        return name, pool.submit(build_page, loaded).result()


def build_page(participant: ParticipantTrials) -> str:
    """The HTML page of every trial of ``participant`` (rebuilt and recorded here)."""
    return replay_page(participant, replay_trials(participant))


def file_label(ref: TrialRef) -> str:
    """A trial in a file name: ``practice-2``, ``block1-trial3``."""
    return f"practice-{ref.trial}" if ref.practice else f"block{ref.block}-trial{ref.trial}"


def replay_trials(participant: ParticipantTrials,
                  progress: Callable[[int, int, TrialToReplay], None] | None = None) -> list[ReplayedTrial]:
    """Reconstruct and record each trial (``progress(done, total, trial)`` after each)."""
    out = []
    for done, trial in enumerate(participant.trials, 1):
        replay = reconstruct(trial.record)
        out.append(ReplayedTrial(trial, replay, record(replay)))
        if progress is not None:
            progress(done, len(participant.trials), trial)
    return out


def replay_page(participant: ParticipantTrials, trials: Sequence[ReplayedTrial]) -> str:
    """The HTML page of ``trials`` (one or more of ``participant``'s)."""
    data = {"study": participant.study, "participant": participant.participant,
            "trials": [_trial_data(t) for t in trials]}
    title = (f"Replay: {participant.participant}, {trials[0].trial.label}" if len(trials) == 1
             else f"Replay: {participant.participant}, {len(trials)} trials")
    page = (STATIC_DIR / "replay.html").read_text(encoding="utf-8")
    data_json = json.dumps(data, separators=(",", ":")).replace("<", "\\u003c")  # JSON safe inside a script element
    fills = {"{{TITLE}}": html.escape(title), "{{DATA}}": data_json,
             "{{CLIENT}}": CLIENT_PAGE.read_text(encoding="utf-8").replace("</script", "<\\/script"),
             "{{SCRIPT}}": _in_script((STATIC_DIR / "js" / "replay.js").read_text(encoding="utf-8"))}
    for mark, text in fills.items():
        head, _, tail = page.partition(mark)
        page = head + text + tail
    return page


def _in_script(script: str) -> str:
    """JavaScript safe inside a script element (``</`` only appears in its strings, where ``<\\/`` reads the same)."""
    return script.replace("</", "<\\/")


def _trial_data(trial: ReplayedTrial) -> dict[str, Any]:
    replay, record_ = trial.replay, trial.trial.record
    return {"label": trial.trial.label, "ref": list(trial.trial.ref), "complexity": record_.complexity,
            "robot_action": record_.robot_action.value, "recorded": replay.recorded,
            "reconstructed": replay.reconstructed, "reproduced": replay.reproduced, "missing": replay.missing,
            "duration": round(replay.duration, 3),
            "phases": [{"kind": p.kind, "start": round(p.start, 3), "end": round(p.end, 3)} for p in replay.phases],
            "moments": [{"t": round(m.t, 3), "kind": m.kind, "text": m.text} for m in replay.moments],
            "recording": base64.b64encode(trial.recording).decode("ascii")}
