"""The trial's scene before the decision window opens: whether the session's 3D view holds it, and the
scene and resting robot for the 2-D helper view (the page reports the scene shown with ``trials.scene_shown``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from experiment.engine import StudyRuntime
from experiment.world import teleop_start_state
from experiment.world.teleop import TeleopRules
from experiment.world.trial import scene_seed, trial_scene, trial_scene_stamp
from server.models import Participant, Trial
from server.schemas import TrialSceneRead
from server.services.teleop_views import scene_info, world_view

if TYPE_CHECKING:  # the views call the services: at run time this module needs only their holds_scene
    from server.viewer.manager import SessionViews


def viewer_holds_trial(viewers: SessionViews, participant: Participant, runtime: StudyRuntime, trial: Trial) -> bool:
    """Whether this process's 3D viewer of the session holds the trial's scene with a client connected.

    A session's viewer lives in the process that serves its requests (``server.workers`` routes by token), and
    viser sends a connected client every scene change at once: a page whose 3D view is drawing is then drawing
    this scene. False while the viewer still shows the previous trial (its poll has not caught up) or has no
    client (the view is still loading, or failed).
    """
    seed = scene_seed(runtime.config.seed, participant.public_id, trial.block_name, trial.trial)
    return viewers.holds_scene(participant.id, seed, trial.complexity)


def trial_stamp(participant: Participant, runtime: StudyRuntime, trial: Trial) -> str:
    """The stamp of the trial's scene (``experiment.world.scene_stamp``)."""
    return trial_scene_stamp(runtime.config.seed, participant.public_id, trial.block_name, trial.trial,
                             trial.complexity)


def scene_for_helper(participant: Participant, runtime: StudyRuntime, trial: Trial) -> TrialSceneRead:
    """The trial's scene and the robot parked at the shelf, where it works from (the 2-D view draws the bin on
    the parked robot, and is drawn the same way when the participant steers), as the teleoperation socket
    describes them."""
    scene = trial_scene(runtime.config.seed, participant.public_id, trial.block_name, trial.trial, trial.complexity)
    return TrialSceneRead(scene=scene_info(scene, TeleopRules()), world=world_view(teleop_start_state(scene)),
                          scene_stamp=scene.stamp)
