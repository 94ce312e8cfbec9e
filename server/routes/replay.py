"""Admin API: a participant's trials as a 3D replay file (``server.viewer.replay_page``)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query
from fastapi.responses import HTMLResponse
from pydantic import StringConstraints

from server.bodies import StrictJsonRoute
from server.deps import AdminDep, ServicesDep
from server.schemas import error_responses
from server.services.replay import parse_trial
from server.viewer.replay_page import participant_replay

router = APIRouter(route_class=StrictJsonRoute, prefix="/api/admin", tags=["admin"], dependencies=[AdminDep])

#: ``server.services.replay.parse_trial``'s form.
TrialText = Annotated[str, StringConstraints(pattern=r"^(0|1|true|false|practice|scored):[0-9]{1,6}:[0-9]{1,6}$")]
Trials = Annotated[list[TrialText] | None, Query(max_length=200, description=(
    "A trial as practice:block:trial (0:1:3 is block 1's trial 3, 1:0:2 practice trial 2); repeat for several. "
    "Without it: every trial of the participant."))]


@router.get("/studies/{slug}/participants/{public_id}/replay",
            responses={200: {"content": {"text/html": {"schema": {"type": "string"}}},
                             "description": "One self-contained HTML file (an attachment)"}, **error_responses(404)})
def participant_replay_file(slug: str, public_id: str, services: ServicesDep, trial: Trials = None) -> HTMLResponse:
    """The participant's trials rebuilt from the database alone (the scene, the decision window, the robot's attempt
    or the re-simulated teleoperation, the camera changes) as one HTML file that plays offline: viser's 3D player
    beside each trial's timeline. A trial whose reconstruction does not reach its recorded outcome says what is
    missing."""
    refs = [parse_trial(text) for text in trial] if trial else None
    name, page = participant_replay(services.database, slug, public_id, refs)
    return HTMLResponse(page, headers={"Content-Disposition": f'attachment; filename="{name}"',
                                       "Cache-Control": "no-store"})
