"""A spindle that keeps learning: a candidate model refitted from production, judged against the
live model on measurements it never saw, and the rule that decides whether it replaces it.

The input is a journal export (:func:`compensator.io.journal_export.export_journal`): every cycle
of the service, with the tool-setter measurements it accepted on their rows. Then:

1. **Faults out.** A measurement taken in a cycle that journaled a fault (the speed not read or
   assumed, the link down, an outage, the machine not ready, an input failing, a clock step, the
   estimate refused: ``FAULT_ALARMS``) is left out, and counted. Measurements the service rejected
   beyond its gate are never in the export.
2. **Forward split.** The newest measurements are held out: ``holdout_share`` of them, at least
   ``min_holdout``. The candidate is fitted on the log before the first of them, by the one
   identification (:func:`calibration.fit.fit_logs`), with the live model's inputs.
3. **Judged on the same rows.** Both models run over the whole export through the service's own
   estimate (:func:`calibration.replay.replay`): open loop, and with the observer fusing every
   measurement as the service does (each held-out one scored on the estimate just before it was
   fused). The scores are the RMS of the misses at the held-out measurements.
4. **The rule** (:func:`decide`). Promote only when there are at least ``min_train`` measurements
   to fit and ``min_holdout`` to judge, the candidate's open-loop RMS is below the live model's by
   ``margin`` or more (``(1 - margin) x live``), and with the observer it is no worse than the
   live model's by more than ``observer_tolerance``. Otherwise it is rejected, with the reason.

The command (``thermocomp refit``) adds what a reload checks (the model loads, names the spindle,
is plausible) and writes the history.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from compensator.errors import CalibrationError
from compensator.estimate import Estimate
from compensator.fitrecord import fit_of
from compensator.io import RunLog
from compensator.io.journal import FAULT_ALARMS
from compensator.modelbase import with_fit
from compensator.plausibility import direction_of, steady_state_um
from compensator.predictor import Predictor

from .folds import IDLE_RPM
from .replay import Probes, replay


@dataclass(frozen=True)
class Rule:
    """When a candidate may replace the live model."""

    min_train: int = 24
    """Measurements the candidate must be fitted on, at least."""
    min_holdout: int = 8
    """Measurements it must be judged on, at least."""
    holdout_share: float = 0.25
    """The newest share of the measurements held out to judge."""
    margin: float = 0.10
    """Open loop, the candidate must miss less than the live model by this share."""
    observer_tolerance: float = 0.05
    """With the observer, it may miss more than the live model by this share at most."""
    fit_days: float = 7.0
    """The candidate is fitted on the newest this many days before the held-out measurements
    (0: everything since the live model went into use): a spindle that changes is described by
    its newest weeks."""
    shadow_min: int = 24
    """Measurements a candidate in shadow must be judged on, at least."""
    t_crit: float = 2.0
    """In shadow, the paired difference of the squared misses must lie this many standard
    errors below zero: better beyond the measurements' own noise."""

    def holdout(self, n: int) -> int:
        return max(self.min_holdout, math.ceil(self.holdout_share * n))


@dataclass(frozen=True)
class Score:
    """One model's misses at the held-out measurements [um]."""

    open_loop_rms_um: float
    observer_rms_um: float | None
    open_loop_max_um: float


@dataclass(frozen=True)
class Decision:
    promote: bool
    reason: str
    held_back: bool = False
    """Too few measurements: nothing was fitted."""


@dataclass
class Refit:
    """What a refit made of an export."""

    decision: Decision
    candidate: Predictor | None = None
    live: Score | None = None
    scored: Score | None = None
    measurements: int = 0
    """Usable measurements in the export (faults left out)."""
    train: int = 0
    holdout: int = 0
    cut_s: float | None = None
    """Time of the first held-out measurement [s, the export's clock]."""
    notes: list[str] = field(default_factory=list)
    identification: Any = None

    def figures(self) -> dict[str, Any]:
        """For the history record and --json."""
        out: dict[str, Any] = {
            "measurements": self.measurements,
            "train": self.train,
            "holdout": self.holdout,
        }
        for name, s in (("live", self.live), ("candidate", self.scored)):
            if s is not None:
                out[name] = {
                    "open_loop_rms_um": round(s.open_loop_rms_um, 4),
                    "open_loop_max_um": round(s.open_loop_max_um, 4),
                    "observer_rms_um": None
                    if s.observer_rms_um is None
                    else round(s.observer_rms_um, 4),
                }
        return out


def usable_measurements(log: RunLog) -> tuple[np.ndarray, int]:
    """The rows whose measurement can judge a model: measured, in a cycle that journaled no
    fault; and how many measured rows were left out for a fault."""
    measured = log.measured
    alarms = log.extras.get("alarms")
    if alarms is None:
        return measured, 0
    bits = np.nan_to_num(np.asarray(alarms, dtype=float), nan=0.0).astype(np.int64)
    faulted = (bits & FAULT_ALARMS) != 0
    return measured & ~faulted, int((measured & faulted).sum())


def at_the_reference_row(log: RunLog, rows: np.ndarray) -> tuple[RunLog, np.ndarray]:
    """Each measurement moved to the row of the estimate the service compared it with. A journal
    export puts it on the cycle that read it; a tool setter measures at rest, and when the spindle
    had started again by then, the service took the cycle before, which ran slower
    (:meth:`compensator.estimate.Estimate.step`). A fit that kept it on the later row would learn
    a growth at speed that was measured at rest."""
    y = np.asarray(log.elongation_um, dtype=float).copy()
    sigma = log.extras.get("measurement_sigma_um")
    sigma = None if sigma is None else np.asarray(sigma, dtype=float).copy()
    speed = np.abs(np.asarray(log.speed_rpm, dtype=float))
    rows = rows.copy()
    for k in np.flatnonzero(rows):
        if k > 0 and speed[k - 1] < speed[k] and not np.isfinite(y[k - 1]):
            y[k - 1], y[k] = y[k], np.nan
            rows[k - 1], rows[k] = True, False
            if sigma is not None:
                sigma[k - 1], sigma[k] = sigma[k], np.nan
    extras = dict(log.extras)
    if sigma is not None:
        extras["measurement_sigma_um"] = sigma
    return replace(log, elongation_um=y, extras=extras), rows


def score(
    estimate: Estimate,
    log: RunLog,
    rows: np.ndarray,
    probe_rows: np.ndarray,
    sigma_um: np.ndarray,
    observer: bool,
) -> Score:
    """``estimate``'s misses at ``rows`` over ``log``: open loop, and (``observer``) with the
    measurements of ``probe_rows`` fused, each scored before it was fused."""
    y = np.asarray(log.elongation_um, dtype=float)
    k = np.flatnonzero(rows)
    open_loop = replay(
        estimate.model, log, compare=False, estimate=replace(estimate, observer=None)
    ).predicted_um
    miss = y[k] - open_loop[k]
    fused_rms = None
    if observer and estimate.fused is not None:
        p = np.flatnonzero(probe_rows)
        probes = Probes(log.time_s[p], y[p], sigma_um[p], "journal")
        fused = replay(
            estimate.model, log, probes=probes, compare=False, estimate=estimate
        ).predicted_um
        # the estimate before the measurement was fused: the row's own is after it (at or before)
        before = fused[np.maximum(k - 1, 0)] + (open_loop[k] - open_loop[np.maximum(k - 1, 0)])
        fused_rms = float(np.sqrt(np.mean((y[k] - before) ** 2)))
    return Score(float(np.sqrt(np.mean(miss**2))), fused_rms, float(np.max(np.abs(miss))))


AT_SPEED_CHECK_S = 60.0
"""The growth this long after a start from rest is what a refit on measurements taken at rest
must leave as it was (the elastic and the fastest thermal part, which no such measurement sees)."""
AT_SPEED_TOLERANCE_UM = 1.0


def unseen_at_speed(live: Predictor, candidate: Predictor, margin: float) -> str | None:
    """Why ``candidate`` may not replace ``live`` when every measurement it was judged on was
    taken at rest, or None. At rest, neither the fit nor the judgement sees the growth that
    exists only while the spindle turns; a candidate that changes it (a fit from measurements at
    rest leaves it out) would be judged better and cut worse. The rule: 60 s after a start from
    rest to each quarter of the calibrated range, the candidate's growth stays within ``margin``
    of the live model's (at least 1 um)."""
    top = float(live.speed_range_rpm[1])
    t = np.arange(0.0, AT_SPEED_CHECK_S + 1.0, 1.0)
    worst = None
    for frac in (0.25, 0.5, 0.75, 1.0):
        n = np.full(t.size, frac * top)
        n[0] = 0.0
        run_live, run_cand = live.simulate_um(n, t), candidate.simulate_um(n, t)
        a, b = float(run_live[-1] - run_live[0]), float(run_cand[-1] - run_cand[0])
        allowed = max(AT_SPEED_TOLERANCE_UM, margin * abs(a))
        if abs(b - a) > allowed and (worst is None or abs(b - a) > abs(worst[2] - worst[1])):
            worst = (frac * top, a, b, allowed)
    if worst is None:
        return None
    at_rpm, a, b, allowed = worst
    return (
        f"every measurement was taken at rest, so nothing vouches for the growth while the spindle "
        f"turns, and the candidate changes it: {AT_SPEED_CHECK_S:.0f} s after a start to {at_rpm:.0f} rpm it "
        f"predicts {b:+.2f} um where the live model predicts {a:+.2f} um (more than {allowed:.2f} um apart); "
        "measure at speed (a laser setter, --probe-spindle keep) to refit that part"
    )


def decide(rule: Rule, live: Score, cand: Score) -> Decision:
    """The promotion rule (see the module): better by the margin open loop, no worse with the
    observer."""
    bar = (1.0 - rule.margin) * live.open_loop_rms_um
    if not cand.open_loop_rms_um <= bar:
        return Decision(
            False,
            f"open loop it misses {cand.open_loop_rms_um:.2f} um RMS on the held-out "
            f"measurements against the live model's {live.open_loop_rms_um:.2f} um: not "
            f"{100 * rule.margin:.0f} % better",
        )
    if cand.observer_rms_um is not None and live.observer_rms_um is not None:
        worst = (1.0 + rule.observer_tolerance) * live.observer_rms_um
        if cand.observer_rms_um > worst:
            return Decision(
                False,
                f"with the observer it misses {cand.observer_rms_um:.2f} um RMS against "
                f"the live model's {live.observer_rms_um:.2f} um",
            )
    return Decision(
        True,
        f"open loop {cand.open_loop_rms_um:.2f} um RMS on the held-out measurements "
        f"against the live model's {live.open_loop_rms_um:.2f} um"
        + (
            ""
            if cand.observer_rms_um is None or live.observer_rms_um is None
            else f"; with the observer {cand.observer_rms_um:.2f} against {live.observer_rms_um:.2f} um"
        ),
    )


def refit(
    log: RunLog,
    live: Estimate,
    make_estimate,
    *,
    rule: Rule = Rule(),
    spindle_id: str | None = None,
    default_sigma_um: float = 0.5,
    **meta: Any,
) -> Refit:
    """Fit a candidate on ``log`` (a journal export) before its newest measurements and judge it
    against ``live`` (the live model's estimate as the service runs it) on them.
    ``make_estimate(model)`` builds the candidate's estimate as the service would."""
    from .fit import fit_logs

    rows, faulted = usable_measurements(log)
    log, rows = at_the_reference_row(log, rows)
    out = Refit(Decision(False, ""), measurements=int(rows.sum()))
    if faulted:
        out.notes.append(
            f"{faulted} measurement(s) taken while the journal showed a fault (link, speed, "
            "inputs, clock) left out"
        )
    n = out.measurements
    h = rule.holdout(n)
    if n - h < rule.min_train:
        out.decision = Decision(
            False,
            f"{n} usable measurement(s): the rule needs {rule.min_train} to fit and "
            f"{max(rule.min_holdout, h)} to judge; nothing fitted",
            held_back=True,
        )
        return out
    k = np.flatnonzero(rows)
    first_held = int(k[n - h])
    out.train, out.holdout, out.cut_s = n - h, h, float(log.time_s[first_held])
    y = np.asarray(log.elongation_um, dtype=float)
    y_usable = np.where(rows, y, np.nan)
    clean = replace(log, elongation_um=y_usable)
    first_train = 0
    if rule.fit_days > 0:
        first_train = int(np.searchsorted(log.time_s, out.cut_s - rule.fit_days * 86400.0))
        kept = int(rows[first_train:first_held].sum())
        if kept < rule.min_train:  # too few in the window: the newest min_train instead
            first_train = int(k[max(0, n - h - rule.min_train)])
        out.train = int(rows[first_train:first_held].sum())
    train = _rows(clean, slice(first_train, first_held))
    names = tuple(getattr(live.model, "input_names", ()) or ())
    # the growth points the way the live model's calibration measured it: a stretch of production
    # (a chip on the setter, a cool week) must not turn it round
    direction = direction_of(fit_of(live.model).growth_direction)
    if direction is None:
        top = live.model.speed_range_rpm[1]
        g = steady_state_um(live.model, top) - steady_state_um(live.model, 0.0)
        direction = 1 if g >= 0 else -1
    try:
        ident = fit_logs(
            [train],
            names,
            labels=["production"],
            spindle_id=spindle_id,
            growth_direction=direction,
            **meta,
        )
    except CalibrationError as err:
        out.decision = Decision(False, f"the fit refused: {err}")
        return out
    out.identification, out.candidate = ident, ident.model
    held = rows.copy()
    held[:first_held] = False
    sigma = np.asarray(
        log.extras.get("measurement_sigma_um", np.full(len(log), default_sigma_um)), dtype=float
    )
    sigma = np.where(np.isfinite(sigma) & (sigma > 0), sigma, default_sigma_um)
    observer = live.fused is not None
    candidate = ident.model
    live_observer = fit_of(live.model).observer
    if live_observer is not None and candidate.fit.observer is None:
        # the observer's noise was fitted on the calibration's dense residuals, which measurements
        # minutes apart cannot give: the candidate keeps the live model's, so both are judged, and
        # the promoted one runs, with the observer the service has
        candidate = with_fit(candidate, observer=live_observer)
        out.candidate = candidate
    out.live = score(live, clean, held, rows, sigma, observer)
    out.scored = score(make_estimate(candidate), clean, held, rows, sigma, observer)
    out.decision = decide(rule, out.live, out.scored)
    at_rest = not bool((np.abs(np.asarray(log.speed_rpm, dtype=float))[rows] > IDLE_RPM).any())
    if at_rest:
        out.notes.append("every measurement was taken at rest")
        why = unseen_at_speed(live.model, candidate, rule.margin) if out.decision.promote else None
        if why is not None:
            out.decision = Decision(False, why)
    return out


def _rows(log: RunLog, rows: slice) -> RunLog:
    """The rows ``rows`` of a log, every column with them."""
    extras = {k: np.asarray(v)[rows] for k, v in log.extras.items()}
    return replace(
        log,
        time_s=log.time_s[rows],
        speed_rpm=log.speed_rpm[rows],
        elongation_um=None if log.elongation_um is None else log.elongation_um[rows],
        extras=extras,
        gaps=tuple(g for g in log.gaps if g.start_s + g.duration_s <= log.time_s[rows][-1]),
    )


@dataclass
class ShadowJudgement:
    decision: Decision
    live: Score | None = None
    shadow: Score | None = None
    measurements: int = 0
    t_stat: float | None = None
    """The paired difference of the squared misses (candidate - live), in standard errors."""
    effective: float | None = None
    """The measurements' effective number once weighted to the time cut at each speed."""

    def figures(self) -> dict[str, Any]:
        out: dict[str, Any] = {"measurements": self.measurements}
        for name, sc in (("live", self.live), ("candidate", self.shadow)):
            if sc is not None:
                out[name] = {
                    "open_loop_rms_um": round(sc.open_loop_rms_um, 4),
                    "open_loop_max_um": round(sc.open_loop_max_um, 4),
                    "observer_rms_um": None
                    if sc.observer_rms_um is None
                    else round(sc.observer_rms_um, 4),
                }
        if self.t_stat is not None:
            out["paired_t"] = round(self.t_stat, 2)
        if self.effective is not None:
            out["effective_measurements"] = round(self.effective, 1)
        return out


SPEED_BANDS = 5
"""The calibrated range in this many bands of speed, and rest: the measurements are weighted so
that each band counts as long as the spindle cut in it."""


def misses(
    estimate: Estimate,
    log: RunLog,
    rows: np.ndarray,
    sigma_um: np.ndarray,
    start: int,
    initial_um: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``estimate`` run as the service runs it over ``log`` from row ``start`` (begun at
    ``initial_um``, as a start or a promotion begins it), fusing the measurements of ``rows``:
    at each of them from ``start`` on, the miss of the estimate it met (before it was fused) and
    the model's own miss; and the estimate every row (NaN before ``start``)."""
    from .replay import _steps

    t, dt, wall = _steps(log)
    wall = t if wall is None else wall
    y = np.asarray(log.elongation_um, dtype=float)
    speed = np.asarray(log.speed_rpm, dtype=float)
    names = estimate.model.input_names
    cols = {n: np.asarray(log.extras[n], dtype=float) for n in names}
    st = estimate.begin(initial_um, float(speed[start]))
    met, own = [], []
    path = np.full(len(log), np.nan)
    for k in range(start, len(log)):
        values = {n: float(c[k]) for n, c in cols.items()} if cols else None
        st, _ = estimate.step(
            st,
            float(speed[k]),
            0.0 if k == start else float(dt[k]),
            now_s=float(t[k]),
            wall_s=float(wall[k]),
            inputs=values,
        )
        if rows[k]:
            ref = (
                st.probe_reference_um
                if st.probe_reference_um is not None
                else float(st.in_use.elongation_um)
            )
            own.append(y[k] - ref)
            if estimate.fused is not None:
                st, _, before = estimate.measure(st, float(y[k]), float(sigma_um[k]), "journal")
                met.append(y[k] - before)
            else:
                met.append(y[k] - ref)
        path[k] = st.estimate_um
    return np.asarray(met), np.asarray(own), path


def cutting_weights(log: RunLog, rows: np.ndarray, top_rpm: float) -> np.ndarray:
    """A weight for each measurement of ``rows`` (summing to 1): the share of the time the
    spindle cut in its speed band over the log, shared among the band's measurements. What a
    user feels is the error while cutting; a tool setter measures where the program stops,
    which is not where it cuts."""
    speed = np.abs(np.asarray(log.speed_rpm, dtype=float))
    cut = log.extras.get("cutting")
    cutting = (
        speed > IDLE_RPM
        if cut is None or np.asarray(cut).dtype == object
        else np.nan_to_num(np.asarray(cut, dtype=float), nan=0.0) > 0.5
    )
    edges = np.r_[
        0.0,
        IDLE_RPM,
        np.linspace(IDLE_RPM, max(top_rpm, 2 * IDLE_RPM), SPEED_BANDS + 1)[1:-1],
        np.inf,
    ]
    band = np.clip(np.digitize(speed, edges) - 1, 0, edges.size - 2)
    dt = np.diff(np.asarray(log.time_s, dtype=float), append=log.time_s[-1])
    time_in = np.bincount(band[cutting], weights=dt[cutting], minlength=edges.size - 1)
    k = np.flatnonzero(rows)
    count = np.bincount(band[k], minlength=edges.size - 1)
    w = time_in[band[k]] / np.maximum(count[band[k]], 1)
    if not w.sum() > 0:
        return np.full(k.size, 1.0 / max(k.size, 1))
    return w / w.sum()


def judge_shadow(
    log: RunLog,
    live: Estimate,
    candidate: Estimate,
    start_s: float,
    rule: Rule = Rule(),
    default_sigma_um: float = 0.5,
) -> ShadowJudgement:
    """A candidate that ran in shadow from ``start_s``, judged on what it would have done: both
    estimates run as the service runs them (the same observer fusing the same measurements),
    the live one over the whole of ``log`` (the journal since it went into use), the candidate
    from ``start_s``, begun at the live estimate there as a promotion begins it. At each usable
    measurement from ``start_s`` on, each one's miss of the estimate the measurement met,
    weighted to the time the spindle cut at each speed (:func:`cutting_weights`). Promoted only
    on ``shadow_min`` measurements or more, better by the margin and beyond the noise: the paired
    difference of the squared misses ``t_crit`` standard errors below zero."""
    rows, _ = usable_measurements(log)
    start = int(np.searchsorted(log.time_s, start_s))
    judged = rows.copy()
    judged[:start] = False
    n = int(judged.sum())
    out = ShadowJudgement(Decision(False, ""), measurements=n)
    if n < rule.shadow_min or start >= len(log):
        out.decision = Decision(
            False,
            f"{n} measurement(s) while it ran in shadow: the rule needs {rule.shadow_min}",
            held_back=True,
        )
        return out
    sigma = np.asarray(
        log.extras.get("measurement_sigma_um", np.full(len(log), default_sigma_um)), dtype=float
    )
    sigma = np.where(np.isfinite(sigma) & (sigma > 0), sigma, default_sigma_um)
    journaled = log.extras.get("predicted_um")
    first = (
        float(journaled[0])
        if journaled is not None and np.isfinite(np.asarray(journaled, dtype=float)[0])
        else None
    )
    lmet, lown, lpath = misses(live, log, rows, sigma, 0, first)  # type: ignore[arg-type]
    at = np.isin(np.flatnonzero(rows), np.flatnonzero(judged))
    lmet, lown = lmet[at], lown[at]
    begin_um = float(lpath[start - 1]) if start > 0 else float(lpath[start])
    cmet, cown, _ = misses(candidate, log, judged, sigma, start, begin_um)
    w = cutting_weights(log, judged, float(live.speed_range_rpm[1]))
    fused = live.fused is not None

    def sc(met: np.ndarray, own: np.ndarray) -> Score:
        return Score(
            float(np.sqrt(np.sum(w * own**2))),
            float(np.sqrt(np.sum(w * met**2))) if fused else None,
            float(np.max(np.abs(own))),
        )

    out.live, out.shadow = sc(lmet, lown), sc(cmet, cown)
    d = cmet**2 - lmet**2
    mean = float(np.sum(w * d))
    se = float(np.sqrt(np.sum(w**2 * (d - mean) ** 2)))
    out.t_stat = mean / se if se > 0 else (0.0 if mean == 0 else math.copysign(math.inf, mean))
    out.effective = float(1.0 / np.sum(w**2))
    a = out.live.observer_rms_um if fused else out.live.open_loop_rms_um
    b = out.shadow.observer_rms_um if fused else out.shadow.open_loop_rms_um
    assert a is not None and b is not None
    what = "with the observer, as the service runs it," if fused else "open loop"
    figs = (
        f"{what} it misses {b:.2f} um RMS at the {n} measurements taken while it ran in shadow "
        f"(weighted to the time cut at each speed) against the live model's {a:.2f} um"
    )
    if not b <= (1.0 - rule.margin) * a:
        out.decision = Decision(False, f"in shadow: {figs}: not {100 * rule.margin:.0f} % better")
    elif not out.t_stat <= -rule.t_crit:
        out.decision = Decision(
            False,
            f"in shadow: {figs}, but within the measurements' noise (paired t {out.t_stat:+.1f}, "
            f"needs {-rule.t_crit:+.1f})",
        )
    else:
        out.decision = Decision(True, f"in shadow: {figs} (paired t {out.t_stat:+.1f})")
    return out
