"""What the server says to a participant, in the participant's language (``server.i18n``, ``Participant.language``):
the study's texts (the lab's, per language; the built-in defaults from the catalogue), the robot's messages, the
practice hints, the line above a questionnaire page, the item to collect and the study's duration."""

from __future__ import annotations

from dataclasses import dataclass

from babel.lists import format_list

from experiment.config import StudyConfig, TextsConfig, text_in
from experiment.task import HumanAction, RobotAction
from experiment.world.guidance import GuidanceMessage, TargetParts
from server.i18n import N_, SOURCE_LANGUAGE, Translator

ROBOT_MESSAGES = {RobotAction.AUTO: N_("robot.auto"), RobotAction.ASK: N_("robot.ask")}
PRACTICE_HINTS: dict[str | None, str] = {  # keyed by HumanAction (a str) or None
    HumanAction.RELY: N_("practice.hint.rely"),
    HumanAction.INTERVENE: N_("practice.hint.intervene"),
    None: N_("practice.hint.ask"),
}
#: The catalogue's words for the item's colour, shape, shelf and column (``experiment.world.guidance`` names, in order).
COLOR_KEYS = (N_("target.color.dark_yellow"), N_("target.color.blue"), N_("target.color.green"),
              N_("target.color.pink"), N_("target.color.yellow"), N_("target.color.purple"),
              N_("target.color.orange"), N_("target.color.turquoise"))
SHAPE_KEYS = {"cylinder": N_("target.shape.can"), "box": N_("target.shape.box")}
TIER_KEYS = (N_("target.tier.bottom"), N_("target.tier.top"))
COLUMN_KEYS = (N_("target.column.far_right"), N_("target.column.right_of_centre"),
               N_("target.column.left_of_centre"), N_("target.column.far_left"))
#: The study texts' built-in defaults (``TextsConfig``), said in the participant's language when a study keeps them.
DEFAULT_TEXT_KEYS = {"title": N_("default_texts.title"), "block_label": N_("default_texts.block_label"),
                     "consent": N_("default_texts.consent"), "instructions": N_("default_texts.instructions"),
                     "debrief": N_("default_texts.debrief")}


def translator(language: str) -> Translator:
    return Translator(language)


@dataclass(frozen=True)
class StudyTexts:
    """The study's texts (config ``texts``) in one participant's language."""

    title: str
    block_label: str
    consent: str
    instructions: str
    debrief: str


def participant_texts(config: StudyConfig, language: str, tr: Translator) -> StudyTexts:
    """The study's texts as the participant reads them: the lab's text in their language (a single string serves
    every language); a text the study left at its English default, in the catalogue's words for the language."""
    texts = config.texts
    said = {name: text_in(getattr(texts, name), language, config.default_language) for name in DEFAULT_TEXT_KEYS}
    if tr.language != SOURCE_LANGUAGE:
        said |= {name: tr.t(key) for name, key in DEFAULT_TEXT_KEYS.items()
                 if said[name] == TextsConfig.model_fields[name].default}
    return StudyTexts(**said)


def target_description(parts: TargetParts, tr: Translator) -> str:
    """The item to collect in words: "the purple can on the top shelf, far left"."""
    return tr.t("target.description", color=tr.t(COLOR_KEYS[parts.color]), shape=tr.t(SHAPE_KEYS[parts.shape]),
                tier=tr.t(TIER_KEYS[parts.tier]), column=tr.t(COLUMN_KEYS[parts.column]))


def duration_text(low_minutes: int, high_minutes: int, tr: Translator) -> str:
    """"about 10–25 minutes"."""
    return tr.tn("units.duration_range", high_minutes, low=low_minutes, high=high_minutes)


def guidance_text(message: GuidanceMessage, tr: Translator) -> str:
    """The teleoperation guidance's sentence: each placeholder a list of phrases joined by the language's "and"."""
    locale = tr.language.replace("-", "_")
    return tr.t(message.key, **{name: format_list([tr.t(key) for key in keys], locale=locale)
                                for name, keys in message.params})


def robot_message(action: RobotAction, target: str, tr: Translator) -> str:
    return tr.t(ROBOT_MESSAGES[action], target=target)


def about_line(robot: str, shelf: int | None, *, just_finished: bool, tr: Translator) -> str:
    """The line above a questionnaire page about a robot (or a shelf done with it)."""
    if shelf is not None:
        return tr.t("survey.about_shelf", shelf=shelf, robot=robot)
    if just_finished:
        return tr.t("survey.about_robot_just", robot=robot)
    return tr.t("survey.about_robot", robot=robot)
