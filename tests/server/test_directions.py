"""Which way each key moves the gripper, as the page's texts say it (issue 37): the guidance names the keys that
bring the gripper to the item (or the bin), each key's move agrees with the page's key bindings, and in the World
view the moves read on screen as the texts say (W into the picture, S back, A left, D right)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from experiment.world import build_scene, teleop_start_state
from experiment.world import constants as K
from experiment.world.guidance import MOVE_KEYS, GuidanceStep, guidance, keys_towards
from experiment.world.robot import arm_points
from server.i18n import Translator, shipped_languages
from server.services.wording import guidance_text
from server.viewer.cameras import PAGE_ASPECT, WORLD_FRAMING, project, world_camera
from server.viewer.scene import MARKER_HEIGHT

STATIC = Path(__file__).resolve().parents[2] / "static"
AXES = {"x": 0, "y": 1}
ENGLISH = Translator("en")


def page_bindings() -> dict[str, tuple[int, int]]:
    """Each letter key's world axis and sign, read from the page's own code: static/js/trial.js MOVE_KEYS (key to
    action) and static/js/teleop.js ACTIONS (action to ["ee", axis, sign])."""
    trial_js, teleop_js = (STATIC / "js" / "trial.js").read_text(), (STATIC / "js" / "teleop.js").read_text()
    keys = dict(re.findall(r'Key([A-Z]): "([xyz][+-])"', trial_js.split("const MOVE_KEYS", 1)[1].split("};", 1)[0]))
    actions = {a: (int(axis), int(sign)) for a, axis, sign in
               re.findall(r'"([xyz][+-])": \["ee", (\d), (-?1)\]', teleop_js)}
    return {key: actions[action] for key, action in keys.items()}


def keys_in(text: str) -> list[str]:
    return re.findall(r"\b([WASD]) \(", text)


def test_the_guidance_key_words_are_the_page_bindings():
    bindings = page_bindings()
    assert set(bindings) >= {"W", "S", "A", "D", "R", "F"}
    for (axis, sign), words in MOVE_KEYS.items():
        for language in shipped_languages():  # every language names the same key
            said = Translator(language).t(words)
            if language == "ar" and said == ENGLISH.t(words):
                continue  # (Arabic falls back to English here)
            (key,) = keys_in(said)
            assert bindings[key] == (AXES[axis], sign), said


@pytest.mark.parametrize("delta, keys", [((0.3, 0.0), ["W"]), ((-0.3, 0.02), ["S"]), ((0.02, 0.25), ["A"]),
                                         ((0.0, -0.25), ["D"]), ((0.3, 0.2), ["W", "A"]), ((-0.2, -0.3), ["S", "D"])])
def test_keys_towards_names_the_keys_of_the_move(delta, keys):
    assert keys_in(" and ".join(ENGLISH.t(key) for key in keys_towards((*delta, 0.0)))) == keys


@pytest.mark.parametrize("complexity", ["low", "high"])
@pytest.mark.parametrize("slot", range(K.N_SLOTS))
def test_the_guidance_says_which_keys_bring_the_gripper_over_the_item(slot, complexity):
    scene = build_scene(complexity, 300 + slot, target_slot=slot)
    state = teleop_start_state(scene)
    g = guidance(state, scene)
    assert g.step == GuidanceStep.MOVE_ABOVE_ITEM
    text = guidance_text(g.message, ENGLISH)
    keys = keys_in(text)
    assert keys and "hold" in text, text
    bindings = page_bindings()
    move = np.zeros(2)
    for key in keys:
        axis, sign = bindings[key]
        move[axis] += sign
    to_item = np.array(g.to_grasp[:2])
    assert move @ to_item > 0.7 * np.linalg.norm(move) * np.linalg.norm(to_item), (text, to_item)


def test_in_the_world_view_the_keys_move_the_gripper_as_the_texts_say():
    """W into the picture (up the screen), S back (down), A left, D right: at the gripper of the parked robot, for
    every slot, in the 1280x720 page's view."""
    position, look_at = world_camera(MARKER_HEIGHT, PAGE_ASPECT)
    bindings = page_bindings()
    for slot in range(K.N_SLOTS):
        state = teleop_start_state(build_scene("low", 0, target_slot=slot))
        tcp = np.array(arm_points(state.base, state.joints).tcp)
        for key, (up, right) in {"W": (1, 0), "S": (-1, 0), "A": (0, -1), "D": (0, 1)}.items():
            axis, sign = bindings[key]
            step = np.zeros(3)
            step[axis] = 0.05 * sign
            before, after = project(np.array([tcp, tcp + step]), position, look_at, WORLD_FRAMING.vfov_deg,
                                    PAGE_ASPECT)[:, :2]
            dx, dy = after - before
            if up:
                assert np.sign(dy) == up and abs(dy) > abs(dx) * 0.5, (key, slot, dx, dy)
            else:
                assert np.sign(dx) == right and abs(dx) > abs(dy), (key, slot, dx, dy)


def test_the_instructions_and_the_tutorial_say_the_same_directions():
    html = (STATIC / "participant.html").read_text()  # the page shows these catalogue texts
    assert 'data-i18n="instructions.controls.moves"' in html and 'data-i18n="teleop.tutorial_keys"' in html
    def text(key: str) -> str:
        return re.sub(r"\s+", " ", re.sub(r"<[^>]+>", "", ENGLISH.t(key)))
    assert "W moves the gripper towards the shelf (into the picture) and S away from it (towards you)" in text(
        "instructions.controls.moves")
    assert "A moves it to the left and D to the right of the screen" in text("instructions.controls.moves")
    assert "In the World view: W to the shelf · S back to you · A left · D right · R up · F down" in text(
        "teleop.tutorial_keys")
