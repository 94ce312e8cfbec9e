"""Replays of a participant's trials from the database alone: the rows read into ``experiment.replay.TrialRecord``s.

One read unit reads the participant, their trials, the study versions those ran under, and the events a replay needs
(teleoperation logs, guided practice retries, camera changes); ``experiment.replay.reconstruct`` rebuilds each trial
and ``server.viewer.replay_page`` writes the HTML.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from experiment.config import StudyConfig
from experiment.events import EventKind
from experiment.flow import TrialRef
from experiment.replay import CameraChange, LogBatch, TrialRecord
from experiment.task import HumanAction, Outcome, RobotAction
from experiment.world.resimulate import TeleopClock
from experiment.world.teleop import TeleopRules
from server.errors import Invalid, NotFound
from server.models import Event, Participant, StudyVersion, Trial
from server.services.admin import participant_by_public_id
from server.services.studies import get_study
from server.world.teleop import GRIPPER_ACTION_S, MAX_TELEOP_SPEEDUP

_KINDS = (EventKind.TELEOP_LOG, EventKind.TELEOP_RETRY, EventKind.CAMERA)


@dataclass(frozen=True)
class TrialToReplay:
    """One trial of a participant, ready to reconstruct."""

    ref: TrialRef
    label: str  # "practice trial 1", "block 2 (aware), trial 5"
    record: TrialRecord


@dataclass(frozen=True)
class ParticipantTrials:
    study: str
    participant: str
    trials: list[TrialToReplay]


def parse_trial(text: str) -> TrialRef:
    """``practice:block:trial`` (e.g. ``0:1:3`` or ``true:0:2``) as a ``TrialRef``; Invalid if it is not one."""
    parts = text.split(":")
    flags = {"0": False, "1": True, "false": False, "true": True, "scored": False, "practice": True}
    if len(parts) != 3 or parts[0].lower() not in flags or not all(p.isdigit() for p in parts[1:]):
        raise Invalid(f"a trial is practice:block:trial (e.g. 0:1:3 for block 1's trial 3, 1:0:2 for practice trial "
                      f"2), not {text!r}")
    return TrialRef(flags[parts[0].lower()], int(parts[1]), int(parts[2]))


def load_trials(session: Session, slug: str, public_id: str, refs: Sequence[TrialRef] | None = None
                ) -> ParticipantTrials:
    """The participant's trials (all, or ``refs`` in that order), with what a replay needs of each."""
    study = get_study(session, slug)
    participant = participant_by_public_id(session, study, public_id)
    rows = list(session.scalars(select(Trial).where(Trial.participant_id == participant.id)
                                .order_by(Trial.practice.desc(), Trial.block, Trial.trial)))
    if refs is not None:
        by_ref = {row.ref: row for row in rows}
        if missing := [ref for ref in refs if ref not in by_ref]:
            raise NotFound(f"participant {public_id!r} has no {', '.join(ref.describe() for ref in missing)}")
        rows = [by_ref[ref] for ref in refs]
    versions = {v.id: StudyConfig.model_validate(v.config) for v in session.scalars(
        select(StudyVersion).where(StudyVersion.id.in_(sorted({row.study_version_id for row in rows}))))}
    events = list(session.scalars(select(Event).where(Event.participant_id == participant.id, Event.kind.in_(_KINDS))
                                  .order_by(Event.id)))
    trials = [TrialToReplay(row.ref, _label(row), _record(participant, row, versions[row.study_version_id], events))
              for row in rows]
    return ParticipantTrials(slug, public_id, trials)


def _label(row: Trial) -> str:
    if row.practice:
        return f"practice trial {row.trial}"
    return f"block {row.block} ({row.block_name}), trial {row.trial}"


def _record(participant: Participant, row: Trial, config: StudyConfig, events: Sequence[Event]) -> TrialRecord:
    start = row.started_at

    def since(at: datetime | None) -> float | None:
        return None if at is None else (at - start).total_seconds()

    mine = [e for e in events if _of_trial(e, row.ref)]
    speed = config.timing.animation_speed
    return TrialRecord(
        study_seed=row.seed if row.seed is not None else config.seed, participant_key=participant.public_id,
        ref=row.ref, block_name=row.block_name, complexity=row.complexity.value,
        robot_action=RobotAction(row.robot_action),
        human_action=HumanAction(row.human_action) if row.human_action is not None else None,
        outcome=Outcome(row.outcome) if row.outcome is not None else None, failure_mode=row.failure_mode,
        animation_speed=speed,
        clock=TeleopClock(min(speed, MAX_TELEOP_SPEEDUP), GRIPPER_ACTION_S,
                          TeleopRules(row.grasp_radius_m or config.teleop.grasp_radius_m,
                                      row.align_radius_m if row.align_radius_m is not None
                                      else config.teleop.align_radius_m)),
        scene_shown_s=since(row.scene_shown_at),
        scene_shown_view=row.scene_shown_view.value if row.scene_shown_view is not None else None,
        window_opened_s=since(row.window_opened_at),
        window_opened_by=row.window_opened_by.value if row.window_opened_by is not None else None,
        decided_s=since(row.decided_at), decision_time_ms=row.decision_time_ms, attempt_end_s=since(row.attempt_end_at),
        teleop_deadline_s=since(row.teleop_deadline_at), teleop_success=row.teleop_success,
        teleop_time_ms=row.teleop_time_ms, completed_s=since(row.completed_at),
        logs=tuple(LogBatch(tuple(e.payload.get("entries") or ()), since(e.created_at))
                   for e in mine if e.kind == EventKind.TELEOP_LOG),
        retries_s=tuple(s for e in mine if e.kind == EventKind.TELEOP_RETRY if (s := since(e.created_at)) is not None),
        camera=tuple(_camera(events, start, row.completed_at)),
        initial_view=_view_before(events, start))


def _of_trial(event: Event, ref: TrialRef) -> bool:
    payload = event.payload
    return (event.kind != EventKind.CAMERA and payload.get("practice") == ref.practice
            and payload.get("block") == ref.block and payload.get("trial") == ref.trial)


def _camera(events: Iterable[Event], start: datetime, end: datetime | None) -> Iterable[CameraChange]:
    """The camera presets chosen while the trial ran (camera events name no trial: they are placed by time)."""
    for event in events:
        if event.kind == EventKind.CAMERA and start <= event.created_at and (end is None or event.created_at <= end):
            yield CameraChange((event.created_at - start).total_seconds(), str(event.payload.get("view", "world")))


def _view_before(events: Iterable[Event], start: datetime) -> str:
    """The camera preset the trial started in: the last one chosen before it (the view keeps it between trials)."""
    views = [e for e in events if e.kind == EventKind.CAMERA and e.created_at < start]
    return str(views[-1].payload.get("view", "world")) if views else "world"
