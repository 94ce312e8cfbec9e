"""Every number taken from the source study, in one place.

Source: Mangalindan, Rovira & Srivastava, "When To Seek Help: Trust-Aware
Assistance-Seeking in Human-Supervised Autonomy" (``shared/paper.tex``).
Each constant cites the section (§) or equation it comes from. Other modules
import these; they never repeat the literals. Where the paper's text has a
known slip (SPEC §11), the comment says which reading is used.

Index conventions used by the array-valued parameters (see ``experiment.task``):
complexity low=0/high=1, robot action auto=0/ask=1, experience negative=0/
positive=1, trust low=0/high=1.
"""

from __future__ import annotations

# --- Task (§2) -------------------------------------------------------------

#: Probability that an autonomous attempt succeeds, by complexity (§2, §4).
P_SUCCESS_LOW = 0.97
P_SUCCESS_HIGH = 0.75

#: Reward table R^a_{o,E}, eq. (1).
REWARD_AUTO_RELY_SUCCESS = 3.0
REWARD_ASK = 1.0
REWARD_AUTO_INTERVENE = 0.0
REWARD_AUTO_RELY_FAILURE = -4.0

#: Discount factor of the POMDP (§3.2: "The discount factor γ is chosen as 0.99").
DISCOUNT = 0.99

# --- Study 1: model estimation (§4) ----------------------------------------

#: 71 trials: 41 low + 30 high complexity.
STUDY1_TRIALS_LOW = 41
STUDY1_TRIALS_HIGH = 30
#: The robot asks for help with probability 0.10 in low, 0.33 in high complexity.
STUDY1_P_ASK_LOW = 0.10
STUDY1_P_ASK_HIGH = 0.33
#: Participants recruited / kept after exclusions.
STUDY1_PARTICIPANTS = 39
STUDY1_PARTICIPANTS_KEPT = 33
#: Compensation: up to $15 announced (§4).
STUDY1_COMPENSATION_MAX_USD = 15.0

# --- Estimated IOHMM (§4.1–4.2, Figs. 4–6) ----------------------------------

#: P(T_1 = high) (§4.1).
PAPER_INITIAL_HIGH = 0.82

#: P(o = rely | T, C, a = auto) (§4.1, Fig. 4). When the robot asks the human
#: always assists: P(o = intervene | T, C, ask) = 1 (structural).
PAPER_P_RELY: dict[tuple[str, ...], float] = {
    # (complexity, trust): probability
    ("low", "high"): 1.00,
    ("low", "low"): 0.97,
    ("high", "high"): 0.94,
    ("high", "low"): 0.43,
}

#: P(T_{t+1} = high | T_t, E_{t+1}, C_t, a_t) (§4.2, Figs. 5–6), keyed by
#: (complexity, robot action, experience, trust before). The input combinations
#: (low, ask, positive) and (high, ask, negative) cannot occur under the
#: experience rule of §2, so the paper estimates nothing for them.
PAPER_P_HIGH_NEXT: dict[tuple[str, ...], float] = {
    # Fig. 5a: success in low complexity leaves trust unchanged.
    ("low", "auto", "positive", "high"): 1.00,
    ("low", "auto", "positive", "low"): 0.00,
    # Fig. 5b: failure in low: high -> low with 0.71; low stays low.
    ("low", "auto", "negative", "high"): 0.29,
    ("low", "auto", "negative", "low"): 0.00,
    # Fig. 5c: asking in low complexity leaves trust unchanged.
    ("low", "ask", "negative", "high"): 1.00,
    ("low", "ask", "negative", "low"): 0.00,
    # Fig. 6a: success in high: high stays high; low -> high with 0.64.
    ("high", "auto", "positive", "high"): 1.00,
    ("high", "auto", "positive", "low"): 0.64,
    # Fig. 6b: failure in high: high -> low with 0.33; low stays low with 0.88.
    # (The text labels this case E+ once; it is E-, SPEC §11.)
    ("high", "auto", "negative", "high"): 0.67,
    ("high", "auto", "negative", "low"): 0.12,
    # Fig. 6c: asking in high: high stays high; low -> high with 0.13.
    ("high", "ask", "positive", "high"): 1.00,
    ("high", "ask", "positive", "low"): 0.13,
}

#: Laplace standard errors printed in Table 2 (§4.3), keyed like the parameter
#: they belong to. The table's last two rows print a- where the emission
#: parameters for a+ are meant (SPEC §11). Kept for the report's comparison.
PAPER_TABLE2_STDERR: dict[tuple[str, ...], float] = {
    ("low", "auto", "positive", "high"): 0.04,
    ("high", "auto", "positive", "high"): 0.04,
    ("low", "auto", "positive", "low"): 0.09,
    ("high", "auto", "positive", "low"): 0.27,
    ("low", "auto", "negative", "high"): 0.19,
    ("high", "auto", "negative", "high"): 0.07,
    ("low", "auto", "negative", "low"): 0.56,
    ("high", "auto", "negative", "low"): 0.30,
    ("low", "ask", "negative", "high"): 0.11,
    ("high", "ask", "positive", "high"): 0.06,
    ("low", "ask", "negative", "low"): 0.34,
    ("high", "ask", "positive", "low"): 0.17,
    ("low", "high"): 0.00,  # P(rely | high trust, low, auto)
    ("high", "high"): 0.02,
    ("low", "low"): 0.01,
    ("high", "low"): 0.15,
}

# --- Policies (§5.1) --------------------------------------------------------

#: Threshold on P(trust high) printed for the trust-aware policy in high
#: complexity ("approximately 0.73"). Our solver's value is reported next to
#: it; see SPEC §11 for why the printed, rounded parameters differ slightly.
PAPER_TRUST_AWARE_THRESHOLD_HIGH = 0.73

#: Empirical intervention rates P(o = intervene | C, auto) from study 1 (§5.1).
PAPER_INTERVENTION_RATE_LOW = 0.006
PAPER_INTERVENTION_RATE_HIGH = 0.1848
#: Expected rewards of acting autonomously printed in §5.1. The low value
#: (2.79) ignores interventions; the formula with the printed rates gives
#: ≈ 2.77 (SPEC §11). Kept to compare against, never used to decide.
PAPER_EXPECTED_REWARD_AUTO_LOW = 2.79
PAPER_EXPECTED_REWARD_AUTO_HIGH = 1.02

# --- Study 2: policy evaluation (§5.2) --------------------------------------

#: Two blocks of 40 trials, 20 low + 20 high complexity each.
STUDY2_TRIALS_LOW_PER_BLOCK = 20
STUDY2_TRIALS_HIGH_PER_BLOCK = 20
STUDY2_PARTICIPANTS = 20
STUDY2_PARTICIPANTS_KEPT = 18
#: Results printed in §5.2–5.3 (for the report's comparison).
PAPER_MEDIAN_SCORE_AGNOSTIC = 69
PAPER_MEDIAN_SCORE_AWARE = 84
PAPER_SCORE_TTEST_P = 0.0007
#: Schaefer TPS-HRI scores (mean of the 14 reverse-coded items, %) before the experiment and after
#: each policy (§5.3, Table 3's aggregate row). §5.3 once prints 65.44 for the pre-experiment mean;
#: Table 3 and the later sentences say 64.64, which is used here.
PAPER_SCHAEFER_MEAN_PRE = 64.64
PAPER_SCHAEFER_MEAN_AGNOSTIC = 66.39
PAPER_SCHAEFER_MEAN_AWARE = 72.14
#: Table 3's aggregate row: median and variance of the scores per condition.
PAPER_SCHAEFER_MEDIAN_PRE = 65.0
PAPER_SCHAEFER_MEDIAN_AGNOSTIC = 69.29
PAPER_SCHAEFER_MEDIAN_AWARE = 72.50
PAPER_SCHAEFER_VARIANCE_PRE = 138.79
PAPER_SCHAEFER_VARIANCE_AGNOSTIC = 54.17
PAPER_SCHAEFER_VARIANCE_AWARE = 68.19
#: p-values of the score comparisons (§5.3); they are what MATLAB ``ttest2`` gives with the
#: printed means and variances (n = 18 each), so the paper compared the conditions as independent samples.
PAPER_SCHAEFER_P_AWARE_VS_AGNOSTIC = 0.0342
PAPER_SCHAEFER_P_PRE_VS_AGNOSTIC = 0.5973
PAPER_SCHAEFER_P_PRE_VS_AWARE = 0.0338
#: Table 4 (appendix): shelf-survey trust and reliance answers (0-10) per policy: (mean, median, variance).
PAPER_SHELF_TRUST_AGNOSTIC = (6.68, 7.33, 4.19)
PAPER_SHELF_TRUST_AWARE = (7.71, 7.75, 2.02)
PAPER_SHELF_RELIANCE_AGNOSTIC = (7.66, 7.83, 2.92)
PAPER_SHELF_RELIANCE_AWARE = (7.62, 7.83, 2.15)
#: Supplemental study: $10 base plus a performance bonus (§5.2, appendix).
SUPPLEMENT_BASE_COMPENSATION_USD = 10.0

# --- Trust vs. survey (§4.4–4.5) ---------------------------------------------

#: Logistic fit P^T(r) = L / (1 + exp(-k (r - r0))) of the median belief per
#: trust answer r on the 0–10 scale.
PAPER_LOGISTIC_L = 0.8849
PAPER_LOGISTIC_K = 1.184
PAPER_LOGISTIC_R0 = 2.932
#: Linear fit of the reliance answer on the trust answer: Rel(r) = 0.63 r + 3.27.
PAPER_RELIANCE_SLOPE = 0.63
PAPER_RELIANCE_INTERCEPT = 3.27
#: Goodness of the logistic fit as MATLAB ``fit`` reports it (§4.4): SSE and RMSE = sqrt(SSE / (n - 3)).
PAPER_LOGISTIC_SSE = 0.0213
PAPER_LOGISTIC_RMSE = 0.0653

# --- Questionnaires (§4.4, appendix) ------------------------------------------

#: Trust and reliance items after each shelf: 11-point 0–10 scales.
SHELF_SCALE_MIN = 0
SHELF_SCALE_MAX = 10
#: Trust Perception Scale–HRI 14-item subscale (Schaefer 2016): 0–100 % in 10s.
SCHAEFER_SCALE_MIN = 0
SCHAEFER_SCALE_MAX = 100
SCHAEFER_SCALE_STEP = 10
#: Jian, Bisantz & Drury (2000) checklist for trust between people and automation: 7-point scale,
#: 1 "not at all" to 7 "extremely".
JIAN_SCALE_MIN = 1
JIAN_SCALE_MAX = 7
#: Muir's single trust rating (Muir 1989; Muir & Moray 1996): 0–100, offered in steps of 10 (the published step is
#: not verified; whole points would put 101 buttons on the participant's page).
MUIR_SCALE_MIN = 0
MUIR_SCALE_MAX = 100
MUIR_SCALE_STEP = 10

# --- How long the study takes a participant (experiment.duration) ----------------
# Not from the paper: what a person needs, for the duration the consent and instructions pages announce.
# Each is a (quick participant, slow participant) pair; the estimate is the range between them.

#: Reading speed of instructional text, words a minute (typical silent reading of unfamiliar instructions).
READING_WORDS_PER_MINUTE = (240.0, 150.0)
#: Words of the instructions page's own text (controls, how to collect an item: static/participant.html), read
#: besides the study's consent and instruction texts.
INSTRUCTIONS_PAGE_WORDS = 340
#: One teleoperation by a person, s: the operator benchmark's simulated person (``benchmarks/bench_teleop.py``,
#: reaction time and key holding of a person) took a median of 10.6–15.0 s; a slow participant twice that.
TELEOP_PERSON_S = (12.0, 30.0)
#: The guided practice teleoperation (the tutorial), s: reading each step before doing it.
TUTORIAL_TELEOP_S = (60.0, 180.0)
#: Between two trials, s: the outcome on screen (1.5 s), "get ready" (0.8 s), reading the robot's message.
TRIAL_OVERHEAD_S = (3.0, 6.0)
#: Answering one questionnaire item, s, and reading a questionnaire page's instructions and sending it, s.
QUESTION_ITEM_S = (4.0, 8.0)
QUESTIONNAIRE_PAGE_S = (8.0, 20.0)
#: Consent, debrief and completion code: reading the fixed parts and clicking through, s.
FIXED_PAGES_S = (30.0, 90.0)

# --- Item types, attention checks (experiment.questionnaires, experiment.attention) ------
# Not from the paper: limits of the questionnaire items a study may add.

#: A free-text answer's length limit when its item sets none (characters), and the largest limit an item may set.
TEXT_ANSWER_MAX_LENGTH = 2000
TEXT_ANSWER_LIMIT = 10000
#: Failed attention checks that end a session under the rule ``screen_out`` when the study sets no number: two,
#: because recruitment platforms (Prolific's attention-check policy) do not let a study act on a single failure.
ATTENTION_MAX_FAILURES = 2

# --- Limits of a study's design (experiment.config) -------------------------------------
# Not from the paper (its blocks have 40 and 71 trials): a bound far beyond what one person can do in a session,
# so that a slip of the keyboard (an extra zero or six) is refused with a reason rather than building a schedule
# that exhausts the server's memory when the first session starts.

#: Most trials one block may have.
MAX_TRIALS_PER_BLOCK = 10_000

# --- Choosing the number of trust states (issue 40; the method's numbers, not the paper's) ---------------

#: Candidates: the paper's two levels, and up to four (more states than the data can separate only add noise).
STATES_MIN = 2
STATES_MAX = 4
#: EM restarts per fit: EM finds local maxima, more often with more states; 20 as the two-state fit (§4.3 uses EM).
STATES_RESTARTS = 20
#: Restarts that run to convergence after successive halving (as the two-state fit).
STATES_KEEP = 4
#: Iterations per halving stage.
STATES_STAGE_ITER = 5
#: Cap on SQUAREM iterations in all; a fit that hits it is reported as not converged, never hidden.
STATES_MAX_ITER = 2000
#: Converged: an iteration gains ≤ tol·(1 + |log-likelihood|). Tight, because EM crawls where the likelihood is
#: flat (1e-8 stopped 0.1 short of the maximum on 300 × 71 trials; 1e-10 costs 10 % more time than 1e-8).
STATES_TOL = 1e-10
#: Restart 0: P(rely | state) spread over [0.5 − s/2, 0.5 + s/2], the range reliance rates take in the data.
STATES_START_SPREAD = 0.8
#: Restart 0: P(stay in the same state); trust is persistent (§4.2: most transitions keep the level).
STATES_START_STAY = 0.8
#: Cross-validation folds of whole participants: 5 is the usual bias/variance compromise (Hastie et al. §7.10).
SELECTION_FOLDS = 5
#: The standard-error rule (after Hastie et al. §7.10's one-SE rule): the fewest states whose held-out score is
#: within this many standard errors (paired by participant) of the best, so that an extra state must earn its
#: place beyond chance. 2, not 1: with the SE resting on every participant, 1 SE let an unneeded fourth state
#: through on 300 × 71 trials of three-state data (it led by 1.7 SE); 2 SE is a one-sided ≈ 2.5 % chance.
SELECTION_SE_RULE = 2.0
#: A cross-validation fold's fit runs 1/share of the restarts (and finalists), restart 0 being the estimate on all
#: participants: the fold's maximum is near it, and the selection's 3 × 6 fits stay within minutes.
SELECTION_FOLD_RESTART_SHARE = 4
#: Held-out scoring keeps P(rely) this far from 0 and 1: an estimate at a bound would otherwise make one
#: held-out trial impossible (log-likelihood −∞) and end the comparison (log 1e-4 ≈ −9.2 per such trial).
SELECTION_PROBABILITY_FLOOR = 1e-4

# --- Parameter recovery (issue 40; the method's numbers) ----------------------------------------------------

#: Where the Laplace 95 % intervals are trusted: their coverage over simulated studies within this range.
RECOVERY_COVERAGE_RANGE = (0.90, 0.97)
#: A design identifies a parameter when at least this share of simulated studies gives it a Laplace interval
#: (exercised, not at a bound, not in a flat direction of the likelihood).
RECOVERY_IDENTIFIED_SHARE = 0.5

# --- Self-reported trust as a second observation (issue 40; the method's numbers, not the paper's) -------------

#: The shelf questionnaire's item used as the trust rating (paper §4.4: "To what extent do you trust …").
RATING_ITEM = "trust"
#: Newton steps of the rating emission per EM iteration (a generalised EM: each step only has to not lower the
#: likelihood); 3 reach the maximisation step's optimum to ~1e-8 on the studies tried, at a small share of an
#: E-step's time.
RATING_NEWTON_STEPS = 3
#: Bounds of the beta-binomial's α and β: below 0.05 a state would rate only at the scale's ends; above 1e4 it is
#: a binomial (no spread beyond chance), where the likelihood is flat in the concentration.
RATING_CONCENTRATION_RANGE = (0.05, 1e4)
#: Widest rating scale a model may give (points between its ends): a model file cannot ask for a huge table.
RATING_MAX_LEVELS = 1000
#: Restart 0's concentration α + β (a spread of about ±1.5 points on the 0…10 scale around the state's mean).
RATING_START_CONCENTRATION = 10.0
#: The other restarts draw each state's rating mean (as a share of the scale) uniformly from this range, and its
#: concentration log-uniformly from the next: from ratings spread over the whole scale to a binomial's spread.
RATING_START_MEAN_RANGE = (0.1, 0.9)
RATING_START_CONCENTRATION_RANGE = (2.0, 50.0)
