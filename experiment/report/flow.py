"""Section 1: participant flow and data quality.

Counts come from ``participants.csv`` (every participant who opened the link and
whose data were not deleted: a withdrawal under ``privacy.withdrawal: keep``
stays, marked withdrawn). Data-quality flags come from
``experiment.quality.flags_by_participant`` — hints for the experimenter,
not exclusion rules — plus the one fact the report itself depends on: how
many sequences in the model data are incomplete.
"""

from __future__ import annotations

from collections import Counter

from experiment import defaults
from experiment.quality import flags_by_participant
from experiment.report.content import Missing, Paragraph, Section, TableBlock
from experiment.report.data import ExportData

#: Flagged participants listed one per row, at most (the counts cover all).
MAX_LISTED = 40


def flow_section(data: ExportData) -> Section:
    section = Section("flow", "Participant flow and data quality")
    if data.participants is None:
        section.add(Missing("No participants.csv in the export: the flow below counts only participants with "
                            "trials."))
        section.figures["flow"] = {"analysed": len(data.trials)}
    else:
        section.add(*_flow(data, section))
    section.add(*_quality(data, section))
    return section


def _flow(data: ExportData, section: Section) -> list:
    people = data.participants or []
    status = Counter(p["status"] for p in people)
    counts = {"joined": len(people), "consented": sum(1 for p in people if p["consented_at"]),
              "declined": status["declined"], "started": sum(1 for p in people if p["started_at"]),
              "completed": status["completed"], "screened_out": status["screened_out"],
              "abandoned": status["abandoned"], "withdrawn": status["withdrawn"],
              "active": status["active"], "excluded": sum(1 for p in people if p["excluded"] == "1"),
              "analysed": len(data.trials)}
    meaning = {"joined": "opened the study link", "consented": "gave consent", "declined": "declined consent",
               "started": "started the scored trials", "completed": "finished the session",
               "screened_out": "ended by an eligibility question or failed attention checks",
               "abandoned": "left (idle timeout)", "withdrawn": "withdrew (data kept, excluded)",
               "active": "still in progress at export time", "excluded": "excluded from analysis by the experimenter",
               "analysed": "in the model data (non-practice trials, not excluded)"}
    section.figures["flow"] = counts
    out: list = [TableBlock("Participant flow", ["stage", "participants", "meaning"],
                            [[k, str(v), meaning[k]] for k, v in counts.items()],
                            f"The paper: study 1 recruited {defaults.STUDY1_PARTICIPANTS} and kept "
                            f"{defaults.STUDY1_PARTICIPANTS_KEPT}; study 2 recruited {defaults.STUDY2_PARTICIPANTS} "
                            f"and kept {defaults.STUDY2_PARTICIPANTS_KEPT}.")]
    previews = sum(1 for p in people if p.get("preview") == "1")  # exports leave them out unless asked
    if previews:
        section.figures["preview_sessions"] = previews
        out.append(Paragraph(f"This export includes {previews} preview session{'s' if previews != 1 else ''} "
                             "(the experimenter's own, participants.csv preview = 1): they are counted above and "
                             "analysed like participants. Export without them for the study's results."))
    orders = Counter(p["block_order"] for p in people if p["status"] == "completed" and p["block_order"])
    if len(orders) > 1:
        rows = [[order.replace("|", " → "), str(n)] for order, n in sorted(orders.items())]
        out.append(TableBlock("Block orders of the participants who completed (counterbalancing)",
                              ["block order", "participants"], rows))
    reasons = [[p["participant_id"], p["exclusion_reason"]] for p in people if p["excluded"] == "1"]
    if reasons:
        out.append(TableBlock("Exclusions", ["participant", "reason"], reasons[:MAX_LISTED],
                              f"{len(reasons) - MAX_LISTED} more not listed." if len(reasons) > MAX_LISTED else ""))
    return out


def _quality(data: ExportData, section: Section) -> list:
    lengths = {pid: len(rows) for pid, rows in data.trials.items()}
    full = max(lengths.values())
    short = sorted(pid for pid, n in lengths.items() if n < full)
    out: list = [Paragraph(f"Model data: {len(lengths)} participants; {len(short)} of them have fewer scored trials "
                           f"than the most complete ({full}). The fit uses every scored trial, so incomplete sessions "
                           "contribute their trials; the reward comparison uses complete blocks only.")]
    section.figures["incomplete_sequences"] = len(short)
    if data.participants is None:
        return out + [Missing("Data-quality flags need participants.csv.")]
    # Hook: data-quality flags are computed by experiment.quality (shared with the admin dashboard).
    flags = flags_by_participant(data.all_trials, data.surveys or [], data.participants)
    flagged = [(pid, f) for pid, f in flags.items() if f]
    by_code = Counter(flag.code for _, f in flagged for flag in f)
    section.figures["quality_flags"] = dict(by_code)
    if not flagged:
        return out + [Paragraph("Data-quality flags: none raised.")]
    status = {p["participant_id"]: p for p in data.participants}
    rows = [[pid, status[pid]["status"], "yes" if status[pid]["excluded"] == "1" else "no",
             "; ".join(f"{flag.code}: {flag.detail}" for flag in f)] for pid, f in flagged]
    summary = ", ".join(f"{code} × {n}" for code, n in sorted(by_code.items()))
    return out + [TableBlock(f"Data-quality flags ({summary}): hints to look closer, not exclusion rules",
                             ["participant", "status", "excluded", "flags"], rows[:MAX_LISTED],
                             f"{len(rows) - MAX_LISTED} more flagged participants not listed."
                             if len(rows) > MAX_LISTED else "")]
