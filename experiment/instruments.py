"""The instrument library: the built-in questionnaires, each with its citation, item texts, scale, reverse-coded
items and scoring rule in one place (SPEC §5; the model is ``experiment.questionnaires``).

``BUILTIN_QUESTIONNAIRES`` holds them by id; a study uses one by naming its id
(``questionnaires_before``, a block's ``questionnaires_after``,
``shelf_questionnaire``), and its configuration then holds a copy
(``StudyConfig``), so the codebook and surveys.csv carry the instrument,
version and scoring provenance of the version it was answered under. The
default questionnaires of a study are the shelf questions and ``SCHAEFER_14``:

- ``SHELF_TRUST_RELIANCE``: the trust and reliance questions asked after each
  shelf (paper §4.4–4.5 and appendix; after Lee & Moray 1992, 1994), each on
  an 11-point 0–10 scale, in the paper's words ("the automation"). Not
  combined into a score. The paper's templates ask it.
- ``SHELF_TRUST_RELIANCE_NAMED``: the same two questions naming the robot as
  every other page does ("To what extent do you trust Robot A in this
  scenario?": ``{robot}`` is replaced by the block's label); the default of a
  study. A study chooses the wording by its ``shelf_questionnaire``.
- ``TPS_HRI_40`` and ``SCHAEFER_14``: the Trust Perception Scale–HRI and its
  14-item subscale, K. E. Schaefer (2016), "Measuring trust in human robot
  interactions: Development of the 'Trust Perception Scale-HRI'", in *Robust
  Intelligence and Trust in Autonomous Systems*, pp. 191–218, Springer,
  doi:10.1007/978-1-4899-7668-0_10. Each item completes "What percentage of
  the time will this robot …" and is rated 0–100 % in steps of 10; the score
  is the mean of the (reverse-coded) item ratings (paper §5.3). The subscale's
  items are the 40-item scale's own ``Item`` objects (one definition each,
  ``TPS_HRI_ITEMS``). Reverse-coded: "have errors", "be unresponsive",
  "malfunction" (both versions), and in the 40-item version also "require
  frequent maintenance" and "be incompetent".
- ``JIAN_TRUST_CHECKLIST``: the 12-item Checklist for Trust between People and
  Automation, J.-Y. Jian, A. M. Bisantz & C. G. Drury (2000), "Foundations for
  an empirically determined scale of trust in automated systems",
  *International Journal of Cognitive Ergonomics* 4(1), 53–71,
  doi:10.1207/S15327566IJCE0401_04. 7-point scale, 1 "not at all" to
  7 "extremely"; items 1–5 are the distrust items and are reverse-coded, so
  the score (the mean) is a trust score on 1–7.
- ``MUIR_TRUST_RATING``: one overall trust rating, after B. M. Muir (1989),
  *Operators' trust in and percentage of time spent using the automatic
  controllers in supervisory process control task*, PhD thesis, University of
  Toronto, and B. M. Muir & N. Moray (1996), "Trust in automation. Part II.
  Experimental studies of trust and human intervention in a process control
  simulation", *Ergonomics* 39(3), 429–460, doi:10.1080/00140139608964474.
  Rated 0–100; the score is the rating.

What was checked, and against what (December 2026, public web pages and
public repositories only; the chapter, the articles and the thesis themselves
could not be read):

- TPS-HRI: the 0–100 % rating, 40 items, a 14-item subscale and a percentage
  score are in the chapter's abstract (Mendeley catalogue page). The HRI Scale
  Database's page on the scale
  (hriscaledatabase.psychology.gmu.edu/trust/2024/10/31/trustschaefer.html)
  shows the stem "What % of the time will this robot be…" and, in this order,
  its items "considered part of the team", "responsible", "supportive",
  "incompetent", "dependable" (subscale), "friendly", "reliable"; the rest of
  its list could not be read (a later version of the page withholds the items
  pending the author's permission), and it notes that the chapter's text
  names only 11 of the 14 subscale items. The other 33 item texts, the order
  and the 40-item reverse-coded set were checked only against two independent
  study implementations on GitHub (a PHP form and a jsPsych trial), which
  agree on all 40 texts and on the five reverse-coded items; the PHP form also
  marks as the subscale the same 14 items as ``SCHAEFER_14``. Not verified
  against the chapter: the exact wording of those 33 items (the two differ on
  "make sensible decision(s)"; the plural is used here), and whether the
  chapter's scoring instructions reverse-code any further item (e.g. "be led
  astray by unexpected changes in the environment", not reverse-coded here nor
  in either implementation).
- Jian et al.: the 12 items, their order and that items 1–5 are the
  negatively worded (distrust) ones, against Table 2 of an article quoting the
  scale (pmc.ncbi.nlm.nih.gov/articles/PMC9945264/table/tab2; wording adapted
  there to its system, items marked − and +); the "the system" wording as in
  several independent implementations on GitHub; the DOI as several reference
  lists cite it. The 1 "not at all" – 7 "extremely" anchors agree with those
  implementations but were not checked against the article.
- Muir: the thesis title (as a 2020 HFES review's reference list gives it) and
  the article's citation and DOI. Not verified: the published scale (0–100 as
  the brief says; whether it was a line or a numbered scale, its step and its
  anchors are not known here, so steps of 10 — 11 buttons, as the TPS-HRI's
  percentages; whole points made a page of 101 buttons — and the shelf
  questions' "Not at all" / "Completely" labels are used; a lab that needs
  another step defines its own questionnaire) and the question's wording, which is
  ours ("How much do you trust the robot?"; Muir & Moray asked about the
  pasteuriser plant's automatic controllers).

Languages: every instrument's own texts are English (as published, or our
wording); each also has German (``experiment.instruments_de``, formal "Sie"),
the lab's own translation, not validated: no published German version is
reproduced, so none carries a translation citation. Per instrument and
language, ``experiment.questionnaire_translations.language_statuses`` says
whose texts they are (original, published translation, the lab's own); the
admin API lists them (``GET /api/admin/instruments``). A study that needs a
validated translation defines the questionnaire with that version's texts and
the translation's ``citation``.

Besides the published instruments, two of trustlab's own (our wording, no
citation): ``DEMOGRAPHICS`` (age band, gender, experience with robots and
with video games; single-choice items, each with "Prefer not to say") and
``COMMENTS`` (one optional free-text item). Neither is about a robot
(``about_robot`` false): a study asks them at the end
(``questionnaires_end``) or before the blocks, and their pages name no robot.
"""

from __future__ import annotations

from experiment import defaults, instruments_de
from experiment.questionnaires import ROBOT_PLACEHOLDER, ChoiceOption, Item, Questionnaire, Scale

SHELF_TRUST_RELIANCE = Questionnaire(
    id="shelf_trust_reliance",
    title="Trust and reliance",
    participant_title="Two questions about the last shelf",
    instructions="Please answer both questions about the shelf you just finished.",
    scale=Scale(min=defaults.SHELF_SCALE_MIN, max=defaults.SHELF_SCALE_MAX, step=1,
                anchors={defaults.SHELF_SCALE_MIN: "Not at all", defaults.SHELF_SCALE_MAX: "Completely"}),
    items=[
        Item(id="trust", text="To what extent do you trust the automation in this scenario?"),
        Item(id="reliance", text="To what extent did you rely on the automation in this scenario?"),
    ],
    scoring="none",
    translations=[instruments_de.shelf(named=False)],
    citation=("Mangalindan, Rovira & Srivastava, \"When To Seek Help: Trust-Aware Assistance-Seeking in "
              "Human-Supervised Autonomy\", §4.4–4.5 and appendix; after Lee & Moray (1992), Ergonomics 35(10), "
              "1243–1270, and Lee & Moray (1994), International Journal of Human-Computer Studies 40(1), 153–184"),
    version="2 items, after each shelf",
    scoring_rule="Not combined into a score; each answer (0–10) is analysed on its own.",
)

#: The shelf questions naming the robot: the paper's two questions with "the automation" replaced by the robot's
#: name as every page shows it (e.g. "Robot A"), so that a participant reads one name for the robot throughout.
SHELF_TRUST_RELIANCE_NAMED = Questionnaire.model_validate(dict(SHELF_TRUST_RELIANCE) | {
    "id": "shelf_trust_reliance_named",
    "title": "Trust and reliance (naming the robot)",
    "items": [
        Item(id="trust", text=f"To what extent do you trust {ROBOT_PLACEHOLDER} in this scenario?"),
        Item(id="reliance", text=f"To what extent did you rely on {ROBOT_PLACEHOLDER} in this scenario?"),
    ],
    "version": "2 items, after each shelf; the robot named where the paper says \"the automation\"",
    "translations": [instruments_de.shelf(named=True)],
})

_SCHAEFER_CITATION = ("Schaefer, K. E. (2016). Measuring trust in human robot interactions: Development of the "
                      "\"Trust Perception Scale-HRI\". In Robust Intelligence and Trust in Autonomous Systems "
                      "(pp. 191–218). Springer.")
_SCHAEFER_DOI = "10.1007/978-1-4899-7668-0_10"
_SCHAEFER_STEM = "What percentage of the time will this robot …"

#: The 40 items of the Trust Perception Scale–HRI, in the form's order: (id, text after "What percentage of the
#: time will this robot …", reverse-coded). The 14-item subscale takes its items from here.
TPS_HRI_ITEMS: dict[str, Item] = {id_: Item(id=id_, text=text, reverse_coded=rev) for id_, text, rev in [
    ("act_consistently", "act consistently", False),
    ("protect_people", "protect people", False),
    ("act_as_part_of_the_team", "act as part of the team", False),
    ("function_successfully", "function successfully", False),
    ("malfunction", "malfunction", True),
    ("clearly_communicate", "clearly communicate", False),
    ("require_frequent_maintenance", "require frequent maintenance", True),
    ("openly_communicate", "openly communicate", False),
    ("have_errors", "have errors", True),
    ("perform_better_than_a_novice", "perform a task better than a novice human user", False),
    ("know_friend_from_foe", "know the difference between friend and foe", False),
    ("provide_feedback", "provide feedback", False),
    ("adequate_decision_making", "possess adequate decision-making capability", False),
    ("warn_of_risks", "warn people of potential risks in the environment", False),
    ("meet_the_needs_of_the_mission", "meet the needs of the mission", False),
    ("provide_appropriate_information", "provide appropriate information", False),
    ("communicate_with_people", "communicate with people", False),
    ("work_best_with_a_team", "work best with a team", False),
    ("keep_classified_information_secure", "keep classified information secure", False),
    ("perform_exactly_as_instructed", "perform exactly as instructed", False),
    ("make_sensible_decisions", "make sensible decisions", False),
    ("work_close_to_people", "work in close proximity with people", False),
    ("tell_the_truth", "tell the truth", False),
    ("perform_many_functions", "perform many functions at one time", False),
    ("follow_directions", "follow directions", False),
    ("part_of_the_team", "be considered part of the team", False),
    ("responsible", "be responsible", False),
    ("supportive", "be supportive", False),
    ("incompetent", "be incompetent", True),
    ("dependable", "be dependable", False),
    ("friendly", "be friendly", False),
    ("reliable", "be reliable", False),
    ("pleasant", "be pleasant", False),
    ("unresponsive", "be unresponsive", True),
    ("autonomous", "be autonomous", False),
    ("predictable", "be predictable", False),
    ("conscious", "be conscious", False),
    ("lifelike", "be lifelike", False),
    ("good_teammate", "be a good teammate", False),
    ("led_astray", "be led astray by unexpected changes in the environment", False),
]}

#: The 14-item subscale's items, in the order this study's form asks them.
_SCHAEFER_14_IDS = ["function_successfully", "act_consistently", "reliable", "predictable", "dependable",
                    "follow_directions", "meet_the_needs_of_the_mission", "perform_exactly_as_instructed",
                    "have_errors", "provide_appropriate_information", "unresponsive", "malfunction",
                    "communicate_with_people", "provide_feedback"]


def _tps_hri(id_: str, version: str, items: list[Item]) -> Questionnaire:
    reversed_items = ", ".join(f'"{item.text}"' for item in items if item.reverse_coded)
    return Questionnaire(
        id=id_,
        title=f"Trust Perception Scale–HRI ({version})",
        participant_title="Your view of the robot",
        instructions=_SCHAEFER_STEM,
        scale=Scale(min=defaults.SCHAEFER_SCALE_MIN, max=defaults.SCHAEFER_SCALE_MAX,
                    step=defaults.SCHAEFER_SCALE_STEP, unit="%"),
        items=items,
        scoring="mean",
        translations=[instruments_de.tps_hri([item.id for item in items])],
        citation=_SCHAEFER_CITATION,
        doi=_SCHAEFER_DOI,
        version=version,
        scoring_rule=(f"Reverse-code {reversed_items} (100 − rating); the score is the mean of the {len(items)} "
                      "ratings, a percentage (0–100)."),
    )


TPS_HRI_40 = _tps_hri("tps_hri_40", "40-item", list(TPS_HRI_ITEMS.values()))
SCHAEFER_14 = _tps_hri("schaefer_14", "14-item subscale", [TPS_HRI_ITEMS[i] for i in _SCHAEFER_14_IDS])

#: Jian, Bisantz & Drury's checklist: (id, statement, reverse-coded). Items 1–5 are the distrust items.
_JIAN_ITEMS = [
    ("deceptive", "The system is deceptive.", True),
    ("underhanded", "The system behaves in an underhanded manner.", True),
    ("suspicious", "I am suspicious of the system's intent, action, or outputs.", True),
    ("wary", "I am wary of the system.", True),
    ("harmful", "The system's actions will have a harmful or injurious outcome.", True),
    ("confident", "I am confident in the system.", False),
    ("security", "The system provides security.", False),
    ("integrity", "The system has integrity.", False),
    ("dependable", "The system is dependable.", False),
    ("reliable", "The system is reliable.", False),
    ("trust", "I can trust the system.", False),
    ("familiar", "I am familiar with the system.", False),
]

JIAN_TRUST_CHECKLIST = Questionnaire(
    id="jian_trust_checklist",
    title="Checklist for Trust between People and Automation (Jian, Bisantz & Drury 2000)",
    participant_title="Your view of the robot",
    instructions=("Here \"the system\" is the robot you worked with. Rate how much each statement describes "
                  "your feelings about it."),
    scale=Scale(min=defaults.JIAN_SCALE_MIN, max=defaults.JIAN_SCALE_MAX, step=1,
                anchors={defaults.JIAN_SCALE_MIN: "Not at all", defaults.JIAN_SCALE_MAX: "Extremely"}),
    items=[Item(id=i, text=text, reverse_coded=rev) for i, text, rev in _JIAN_ITEMS],
    scoring="mean",
    translations=[instruments_de.JIAN],
    citation=("Jian, J.-Y., Bisantz, A. M., & Drury, C. G. (2000). Foundations for an empirically determined scale "
              "of trust in automated systems. International Journal of Cognitive Ergonomics, 4(1), 53–71."),
    doi="10.1207/S15327566IJCE0401_04",
    version="12-item",
    scoring_rule=("Reverse-code items 1–5, the distrust items (8 − rating); the score is the mean of the 12 "
                  "ratings, a trust score on 1–7."),
)

MUIR_TRUST_RATING = Questionnaire(
    id="muir_trust_rating",
    title="Overall trust rating (after Muir 1989; Muir & Moray 1996)",
    participant_title="Your trust in the robot",
    instructions="Rate how much you trust the robot, from 0 (not at all) to 100 (completely).",
    scale=Scale(min=defaults.MUIR_SCALE_MIN, max=defaults.MUIR_SCALE_MAX, step=defaults.MUIR_SCALE_STEP,
                anchors={defaults.MUIR_SCALE_MIN: "Not at all", defaults.MUIR_SCALE_MAX: "Completely"}),
    items=[Item(id="trust", text="How much do you trust the robot?")],
    scoring="mean",
    translations=[instruments_de.MUIR],
    citation=("Muir, B. M. (1989). Operators' trust in and percentage of time spent using the automatic controllers "
              "in supervisory process control task (Doctoral dissertation, University of Toronto); Muir, B. M., & "
              "Moray, N. (1996). Trust in automation. Part II. Experimental studies of trust and human intervention "
              "in a process control simulation. Ergonomics, 39(3), 429–460."),
    doi="10.1080/00140139608964474",
    version="single item (wording adapted to a robot)",
    scoring_rule="The rating itself (0–100); no item is reverse-coded.",
)


def _choice(id_: str, text: str, options: list[tuple[str, str]], *, required: bool = True) -> Item:
    return Item(id=id_, text=text, kind="choice", required=required,
                options=[ChoiceOption(value=value, label=label) for value, label in options])


_PREFER_NOT = ("prefer_not_to_say", "Prefer not to say")

DEMOGRAPHICS = Questionnaire(
    id="demographics",
    title="Demographics (trustlab)",
    participant_title="A few questions about you",
    instructions="These questions help us describe who took part. Choose the answer that fits best.",
    items=[
        _choice("age_band", "How old are you?", [("age_18_24", "18–24"), ("age_25_34", "25–34"),
                                                 ("age_35_44", "35–44"), ("age_45_54", "45–54"),
                                                 ("age_55_64", "55–64"), ("age_65_plus", "65 or older"),
                                                 _PREFER_NOT]),
        _choice("gender", "What is your gender?", [("woman", "Woman"), ("man", "Man"),
                                                   ("non_binary", "Non-binary"),
                                                   ("self_described", "I describe myself another way"),
                                                   _PREFER_NOT]),
        _choice("robot_experience", "How much experience do you have with robots (using, programming or working "
                "next to them)?", [("none", "None"), ("a_little", "A little (seen or tried one a few times)"),
                                   ("some", "Some (used one now and then)"),
                                   ("a_lot", "A lot (use, build or program them regularly)"), _PREFER_NOT]),
        _choice("video_game_experience", "How often do you play video games?",
                [("never", "Never"), ("less_than_monthly", "Less than once a month"),
                 ("monthly", "A few times a month"), ("weekly", "Every week"), _PREFER_NOT]),
    ],
    scoring="none",
    about_robot=False,
    translations=[instruments_de.DEMOGRAPHICS],
    version="4 items (trustlab's own wording)",
    scoring_rule="Not scored; each answer is the chosen option's value (surveys.csv column text).",
)

COMMENTS = Questionnaire(
    id="comments",
    title="Comments (trustlab)",
    participant_title="Anything else?",
    instructions="If you have any comments about the study, please write them here. This is optional.",
    items=[Item(id="comments", text="Your comments", kind="text", required=False, max_length=2000)],
    scoring="none",
    about_robot=False,
    translations=[instruments_de.COMMENTS],
    version="1 optional free-text item (trustlab's own wording)",
    scoring_rule="Not scored; the text as written (surveys.csv column text).",
)

#: Built-in questionnaires by id, for study configurations that name them.
BUILTIN_QUESTIONNAIRES: dict[str, Questionnaire] = {q.id: q for q in (
    SHELF_TRUST_RELIANCE, SHELF_TRUST_RELIANCE_NAMED, SCHAEFER_14, TPS_HRI_40, JIAN_TRUST_CHECKLIST, MUIR_TRUST_RATING,
    DEMOGRAPHICS, COMMENTS)}
