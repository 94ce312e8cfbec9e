"""German texts of the built-in instruments (``experiment.instruments``), addressing the participant formally ("Sie").

Every one is the lab's own translation, not validated: none is a published German version (no ``citation``), so a
study that needs a validated German instrument defines its own questionnaire with that version's texts and its
citation. The scales' points, item ids and option values are the instruments' own; only what is read is German.
"""

from __future__ import annotations

from experiment.questionnaire_translations import ItemTranslation, OptionTranslation, QuestionnaireTranslation

GERMAN = "de"
_NOT_AT_ALL = "Überhaupt nicht"
_COMPLETELY = "Voll und ganz"
_YOUR_VIEW = "Ihre Einschätzung des Roboters"
_PREFER_NOT = ("prefer_not_to_say", "Keine Angabe")


def _items(texts: dict[str, str]) -> list[ItemTranslation]:
    return [ItemTranslation(id=id_, text=text) for id_, text in texts.items()]


def _choice(id_: str, text: str, options: list[tuple[str, str]]) -> ItemTranslation:
    return ItemTranslation(id=id_, text=text, options=[OptionTranslation(value=v, label=label) for v, label in options])


def shelf(*, named: bool) -> QuestionnaireTranslation:
    """The shelf questions: the paper's wording ("die Automatisierung") or naming the robot (``{robot}``)."""
    agent = "{robot}" if named else "die Automatisierung"
    trusted = "{robot}" if named else "der Automatisierung"
    return QuestionnaireTranslation(
        language=GERMAN, participant_title="Zwei Fragen zum letzten Regal",
        instructions="Bitte beantworten Sie beide Fragen zu dem Regal, das Sie gerade abgeschlossen haben.",
        anchors={0: _NOT_AT_ALL, 10: _COMPLETELY},
        items=_items({"trust": f"Inwieweit vertrauen Sie {trusted} in diesem Szenario?",
                      "reliance": f"Inwieweit haben Sie sich in diesem Szenario auf {agent} verlassen?"}))


#: The TPS-HRI's items, each completing "Wie viel Prozent der Zeit wird dieser Roboter …".
TPS_HRI_TEXTS = {
    "act_consistently": "beständig handeln",
    "protect_people": "Menschen schützen",
    "act_as_part_of_the_team": "als Teil des Teams handeln",
    "function_successfully": "erfolgreich funktionieren",
    "malfunction": "eine Fehlfunktion haben",
    "clearly_communicate": "klar kommunizieren",
    "require_frequent_maintenance": "häufig gewartet werden müssen",
    "openly_communicate": "offen kommunizieren",
    "have_errors": "Fehler aufweisen",
    "perform_better_than_a_novice": "eine Aufgabe besser ausführen als ein unerfahrener menschlicher Nutzer",
    "know_friend_from_foe": "den Unterschied zwischen Freund und Feind kennen",
    "provide_feedback": "Rückmeldung geben",
    "adequate_decision_making": "über eine angemessene Entscheidungsfähigkeit verfügen",
    "warn_of_risks": "Menschen vor möglichen Gefahren in der Umgebung warnen",
    "meet_the_needs_of_the_mission": "die Anforderungen des Einsatzes erfüllen",
    "provide_appropriate_information": "angemessene Informationen liefern",
    "communicate_with_people": "mit Menschen kommunizieren",
    "work_best_with_a_team": "am besten im Team arbeiten",
    "keep_classified_information_secure": "vertrauliche Informationen sicher verwahren",
    "perform_exactly_as_instructed": "genau nach Anweisung arbeiten",
    "make_sensible_decisions": "vernünftige Entscheidungen treffen",
    "work_close_to_people": "in unmittelbarer Nähe von Menschen arbeiten",
    "tell_the_truth": "die Wahrheit sagen",
    "perform_many_functions": "viele Funktionen gleichzeitig ausführen",
    "follow_directions": "Anweisungen befolgen",
    "part_of_the_team": "als Teil des Teams angesehen werden",
    "responsible": "verantwortungsbewusst sein",
    "supportive": "unterstützend sein",
    "incompetent": "inkompetent sein",
    "dependable": "verlässlich sein",
    "friendly": "freundlich sein",
    "reliable": "zuverlässig sein",
    "pleasant": "angenehm sein",
    "unresponsive": "nicht reagieren",
    "autonomous": "autonom sein",
    "predictable": "vorhersehbar sein",
    "conscious": "ein Bewusstsein haben",
    "lifelike": "lebensecht wirken",
    "good_teammate": "ein gutes Teammitglied sein",
    "led_astray": "sich durch unerwartete Veränderungen in der Umgebung in die Irre führen lassen",
}


def tps_hri(item_ids: list[str]) -> QuestionnaireTranslation:
    """The TPS-HRI (40 items or the 14-item subscale: ``item_ids``)."""
    return QuestionnaireTranslation(language=GERMAN, participant_title=_YOUR_VIEW,
                                    instructions="Wie viel Prozent der Zeit wird dieser Roboter …", unit="%",
                                    items=_items({i: TPS_HRI_TEXTS[i] for i in item_ids}))


JIAN = QuestionnaireTranslation(
    language=GERMAN, participant_title=_YOUR_VIEW,
    instructions=("Mit „dem System“ ist hier der Roboter gemeint, mit dem Sie gearbeitet haben. Bitte geben Sie an, "
                  "wie sehr jede Aussage Ihre Empfindungen ihm gegenüber beschreibt."),
    anchors={1: _NOT_AT_ALL, 7: "Äußerst"},
    items=_items({
        "deceptive": "Das System ist irreführend.",
        "underhanded": "Das System verhält sich hinterhältig.",
        "suspicious": "Ich bin misstrauisch gegenüber den Absichten, Handlungen oder Ergebnissen des Systems.",
        "wary": "Ich bin dem System gegenüber vorsichtig.",
        "harmful": "Die Handlungen des Systems werden schädliche oder verletzende Folgen haben.",
        "confident": "Ich bin dem System gegenüber zuversichtlich.",
        "security": "Das System bietet Sicherheit.",
        "integrity": "Das System ist integer.",
        "dependable": "Das System ist verlässlich.",
        "reliable": "Das System ist zuverlässig.",
        "trust": "Ich kann dem System vertrauen.",
        "familiar": "Ich bin mit dem System vertraut.",
    }))

MUIR = QuestionnaireTranslation(
    language=GERMAN, participant_title="Ihr Vertrauen in den Roboter",
    instructions=("Bitte geben Sie an, wie sehr Sie dem Roboter vertrauen, von 0 (überhaupt nicht) bis 100 (voll und "
                  "ganz)."),
    anchors={0: _NOT_AT_ALL, 100: _COMPLETELY},
    items=_items({"trust": "Wie sehr vertrauen Sie dem Roboter?"}))

DEMOGRAPHICS = QuestionnaireTranslation(
    language=GERMAN, participant_title="Einige Fragen zu Ihrer Person",
    instructions=("Diese Fragen helfen uns zu beschreiben, wer an der Studie teilgenommen hat. Bitte wählen Sie "
                  "jeweils die Antwort, die am besten passt."),
    items=[
        _choice("age_band", "Wie alt sind Sie?", [("age_18_24", "18–24"), ("age_25_34", "25–34"),
                                                   ("age_35_44", "35–44"), ("age_45_54", "45–54"),
                                                   ("age_55_64", "55–64"), ("age_65_plus", "65 oder älter"),
                                                   _PREFER_NOT]),
        _choice("gender", "Welchem Geschlecht ordnen Sie sich zu?", [
            ("woman", "Frau"), ("man", "Mann"), ("non_binary", "Nicht-binär"),
            ("self_described", "Ich beschreibe mich auf andere Weise"), _PREFER_NOT]),
        _choice("robot_experience", "Wie viel Erfahrung haben Sie mit Robotern (sie zu benutzen, zu programmieren "
                "oder neben ihnen zu arbeiten)?", [
                    ("none", "Keine"), ("a_little", "Wenig (ein paar Mal gesehen oder ausprobiert)"),
                    ("some", "Etwas (ab und zu benutzt)"),
                    ("a_lot", "Viel (ich benutze, baue oder programmiere sie regelmäßig)"), _PREFER_NOT]),
        _choice("video_game_experience", "Wie oft spielen Sie Videospiele?", [
            ("never", "Nie"), ("less_than_monthly", "Seltener als einmal im Monat"),
            ("monthly", "Ein paar Mal im Monat"), ("weekly", "Jede Woche"), _PREFER_NOT]),
    ])

COMMENTS = QuestionnaireTranslation(
    language=GERMAN, participant_title="Möchten Sie noch etwas anmerken?",
    instructions=("Wenn Sie Anmerkungen zur Studie haben, schreiben Sie sie bitte hier hinein. Diese Angabe ist "
                  "freiwillig."),
    items=_items({"comments": "Ihre Anmerkungen"}))
