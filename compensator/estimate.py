"""The estimate the offset follows, one object for the service and for replay. Pure: no I/O.

:class:`Estimate` holds what a spindle's estimate is made of: the model as loaded, its
speed-only fallback (the model itself when it has no inputs), the observer that fuses probe
measurements (optional) and the speed policy above the calibrated range. Its state,
:class:`EstimateState`, is one immutable value that saves and restores as a whole
(:meth:`Estimate.state_dict`, :meth:`Estimate.parse_saved`, :meth:`Estimate.resume`).

Each cycle the caller reads the speed and the inputs (or fails to) and calls
:meth:`Estimate.step`; a measurement is fused with :meth:`Estimate.measure`. The runtime
(``thermocomp.runtime.spindle``) does this with the controller's values and keeps the I/O,
alarms and events; replay (``calibration.replay``) does it over a journal's rows. Both get the
same numbers because there is only this code.

What it decides, cycle by cycle:

- the speed: clamped to the top of the calibrated range (``over_range = "clamp"``), or used as
  read (``"extrapolate"``); either way :attr:`Step.over_range` says so;
- the model with inputs: used while every input is read, valid and not stale (unchanged for
  ``input_stale_s``); after a fault the speed-only fallback stands in until the inputs have been
  good for ``input_recover_s`` again, and the model with inputs restarts from the fallback's
  elongation, so the switch does not jump. The fallback is stepped every cycle;
- the observer: its state rides on the speed-only model's (:class:`~compensator.fusion.FusedState`);
  at a switch between the two models the bias is rebased so that the estimate does not jump.
  A measurement is compared with the estimate of this cycle or of the last one, whichever ran
  slower (a tool setter measures at rest; the counter may be seen only once the spindle runs
  again, and the elastic part follows the speed at once).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from .errors import ModelError
from .fusion import FusedPredictor, FusedState
from .modelbase import SAVED_LIMIT_UM, saved_numbers
from .observer import ObserverConfig, ObserverState, Update
from .predictor import Predictor
from .units import RANGE_TOLERANCE

OverRange = Literal["clamp", "extrapolate"]

MAX_SPEED_MARGIN = 0.1
"""A speed more than this share above the spindle's stated maximum is no reading of it."""

UNSTATED_MAX_FACTOR = 2.0
"""Without a stated maximum: a speed above this many times the calibrated top is no reading."""


@dataclass(frozen=True)
class EstimateState:
    """Everything the estimate remembers from one cycle to the next."""

    core: Any
    """The speed-only model's state; a :class:`FusedState` (with the observer's) when fused."""
    inputs: Any = None
    """The model with inputs' state while it is the one in use; None on the fallback."""
    references: Mapping[str, float] | None = None
    """Input references from a cold start (models whose inputs count from there)."""
    input_cold: bool = False
    """No estimate of our own yet: the model with inputs starts at its equilibrium."""
    saved_input: tuple[Any, float] | None = None
    """A saved input state and its wall time [s], resumed once the inputs are read."""
    inputs_good_since_s: float | None = None
    last_inputs: tuple[tuple[str, float, float], ...] = ()
    """(name, value, unchanged since [s]) of each input: staleness."""
    extrapolated: str | None = None
    """Why the inputs lie outside the trained range, while they do."""
    outside_spans: float = 0.0
    """How far outside the trained range the inputs lie, in spans of it (0 inside or on the
    fallback): :func:`compensator.expected.distance_outside`."""
    last_cycle: tuple[float, float, bool] | None = None
    """(speed [rpm], elongation of the model in use [um], on inputs) of the last cycle."""
    probe_reference_um: float | None = None
    """The model elongation a measurement seen this cycle is compared with."""
    started: bool = False
    """A cycle has run since the start (a reload carries on; a restart begins again)."""

    @property
    def speed_only(self) -> Any:
        """The speed-only model's own state (without the observer)."""
        return self.core.model if isinstance(self.core, FusedState) else self.core

    @property
    def in_use(self) -> Any:
        """The state of the model whose estimate is in use."""
        return self.inputs if self.inputs is not None else self.speed_only

    @property
    def bias_um(self) -> float:
        return self.core.bias_um if isinstance(self.core, FusedState) else 0.0

    @property
    def estimate_um(self) -> float:
        """The estimate the offset follows: the model in use, plus the observer's bias."""
        return float(self.in_use.elongation_um) + self.bias_um

    @property
    def since_measurement_s(self) -> float | None:
        return self.core.since_measurement_s if isinstance(self.core, FusedState) else None


@dataclass(frozen=True)
class Step:
    """What one cycle decided, for the caller's alarms and events."""

    speed_rpm: float
    """The speed the models were stepped with (clamped when over range and so configured)."""
    over_range: bool = False
    input_fallback: bool = False
    """The fallback stands in this cycle (an input fault, or waiting for the inputs to recover)."""
    fell_back: str | None = None
    """Why the inputs were given up this cycle (the model with inputs was in use, or recovering)."""
    restored: bool = False
    """The model with inputs took over this cycle."""


@dataclass(frozen=True)
class Series:
    """:meth:`Estimate.run` over a log: per row, the estimate, the model in use without the
    observer's bias, the speed stepped with, whether it was over range and whether the fallback
    stood in; the outcome of each probe; the state at the end."""

    estimate_um: np.ndarray
    model_um: np.ndarray
    speed_rpm: np.ndarray
    over_range: np.ndarray
    fallback: np.ndarray
    outcomes: tuple[str, ...]
    state: EstimateState


@dataclass(frozen=True)
class Saved:
    """A state file's estimate, checked, before it is advanced through the downtime."""

    core: Any
    references: dict[str, float] | None
    input_state: Any
    input_wall_s: float


def _check(state: EstimateState, what: str) -> None:
    """ModelError (the caller keeps the state it had) where ``what`` would leave an estimate no
    spindle can have: not finite, or beyond :data:`~compensator.model.SAVED_LIMIT_UM`."""
    for name, value in (
        ("estimate", state.estimate_um),
        ("speed-only model", state.speed_only.elongation_um),
    ):
        if not abs(float(value)) <= SAVED_LIMIT_UM:
            raise ModelError(
                f"{what} would set the {name} to {float(value):g} um, which no spindle "
                "reaches: refused, the estimate kept"
            )


@dataclass(frozen=True)
class Estimate:
    """The model, its fallback, the observer and the speed clamp (see the module)."""

    model: Predictor
    observer: ObserverConfig | None = None
    over_range: OverRange = "clamp"
    input_stale_s: float = 300.0
    input_recover_s: float = 60.0
    max_speed_rpm: float | None = None
    """The spindle's rated maximum speed; None: not stated (see :attr:`speed_limit_rpm`)."""
    _core: Predictor = field(init=False, repr=False, compare=False)
    """The speed-only model, fused with the observer when there is one (:attr:`core`)."""

    def __post_init__(self) -> None:
        speed_only = self.model.fallback or self.model
        object.__setattr__(
            self,
            "_core",
            speed_only if self.observer is None else FusedPredictor(speed_only, self.observer),
        )

    # -- what it is made of ----------------------------------------------------------------
    @property
    def core(self) -> Predictor:
        """The speed-only model, fused with the observer when there is one."""
        return self._core

    @property
    def fused(self) -> FusedPredictor | None:
        return self.core if isinstance(self.core, FusedPredictor) else None

    @property
    def with_inputs(self) -> Predictor | None:
        return self.model if self.model.input_names else None

    @property
    def speed_range_rpm(self) -> tuple[float, float]:
        return self.core.speed_range_rpm

    @property
    def speed_limit_rpm(self) -> float:
        """Above this no spindle turns: the stated maximum plus a margin, else a multiple of the
        calibrated top. A speed beyond it is a failed read (a register read as 0xFFFFFFFF), in
        either ``over_range`` policy."""
        if self.max_speed_rpm is not None:
            return self.max_speed_rpm * (1.0 + MAX_SPEED_MARGIN)
        return UNSTATED_MAX_FACTOR * max(self.core.speed_range_rpm[1], 1.0)

    def plausible(self, speed_rpm: float) -> bool:
        """A speed a spindle can turn at: finite and within :attr:`speed_limit_rpm`."""
        return math.isfinite(speed_rpm) and abs(speed_rpm) <= self.speed_limit_rpm

    # -- start -----------------------------------------------------------------------------
    def cold(self) -> EstimateState:
        """Nothing known: every model at its own equilibrium at rest."""
        return EstimateState(self.core.start(None, 0.0), input_cold=True)

    def parse_saved(self, saved: Mapping[str, Any]) -> Saved:
        """The estimate in a state file written by :meth:`state_dict`. ``ModelError`` (or a
        ``ValueError``, ``KeyError``, ``TypeError``) for one that cannot be trusted."""
        core = self.core.state_from_dict(saved)
        if not abs(core.elongation_um) <= SAVED_LIMIT_UM:
            raise ModelError(f"elongation {core.elongation_um:g} um is not a spindle's")
        refs = saved.get("input_references")
        refs = (
            {str(k): saved_numbers("input_references", [v], 1e9)[0] for k, v in refs.items()}
            if isinstance(refs, dict)
            else None
        )
        wall = saved_numbers("saved_wall_s", [saved["saved_wall_s"]], 1e11)[0]
        input_state, input_wall = None, wall
        if self.with_inputs is not None and saved.get("input_state") is not None:
            input_state = self.with_inputs.state_from_dict(saved["input_state"])
            if not abs(input_state.elongation_um) <= SAVED_LIMIT_UM:
                raise ModelError(
                    f"input model's elongation {input_state.elongation_um:g} um is not a spindle's"
                )
            input_wall = saved_numbers("input_wall_s", [saved.get("input_wall_s", wall)], 1e11)[0]
        return Saved(core, refs, input_state, input_wall)

    def resume(
        self, saved: Saved, downtime_s: float, wall_s: float, max_age_s: float
    ) -> EstimateState:
        """``saved`` advanced through ``downtime_s`` as an idle spindle (it stood still while
        nothing ran). Its input state is kept to resume when the inputs are read, if it is not
        older than ``max_age_s``."""
        core = self.core.step(saved.core, 0.0, max(0.0, downtime_s))
        refs = None
        if (
            self.with_inputs is not None
            and saved.references is not None
            and set(saved.references) >= set(self.with_inputs.input_names)
            and all(math.isfinite(v) for v in saved.references.values())
        ):
            refs = dict(saved.references)  # the cold start's, kept across restarts
        kept = None
        if saved.input_state is not None and wall_s - saved.input_wall_s <= max_age_s:
            kept = (saved.input_state, saved.input_wall_s)
        return EstimateState(core, references=refs, saved_input=kept)

    def adopt(self, state: EstimateState) -> EstimateState:
        """A state of an estimate of the same model (a reload), with the observer turned on or
        off as this one has it."""
        core = state.core
        if self.fused is not None and not isinstance(core, FusedState):
            core = FusedState(core, ObserverState.prior(self.fused.config))
        elif self.fused is None and isinstance(core, FusedState):
            core = core.model  # turned off: the model alone, through the slew limit
        return replace(state, core=core)

    # -- one cycle ---------------------------------------------------------------------------
    def clamp(self, speed_rpm: float) -> tuple[float, bool]:
        """The speed to step with, and whether it was above the calibrated range."""
        if not self.core.above_range(speed_rpm):
            return speed_rpm, False
        if self.over_range == "clamp":
            return math.copysign(self.core.speed_range_rpm[1], speed_rpm), True
        return speed_rpm, True

    def begin(self, elongation_um: float | None, speed_rpm: float) -> EstimateState:
        """A start at ``elongation_um`` (None: the model's own equilibrium) with the spindle at
        ``speed_rpm``, as a replay starts; the model with inputs starts with the first inputs."""
        return EstimateState(
            self.core.start(elongation_um, self.clamp(speed_rpm)[0]),
            input_cold=elongation_um is None,
        )

    def step(
        self,
        state: EstimateState,
        speed_rpm: float,
        dt_s: float,
        *,
        now_s: float,
        wall_s: float,
        inputs: Mapping[str, float] | None = None,
        input_error: str | None = None,
    ) -> tuple[EstimateState, Step]:
        """One cycle: ``speed_rpm`` as read (clamped here), held over ``dt_s``; ``inputs`` as read,
        or ``input_error`` when they could not be; ``now_s`` a monotonic time, ``wall_s`` the
        wall clock (a saved input state is advanced to it). On the first cycle after a start the
        model with inputs takes over at once; after a fault, once the inputs have recovered."""
        if not self.plausible(speed_rpm):
            raise ModelError(
                f"speed {speed_rpm:g} rpm is no spindle's (above "
                f"{self.speed_limit_rpm:g} rpm): not stepped with"
            )
        speed, over = self.clamp(speed_rpm)
        first = not state.started
        st = replace(state, core=self.core.step(state.core, speed, dt_s), started=True)
        info = Step(speed, over)
        if self.with_inputs is not None:
            st, info = self._inputs(
                st, info, speed, dt_s, now_s, wall_s, inputs, input_error, first
            )
        if self.fused is not None:
            last = st.last_cycle
            on_inputs = st.inputs is not None
            ref = (
                last[1]
                if last is not None and last[0] < speed and last[2] == on_inputs
                else float(st.in_use.elongation_um)
            )
            st = replace(
                st,
                probe_reference_um=ref,
                last_cycle=(speed, float(st.in_use.elongation_um), on_inputs),
            )
        _check(st, "the step")
        return st, info

    def _inputs(
        self,
        st: EstimateState,
        info: Step,
        speed: float,
        dt_s: float,
        now_s: float,
        wall_s: float,
        values: Mapping[str, float] | None,
        error: str | None,
        first: bool,
    ) -> tuple[EstimateState, Step]:
        model = self.with_inputs
        assert model is not None
        why = error if error is not None else model.check_inputs(values or {})
        values = dict(values or {})
        if why is None:
            last = {n: (v, since) for n, v, since in st.last_inputs}
            for name in model.input_names:
                v = values[name]
                prev = last.get(name)
                since = prev[1] if prev is not None and prev[0] == v else now_s
                last[name] = (v, since)
                if now_s - since >= self.input_stale_s:
                    why = f"{name}: stale, {v:g} for {now_s - since:.0f} s"
            st = replace(st, last_inputs=tuple((n, v, s) for n, (v, s) in last.items()))
        if why is not None:
            fell = why if st.inputs is not None or st.inputs_good_since_s is not None else None
            if st.inputs is not None:
                st = self._rebase(st, st.inputs, st.speed_only)
            # from now on the fallback's elongation is the estimate to continue from
            st = replace(
                st,
                inputs=None,
                inputs_good_since_s=None,
                input_cold=False,
                saved_input=None,
                extrapolated=None,
                outside_spans=0.0,
            )
            return st, replace(info, input_fallback=True, fell_back=fell)
        if st.inputs is None:
            good_since = st.inputs_good_since_s if st.inputs_good_since_s is not None else now_s
            st = replace(st, inputs_good_since_s=good_since)
            if now_s - good_since < self.input_recover_s and not first:
                return st, replace(info, input_fallback=True)
            started = self._start_inputs(st, speed, wall_s, values)
            st = self._rebase(
                replace(st, saved_input=None, input_cold=False), st.speed_only, started
            )
            refs = getattr(started, "references", None)
            st = replace(st, inputs=started, references=dict(refs) if refs is not None else None)
            info = replace(info, restored=True)
        else:
            st = replace(st, inputs=model.step(st.inputs, speed, dt_s, values))
        outside = getattr(model, "outside_trained", None)
        why_out = outside(values) if outside is not None else None
        spans = (
            float(model.distance_outside(values))
            if why_out and hasattr(model, "distance_outside")
            else 0.0
        )
        if why_out and spans > 0:
            why_out += f" ({spans:.2f} span(s) out)"
        return replace(st, extrapolated=why_out, outside_spans=spans), info

    def _start_inputs(
        self, st: EstimateState, speed: float, wall_s: float, values: Mapping[str, float]
    ) -> Any:
        """The input model's state when it takes over: the saved one advanced idle through the
        downtime (inputs held at today's); at a cold start its equilibrium with this speed and
        these inputs; else the fallback's elongation (no jump at the switch)."""
        model = self.with_inputs
        assert model is not None
        if st.saved_input is not None:
            state, since = st.saved_input
            return model.step(state, 0.0, max(0.0, wall_s - since), values)
        # a model with cold-start references takes these values as references (None: none yet)
        return model.start(
            None if st.input_cold else st.speed_only.elongation_um, speed, values, st.references
        )

    def _rebase(self, st: EstimateState, from_state: Any, to_state: Any) -> EstimateState:
        """The observer's bias moved from one model's estimate to the other's, so that the
        estimate stays where it is (the speed-only model's state kept)."""
        if self.fused is None:
            return st
        moved = self.fused.rebase(replace(st.core, model=from_state), to_state)
        return replace(st, core=replace(st.core, observer=moved.observer))

    # -- measurements -------------------------------------------------------------------------
    def measure(
        self,
        state: EstimateState,
        measured_um: float,
        sigma_um: float,
        source: str = "measurement",
    ) -> tuple[EstimateState, Update, float]:
        """Fuse one measurement from ``source`` against this cycle's reference (:meth:`step`),
        within the observer's bounds (the correction's, and ``source``'s move). Returns the new
        state, the observer's update and the estimate the measurement met [um]."""
        fused = self.fused
        if fused is None or not isinstance(state.core, FusedState):
            raise ModelError("this estimate has no observer")
        ref = (
            state.probe_reference_um
            if state.probe_reference_um is not None
            else float(state.in_use.elongation_um)
        )
        before = ref + state.bias_um
        out, up = fused.measure(
            replace(state.core, model=state.in_use),
            measured_um,
            sigma_um,
            model_at_probe_um=ref,
            source=source,
        )
        new = replace(state, core=replace(out, model=state.speed_only))
        _check(new, f"the measurement {measured_um:g} um")
        return new, up, before

    # -- over a whole log ----------------------------------------------------------------------
    def clamp_series(self, speed_rpm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`clamp` over an array: the speeds to step with, and where they were over range."""
        speed = np.asarray(speed_rpm, dtype=float)
        top = self.core.speed_range_rpm[1]
        over = np.abs(speed) > top * (1 + RANGE_TOLERANCE)  # the models' above_range
        if self.over_range == "clamp" and over.any():
            speed = np.where(over, np.copysign(top, speed), speed)
        return speed, over

    def simulate_um(
        self, speed_rpm: np.ndarray, time_s: np.ndarray, initial_um: float | None = None
    ) -> np.ndarray:
        """The speed-only estimate without measurements over a whole log, vectorised: what
        :meth:`run` gives from :meth:`begin` when there are no inputs and no probes (tested)."""
        if self.with_inputs is not None:
            raise ModelError(
                "a model with inputs runs through Estimate.run (its fallback may stand in)"
            )
        speed = np.asarray(speed_rpm, dtype=float)
        bad = np.flatnonzero(~(np.abs(speed) <= self.speed_limit_rpm))
        if bad.size:
            raise ModelError(
                f"row {int(bad[0])}: speed {speed[bad[0]]:g} rpm is no spindle's (above "
                f"{self.speed_limit_rpm:g} rpm)"
            )
        return self.core.simulate_um(self.clamp_series(speed)[0], time_s, None, initial_um)

    def run(
        self,
        state: EstimateState,
        time_s: np.ndarray,
        speed_rpm: np.ndarray,
        *,
        dt_s: np.ndarray | None = None,
        wall_s: np.ndarray | None = None,
        inputs: Mapping[str, np.ndarray] | None = None,
        probes: Sequence[tuple[int, float, float] | tuple[int, float, float, str]] = (),
    ) -> Series:
        """:meth:`step` over every row of a log, as the service ran it: ``dt_s`` per row (default
        the time steps, 0 on the first row), ``inputs`` per row (a NaN cell is an input the
        service could not use), and ``probes`` (row, measured [um], sigma [um][, source]), fused
        after that row's step in their order (without a source, all count as one:
        ``measurement``)."""
        t = np.asarray(time_s, dtype=float)
        n = t.size
        dt = np.diff(t, prepend=t[:1]) if dt_s is None else np.asarray(dt_s, dtype=float)
        now = t[0] + np.cumsum(dt) if n else t  # monotonic time: what the service's clock said
        wall = now if wall_s is None else np.asarray(wall_s, dtype=float)
        cols = {k: np.asarray(v, dtype=float) for k, v in (inputs or {}).items()}
        est, model, used = np.empty(n), np.empty(n), np.empty(n)
        over, fallback = np.zeros(n, bool), np.zeros(n, bool)
        outcomes: list[str] = []
        by_row: dict[int, list[tuple[float, float, str]]] = {}
        for probe in probes:
            row, y, sigma = probe[:3]
            source = str(probe[3]) if len(probe) > 3 else "measurement"
            by_row.setdefault(int(row), []).append((float(y), float(sigma), source))
        st = state
        for k in range(n):
            values = {name: float(col[k]) for name, col in cols.items()} if cols else None
            st, info = self.step(
                st,
                float(speed_rpm[k]),
                float(dt[k]),
                now_s=float(now[k]),
                wall_s=float(wall[k]),
                inputs=values,
            )
            for y, sigma, source in by_row.get(k, ()):
                st, up, _ = self.measure(st, y, sigma, source)
                outcomes.append(up.outcome)
            est[k], model[k], used[k] = (
                st.estimate_um,
                float(st.in_use.elongation_um),
                info.speed_rpm,
            )
            over[k], fallback[k] = info.over_range, info.input_fallback
        return Series(est, model, used, over, fallback, tuple(outcomes), st)

    # -- saving ---------------------------------------------------------------------------------
    def state_dict(self, state: EstimateState, wall_s: float) -> dict[str, Any]:
        """The whole state for the state file: the observer's bias on the speed-only model's
        footing (a restart starts with it), the input references, the input model's state."""
        core = state.core
        if self.fused is not None and state.inputs is not None:
            core = self._rebase(state, state.inputs, state.speed_only).core
        out = {**self.core.state_dict(core), "elongation_um": core.elongation_um}
        if state.references:
            out["input_references"] = dict(state.references)
        if self.with_inputs is not None:
            if state.inputs is not None:
                out.update(
                    input_state=self.with_inputs.state_dict(state.inputs), input_wall_s=wall_s
                )
            elif state.saved_input is not None:
                out.update(
                    input_state=self.with_inputs.state_dict(state.saved_input[0]),
                    input_wall_s=state.saved_input[1],
                )
        return out
