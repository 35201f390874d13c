"""The one identification: every candidate judged by the same folds, in free run, and the best
honest one chosen. ``thermocomp fit``, the wizard, ``make demo`` and the cooling studies all
come here through :func:`calibration.fit.fit_logs`. Pure computation on a
:class:`~calibration.dataset.Dataset`: no file I/O.

The candidates are the entries of :data:`REGISTRY`, one per model structure
(:mod:`calibration.estimators`). Adding a form is one estimator module and one line there:

- ``exp-baseline``: one time constant chosen by CV, S∞ quadratic in n. The bar every other
  candidate must clear.
- ``physical``: the output-error form ``speed-state+elastic`` (a thermal state whose dissipation
  depends on speed, plus an elastic term), refitted per fold.
- ``ridge``: ridge over n, n² through a bank of first-order filters, α by CV.
- ``ridge+static``: ridge over n, n² through a bank of lags and every named input static, α on
  forward-chained half cycles. With inputs, the structure that stands first.
- ``ridge+inputs``: the same with the named inputs (temperatures...) through their own banks.
- ``paper-ols``: the paper's one-step OLS, scored in free run for the comparison; never chosen.

Folds: leave-one-cycle-out when the logs hold two cycles or more, otherwise contiguous blocks
(:func:`calibration.dataset.join`). Every candidate free-runs each whole log from its start and
is scored on the measured rows of the held-out fold. With sparse targets (a journal export) the
candidates that need the elongation on every row are left out, and the report says so.

Two held-out figures per candidate: leave-one-fold-out (nested where its hyperparameters were
chosen by CV) and forward (:func:`calibration.folds.forward_of`: origins every half cycle, each
stretch predicted in free run by a model chosen and fitted on the rows before its origin). A
candidate is refused when the worse of the two is worse than the baseline's, or when its gains
fail the sanity bound. With two cycles or more the structures are then walked from simple to
flexible (:data:`COMPLEXITY`), speed-only first (the fallback), then the inputs: from
``ridge+static`` when it passed (the inputs are then kept), else from the speed-only choice. A
more flexible one displaces the one standing only when the forward folds show it better by more
than one standard error of the paired per-fold difference with no worse median or worst fold,
or lower the worst fold by more than :data:`TAIL` with a median within TAIL (:func:`_duel`);
past ``ridge+static`` it needs :data:`MIN_FLEXIBLE_FOLDS` forward folds to try. The reason is
one paragraph. On a log of one cycle (blocks) ``ridge+static`` is the structure for the inputs
when it passed; there, or judged in closed loop, the lowest figure wins otherwise, a simpler one
within :data:`~calibration.metrics.PARSIMONY`, as before. When every
speed-only candidate fails the physics check but one with inputs passed, the fallback is the
most conservative speed-only model (:func:`conservative_fallback`), and the channel still fits.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, ParamSpec, TypeVar

import numpy as np
from threadpoolctl import threadpool_limits

from compensator.errors import CalibrationError
from compensator.expected import ExpectedError, memory_s_of
from compensator.fitrecord import FIT_SCHEMA_VERSION, FitRecord
from compensator.modelbase import with_fit
from compensator.plausibility import steady_growth_refusal, time_constant_refusal

from . import closedloop
from . import folds as fl
from .candidate import MIN_FORWARD_FOLDS, Candidate
from .dataset import Dataset, LogData, join
from .estimators import baseline, output_error, paper_ols
from .estimators import ridge_bank as rb
from .folds import CYCLE_RULE
from .metrics import MIN_BAND_ROWS, PARSIMONY, expected_error, finite, measured_stats

__all__ = ["REGISTRY", "Candidate", "Entry", "Identification", "LogData", "identify"]


# -- the registry -------------------------------------------------------------------------------

STATIC = "ridge+static"
"""With inputs, the structure that stands first: a plain ridge over the static inputs and a
bank of speed lags, the one the real record's forward folds never found far off."""

Context = Mapping[str, Any]
"""What every entry may read: ``names`` (the inputs), ``nested``, ``meta`` (model fields)."""


def _from_ridge(
    name: str, family: str, description: str, res: rb.RidgeFit, ds: Dataset
) -> Candidate:
    c = Candidate(
        name,
        family,
        description,
        res.cv_rms_um,
        res.cv_max_abs_um,
        res.nested_rms_um,
        res.nested_max_abs_um,
        [f.rms_um for f in res.folds],
        fit_cpu_s=res.fit_cpu_s,
    )
    pred = res.predict_dataset(ds)
    c.in_sample_rms_um, c.in_sample_max_abs_um = measured_stats(
        np.where(ds.measured, ds.elongation_um - pred, np.nan)
    )
    c.details = {
        "grid": res.grid.label,
        "alpha": res.alpha,
        "states": len({t for t in (*res.grid.speed_taus_s, *res.grid.input_taus_s) if t > 0}),
        "steady_range_um": res.steady_range_um(),
    }
    c.notes += list(res.notes)
    c.refusals += list(res.refusals)
    c.held_out_residual_um = res.held_out_residual_um
    c.slowest_tau_s = res.slowest_tau_s
    c.forward_rms_um, c.forward_max_abs_um = res.forward_rms_um, res.forward_max_abs_um
    c.forward_folds_rms_um = [f.rms_um for f in res.forward_folds or ()]
    c.forward_residual_um = res.forward_residual_um
    c.forward_clipped_residual_um, c.forward_distance = (
        res.forward_clipped_residual_um,
        res.forward_distance,
    )
    return c


def _baseline(ds: Dataset, ctx: Context) -> tuple[Candidate, rb.RidgeFit]:
    res = baseline.fit(ds, nested=ctx["nested"])
    c = _from_ridge(baseline.NAME, "speed", baseline.DESCRIPTION, res, ds)
    c.details["tau_s"] = res.grid.speed_taus_s[0]
    return c, res


def _ridge(ds: Dataset, ctx: Context) -> tuple[Candidate, rb.RidgeFit]:
    res = rb.fit(
        ds, grids=[rb.auto_grid(ds.time_s, ds.speed_rpm, ds.cycles, False)], nested=ctx["nested"]
    )
    return _from_ridge(
        "ridge", "speed", "ridge over n, n² through first-order filter banks; alpha by CV", res, ds
    ), res


def _ridge_inputs(
    ds: Dataset, ctx: Context, structure: str = "all"
) -> tuple[Candidate, rb.RidgeFit | None]:
    names = ctx["names"]
    try:
        res = rb.fit(
            ds,
            grids=[rb.auto_grid(ds.time_s, ds.speed_rpm, ds.cycles, True)],
            input_names=names,
            nested=ctx["nested"],
            structure=structure,
            units=ctx.get("units"),
        )
    except CalibrationError as err:
        if structure == "all":
            raise
        return Candidate(
            f"ridge+{structure}", "inputs", f"ridge with {structure} inputs", refusals=[str(err)]
        ), None
    if structure == "few":
        name, what = (
            "ridge+few",
            f"ridge over n, n² and the inputs a forward selection kept ({', '.join(res.input_names)})",
        )
    elif structure == "pca":
        name, what = (
            "ridge+pca",
            f"ridge over n, n² and {res.structure_detail} of {len(names)} input(s)",
        )
    elif structure == "bounded":
        name, what = (
            "ridge+bounded",
            (
                f"ridge over n, n² and {len(names)} input(s), each temperature's steady "
                f"sensitivity within {rb.BOUND_UM_PER_K:.1f} um/K"
            ),
        )
    else:
        name, what = "ridge+inputs", f"ridge over n, n² and {len(names)} input(s)"
    c = _from_ridge(name, "inputs", what + " through filter banks; alpha by CV", res, ds)
    c.details["inputs_used"] = list(res.input_names)
    return c, res


def _ridge_static(ds: Dataset, ctx: Context) -> tuple[Candidate, rb.RidgeFit]:
    names = ctx["names"]
    res = rb.fit(
        ds,
        grids=[static_grid(ds)],
        input_names=names,
        alpha_by="chained",
        nested=ctx["nested"],
        units=ctx.get("units"),
    )
    what = (
        f"ridge over n, n² through a filter bank and {len(names)} input(s) static (no filter); "
        "alpha on forward-chained half cycles"
    )
    c = _from_ridge(STATIC, "inputs", what, res, ds)
    c.details["inputs_used"] = list(res.input_names)
    return c, res


def static_grid(ds: Dataset) -> rb.TauGrid:
    """The lagged rungs of :func:`~calibration.estimators.ridge_bank.auto_grid`'s speed bank, the
    inputs static only: a temperature's effect taken as it stands, no lag for the inputs to fit,
    and no instantaneous speed term (heat takes time; the static temperatures already carry the
    level: with it, the next stretch erred 12-30 % more on the real record at two cycles)."""
    speed = rb.auto_grid(ds.time_s, ds.speed_rpm, ds.cycles, False).speed_taus_s
    return rb.TauGrid(tuple(t for t in speed if t > 0) or speed, (0.0,))


@dataclass(frozen=True)
class Entry:
    """One candidate structure: how to fit and score it on a dataset (``evaluate`` returns the
    scored :class:`Candidate` and the fitted object, which has ``to_model`` unless the candidate
    carries its model already), and when it applies."""

    name: str
    family: str
    evaluate: Callable[[Dataset, Context], tuple[Candidate, Any]]
    progress: str
    every_row: bool = False
    """It needs the elongation on every row: left out for sparse targets."""
    needs_inputs: bool = False
    option: str | None = None
    """The keyword of :func:`identify` that can leave it out."""
    min_folds: int = 2
    """Fewer folds than this leave it out: choosing among input structures on two folds picked
    the wrong one on the real record (forward error up to 4x)."""
    min_inputs: int = 0
    """Fewer inputs than this leave it out: sharing strength is for many nearly collinear
    sensors (16 on one casting); three independent ones keep a bank each."""
    complexity: int = 0
    """Its place in the order of structures, simple to flexible (:data:`COMPLEXITY`): a more
    flexible one is chosen over a simpler one only when the folds say it is better by more than
    their spread."""


MIN_SHARED_INPUTS = 6
"""The structures that share strength among inputs are tried from this many inputs."""

COMPLEXITY = {
    baseline.NAME: 0,
    output_error.NAME: 1,
    "ridge": 2,
    STATIC: 3,
    "ridge+few": 4,
    "ridge+pca": 4,
    "ridge+bounded": 4,
    "ridge+inputs": 5,
}
"""The structures from simple to flexible: the exponential baseline, the physical form, ridge on
speed, ridge with the inputs static, ridge with the inputs sharing strength (a few, their
principal components, bounded sensitivities), ridge with every input through its own bank."""

REGISTRY: tuple[Entry, ...] = (
    Entry(baseline.NAME, "speed", _baseline, "fitting the exponential baseline"),
    Entry(
        output_error.NAME,
        "speed",
        output_error.candidate,
        f"fitting {output_error.PHYSICAL_FORM} per fold",
        option="physical",
        complexity=1,
    ),
    Entry("ridge", "speed", _ridge, "fitting ridge (speed)", complexity=2),
    Entry(
        "ridge+inputs",
        "inputs",
        _ridge_inputs,
        "fitting ridge with the inputs",
        needs_inputs=True,
        complexity=5,
    ),
    Entry(
        STATIC,
        "inputs",
        _ridge_static,
        "fitting ridge with the inputs static",
        needs_inputs=True,
        complexity=3,
    ),
    Entry(
        "ridge+few",
        "inputs",
        lambda ds, ctx: _ridge_inputs(ds, ctx, "few"),
        "fitting ridge with the few inputs a forward selection keeps",
        needs_inputs=True,
        min_folds=3,
        min_inputs=MIN_SHARED_INPUTS,
        complexity=4,
    ),
    Entry(
        "ridge+pca",
        "inputs",
        lambda ds, ctx: _ridge_inputs(ds, ctx, "pca"),
        "fitting ridge with principal components of the inputs",
        needs_inputs=True,
        min_folds=3,
        min_inputs=MIN_SHARED_INPUTS,
        complexity=4,
    ),
    Entry(
        "ridge+bounded",
        "inputs",
        lambda ds, ctx: _ridge_inputs(ds, ctx, "bounded"),
        "fitting ridge with physically bounded sensitivities",
        needs_inputs=True,
        min_folds=3,
        min_inputs=MIN_SHARED_INPUTS,
        complexity=4,
    ),
    Entry(
        paper_ols.NAME, "reference", paper_ols.candidate, "scoring the paper's OLS", every_row=True
    ),
)
"""The candidates, simple to rich within a family (a simpler one wins within PARSIMONY). The
first is the bar every other must clear."""


# -- the result ---------------------------------------------------------------------------------


@dataclass
class Identification:
    dataset: Dataset
    candidates: list[Candidate]
    chosen: Candidate
    model: Any
    reason: str
    warnings: list[str]
    fit_cpu_s: float
    derived: list[dict[str, Any]] = field(default_factory=list)
    closed_loop: closedloop.Plan | None = None

    def free_run_um(self) -> dict[str, np.ndarray]:
        """The model's in-sample free run over each log (by name), from its first measured
        elongation (at rest when the first row is not measured)."""
        ds, m = self.dataset, self.model
        out = {}
        with np.errstate(all="ignore"):
            for name, (a, b) in zip(ds.names, ds.segments):
                inputs = {n: v[a:b] for n, v in ds.inputs.items()} if m.input_names else None
                y0 = float(ds.elongation_um[a])
                out[name] = m.simulate_um(
                    ds.speed_rpm[a:b], ds.time_s[a:b], inputs, y0 if math.isfinite(y0) else None
                )
        return out

    def report(self) -> dict[str, Any]:
        ds = self.dataset
        return {
            "format": "thermocomp.fit-report/2",
            "method": "cycles",
            "cycle_rule": CYCLE_RULE,
            "cycles": list(ds.cycle_lines),
            "scored_by": f"{ds.scheme} free run",
            "forward_decides": ds.unit == "cycle",
            "folds": [[int(a), int(b)] for a, b in ds.folds],
            "forward_splits": [
                [int(a), int(b)]
                for _, (a, b) in fl.forward_of(
                    ds.time_s, ds.speed_rpm, ds.folds, ds.unit == "cycle", ds.measured
                )
            ],
            "forward_rule": fl.FORWARD_ORIGIN_RULE if ds.unit == "cycle" else None,
            "logs": list(ds.names),
            "candidates": [c.row() for c in self.candidates],
            "chosen": self.chosen.name,
            "model_form": self.model.form,
            "reason": self.reason,
            "derived": self.derived,
            "closed_loop": None if self.closed_loop is None else self.closed_loop.report(),
            "warnings": self.warnings,
            "fit_cpu_s": round(self.fit_cpu_s, 2),
        }


# -- the choice ---------------------------------------------------------------------------------


def _coverage(ds: Dataset) -> list[str]:
    out = []
    if not ds.dense:
        m = int(ds.measured.sum())
        out.append(
            f"sparse targets: fitted and scored on the {m} measured rows of {ds.measured.size} (the "
            "cycles and the free run on every row); the paper's OLS, the "
            "closed-loop plan and the HAC standard errors need the elongation on every row and "
            "are left out"
        )
        if ds.dropped_folds:
            out.append(
                f"{ds.dropped_folds} {ds.unit}(s) without a measurement: run through, not fitted or scored"
            )
    if ds.unit == "block":
        out.append(
            "the logs hold one heat-up/cool-down cycle: scored on contiguous blocks of it; "
            "record another cycle for a leave-one-cycle-out score"
        )
    return out


P = ParamSpec("P")
R = TypeVar("R")


def _one_blas_thread(fn: Callable[P, R]) -> Callable[P, R]:
    """Run ``fn`` with the linear algebra on one thread. The identification solves thousands of
    small least-squares problems (a few hundred columns): BLAS threads only contend for them,
    and on a 2-core machine the real record's fit took 5x the CPU and 6x the time with them."""

    @functools.wraps(fn)
    def run(*args: P.args, **kwargs: P.kwargs) -> R:
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return run


@_one_blas_thread
def identify(
    logs: Sequence[LogData] | Dataset,
    input_names: Sequence[str] = (),
    *,
    units: Mapping[str, str] | None = None,
    physical: bool = True,
    nested: bool = True,
    probe_target_um: float | None = closedloop.DEFAULT_TARGET_UM,
    probe_every_s: float | None = None,
    progress: Callable[[str], None] | None = None,
    growth_direction: int | None = None,
    measured_span_um: float | None = None,
    **meta: Any,
) -> Identification:
    """Fit every candidate of :data:`REGISTRY` that applies, score it on the same folds in free
    run, choose, and build the model.

    ``meta`` (spindle_id, machine_id, created_utc) goes into the model. With probes planned
    (``probe_every_s``) a candidate is judged by its closed loop on held-out folds instead; that
    and the closed-loop plan need the elongation on every row. A speed-only candidate whose
    steady growth physics forbids (:func:`compensator.plausibility.steady_growth_refusal`, in
    ``growth_direction``, against the ``measured_span_um``) is refused, so the choice falls to the
    next. Raises :class:`CalibrationError` when nothing can be validated.
    """
    cpu0 = time.process_time()
    say = progress or (lambda _m: None)
    names = tuple(sorted(set(input_names)))
    ds = logs if isinstance(logs, Dataset) else join(logs, names)
    if not ds.dense and probe_every_s is not None:
        raise CalibrationError(
            "--probe-every plans the closed loop on an elongation measured on every "
            "row; the logs have it on some rows only (sparse)"
        )
    warnings = _coverage(ds)
    ctx = {"names": names, "nested": nested and len(ds.folds) >= 3, "meta": meta, "units": units}
    options = {"physical": physical}
    suffix = "" if ds.dense else " (measured rows)"
    cands: list[Candidate] = []
    fitted: dict[str, Any] = {}
    for entry in REGISTRY:
        if (
            (entry.every_row and not ds.dense)
            or (entry.needs_inputs and not names)
            or (entry.option is not None and not options[entry.option])
            or len(ds.folds) < entry.min_folds
            or len(names) < entry.min_inputs
        ):
            continue
        say(entry.progress + suffix)
        c, f = entry.evaluate(ds, ctx)
        c.forward_decides = ds.unit == "cycle"
        cands.append(c)
        fitted[c.name] = f

    # with probes planned, a candidate is judged by its closed loop on held-out folds
    plans: dict[str, closedloop.Plan | None] = {}
    intervals = tuple(
        sorted({*closedloop.INTERVALS_S, *([probe_every_s] if probe_every_s else [])})
    )
    target = probe_target_um if probe_target_um is not None else closedloop.DEFAULT_TARGET_UM

    def loop_of(c: Candidate) -> closedloop.Plan | None:
        if c.name not in plans:
            tau = c.slowest_tau_s or (
                max(c.model.time_constants_s(0.0)) if c.model is not None else 0.0
            )
            ok = c.held_out_residual_um is not None and tau > 0 and len(ds.folds) >= 2 and ds.dense
            planned = (
                closedloop.plan(ds.time_s, c.held_out_residual_um, ds.folds, tau, target, intervals)
                if ok
                else None
            )
            plans[c.name] = planned
            if planned is not None:
                c.details["closed_loop_rms_um"] = {
                    f"{r['interval_s']:.0f}": round(r["rms_um"], 4) for r in planned.table[1:]
                }
        return plans[c.name]

    def score(c: Candidate) -> float:
        if probe_every_s is None:
            return c.decisive_rms_um
        p = loop_of(c)
        return math.inf if p is None else p.rms_at(probe_every_s)

    what = (
        "held-out RMS (the worse of nested and forward)"
        if probe_every_s is None
        else f"closed-loop RMS (a probe every {probe_every_s:g} s)"
    )
    if probe_every_s is not None:
        say(f"scoring every candidate in closed loop, a probe every {probe_every_s:g} s")
    bar = score(cands[0])
    for c in cands:
        if c.family == "reference":
            continue
        if c is not cands[0] and score(c) > bar:
            c.refusals.append(
                f"{what} {score(c):.2f} um is worse than the exponential baseline's {bar:.2f} um"
            )
        c.accepted = not c.refusals

    # build the speed-only models the choice may need
    for c in cands:
        if c.family == "speed" and c.accepted and c.model is None:
            c.model, refusal = rb.to_model_or_refuse(fitted[c.name], c.name, fit={}, **meta)
            if refusal:
                c.accepted, c.refusals = False, [*c.refusals, refusal]
    judged = growth_direction is not None or measured_span_um is not None  # fit_data's callers
    for c in cands:
        if c.family == "speed" and c.accepted and c.model is not None:
            # a time scale no spindle has falls to the next candidate, not the whole fit
            why = time_constant_refusal(c.model)
            if why is None and judged:
                why = steady_growth_refusal(c.model, growth_direction, measured_um=measured_span_um)
            if why is not None:
                c.accepted, c.refusals = False, [*c.refusals, f"physics: {why}"]
    speed = [c for c in cands if c.family == "speed" and c.accepted and c.model is not None]
    fallback_note: str | None = None
    if not speed:
        # a model with inputs that passed needs a speed-only stand-in, not a refusal
        safe = None
        if any(c.family == "inputs" and c.accepted for c in cands):
            safe = conservative_fallback(ds, fitted, growth_direction, measured_span_um, meta)
        if safe is None:
            raise CalibrationError(
                "no speed-only candidate passed the checks: "
                + "; ".join(
                    f"{c.name}: {', '.join(c.refusals)}" for c in cands if c.family == "speed"
                )
            )
        failed = [c.name for c in cands if c.family == "speed"]
        fallback_note = (
            f"no speed-only candidate passed the checks ({', '.join(failed)}); the fallback, used "
            f"only when an input fails, is {safe.name}: {safe.description}"
        )
        warnings.append(fallback_note)
        cands.append(safe)
        speed = [safe]
    splits = fl.forward_of(ds.time_s, ds.speed_rpm, ds.folds, ds.unit == "cycle", ds.measured)
    if probe_every_s is None and ds.unit == "cycle":
        chosen, final, model, reason = _choose_by_folds(
            cands, speed, fitted, ds, splits, warnings, fallback_note, len(names), units, meta
        )
        paper = next((c for c in cands if c.family == "reference"), None)
        if paper is not None and math.isfinite(paper.cv_rms_um):  # for the comparison
            reason += f" For comparison, the paper's OLS scores {paper.cv_rms_um:.2f} um."
        return _finish(
            ds,
            cands,
            chosen,
            final,
            model,
            reason,
            warnings,
            fitted,
            loop_of,
            probe_target_um,
            cpu0,
            say,
        )
    best = min(speed, key=score)
    chosen = next(c for c in speed if score(c) <= score(best) * (1 + PARSIMONY))
    kept = None if probe_every_s is not None else _physical_within_noise(speed, chosen, ds)
    if kept is not None:
        chosen, kept_why = kept
    basis = "nested " if chosen.nested_rms_um is not None else ""
    ahead = f", forward {chosen.forward_rms_um:.2f} um" if chosen.forward_rms_um is not None else ""
    if probe_every_s is None:
        figure = (
            "held-out free-run RMS (the worse of nested and forward)"
            if chosen.decisive_rms_um != chosen.honest_rms_um
            or len(chosen.forward_folds_rms_um) >= MIN_FORWARD_FOLDS
            else f"{basis}{ds.scheme} free-run RMS"
        )
        reason = (
            f"{chosen.name} has the lowest {figure} among the speed-only candidates, "
            f"{chosen.decisive_rms_um:.2f} um ({basis}{ds.scheme} {chosen.honest_rms_um:.2f} um{ahead})"
        )
    else:
        reason = (
            f"{chosen.name} has the lowest {ds.scheme} {what} among the speed-only candidates "
            f"({', '.join(f'{c.name} {score(c):.2f} um' for c in speed)}); its {basis}free-run RMS "
            f"{chosen.honest_rms_um:.2f} um{ahead}"
        )
    if kept is not None:
        reason += f" ({kept_why})"
    elif chosen is not best:
        reason += f" (within {PARSIMONY:.0%} of {best.name}, and simpler)"
    model = _with_record(chosen, ds, reason)
    final = chosen
    with_inputs = _best_with_inputs(
        [c for c in cands if c.family == "inputs"], score, static_first=probe_every_s is None
    )
    if with_inputs is not None:
        # one cycle: the static structure keeps the inputs; its few blocks cannot show speed
        # alone better (on the real record, dropping them erred 9.9 um on the next half cycle)
        keep_inputs = probe_every_s is None and with_inputs.name == STATIC and with_inputs.accepted
        if keep_inputs:
            reason += (
                f"; with inputs {score(with_inputs):.2f} um: {STATIC} keeps the {len(names)} "
                f"input(s) (one cycle: too few forward folds to drop them for speed alone), "
                f"{chosen.name} stands in when one fails"
            )
        model, final, reason = with_inputs_or_not(
            with_inputs,
            chosen,
            fitted[with_inputs.name],
            model,
            ds,
            reason,
            warnings,
            score=score,
            what=what,
            n_inputs=len(names),
            units=units,
            meta=meta,
            judged=keep_inputs,
        )
    if fallback_note is not None:
        reason += f"; {fallback_note}"
    paper = next((c for c in cands if c.family == "reference"), None)
    if paper is not None and math.isfinite(paper.cv_rms_um):
        reason += f"; the paper's OLS scores {paper.cv_rms_um:.2f} um"
    return _finish(
        ds,
        cands,
        chosen,
        final,
        model,
        reason,
        warnings,
        fitted,
        loop_of,
        probe_target_um,
        cpu0,
        say,
    )


def _finish(
    ds: Dataset,
    cands: list[Candidate],
    chosen: Candidate,
    final: Candidate,
    model: Any,
    reason: str,
    warnings: list[str],
    fitted: Mapping[str, Any],
    loop_of: Callable[[Candidate], closedloop.Plan | None],
    probe_target_um: float | None,
    cpu0: float,
    say: Callable[[str], None],
) -> Identification:
    """What every choice ends with: the line on speed alone, the derived quantities, the
    closed-loop plan and its observer."""
    if final is not chosen and chosen.name == baseline.MONOTONE_NAME:
        # the model file says why its fallback is the conservative one
        model = with_fit(model, fallback=next(w for w in warnings if "no speed-only" in w))
    statement = _speed_alone(ds, chosen, final, fitted.get("ridge"), loop_of if ds.dense else None)
    if statement:
        warnings.append(statement)
    derived = (
        rb.derived(fitted[final.name], ds)
        if isinstance(fitted.get(final.name), rb.RidgeFit) and final.name != baseline.NAME
        else []
    )
    loop = None
    if probe_target_um is not None and ds.dense:
        say("planning the closed loop (probe intervals)")
        loop = loop_of(final)
    if loop is not None:
        fb = model.fallback
        fb_loop = loop_of(chosen) if fb is not None else None
        model = with_fit(model, observer=loop.observer)
        if fb is not None and fb_loop is not None:  # the fallback keeps the observer fitted to it
            model = model.model_copy(update={"fallback": with_fit(fb, observer=fb_loop.observer)})
    return Identification(
        ds, cands, final, model, reason, warnings, time.process_time() - cpu0, derived, loop
    )


MIN_FLEXIBLE_FOLDS = 5
"""Forward folds a structure more flexible than :data:`STATIC` needs to displace it (four
cycles of past). On the real record's half-cycle origins, every flexible structure that won
its duel on three or four folds erred more on the next half cycle than the static one (7.5-8.0
against 5.8-6.3 um at 2.5 cycles; 2.6-5.8 against 1.5-3.3 um at 3.5 cycles), and every one that
won on five or six folds erred less (0.8-2.3 against 1.4-2.7 um)."""
MIN_PAIRED = 3
"""Folds a one-standard-error comparison needs; with fewer forward folds the whole-cycle
leave-one-out folds join them."""
TAIL = 0.10
"""A more flexible structure that lowers the worst forward fold by more than this share, with a
median no more than this share higher, is taken even within one standard error: one stretch
predicted badly is what the folds' spread hides (on the real record the static structure missed
one heat-up by 16 um where the banks missed it by 5)."""


def _fold_mse(
    residual: np.ndarray | None, folds: Sequence[fl.Fold], rows: np.ndarray
) -> np.ndarray:
    """Mean square [um²] of ``residual`` on the ``rows`` of each fold (NaN where none)."""
    out = np.full(len(folds), np.nan)
    if residual is None:
        return out
    for i, (a, b) in enumerate(folds):
        ok = rows[a:b] & ~np.isnan(residual[a:b])
        if ok.any():
            r = finite(residual[a:b][ok])  # a diverged free run scores huge
            out[i] = float(np.mean(r * r))
    return out


def _one_se(d: np.ndarray) -> tuple[float, float]:
    """The mean of paired per-fold differences and its standard error: the one-standard-error
    rule's two figures (Hastie, Tibshirani and Friedman, section 7.10)."""
    return float(d.mean()), float(d.std(ddof=1) / math.sqrt(d.size))


@dataclass(frozen=True)
class Duel:
    """A more flexible candidate against the simpler one standing, fold by fold."""

    rich: Candidate
    simple: Candidate
    won: bool
    text: str


def _duel(
    rich: Candidate,
    simple: Candidate,
    splits: Sequence[fl.Split],
    ds: Dataset,
    need: int = 0,
) -> Duel:
    """Whether ``rich`` displaces ``simple``: its per-fold mean square lower on average by more
    than one standard error of the paired differences (Hastie, Tibshirani and Friedman, section
    7.10), and neither its median nor its worst forward fold worse than the simpler one's by more
    than :data:`PARSIMONY`; or, the worst fold deciding, its mean square lower on average over
    the forward folds, its worst forward fold lower by more than :data:`TAIL` and its median no
    more than TAIL higher.
    The folds are the forward ones; with fewer than :data:`MIN_PAIRED` the whole-cycle
    leave-one-out folds join them in the paired difference, and with fewer than that in all,
    ``rich`` must be lower on every fold by more than PARSIMONY. With fewer forward folds than
    ``need``, ``simple`` stands."""
    targets = [f for _, f in splits]
    fa = _fold_mse(rich.forward_residual_um, targets, ds.measured)
    fb = _fold_mse(simple.forward_residual_um, targets, ds.measured)
    ok = np.isfinite(fa) & np.isfinite(fb)
    fa, fb = fa[ok], fb[ok]
    if fa.size < need:
        return Duel(
            rich,
            simple,
            False,
            f"{rich.name} against {simple.name}: {fa.size} forward fold(s), fewer than the "
            f"{need} a structure more flexible than {simple.name} needs",
        )
    pa, pb, where = fa, fb, f"{fa.size} forward fold(s)"
    if fa.size < MIN_PAIRED:
        la = _fold_mse(rich.held_out_residual_um, ds.folds, ds.measured)
        lb = _fold_mse(simple.held_out_residual_um, ds.folds, ds.measured)
        both = np.isfinite(la) & np.isfinite(lb)
        pa, pb = np.concatenate([fa, la[both]]), np.concatenate([fb, lb[both]])
        where += f" and {int(both.sum())} leave-one-{ds.unit}-out fold(s)"
    if pa.size == 0:
        return Duel(rich, simple, False, f"{rich.name}: no fold to compare on")
    wa, wb = (fa, fb) if fa.size else (pa, pb)
    med_a, med_b = math.sqrt(float(np.median(wa))), math.sqrt(float(np.median(wb)))
    worst_a, worst_b = math.sqrt(float(wa.max())), math.sqrt(float(wb.max()))
    d = pb - pa
    if d.size >= MIN_PAIRED:
        gain, se = _one_se(d)
        better = gain > se
        how = (
            f"lower by {gain:.2f} um² in mean square per fold, "
            f"{'more' if better else 'less'} than one standard error ({se:.2f} um²) over {where}"
        )
    else:
        better = bool(np.all(np.sqrt(pa) < np.sqrt(pb) * (1 - PARSIMONY)))
        how = f"{'lower' if better else 'not lower'} on every one of {where} by {PARSIMONY:.0%}"
    tail_ok = med_a <= med_b * (1 + PARSIMONY) and worst_a <= worst_b * (1 + PARSIMONY)
    figures = (
        f"median {med_a:.2f} against {med_b:.2f} um, worst {worst_a:.2f} against {worst_b:.2f} um"
    )
    if better and not tail_ok:
        how += f", but its median or worst fold is higher by more than {PARSIMONY:.0%}"
    won = better and tail_ok
    ahead = float((wb - wa).mean())  # the forward folds' own mean gain
    if not won and ahead > 0 and worst_a < worst_b * (1 - TAIL) and med_a <= med_b * (1 + TAIL):
        won = True
        how += (
            f"; its worst forward fold is lower by more than {TAIL:.0%} with the median within "
            f"{TAIL:.0%}: the worst fold decides"
        )
    return Duel(rich, simple, won, f"{rich.name} against {simple.name}: {figures}; {how}")


def _forward_figures(c: Candidate, splits: Sequence[fl.Split], ds: Dataset) -> tuple[float, float]:
    """(median, worst) forward fold RMS [um] of ``c`` on ``splits``; NaN without."""
    f = _fold_mse(c.forward_residual_um, [t for _, t in splits], ds.measured)
    f = f[np.isfinite(f)]
    if not f.size:
        return math.nan, math.nan
    return math.sqrt(float(np.median(f))), math.sqrt(float(f.max()))


def _walk(
    order: Sequence[Candidate], splits: Sequence[fl.Split], ds: Dataset, need: int = 0
) -> tuple[Candidate, list[Duel]]:
    """Simple to flexible: the first stands, each next one displaces the one standing only when
    it wins their :func:`_duel` (on ``need`` forward folds or more)."""
    standing, duels = order[0], []
    for c in order[1:]:
        duel = _duel(c, standing, splits, ds, need)
        duels.append(duel)
        if duel.won:
            standing = c
    return standing, duels


def _choose_by_folds(
    cands: list[Candidate],
    speed: list[Candidate],
    fitted: Mapping[str, Any],
    ds: Dataset,
    splits: Sequence[fl.Split],
    warnings: list[str],
    fallback_note: str | None,
    n_inputs: int,
    units: Mapping[str, str] | None,
    meta: Mapping[str, Any],
) -> tuple[Candidate, Candidate, Any, str]:
    """The choice when the folds are cycles: structures walked from simple to flexible
    (:data:`COMPLEXITY`), a flexible one taken only when it wins its :func:`_duel` against the
    one standing; the speed-only ones first (the fallback), then the inputs from it. Returns
    (the speed-only choice, the final choice, its model, the reason in one paragraph)."""

    def rank(c: Candidate) -> int:
        return COMPLEXITY.get(c.name, len(COMPLEXITY))

    chosen, speed_duels = _walk(sorted(speed, key=rank), splits, ds)
    rich = sorted((c for c in cands if c.family == "inputs" and c.accepted), key=rank)
    pool = [*sorted(speed, key=rank), *rich]
    static = next((c for c in rich if c.name == STATIC), None)
    if static is not None:  # the inputs kept: never dropped for speed alone on a few folds
        flexible = [c for c in rich if c is not static]
        final, input_duels = _walk([static, *flexible], splits, ds, MIN_FLEXIBLE_FOLDS)
    else:
        final, input_duels = _walk([chosen, *rich], splits, ds) if rich else (chosen, [])
    for duel in input_duels:
        if duel.rich is not final and not duel.won:  # lost to the one standing
            duel.rich.accepted = False
            duel.rich.refusals.append(duel.text)
        elif duel.won and duel.simple is not chosen and duel.simple is not final:
            duel.simple.accepted = False
            duel.simple.refusals.append(duel.text)
    model = _with_record(
        chosen, ds, "speed-only fallback: " + _paragraph(chosen, speed, speed_duels, splits, ds)
    )
    reason = _paragraph(
        final,
        pool,
        speed_duels + input_duels,
        splits,
        ds,
    )
    if final is not chosen:
        reason += f" {chosen.name} stands in, speed only, when an input fails."
    if fallback_note is not None:
        reason += f" Note: {fallback_note}."
    if final is chosen:
        model = _with_record(chosen, ds, reason)
        return chosen, chosen, model, reason
    model, kept, reason = with_inputs_or_not(
        final,
        chosen,
        fitted[final.name],
        model,
        ds,
        reason,
        warnings,
        score=lambda c: c.decisive_rms_um,
        what="",
        n_inputs=n_inputs,
        units=units,
        meta=meta,
        judged=True,
    )
    return chosen, kept, model, reason


def _paragraph(
    final: Candidate,
    pool: Sequence[Candidate],
    duels: Sequence[Duel],
    splits: Sequence[fl.Split],
    ds: Dataset,
) -> str:
    """What was chosen, over what, and why, in one paragraph a user can read."""
    med, worst = _forward_figures(final, splits, ds)
    others = [c for c in pool if c is not final]
    ranked = sorted(
        others, key=lambda c: _forward_figures(c, splits, ds)[0] if splits else c.honest_rms_um
    )
    runner = next((c for c in ranked if math.isfinite(_forward_figures(c, splits, ds)[0])), None)
    text = (
        f"{final.name} chosen among {len(pool)} candidate(s) "
        f"({', '.join(c.name for c in pool)}), judged in free run on {len(splits)} forward fold(s) "
        f"(origins every half cycle, each predicted by a model fitted on the rows before it) and "
        f"{len(ds.folds)} leave-one-{ds.unit}-out fold(s)."
    )
    if math.isfinite(med):
        text += f" Forward RMS per fold: median {med:.2f} um, worst {worst:.2f} um"
        text += f" (leave-one-{ds.unit}-out {final.honest_rms_um:.2f} um)."
    else:
        text += f" Leave-one-{ds.unit}-out RMS {final.honest_rms_um:.2f} um."
    if runner is not None:
        rm, rw = _forward_figures(runner, splits, ds)
        text += f" Runner-up: {runner.name}, median {rm:.2f} um, worst {rw:.2f} um."
    text += (
        " Rule: structures are tried from simple to flexible, and a more flexible one is taken "
        "only when it is better by more than one standard error of the paired per-fold "
        f"difference and its median and worst forward folds are no more than {PARSIMONY:.0%} "
        f"higher, or when it lowers the worst forward fold by more than {TAIL:.0%} with a median "
        f"no more than {TAIL:.0%} higher. With inputs, {STATIC} stands first (the inputs are "
        f"kept), and a more flexible structure needs {MIN_FLEXIBLE_FOLDS} forward folds or more."
    )
    decisive = [d for d in duels if d.rich is final and d.won] + [
        d for d in duels if d.simple is final and d.rich is runner
    ]
    if decisive:
        text += " Deciding: " + "; ".join(d.text for d in decisive) + "."
    return text


def conservative_fallback(
    ds: Dataset,
    fitted: Mapping[str, Any],
    growth_direction: int | None,
    measured_span_um: float | None,
    meta: Mapping[str, Any],
) -> Candidate | None:
    """The speed-only stand-in for a model with inputs when every speed-only candidate failed the
    checks: one first-order state with its steady growth held to rise with speed
    (:func:`~calibration.estimators.baseline.fit_monotone`), its time constant the one of the
    exponential baseline's grid with the lowest leave-one-fold-out RMS among those that pass the
    physics check. None when none does (a calibration whose growth speed cannot explain in the
    measured direction at any time constant)."""
    base = fitted.get(baseline.NAME)
    if not isinstance(base, rb.RidgeFit):
        return None
    n = base.speed_max_rpm / 1000.0  # the sign the data leans to, at the top speed
    top = float(base.speed_gains_um.sum(axis=1) @ np.array([n, n * n]))
    direction = growth_direction if growth_direction is not None else (1 if top >= 0 else -1)
    best: tuple[float, float] | None = None
    for tau in rb.BASELINE_TAUS_S:
        if tau < ds.dt_s:
            continue
        res = baseline.fit_monotone(ds, replace(base, grid=rb.TauGrid((tau,))), direction)
        model, refusal = rb.to_model_or_refuse(res, "x", fit={"cv_rms_um": res.cv_rms_um})
        if model is None or refusal:
            continue
        if steady_growth_refusal(model, growth_direction, measured_um=measured_span_um) is None:
            if best is None or res.cv_rms_um < best[1]:
                best = (tau, res.cv_rms_um)
    if best is None:
        return None
    splits = fl.forward_of(ds.time_s, ds.speed_rpm, ds.folds, ds.unit == "cycle", ds.measured)
    res = baseline.fit_monotone(ds, replace(base, grid=rb.TauGrid((best[0],))), direction, splits)
    c = _from_ridge(baseline.MONOTONE_NAME, "speed", baseline.MONOTONE_DESCRIPTION, res, ds)
    c.details["tau_s"] = best[0]
    c.forward_decides = ds.unit == "cycle"
    c.model, refusal = rb.to_model_or_refuse(res, c.name, fit={}, **meta)
    if c.model is None or refusal:
        return None
    c.model = _with_record(c, ds, "conservative fallback")
    c.accepted = True
    return c


def _paired_fold_mse_um2(
    simple: Candidate, rich: Candidate, ds: Dataset
) -> tuple[float, float, int] | None:
    """The mean over folds of (simple's held-out MSE - rich's) on the rows both scored, its
    standard error, and the folds; None below 3 folds."""
    a, b = simple.held_out_residual_um, rich.held_out_residual_um
    if a is None or b is None:
        return None
    both = ds.measured & np.isfinite(a) & np.isfinite(b)  # the rows both scored
    d = _fold_mse(a, ds.folds, both) - _fold_mse(b, ds.folds, both)
    d = d[np.isfinite(d)]
    if d.size < MIN_PAIRED:
        return None
    return (*_one_se(d), int(d.size))


def _physical_within_noise(
    speed: Sequence[Candidate], chosen: Candidate, ds: Dataset
) -> tuple[Candidate, str] | None:
    """The physical form instead of a flexible candidate that beats it by less than the noise of
    the comparison: one standard error of their paired per-fold difference in held-out MSE (the
    one-standard-error rule; Hastie, Tibshirani and Friedman, section 7.10). It has a handful of
    parameters, each with a physical meaning, against a bank's dozens: on a tool setter's few
    noisy measurements the flexible fit won by a hair in CV and erred 2-3x more held out. Judged
    on the backward figure, so only where the forward one does not decide."""
    phys = next((c for c in speed if c.name == output_error.NAME), None)
    if phys is None or chosen is phys or chosen.name == baseline.NAME:
        return None
    if any(c.decisive_rms_um != c.honest_rms_um for c in (phys, chosen)):
        return None
    paired = _paired_fold_mse_um2(phys, chosen, ds)
    if paired is None:
        return None
    gain, se, k = paired
    if gain > se:
        return None
    return phys, (
        f"{chosen.name} is lower by {chosen.honest_rms_um:.2f} against {phys.honest_rms_um:.2f} um, "
        f"a gain in held-out MSE of {gain:.3f} um² within one standard error ({se:.3f} um² over "
        f"{k} {ds.unit}s): the physical form, with fewer parameters, is kept"
    )


def _best_with_inputs(
    cands: Sequence[Candidate], score: Callable[[Candidate], float], static_first: bool = False
) -> Candidate | None:
    """The structure for the inputs, chosen by data. The first (a bank per input) stands unless
    another beats it by more than PARSIMONY: a structure that shares strength must earn its
    place (on the virtual plant, three independent sensors lost to their own principal
    components by a hair in CV and by 40 % on a held-out run). The others say why not.
    ``static_first`` (a log of one cycle): ``ridge+static`` when it passed, the others refused:
    fewer forward folds than :data:`MIN_FLEXIBLE_FOLDS` cannot tell a flexible structure that
    holds from one that fits the few blocks (on the real record, fitted on one cycle, the
    choice by the lowest figure erred up to 25 um on the next half cycle)."""
    if not cands:
        return None
    static = next((c for c in cands if c.name == STATIC and c.accepted), None)
    if static_first and static is not None:
        for c in cands:
            if c is not static and c.accepted:
                c.accepted = False
                c.refusals.append(
                    f"one cycle: fewer than {MIN_FLEXIBLE_FOLDS} forward folds to choose a more "
                    f"flexible structure than {STATIC} by"
                )
        return static
    ok = [c for c in cands if c.accepted]
    default = cands[0]
    if not ok:
        return default
    best = min(ok, key=score)
    pick = (
        best
        if (not default.accepted or score(best) < score(default) * (1 - PARSIMONY))
        else default
    )
    for c in ok:
        if c is not pick:
            c.accepted = False
            why = "lower" if score(pick) < score(c) else f"the plain bank, within {PARSIMONY:.0%}"
            c.refusals.append(
                f"{pick.name} is {why} ({score(pick):.2f} um against {score(c):.2f} um)"
            )
    return pick


SPEED_ALONE_SHARE = 0.5
"""Speed alone cannot carry a log when its best held-out error is this share of the
uncompensated error or more."""


def _speed_alone(
    ds: Dataset,
    chosen: Candidate,
    final: Candidate,
    ridge: Any,
    loop_of: Callable[[Candidate], closedloop.Plan | None] | None,
) -> str | None:
    """One line when speed alone cannot carry the log: the speed-only model's held-out error
    against the uncompensated one, how much alpha alone moves its forward error, and the
    cheapest remedy with its figure (the logged temperatures, a probe interval, a longer
    record)."""
    rows = ds.measured & np.isfinite(ds.elongation_um)
    if not rows.any():
        return None
    raw = float(np.sqrt(np.mean(ds.elongation_um[rows] ** 2)))
    if chosen.decisive_rms_um < SPEED_ALONE_SHARE * raw:
        return None
    line = (
        f"speed alone cannot carry this log: the best speed-only model ({chosen.name}) errs "
        f"{chosen.decisive_rms_um:.1f} um held out, against {raw:.1f} um uncompensated"
    )
    spread = (
        [v for v in ridge.forward_rms_by_alpha_um if math.isfinite(v)]
        if isinstance(ridge, rb.RidgeFit)
        else []
    )
    if spread:
        line += (
            f"; alpha alone moves the speed-only ridge's forward error from {min(spread):.1f} to "
            f"{max(spread):.1f} um"
        )
    if final is not chosen:
        return line + (
            f". The logged inputs carry it ({final.decisive_rms_um:.2f} um held out): keep "
            "them connected, and probe when one fails"
        )
    plan = loop_of(chosen) if loop_of is not None else None
    if plan is not None and plan.recommended_s is not None:
        return line + (
            f". Cheapest remedy: probe every {plan.recommended_s / 60:.0f} min "
            f"({plan.rms_at(plan.recommended_s):.2f} um RMS held out); or log temperatures"
        )
    tau_h = chosen.slowest_tau_s / 3600 if chosen.slowest_tau_s else 0.0
    return line + (
        ". Remedies: log temperatures (--inputs), probe often (fit --probe-every), or record "
        + (
            f"more cycles than the slowest time constant ({tau_h:.0f} h) spans"
            if tau_h
            else "more cycles"
        )
    )


def with_inputs_or_not(
    c_in: Candidate,
    chosen: Candidate,
    ridge_in: Any,
    model: Any,
    ds: Dataset,
    reason: str,
    warnings: list[str],
    *,
    score: Callable[[Candidate], float],
    what: str,
    n_inputs: int,
    units: Any,
    meta: Mapping[str, Any],
    judged: bool = False,
) -> tuple[Any, Candidate, str]:
    """The model with inputs when it beats the chosen speed-only one by ``score`` (``what`` names
    the figure), with that one as its fallback; else the speed-only one, and why. Returns
    (model, the candidate chosen, the reason); refusals go to ``c_in`` and ``warnings``.
    ``judged``: the choice was made already (the reason says why); the model is built."""
    if not judged and c_in.accepted and score(c_in) >= score(chosen):
        c_in.accepted = False
        c_in.refusals.append(
            f"no better than speed only ({what} {score(c_in):.2f} um against "
            f"{score(chosen):.2f} um)"
        )
    if c_in.accepted:
        c_in.model, refusal = rb.to_model_or_refuse(
            ridge_in, c_in.name, units=units, fallback=model, fit={}, **meta
        )
        if refusal:
            c_in.accepted, c_in.refusals = False, [*c_in.refusals, refusal]
    if not c_in.accepted:
        warnings.append(f"the inputs did not help: {'; '.join(c_in.refusals)}")
        return model, chosen, reason + f"; inputs refused: {'; '.join(c_in.refusals)}"
    if not judged:
        reason += (
            f"; with inputs {score(c_in):.2f} um: the model uses {n_inputs} input(s), "
            f"{chosen.name} stands in when one fails"
        )
    policy, span, residual, why = extrapolation(c_in, chosen)
    c_in.details["extrapolation"] = why
    c_in.model = c_in.model.model_copy(update={"extrapolation": policy, "blend_span": span})
    return _with_record(c_in, ds, f"{reason}; {why}", forward=residual), c_in, reason


BLEND_SPANS = (0.25, 1.0)
"""A blend hands over to the fallback completely at this many spans outside the trained range."""


def extrapolation(
    c_in: Candidate, fallback: Candidate
) -> tuple[str, float, np.ndarray | None, str]:
    """What the model does when its inputs leave the trained range, chosen by data: on the rows
    of the forward splits whose inputs left the range the past saw, the RMS of the prediction
    with the gains carried on (``linear``), with the inputs held at the range's ends (``clip``)
    and blended toward the speed-only fallback (``blend``, at each of :data:`BLEND_SPANS`).
    ``linear`` stands unless another is lower by more than PARSIMONY, and is kept without a
    choice below :data:`MIN_FORWARD_FOLDS` folds predicted forward or :data:`MIN_BAND_ROWS`
    rows outside. Returns (policy, blend
    span, the forward residual under it, why in one line)."""
    r_lin, r_clip, dist = (
        c_in.forward_residual_um,
        c_in.forward_clipped_residual_um,
        c_in.forward_distance,
    )
    if r_lin is None or r_clip is None or dist is None:
        return (
            "linear",
            1.0,
            r_lin,
            "outside the trained range: linear (no forward split to choose by)",
        )
    if not c_in.forward_decides:
        # blocks of one cycle: a block predicted forward lies at speeds and temperatures its past
        # never ran, which the model fitted on the whole cycle does not reach (on the real
        # record, held at the range's ends by such a choice, the next half cycle erred 5.6 um
        # against 3.3 carried on)
        return (
            "linear",
            1.0,
            r_lin,
            "outside the trained range: linear (one cycle: its blocks are no forward split to "
            "choose by)",
        )
    d = np.nan_to_num(dist, nan=0.0)
    out = np.isfinite(r_lin) & (d > 0)
    if len(c_in.forward_folds_rms_um) < MIN_FORWARD_FOLDS:
        return (
            "linear",
            1.0,
            r_lin,
            (
                f"outside the trained range: linear ({len(c_in.forward_folds_rms_um)} "
                "fold(s) predicted forward: too few to choose by)"
            ),
        )
    if out.sum() < MIN_BAND_ROWS:
        return (
            "linear",
            1.0,
            r_lin,
            (
                f"outside the trained range: linear ({int(out.sum())} forward row(s) left "
                "the range: too few to choose by)"
            ),
        )
    options: list[tuple[str, float, np.ndarray]] = [("linear", 1.0, r_lin), ("clip", 1.0, r_clip)]
    r_fb = fallback.forward_residual_um
    if r_fb is not None:
        for span in BLEND_SPANS:
            w = np.minimum(d / span, 1.0)
            options.append(
                ("blend", span, np.where(np.isfinite(r_fb), (1 - w) * r_lin + w * r_fb, r_lin))
            )
    rms = [float(np.sqrt(np.mean(r[out] ** 2))) for _, _, r in options]
    best = int(np.argmin(rms))
    pick = best if rms[best] < rms[0] * (1 - PARSIMONY) else 0

    def name(k: int) -> str:
        return options[k][0] + (f" {options[k][1]:g} span" if options[k][0] == "blend" else "")

    figures = ", ".join(f"{name(k)} {v:.2f} um" for k, v in enumerate(rms))
    return (
        options[pick][0],
        options[pick][1],
        options[pick][2],
        (
            f"outside the trained range: {name(pick)}, by forward RMS over the {int(out.sum())} row(s) "
            f"that left it ({figures})"
        ),
    )


def _expected(c: Candidate, ds: Dataset, forward: np.ndarray | None = None) -> ExpectedError | None:
    """The error to expect by speed band, inside and outside the trained input range
    (:func:`~calibration.metrics.expected_error`); ``forward`` is the forward residual under the
    extrapolation chosen (default: the candidate's own)."""
    top = float(np.max(np.abs(ds.speed_rpm)))
    if not c.forward_decides:
        # blocks of one cycle: a block predicted forward lies at speeds its past never ran, an
        # extrapolation the model fitted on the whole cycle does not make (a physical form fitted
        # on the low-speed blocks erred 1000 um there, the model itself 1.4 um on a day's work)
        forward_res, folds = None, 0
    else:
        forward_res = c.forward_residual_um if forward is None else forward
        folds = len(c.forward_folds_rms_um)
    return expected_error(
        forward_res,
        c.held_out_residual_um,
        ds.speed_rpm,
        top,
        c.forward_distance,
        forward_folds=folds,
        folds=ds.folds,  # one cycle's rows err together: the band is taken per fold
        time_s=ds.time_s,
        memory_s=memory_s_of(c.model),
    )


def _with_record(c: Candidate, ds: Dataset, reason: str, forward: np.ndarray | None = None) -> Any:
    """The candidate's model with its fit record: built here, once, for every model fit writes."""
    entries: dict[str, Any] = {
        "schema_version": FIT_SCHEMA_VERSION,
        "method": c.name,
        "scored_by": f"{ds.scheme} free run",
        "folds": len(ds.folds),
        "cv_rms_um": round(c.cv_rms_um, 4),
        "cv_max_abs_um": round(c.cv_max_abs_um, 4),
        "folds_rms_um": tuple(round(v, 4) for v in c.folds_rms_um),
        "reason": reason,
        "expected_error": _expected(c, ds, forward),
    }
    if c.nested_rms_um is not None:
        entries["nested_rms_um"] = round(c.nested_rms_um, 4)
    if c.forward_rms_um is not None:
        entries["forward_rms_um"] = round(c.forward_rms_um, 4)
    if "alpha" in c.details:
        entries["alpha"] = c.details["alpha"]
        entries["grid"] = c.details["grid"]
    # entries left None are not written: a record states what the fit measured
    record = FitRecord.of({k: v for k, v in entries.items() if v is not None})
    return c.model.model_copy(update={"fit": record})
