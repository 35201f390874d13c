"""A virtual spindle plant: a lumped thermal network richer than any model we fit.

Nodes (temperatures in degC):

1. shaft and rear bearings (rotor);
2. spindle nose with the front bearings;
3. housing and motor stator;
4. coolant jacket (water), pulled toward the chiller's outlet temperature;
5. machine structure (head/column), slowly following the ambient air.

The chiller is two more states: its internal set point, which moves toward the
commanded one at ``chiller_rate_k_per_min`` at most (the controller's own set-point ramp), and
its outlet temperature, a first-order lag of ``chiller_lag_s`` behind it. The jacket removes
heat in proportion to (housing - coolant). :meth:`SpindlePlant.set_chiller_setpoint_c`
commands it, within the device's range; a ramp is a constant-rate input, so the step stays
exact.

Heat input per node is a polynomial in n (krpm): motor hysteresis ~ n, eddy
currents and windage ~ n**2, bearing friction ~ n**3 (paper 001, eq. 10).
Convection from the rotating shaft and nose grows with speed as
``h0 + h1*n**0.8``. The ambient air drifts slowly (a daily sine plus a seeded
random walk, and optionally a steady ramp, ``ambient_drift_k_per_h``). Axial elongation is a weighted sum of node temperature rises
plus an instantaneous elastic term ``e1*n + e2*n**2`` (centrifugal and
preload change), which is what makes the paper's 27 000 -> 12 000 rpm drop
lose more than 10 um within a minute. The eddy-current reading adds Gaussian
noise and quantisation.

The drive (:meth:`SpindlePlant.drive`) follows a commanded speed at a finite acceleration
(``accel_rpm_per_s``), so the elastic step of a speed change spreads over the spindle's run-up,
as on a machine. The part is cut only at speed: the tool approaches the part ``approach_s``
after the spindle reached its commanded speed, and leaves it before a new speed is commanded
(:attr:`SpindlePlant.cutting`).

The network is linear in temperature for a held speed, so each step is the
exact zero-order-hold solution (a cached matrix exponential): any step size
gives the same trajectory at the shared instants.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, overload

import numpy as np
from scipy.linalg import expm

from compensator.filters import first_order
from compensator.units import speed_krpm

N_NODES = 5
RAMP_BAND_RPM = 500.0
"""During a ramp the heat is that of the speed band (of this width) the spindle is in."""


@dataclass(frozen=True)
class PlantParams:
    """Physical parameters of one spindle. Units in the names; n in krpm."""

    name: str
    description: str
    max_rpm: float
    capacity_j_per_k: tuple[float, float, float, float, float]
    # conductances between nodes [W/K]
    g_shaft_nose: float
    g_shaft_housing: float
    g_nose_housing: float
    g_housing_coolant: float
    g_coolant_chiller: float
    g_housing_structure: float
    g_structure_air: float
    # convection to air [W/K]: h0 + h1 * n**0.8
    h_shaft_air: tuple[float, float]
    h_nose_air: tuple[float, float]
    h_housing_air: float
    # heat inputs [W] as (c1, c2, c3) for c1*n + c2*n**2 + c3*n**3, per node
    heat_shaft_w: tuple[float, float, float]
    heat_nose_w: tuple[float, float, float]
    heat_housing_w: tuple[float, float, float]
    # axial growth per kelvin of each node [um/K]
    growth_um_per_k: tuple[float, float, float, float, float]
    elastic_um: tuple[float, float]  # e1 [um/krpm], e2 [um/krpm**2]
    ambient_c: float = 22.0
    chiller_c: float = 24.0
    ambient_daily_amplitude_k: float = 0.5
    ambient_walk_k_per_sqrt_h: float = 0.05
    ambient_drift_k_per_h: float = 0.0
    """A steady ramp of the air [K/h] (a hall warming through the day): 0 in the presets; a
    speed-only model cannot see it, so the closed-loop tests use it."""
    g_nose_structure: float = 0.0
    """Conduction from the front bearing through the flange into the head [W/K]: heat that
    bypasses a cooler on the housing (paper 000's external cooler)."""
    noise_um: float = 0.05
    quantum_um: float = 0.1
    accel_rpm_per_s: float = 5000.0
    """How fast the drive changes speed [rpm/s] (10 000 rpm in 2 s); inf: at once."""
    approach_s: float = 3.0
    """From at-speed to the first cut [s]: the tool moves in after the spindle is at speed."""
    chiller_lag_s: float = 120.0
    """The chiller's outlet follows its set point with this first-order lag [s] (60-300 s)."""
    chiller_rate_k_per_min: float = 1.0
    """The chiller's own set-point ramp [K/min]."""
    chiller_min_c: float = 5.0
    chiller_max_c: float = 35.0
    """The range the chiller accepts; a command outside is clamped, as the device does."""


PRESETS: dict[str, PlantParams] = {
    # A 5-axis-centre motorized spindle like paper 001's JUST SF260H:
    # ~34 um at 27 000 rpm after the staircase, > 10 um lost within a minute
    # of the drop to 12 000 rpm.
    "motorized-27k": PlantParams(
        name="motorized-27k",
        description="high-speed motorized spindle, 27 000 rpm, water-cooled (paper 001)",
        max_rpm=27000.0,
        capacity_j_per_k=(6000.0, 5000.0, 60000.0, 30000.0, 2.0e6),
        g_shaft_nose=6.0,
        g_shaft_housing=5.0,
        g_nose_housing=8.0,
        g_housing_coolant=120.0,
        g_coolant_chiller=200.0,
        g_housing_structure=15.0,
        g_structure_air=60.0,
        h_shaft_air=(0.5, 0.35),
        h_nose_air=(1.0, 0.4),
        h_housing_air=4.0,
        heat_shaft_w=(0.6, 0.02, 0.0045),
        heat_nose_w=(0.3, 0.01, 0.0040),
        heat_housing_w=(5.0, 0.9, 0.0),
        growth_um_per_k=(0.9, 0.38, 0.25, 0.0, 0.4),
        elastic_um=(0.05, 0.0205),
    ),
    # A larger belt-driven mechanical spindle: slow, hours-long time constants.
    "mechanical-8k": PlantParams(
        name="mechanical-8k",
        description="belt-driven mechanical spindle, 8 000 rpm, air-cooled, slow",
        max_rpm=8000.0,
        capacity_j_per_k=(40000.0, 30000.0, 250000.0, 60000.0, 4.0e6),
        g_shaft_nose=10.0,
        g_shaft_housing=8.0,
        g_nose_housing=12.0,
        g_housing_coolant=20.0,
        g_coolant_chiller=30.0,
        g_housing_structure=25.0,
        g_structure_air=80.0,
        h_shaft_air=(0.8, 0.5),
        h_nose_air=(1.5, 0.6),
        h_housing_air=10.0,
        heat_shaft_w=(2.0, 0.5, 0.25),
        heat_nose_w=(1.0, 0.4, 0.22),
        heat_housing_w=(4.0, 1.2, 0.0),
        growth_um_per_k=(1.4, 0.7, 0.45, 0.0, 0.6),
        elastic_um=(0.0, 0.04),
        accel_rpm_per_s=2000.0,
    ),
    # Paper 000's mechanical spindle with an external helical cooler (thermal grease to the
    # housing; the front bearing also heats the head through its flange): at 3000 rpm with the
    # coolant at 16 degC in an 18 degC shop the error passes 16 um at 1.5 h and creeps on for
    # hours (27 um at 8 h); 2000 rpm reaches 13 um. 2 K colder coolant: -1 um in 30 min.
    "mechanical-cooled": PlantParams(
        name="mechanical-cooled",
        description="mechanical spindle, 6 000 rpm, external helical cooler (paper 000)",
        max_rpm=6000.0,
        capacity_j_per_k=(30000.0, 25000.0, 200000.0, 20000.0, 690000.0),
        g_shaft_nose=10.0,
        g_shaft_housing=9.0,
        g_nose_housing=12.0,
        g_housing_coolant=100.0,
        g_coolant_chiller=200.0,
        g_housing_structure=20.0,
        g_structure_air=27.0,
        g_nose_structure=20.0,
        h_shaft_air=(0.8, 0.4),
        h_nose_air=(1.2, 0.5),
        h_housing_air=6.0,
        heat_shaft_w=(30.0, 3.0, 0.3),
        heat_nose_w=(26.0, 2.6, 0.26),
        heat_housing_w=(40.0, 6.0, 0.3),
        growth_um_per_k=(0.8, 0.4, 1.2, 0.0, 4.5),
        elastic_um=(0.0, 0.08),
        ambient_c=18.0,
        chiller_c=16.0,
        ambient_daily_amplitude_k=0.3,
        accel_rpm_per_s=2000.0,
        chiller_lag_s=120.0,
        chiller_rate_k_per_min=1.0,
    ),
}


def preset(name: str) -> PlantParams:
    try:
        return PRESETS[name]
    except KeyError as err:
        raise KeyError(f"unknown plant preset {name!r}; choose from {', '.join(PRESETS)}") from err


def _system(p: PlantParams, n_krpm: float) -> tuple[np.ndarray, np.ndarray]:
    """dT/dt = A T + B u with u = (1, T_air, T_chiller), for a held speed."""
    hs = p.h_shaft_air[0] + p.h_shaft_air[1] * n_krpm**0.8
    hn = p.h_nose_air[0] + p.h_nose_air[1] * n_krpm**0.8
    g = np.zeros((N_NODES, N_NODES))

    def link(i: int, j: int, val: float) -> None:
        g[i, j] += val
        g[j, i] += val

    link(0, 1, p.g_shaft_nose)
    link(0, 2, p.g_shaft_housing)
    link(1, 2, p.g_nose_housing)
    link(2, 3, p.g_housing_coolant)
    link(2, 4, p.g_housing_structure)
    if p.g_nose_structure:
        link(1, 4, p.g_nose_structure)
    to_air = np.array([hs, hn, p.h_housing_air, 0.0, p.g_structure_air])
    to_chiller = np.array([0.0, 0.0, 0.0, p.g_coolant_chiller, 0.0])
    cond = g - np.diag(g.sum(axis=1) + to_air + to_chiller)

    def poly(c: tuple[float, float, float]) -> float:
        return c[0] * n_krpm + c[1] * n_krpm**2 + c[2] * n_krpm**3

    heat = np.array([poly(p.heat_shaft_w), poly(p.heat_nose_w), poly(p.heat_housing_w), 0.0, 0.0])
    cap = np.asarray(p.capacity_j_per_k)
    a = cond / cap[:, None]
    b = np.column_stack([heat, to_air, to_chiller]) / cap[:, None]
    return a, b


def _chilled_system(p: PlantParams, n_krpm: float) -> tuple[np.ndarray, np.ndarray]:
    """dx/dt = A x + B u for x = (the nodes, chiller outlet, chiller internal set point) and
    u = (1, T_air, set-point ramp rate [K/s]), for a held speed and ramp rate."""
    a, b = _system(p, n_krpm)
    big = np.zeros((N_NODES + 2, N_NODES + 2))
    big[:N_NODES, :N_NODES] = a
    big[:N_NODES, N_NODES] = b[:, 2]  # the jacket is pulled toward the outlet, not the set point
    big[N_NODES, N_NODES] = -1.0 / p.chiller_lag_s
    big[N_NODES, N_NODES + 1] = 1.0 / p.chiller_lag_s
    u = np.zeros((N_NODES + 2, 3))
    u[:N_NODES, :2] = b[:, :2]
    u[N_NODES + 1, 2] = 1.0
    return big, u


@dataclass
class SpindlePlant:
    """One simulated spindle. Seeded: the same seed gives the same run."""

    params: PlantParams
    seed: int = 0
    time_s: float = 0.0
    temps_c: np.ndarray = field(init=False)
    _ref_c: np.ndarray = field(init=False)
    _rng: np.random.Generator = field(init=False)
    _walk_k: float = field(init=False, default=0.0)
    _speed_rpm: float = field(init=False, default=0.0)
    _command_rpm: float = field(init=False, default=0.0)
    _at_speed_s: float = field(init=False, default=math.inf)
    _setpoint_c: float = field(init=False, default=math.nan)
    _chiller: np.ndarray = field(init=False)
    """The chiller's outlet and internal set point [degC]."""
    _cache: dict[tuple[float, float, float], tuple[np.ndarray, np.ndarray]] = field(
        init=False, default_factory=dict
    )

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)
        self._phase = float(self._rng.uniform(0, 2 * math.pi))
        self.reset_cold()

    def reset_cold(self) -> None:
        """Every node at its idle equilibrium: a spindle rested overnight."""
        p = self.params
        air = self.air_c(self.time_s)
        a, b = _system(p, 0.0)
        self.temps_c = np.linalg.solve(a, -b @ np.array([1.0, air, p.chiller_c]))
        self._ref_c = self.temps_c.copy()
        self._setpoint_c = float(p.chiller_c)
        self._chiller = np.array([p.chiller_c, p.chiller_c], dtype=float)

    def set_chiller_setpoint_c(self, value_c: float) -> float:
        """Command the chiller's set point [degC]; the device clamps it to its range. Returns
        the value it took."""
        if not math.isfinite(value_c):
            raise ValueError(f"bad chiller set point {value_c}")
        p = self.params
        self._setpoint_c = min(max(float(value_c), p.chiller_min_c), p.chiller_max_c)
        return self._setpoint_c

    @property
    def chiller_setpoint_c(self) -> float:
        """The commanded set point [degC]."""
        return self._setpoint_c

    @property
    def supply_c(self) -> float:
        """The chiller's outlet temperature [degC]."""
        return float(self._chiller[0])

    @property
    def coolant_c(self) -> float:
        """The coolant in the jacket [degC]."""
        return float(self.temps_c[3])

    def air_c(self, t_s: float) -> float:
        p = self.params
        return (
            p.ambient_c
            + p.ambient_daily_amplitude_k * math.sin(2 * math.pi * t_s / 86400.0 + self._phase)
            + p.ambient_drift_k_per_h * t_s / 3600.0
            + self._walk_k
        )

    def _transition(
        self, n_krpm: float, dt_s: float, rate_k_per_s: float
    ) -> tuple[np.ndarray, np.ndarray]:
        key = (round(n_krpm, 9), round(dt_s, 12), rate_k_per_s)
        hit = self._cache.get(key)
        if hit is None:
            a, b = _chilled_system(self.params, n_krpm)
            size = a.shape[0]
            m = np.zeros((size + 3, size + 3))
            m[:size, :size] = a
            m[:size, size:] = b
            e = expm(m * dt_s)
            hit = (e[:size, :size].copy(), e[:size, size:].copy())
            if len(self._cache) > 4096:
                self._cache.clear()
            self._cache[key] = hit
        return hit

    def advance(self, speed_rpm: float, dt_s: float) -> None:
        """Hold ``speed_rpm`` for ``dt_s`` seconds."""
        if not (math.isfinite(speed_rpm) and math.isfinite(dt_s)) or dt_s < 0:
            raise ValueError(f"bad plant step: speed {speed_rpm}, dt {dt_s}")
        if dt_s == 0:
            self._speed_rpm = speed_rpm
            return
        p = self.params
        self._walk_k += (
            p.ambient_walk_k_per_sqrt_h
            * math.sqrt(dt_s / 3600.0)
            * float(self._rng.standard_normal())
        )
        air = self.air_c(self.time_s + dt_s / 2)
        n_krpm = speed_krpm(speed_rpm)
        x = np.concatenate([self.temps_c, self._chiller])
        left = dt_s
        while left > 0:
            # the chiller ramps its set point at a constant rate: one exact piece per ramp
            gap = self._setpoint_c - x[-1]
            rate = math.copysign(p.chiller_rate_k_per_min / 60.0, gap) if gap else 0.0
            piece = min(left, abs(gap) / abs(rate)) if rate else left
            phi, gam = self._transition(n_krpm, piece, rate)
            x = phi @ x + gam @ np.array([1.0, air, rate])
            if piece < left or (rate and abs(self._setpoint_c - x[-1]) < 1e-9):
                x[-1] = self._setpoint_c  # the ramp ended inside this step
            left -= piece
        self.temps_c = x[:N_NODES]
        self._chiller = x[N_NODES:]
        self.time_s += dt_s
        self._speed_rpm = speed_rpm

    def drive(self, command_rpm: float, dt_s: float) -> None:
        """Command ``command_rpm`` for ``dt_s`` seconds: the actual speed ramps toward it at
        ``accel_rpm_per_s``, then holds it. The elastic growth follows the speed reached; the heat
        of a ramp is taken in bands of :data:`RAMP_BAND_RPM` (each at its mid speed, bands fixed
        in speed), so it is one function of time and any step size gives the same trajectory."""
        if not (math.isfinite(command_rpm) and math.isfinite(dt_s)) or dt_s < 0:
            raise ValueError(f"bad plant step: speed {command_rpm}, dt {dt_s}")
        if command_rpm != self._command_rpm:
            self._command_rpm = command_rpm
            self._at_speed_s = -math.inf  # a new command: the tool has left the part
        now = self._speed_rpm
        gap = command_rpm - now
        need_s = abs(gap) / self.params.accel_rpm_per_s if gap else 0.0
        reached = need_s <= dt_s
        ramp_s = need_s if reached else dt_s
        if ramp_s > 0:
            end = (
                command_rpm
                if reached
                else now + math.copysign(self.params.accel_rpm_per_s * dt_s, gap)
            )
            self._ramp(now, end, ramp_s)
        if reached:
            self.advance(command_rpm, dt_s - ramp_s)
            held_s = dt_s - ramp_s  # at the commanded speed within this step
            self._at_speed_s = (
                held_s if ramp_s > 0 or self._at_speed_s < 0 else self._at_speed_s + held_s
            )

    def _ramp(self, start_rpm: float, end_rpm: float, duration_s: float) -> None:
        """The speed from ``start_rpm`` to ``end_rpm`` in a straight line over ``duration_s``."""
        rate = (end_rpm - start_rpm) / duration_s
        if rate == 0.0:  # a step too short to move the speed in floating point
            self.advance(start_rpm, duration_s)
            return
        up = rate > 0
        t = 0.0
        while t < duration_s:
            n = start_rpm + rate * t
            band = math.floor(n / RAMP_BAND_RPM + (1e-9 if up else -1e-9))
            edge = (band + 1 if up else band) * RAMP_BAND_RPM
            piece = min((edge - n) / rate, duration_s - t)
            self.advance((band + 0.5) * RAMP_BAND_RPM, piece)
            t += piece
        self._speed_rpm = end_rpm

    @property
    def command_rpm(self) -> float:
        return self._command_rpm

    @property
    def at_speed(self) -> bool:
        """The actual speed equals the commanded one."""
        return self._speed_rpm == self._command_rpm

    @property
    def cutting(self) -> bool:
        """The tool is in the part: the spindle turns at its commanded speed and has done so
        for ``approach_s``."""
        return (
            self._command_rpm != 0 and self.at_speed and self._at_speed_s >= self.params.approach_s
        )

    def elastic_um(self, speed_rpm: float | None = None) -> float:
        n = speed_krpm(self._speed_rpm if speed_rpm is None else speed_rpm)
        e1, e2 = self.params.elastic_um
        return e1 * n + e2 * n * n

    def true_elongation_um(self) -> float:
        """Axial growth of the tool tip relative to the cold start [um]."""
        rise = self.temps_c - self._ref_c
        return float(np.dot(self.params.growth_um_per_k, rise)) + self.elastic_um()

    def measure_um(self, true_um: float | np.ndarray) -> float | np.ndarray:
        """What an eddy-current sensor reads: noise, then quantisation."""
        p = self.params
        noisy = true_um + p.noise_um * self._rng.standard_normal(np.shape(true_um))
        return np.round(noisy / p.quantum_um) * p.quantum_um if p.quantum_um > 0 else noisy

    def run(
        self,
        times_s: np.ndarray,
        speeds_rpm: np.ndarray,
        chiller_setpoint_c: np.ndarray | None = None,
    ) -> PlantRun:
        """Drive the plant over a sampled program (speeds[k] commanded over (times[k-1],
        times[k]]). The run's speed is the actual speed at each sample, as a drive reports it:
        it ramps at ``accel_rpm_per_s``. ``chiller_setpoint_c[k]``, if given, is commanded over
        the same interval (a step run of the chiller)."""
        t = np.asarray(times_s, dtype=float)
        n = np.asarray(speeds_rpm, dtype=float)
        sp = None if chiller_setpoint_c is None else np.asarray(chiller_setpoint_c, dtype=float)
        supply = np.empty_like(t)
        commanded = np.empty_like(t)
        true = np.empty_like(t)
        actual = np.empty_like(t)
        cutting = np.zeros(t.size, dtype=bool)
        temps = np.empty((t.size, N_NODES))
        air = np.empty_like(t)
        prev = t[0]
        self.time_s = float(prev)
        for k in range(t.size):
            if sp is not None:
                self.set_chiller_setpoint_c(float(sp[k]))
            self.drive(float(n[k]), float(t[k] - prev))
            prev = t[k]
            supply[k] = self.supply_c
            commanded[k] = self._setpoint_c
            true[k] = self.true_elongation_um()
            actual[k] = self._speed_rpm
            cutting[k] = self.cutting
            temps[k] = self.temps_c
            air[k] = self.air_c(self.time_s)
        measured = np.asarray(self.measure_um(true), dtype=float)
        return PlantRun(
            t,
            actual,
            true,
            measured,
            temps,
            air,
            cutting,
            supply,
            commanded if sp is not None else None,
        )

    @overload
    def heat_w(self, speed_rpm: float) -> float: ...
    @overload
    def heat_w(self, speed_rpm: np.ndarray) -> np.ndarray: ...
    def heat_w(self, speed_rpm: float | np.ndarray) -> float | np.ndarray:
        """Total heat the spindle dissipates at a speed [W]: what the drive's load shows."""
        n = np.abs(np.asarray(speed_rpm, dtype=float)) / 1000.0
        p = self.params
        c = np.add(np.add(p.heat_shaft_w, p.heat_nose_w), p.heat_housing_w)
        return c[0] * n + c[1] * n**2 + c[2] * n**3

    def sensor_channels(self, run: PlantRun, seed: int | None = None) -> dict[str, np.ndarray]:
        """What the machine's own sensors would publish over the run, each with its lag, noise
        and resolution: the front-bearing temperature (nose node), the motor (stator and
        housing), the coolant return, the ambient air, and the spindle load in % of the load at
        full speed."""
        rng = np.random.default_rng(self.seed + 7919 if seed is None else seed)
        t = run.time_s
        dt = np.diff(t, prepend=t[0])
        out: dict[str, np.ndarray] = {}
        for name, source, lag_s, noise, step in SENSORS:
            x = run.air_c if source is None else run.temps_c[:, source]
            y = first_order(x, dt, lag_s, float(x[0])) + noise * rng.standard_normal(x.size)
            out[name] = np.round(y / step) * step
        load = 100.0 * self.heat_w(run.speed_rpm) / float(self.heat_w(self.params.max_rpm))
        out["spindle_load_pct"] = np.round(
            np.clip(load + 0.5 * rng.standard_normal(load.size), 0, None), 1
        )
        return out

    def with_params(self, **changes: Any) -> SpindlePlant:
        """The same plant with the named parameters changed (any field of :class:`PlantParams`)."""
        return SpindlePlant(replace(self.params, **changes), seed=self.seed)


SENSORS: tuple[tuple[str, int | None, float, float, float], ...] = (
    # name, node (None: the air), sensor lag [s], noise [K], resolution [K]
    ("bearing_temp_c", 1, 30.0, 0.02, 0.01),
    ("motor_temp_c", 2, 60.0, 0.02, 0.01),
    ("coolant_temp_c", 3, 20.0, 0.02, 0.01),
    ("ambient_c", None, 120.0, 0.02, 0.01),
)


@dataclass(frozen=True)
class PlantRun:
    time_s: np.ndarray
    speed_rpm: np.ndarray
    true_um: np.ndarray
    measured_um: np.ndarray
    temps_c: np.ndarray
    air_c: np.ndarray
    cutting: np.ndarray | None = None
    """bool per sample: the tool in the part (:attr:`SpindlePlant.cutting`)."""
    supply_c: np.ndarray | None = None
    """The chiller's outlet [degC]."""
    chiller_setpoint_c: np.ndarray | None = None
    """The commanded chiller set point [degC], where the run commanded one."""

    def columns(self, measured: bool = True) -> dict[str, np.ndarray]:
        """Run-log columns in the common format (``cutting`` as 0/1)."""
        cols = {
            "time_s": self.time_s,
            "speed_rpm": self.speed_rpm,
            "elongation_um": self.measured_um if measured else self.true_um,
            "ambient_c": np.round(self.air_c, 3),
        }
        if self.cutting is not None:
            cols["cutting"] = self.cutting.astype(np.int64)
        if self.chiller_setpoint_c is not None:
            cols["chiller_setpoint_c"] = self.chiller_setpoint_c
        return cols
