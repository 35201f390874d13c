"""A virtual CNC served over a real OPC UA server (asyncua), driven by the spindle plant.

Address space, modelled on OPC 40502 (OPC UA for CNC systems) where it can be::

    Objects/
      CncInterface/                       (CncInterfaceType-like)
        CncSpindleList/
          Spindle1/                       (CncSpindleType-like)
            ActSpeed          Double  rpm   the spindle's actual speed (read-only)
            CmdSpeed          Double  rpm   the programmed speed (read-only)
            AtSpeed           Boolean       the actual speed equals the programmed one
            Cutting           Boolean       the tool is in the part (feeding at speed)
            ThermalOffset     Double  um    thermal tool-length offset (writable by any client)
            Displacement      Double  um    eddy-current reading at the nose (read-only)
        Simulation/
          SimTime             Double  s     simulated time
          TrueElongation      Double  um    the plant's true growth, for scoring
          ToolTipError        Double  um    true growth + applied offset: what the part sees
          CycleStart          Boolean       write true to start the loaded program (writable)

and the simulated tool setter, under ``Spindle1/ToolSetter/``: a method ``Probe()`` (returns the
sequence number the measurement will carry, 0 while a probe cycle is running), and
``Measurement`` (Double, um), ``Sigma`` (Double, um) and ``Sequence`` (UInt32), written as a
probe cycle would: the value first, then the counter.

Every node id is a string node id ``ns=<ns>;s=/<path>`` so that configurations can name
them; ``NODE_PATHS`` lists them. Like a real CNC's variable, ``ThermalOffset`` takes a write from
any client (an operator's or a fault test's, up to ``OFFSET_LIMIT_UM``) and starts at 0 when
the virtual CNC (re)starts. Positive elongation moves the tool tip toward the workpiece;
an offset written here moves it back by the same amount, so a perfect compensator writes
``-elongation`` and ``ToolTipError`` reads 0.

Time runs accelerated (``time_scale`` x wall time) on an injected clock, and a
:class:`~compensator.speed_programs.Program` drives the speed. The plant is stepped on a fixed
sim-time grid (``plant_dt_s``), which keeps its matrix exponentials cached.
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import math
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from compensator.clock import ScaledClock
from compensator.filters import lag_step
from compensator.speed_programs import Program

from .plant import SENSORS, SpindlePlant
from .watchdog import Watch, WatchSettings

if TYPE_CHECKING:
    from asyncua import Node, Server

NAMESPACE_URI = "urn:thermocomp:virtual-cnc"
NODE_PATHS = {
    "act_speed": "/CncInterface/CncSpindleList/Spindle1/ActSpeed",
    "cmd_speed": "/CncInterface/CncSpindleList/Spindle1/CmdSpeed",
    "thermal_offset": "/CncInterface/CncSpindleList/Spindle1/ThermalOffset",
    "displacement": "/CncInterface/CncSpindleList/Spindle1/Displacement",
    "sim_time": "/CncInterface/Simulation/SimTime",
    "true_elongation": "/CncInterface/Simulation/TrueElongation",
    "tool_tip_error": "/CncInterface/Simulation/ToolTipError",
    # the machine's own sensors, as a drive or PLC would publish them
    "bearing_temp_c": "/CncInterface/CncSpindleList/Spindle1/Sensors/BearingTemp",
    "motor_temp_c": "/CncInterface/CncSpindleList/Spindle1/Sensors/MotorTemp",
    "coolant_temp_c": "/CncInterface/CncSpindleList/Spindle1/Sensors/CoolantTemp",
    "ambient_c": "/CncInterface/CncSpindleList/Spindle1/Sensors/AmbientTemp",
    "spindle_load_pct": "/CncInterface/CncSpindleList/Spindle1/Sensors/Load",
}
STATE_PATHS = {
    "at_speed": "/CncInterface/CncSpindleList/Spindle1/AtSpeed",
    "cutting": "/CncInterface/CncSpindleList/Spindle1/Cutting",
}
"""Boolean state of the machining, as a CNC's PLC publishes it: at speed, and cutting (the tool
approaches the part ``approach_s`` after at-speed and leaves it before a speed change)."""
TOOL_SETTER_PATHS = {
    "probe_measurement": "/CncInterface/CncSpindleList/Spindle1/ToolSetter/Measurement",
    "probe_sigma": "/CncInterface/CncSpindleList/Spindle1/ToolSetter/Sigma",
    "probe_sequence": "/CncInterface/CncSpindleList/Spindle1/ToolSetter/Sequence",
}
PROBE_METHOD_PATH = "/CncInterface/CncSpindleList/Spindle1/ToolSetter/Probe"
LIFE_PATHS = {
    "life_counter": "/CncInterface/CncSpindleList/Spindle1/LifeCounter",
    "compensation_valid": "/CncInterface/CncSpindleList/Spindle1/CompensationValid",
}
"""thermocomp's sign of life, writable by any client: the life counter (Int32, 1 .. 32767, 0 =
never written) and the "compensation valid" flag (Boolean). The machine's watch judges them
(:mod:`machine_sim.watchdog`)."""
WATCH_PATHS = {
    "compensation_watch": "/CncInterface/CncSpindleList/Spindle1/CompensationWatch",
    "compensation_reaction": "/CncInterface/CncSpindleList/Spindle1/CompensationReaction",
    "compensation_alarm": "/CncInterface/CncSpindleList/Spindle1/CompensationAlarm",
    "compensation_trips": "/CncInterface/CncSpindleList/Spindle1/CompensationTrips",
    "compensation_tripped_at": "/CncInterface/CncSpindleList/Spindle1/CompensationTrippedAt",
}
"""What the watch sees and does, read-only: its state (String: waiting, ok, stale, invalid), the
reaction in force (String, '' when none), the alarm text (String, '' when none), how often it
tripped (UInt32) and the simulated time of the last trip (Double, s; -1 never)."""
RESET_PATH = "/CncInterface/Simulation/Reset"
"""Write true: the operator's reset (clears the watch's alarm once the sign of life is back)."""
SENSOR_KEYS = ("bearing_temp_c", "motor_temp_c", "coolant_temp_c", "ambient_c", "spindle_load_pct")
CYCLE_START_PATH = "/CncInterface/Simulation/CycleStart"
OFFSET_LIMIT_UM = 1000.0
"""The virtual CNC, like a real one, ignores offsets beyond this (and non-finite ones)."""
SINUMERIK_SPEED_NODE = "/Channel/Spindle/actSpeed[u1,1]"
"""With a SINUMERIK profile: the spindle's actual speed, under the id SINUMERIK's server uses."""
SINUMERIK_SD43900_NODE = "/NC/_N_AX_SEA_ACX/$SA_TEMP_COMP_ABS_VALUE[u3]"
"""With a SINUMERIK profile: setting datum SD43900 of axis 3 (Z) [mm]. The id is this virtual
CNC's; a real server's is browsed under /Sinumerik/SEA or read off its documentation, and
configured (``offset_node``), never assumed."""
SINUMERIK_LIFE_NODES = {
    "life_counter": "/Channel/Parameter/R[u1,98]",
    "compensation_valid": "/Channel/Parameter/R[u1,99]",
}
"""With a SINUMERIK profile: the sign of life in R parameters R98 (counter) and R99 (valid, 1/0),
Doubles as R parameters are, where the profile's OPC UA route writes it; the watch reads them
instead of ``LIFE_PATHS``."""
SINUMERIK_GIVE_ACCESS = "/Methods/GiveUserAccess"
"""``GiveUserAccess(user, right)``: grants ``right`` (``SeaWrite``: write setting data) to a
user; only the administrators may call it."""
SEA_WRITE = "SeaWrite"


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


class SimClock(ScaledClock):
    """Simulated seconds, ``scale`` times faster than ``base`` (the monotonic clock by default).
    Shared by the plant and its clients."""

    def __init__(self, scale: float = 60.0, base: Callable[[], float] = time.monotonic):
        super().__init__(scale, base)


@dataclass(frozen=True)
class ToolSetter:
    """A tool setter (laser or contact): a probe cycle stops the spindle for ``dwell_s``
    (simulated), then measures the true tool-tip elongation with Gaussian noise of
    ``noise_um`` (seeded), rounded to ``resolution_um``. With ``touches`` > 1 the cycle touches
    that many times, ``touch_s`` longer for each one after the first, and hands on their mean
    (independent touches: the noise falls as 1/sqrt(touches))."""

    dwell_s: float = 20.0
    noise_um: float = 0.5
    resolution_um: float = 0.1
    seed: int = 0
    at_speed: bool = False
    """A laser setter measuring the turning tool: the spindle keeps its speed through the cycle,
    and the measurement includes the growth that exists only while it turns."""
    touches: int = 1
    touch_s: float = 1.2
    """One more touch: back off and touch again at the slow feed (0.2 mm each way at 20 mm/min)."""

    def __post_init__(self) -> None:
        for name in ("dwell_s", "noise_um", "resolution_um", "touch_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"tool setter {name} must be a finite number >= 0, got {v}")
        if not (isinstance(self.touches, int) and 1 <= self.touches <= 10):
            raise ValueError(
                f"tool setter touches must be a whole number from 1 to 10, got {self.touches!r}"
            )

    @property
    def cycle_s(self) -> float:
        """One probe cycle, every touch included [s]."""
        return self.dwell_s + (self.touches - 1) * self.touch_s

    @property
    def sigma_um(self) -> float:
        """The noise of the value a cycle hands on: the mean of its touches."""
        return self.noise_um / math.sqrt(self.touches)


@dataclass
class History:
    time_s: np.ndarray
    speed_rpm: np.ndarray
    true_um: np.ndarray
    measured_um: np.ndarray
    offset_um: np.ndarray
    cutting: np.ndarray
    """bool: the tool was in the part at the end of the step."""

    @property
    def tool_tip_error_um(self) -> np.ndarray:
        return self.true_um + self.offset_um


class VirtualMachine:
    """The plant, its speed program, the applied offset and the scoring history.

    Protocol-free: the OPC UA :class:`VirtualCNC` and the in-process ``sim`` adapter both
    drive one of these.
    """

    def __init__(
        self,
        plant: SpindlePlant,
        program: Program | None = None,
        *,
        clock: Callable[[], float] | None = None,
        plant_dt_s: float = 0.5,
        tool_setter: ToolSetter | None = None,
        watch: WatchSettings | None = None,
        say: Callable[[float, str], None] | None = None,
    ):
        """``watch``: how the control watches thermocomp's sign of life and reacts when it is
        missing (default: a 3 s timeout and no reaction, the state shown only). ``say``: called
        with (machine time, one line) for each trip and its reaction, the sign of life coming
        back, a reset and a refused or resumed cycle start (the control's message line)."""
        self.plant = plant
        self.program = program
        self._program_start_s = 0.0
        self.clock = clock or SimClock(60.0)
        self.plant_dt_s = plant_dt_s
        self.offset_um = 0.0
        self.pending: Program | None = None  # loaded, waiting for cycle start
        self.rejected_writes = 0
        self._override_rpm: float | None = None
        self._hist: list[tuple[float, float, float, float, float, bool]] = []
        self._lock = threading.Lock()
        # the machine's own sensors (temperatures, load), lagged like the real ones
        self._lagged = {
            name: float(plant.air_c(0) if node is None else plant.temps_c[node])
            for name, node, *_ in SENSORS
        }
        self._sensor_rng = np.random.default_rng(plant.seed + 104729)
        self.sensor_faults: dict[str, str] = {}  # name -> "nan" | "frozen"
        self._frozen: dict[str, float] = {}
        self.tool_setter = tool_setter or ToolSetter()
        self._probe_rng = np.random.default_rng(self.tool_setter.seed)
        self._probe_until_s: float | None = None  # plant time the running probe cycle ends
        self._probe_rpm = 0.0  # the speed a laser setter at speed holds through its cycle
        self._stops_done = 0  # the program's probe stops (Program.probe_at_s) reached so far
        self._stop_running = False  # the running probe cycle is one of the program's
        # what the probe cycle left, as a controller's variables: value, then counter
        self.probe_value_um = 0.0
        self.probe_true_um = 0.0
        self.probe_sigma_um = self.tool_setter.sigma_um
        self.probe_sequence = 0
        self.watch = Watch(watch, say)
        self.refused_starts = 0  # cycle starts the watch refused

    def fork(self, clock: Callable[[], float]) -> VirtualMachine:
        """An independent copy of the machine as it is now (plant, program, offset, watch and
        record) on ``clock``: a what-if from the same moment."""
        with self._lock:
            state = {k: v for k, v in vars(self).items() if k not in ("_lock", "clock")}
            # the watch's message sink is not copied (a bound method would drag its owner along)
            twin_state = copy.deepcopy(state, {id(self.watch.say): None})
        twin = VirtualMachine.__new__(VirtualMachine)
        vars(twin).update(twin_state)
        twin._lock = threading.Lock()
        twin.clock = clock
        twin.watch.say = None  # a what-if: its trips are not the machine's to report
        return twin

    def life_beat(self, counter: object, valid: object) -> None:
        """thermocomp's sign of life as the control reads it now (the plant's time): the life
        counter and the "compensation valid" flag, judged by :attr:`watch`."""
        with self._lock:
            self.watch.beat(counter, valid, self.plant.time_s)

    def reset(self) -> bool:
        """The operator's reset: clears the watch's alarm once the sign of life is back; True
        when no alarm stands after it."""
        with self._lock:
            return self.watch.reset(self.plant.time_s)

    def load_program(self, program: Program | None) -> None:
        """Start ``program`` now (sim time); None idles the spindle. The program's probe stops
        (``probe_at_s``) each run a probe cycle when the program reaches them."""
        self.program = program
        self._program_start_s = self.plant.time_s
        self._stops_done = 0

    def load_pending(self, program: Program) -> None:
        """Load ``program`` to start on :meth:`cycle_start` (the operator's button)."""
        self.pending = program

    def cycle_start(self) -> bool:
        """The operator's cycle start: resumes a program the watch's feed hold paused, else
        starts the loaded one. Refused (False) while the watch's alarm stands or its feed hold
        waits for the sign of life (:attr:`Watch.refusal` says why)."""
        with self._lock:
            now = self.plant.time_s
            if self.watch.refusal:
                self.refused_starts += 1
                self.watch.note(now, f"cycle start refused: {self.watch.refusal}")
                return False
            if self.watch.resume():
                self.watch.note(now, "cycle start: the program resumes after the feed hold")
                return True
        if self.pending is None:
            return False
        self.load_program(self.pending)
        self.pending = None
        return True

    def override_speed(self, rpm: float | None) -> None:
        """Force a speed regardless of the program (None: follow the program)."""
        self._override_rpm = rpm

    def start_probe(self) -> int:
        """Start a probe cycle now: the spindle stops for the tool setter's ``dwell_s``, then
        the measurement is published (:attr:`probe_value_um`, then :attr:`probe_sequence`) and
        the program resumes where it stopped. The sequence number the measurement will carry,
        or 0 when a probe cycle is running already."""
        self.advance()  # the cycle starts now, not at the last step
        with self._lock:
            if self._probe_until_s is not None:
                return 0
            self._probe_rpm = abs(self.plant._speed_rpm)
            self._probe_until_s = self.plant.time_s + self.tool_setter.cycle_s
            return self.probe_sequence + 1

    @property
    def probing(self) -> bool:
        return self._probe_until_s is not None

    def _stop_if_due(self) -> None:
        """The program reached its next probe stop: the cycle starts now (the lock is held)."""
        p = self.program
        if p is None or self._probe_until_s is not None or self._stops_done >= len(p.probe_at_s):
            return
        if self.plant.time_s - self._program_start_s >= p.probe_at_s[self._stops_done] - 1e-9:
            self._stops_done += 1
            self._stop_running = True
            self._probe_rpm = abs(self.plant._speed_rpm)
            self._probe_until_s = self.plant.time_s + self.tool_setter.cycle_s

    def _finish_probe(self) -> None:
        ts = self.tool_setter
        true = self.plant.true_elongation_um()
        # each touch is read at the setter's resolution, as the control reads the trip; the mean
        # is the cycle's value
        touches = true + ts.noise_um * self._probe_rng.standard_normal(ts.touches)
        if ts.resolution_um > 0:
            touches = np.round(touches / ts.resolution_um) * ts.resolution_um
        self.probe_true_um = true  # for scoring
        self.probe_value_um = float(np.mean(touches))
        self.probe_sigma_um = ts.sigma_um
        self.probe_sequence += 1
        self._program_start_s += ts.cycle_s  # the program waited for the probe cycle
        self._probe_until_s = None
        self._stop_running = False

    def commanded_rpm(self, t_s: float) -> float:
        if self._probe_until_s is not None:
            # a contact setter needs the spindle at rest; a laser at speed holds the speed the
            # program ran when the cycle began (the program waits for it)
            return self._probe_rpm if self.tool_setter.at_speed else 0.0
        if self._override_rpm is not None:
            return self._override_rpm
        if self.program is None:
            return 0.0
        rel = t_s - self._program_start_s
        if rel >= self.program.duration_s:
            return 0.0
        return self.program.speed_at(rel + 1e-9)

    @property
    def program_done(self) -> bool:
        if self.program is None:
            return True
        # a probe stop at the program's end belongs to the program
        return (
            not self._stop_running
            and self._stops_done >= len(self.program.probe_at_s)
            and self.plant.time_s - self._program_start_s >= self.program.duration_s
        )

    @property
    def speed_rpm(self) -> float:
        return abs(self.plant._speed_rpm)

    @property
    def at_speed(self) -> bool:
        return self.plant.at_speed

    @property
    def cutting(self) -> bool:
        """The tool is in the part now (never during a probe cycle: the spindle is stopped; never
        in a feed hold: the axes stand)."""
        return self._probe_until_s is None and not self.watch.held and self.plant.cutting

    @property
    def measured_um(self) -> float:
        return self._hist[-1][3] if self._hist else self.plant.true_elongation_um()

    def apply_offset(self, offset_um: object) -> bool:
        """Take a written offset, as a CNC would: False (and ignored) if not acceptable."""
        if (
            isinstance(offset_um, (int, float))
            and not isinstance(offset_um, bool)
            and math.isfinite(offset_um)
            and abs(offset_um) <= OFFSET_LIMIT_UM
        ):
            self.offset_um = float(offset_um)
            return True
        self.rejected_writes += 1
        return False

    def advance(self) -> None:
        """Step the plant on its fixed grid up to the clock."""
        with self._lock:
            target = self.clock()
            h = self.plant_dt_s
            while self.plant.time_s + h <= target + 1e-9:
                self.watch.update(self.plant.time_s)
                if self.watch.held and self._probe_until_s is None:
                    self._program_start_s += h  # a feed hold: the program's time stands
                self._stop_if_due()
                rpm = self.commanded_rpm(self.plant.time_s + h / 2)
                self.plant.drive(rpm, h)  # the drive ramps to it
                if self.watch.fading:
                    self.offset_um = self.watch.fade(self.offset_um, h)
                for name, node, lag_s, *_ in SENSORS:
                    x = (
                        self.plant.air_c(self.plant.time_s)
                        if node is None
                        else self.plant.temps_c[node]
                    )
                    self._lagged[name] = lag_step(self._lagged[name], float(x), h, lag_s)
                true = self.plant.true_elongation_um()
                meas = float(self.plant.measure_um(true))
                self._hist.append(
                    (
                        self.plant.time_s,
                        abs(self.plant._speed_rpm),
                        true,
                        meas,
                        self.offset_um,
                        self.cutting,
                    )
                )
                if (
                    self._probe_until_s is not None
                    and self.plant.time_s >= self._probe_until_s - 1e-9
                ):
                    self._finish_probe()
            self.watch.update(self.plant.time_s)

    def sensor_values(self) -> dict[str, float]:
        """What the machine's sensors read now (noise, resolution, injected faults)."""
        out = {}
        for name, _node, _lag, noise, step in SENSORS:
            v = self._lagged[name] + noise * float(self._sensor_rng.standard_normal())
            out[name] = round(v / step) * step
        load = (
            100.0
            * float(self.plant.heat_w(self.speed_rpm))
            / float(self.plant.heat_w(self.plant.params.max_rpm))
        )
        out["spindle_load_pct"] = round(
            max(0.0, load + 0.5 * float(self._sensor_rng.standard_normal())), 1
        )
        for name, mode in self.sensor_faults.items():
            if mode == "nan":
                out[name] = math.nan
            elif mode == "frozen":
                out[name] = self._frozen.setdefault(name, out[name])
        for name in list(self._frozen):
            if self.sensor_faults.get(name) != "frozen":
                del self._frozen[name]
        return out

    def history(self, clear: bool = False) -> History:
        with self._lock:
            arr = np.array(self._hist, dtype=float).reshape(-1, 6)
            if clear:
                self._hist.clear()
        time_s, speed_rpm, true_um, measured_um, offset_um = (arr[:, i].copy() for i in range(5))
        return History(time_s, speed_rpm, true_um, measured_um, offset_um, arr[:, 5] != 0)


class VirtualCNC:
    """A :class:`VirtualMachine` behind an asyncua server. Use from asyncio, or via :func:`running`."""

    def __init__(
        self,
        machine: VirtualMachine,
        *,
        host: str = "127.0.0.1",
        port: int | None = None,
        tick_s: float | None = 0.005,
        certificate: str | None = None,
        private_key: str | None = None,
        users: dict[str, str] | None = None,
        control=None,
        admins: frozenset[str] = frozenset(),
        rights: dict[str, set[str]] | None = None,
    ):
        """With ``certificate`` and ``private_key`` the server accepts only
        Basic256Sha256 (Sign, SignAndEncrypt); with ``users`` only those user names and
        passwords, never anonymous. ``tick_s``: how often (wall seconds) the server takes a
        written offset, advances the plant and publishes; None: only when its owner calls
        :func:`step` (lock-step with a :class:`~compensator.clock.SteppedClock`).

        ``control``: an :class:`~machine_sim.controls.EmulatedControl`; the offset node
        then holds the value in that profile's unit, and the control takes it (or refuses it)
        and applies it at its own rate. A SINUMERIK profile adds SINUMERIK's ids: the speed
        ``/Channel/Spindle/actSpeed[u1,1]`` and setting datum SD43900 (the offset node), which
        only users with the ``SeaWrite`` right may write (``rights``: user -> rights), granted by
        ``GiveUserAccess`` called by one of ``admins``."""
        self.machine = machine
        self.failed: dict[str, str] = {}
        """Published nodes (keys of the node tables) that carry a status other than Good, by
        status name (``BadSensorFailure``): a failed sensor, with its last value kept, as a
        controller may publish it. Set by a test; taken at the next publish."""
        self.certificate = certificate
        self.private_key = private_key
        self.users = users
        self.host = host
        self.port = port or free_port(host)
        self.tick_s = tick_s
        self.url = f"opc.tcp://{host}:{self.port}/thermocomp/virtual-cnc/"
        self._server: Server | None = None
        self._nodes: dict = {}
        self._task: asyncio.Task | None = None
        self.ns = 2
        self.loop: asyncio.AbstractEventLoop | None = None  # set by running()
        self.control = control
        self.sinumerik = control is not None and control.profile.name == "sinumerik"
        self.admins = frozenset(admins)
        self.rights: dict[str, set[str]] = {k: set(v) for k, v in (rights or {}).items()}
        self.denied_writes = 0
        self._offset_key = "sd43900" if self.sinumerik else "thermal_offset"
        self._seen_raw = 0.0

    # -- server ----------------------------------------------------------------

    async def start(self) -> None:
        from asyncua import Server, ua, uamethod

        user_manager = None
        if self.users is not None:
            from asyncua.crypto.permission_rules import User, UserRole
            from asyncua.server.user_managers import UserManager

            users = dict(self.users)

            class Passwords(UserManager):
                def get_user(self, iserver, username=None, password=None, certificate=None):
                    if username in users and users[username] == password:
                        return User(role=UserRole.User, name=username)
                    return None

            user_manager = Passwords()
        server = Server(user_manager=user_manager)
        await server.init()
        server.set_endpoint(self.url)
        server.set_server_name("thermocomp virtual CNC")
        if self.certificate and self.private_key:
            await server.load_certificate(self.certificate)
            await server.load_private_key(self.private_key)
            server.set_security_policy(
                [
                    ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
                    ua.SecurityPolicyType.Basic256Sha256_Sign,
                ]
            )
        else:
            server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        if self.users is not None:
            server.set_identity_tokens([ua.UserNameIdentityToken])
        self.ns = await server.register_namespace(NAMESPACE_URI)
        objects = server.nodes.objects
        folders: dict[str, Node] = {}

        async def folder(path: str) -> Node:
            if path in folders:
                return folders[path]
            parent_path, _, name = path.rpartition("/")
            parent = objects if not parent_path else await folder(parent_path)
            node = await parent.add_object(f"ns={self.ns};s={path}", f"{self.ns}:{name}")
            folders[path] = node
            return node

        for key, path in NODE_PATHS.items():
            parent_path, _, name = path.rpartition("/")
            parent = await folder(parent_path)
            node = await parent.add_variable(
                f"ns={self.ns};s={path}",
                f"{self.ns}:{name}",
                ua.Variant(0.0, ua.VariantType.Double),
            )
            if key == "thermal_offset":
                await node.set_writable()  # for every client, like the CNC's own variable
            self._nodes[key] = node
        for key, path in STATE_PATHS.items():
            parent_path, _, name = path.rpartition("/")
            self._nodes[key] = await (await folder(parent_path)).add_variable(
                f"ns={self.ns};s={path}",
                f"{self.ns}:{name}",
                ua.Variant(False, ua.VariantType.Boolean),
            )
        for key, path in TOOL_SETTER_PATHS.items():
            parent_path, _, name = path.rpartition("/")
            initial = (
                ua.Variant(0, ua.VariantType.UInt32)
                if key == "probe_sequence"
                else ua.Variant(0.0, ua.VariantType.Double)
            )
            self._nodes[key] = await (await folder(parent_path)).add_variable(
                f"ns={self.ns};s={path}", f"{self.ns}:{name}", initial
            )
        machine = self.machine

        @uamethod
        def probe(_parent):
            return ua.Variant(machine.start_probe(), ua.VariantType.UInt32)

        await (await folder(PROBE_METHOD_PATH.rpartition("/")[0])).add_method(
            f"ns={self.ns};s={PROBE_METHOD_PATH}",
            f"{self.ns}:Probe",
            probe,
            [],
            [ua.VariantType.UInt32],
        )
        if self.sinumerik:
            await self._add_sinumerik(server, folder, ua, uamethod)
        start = await (await folder("/CncInterface/Simulation")).add_variable(
            f"ns={self.ns};s={CYCLE_START_PATH}",
            f"{self.ns}:CycleStart",
            ua.Variant(False, ua.VariantType.Boolean),
        )
        await start.set_writable()
        self._nodes["cycle_start"] = start
        await self._add_watch(folder, ua)
        # a controller that restarts has lost the variable: 0, whatever the machine held before
        self.machine.apply_offset(0.0)
        self.machine.watch.restart()  # ... and its watch: the life counter reads 0 again
        if self.control is not None:
            self.control.reset()
            self._seen_raw = 0.0
        await server.start()
        self._server = server
        await self._publish()
        if self.tick_s is not None:
            self._task = asyncio.create_task(self._run(self.tick_s))

    async def _add_watch(self, folder, ua) -> None:
        """The sign of life's nodes (writable by any client, as a control's variables), the
        watch's status (read-only) and the operator's reset."""
        types = {
            "life_counter": ua.Variant(0, ua.VariantType.Int32),
            "compensation_valid": ua.Variant(False, ua.VariantType.Boolean),
            "compensation_watch": ua.Variant("waiting", ua.VariantType.String),
            "compensation_reaction": ua.Variant("", ua.VariantType.String),
            "compensation_alarm": ua.Variant("", ua.VariantType.String),
            "compensation_trips": ua.Variant(0, ua.VariantType.UInt32),
            "compensation_tripped_at": ua.Variant(-1.0, ua.VariantType.Double),
            "reset": ua.Variant(False, ua.VariantType.Boolean),
        }
        for key, path in (*LIFE_PATHS.items(), *WATCH_PATHS.items(), ("reset", RESET_PATH)):
            parent_path, _, name = path.rpartition("/")
            node = await (await folder(parent_path)).add_variable(
                f"ns={self.ns};s={path}", f"{self.ns}:{name}", types[key]
            )
            if key in LIFE_PATHS or key == "reset":
                await node.set_writable()
            self._nodes[key] = node

    async def _add_sinumerik(self, server, folder, ua, uamethod) -> None:
        """SINUMERIK's own ids (in this server's namespace, ns=2 as on a SINUMERIK), setting datum
        SD43900 writable only with the SeaWrite right, and GiveUserAccess."""

        speed = await (await folder("/Channel/Spindle")).add_variable(
            f"ns={self.ns};s={SINUMERIK_SPEED_NODE}",
            f"{self.ns}:actSpeed",
            ua.Variant(0.0, ua.VariantType.Double),
        )
        sd = await (await folder("/NC/_N_AX_SEA_ACX")).add_variable(
            f"ns={self.ns};s={SINUMERIK_SD43900_NODE}",
            f"{self.ns}:$SA_TEMP_COMP_ABS_VALUE",
            ua.Variant(0.0, ua.VariantType.Double),
        )
        await sd.set_writable()
        for key, path in SINUMERIK_LIFE_NODES.items():
            r = await (await folder("/Channel/Parameter")).add_variable(
                f"ns={self.ns};s={path}",
                f"{self.ns}:{path.rpartition('/')[2]}",
                ua.Variant(0.0, ua.VariantType.Double),
            )
            await r.set_writable()
            self._nodes[f"sinumerik_{key}"] = r
        self._nodes["sinumerik_speed"] = speed
        self._nodes["sd43900"] = sd
        sd_id = sd.nodeid
        vcnc = self
        internal = (
            server.iserver.isession.user
        )  # the server's own writes (publishing, a refusal's undo)

        @uamethod
        def give_user_access(parent, user, realms):
            # "StateRead; SeaRead; SeaWrite": one call may grant several
            vcnc.rights.setdefault(str(user), set()).update(
                r.strip() for r in str(realms).split(";") if r.strip()
            )
            return ua.Variant(True, ua.VariantType.Boolean)

        method = await (await folder("/Methods")).add_method(
            f"ns={self.ns};s={SINUMERIK_GIVE_ACCESS}",
            f"{self.ns}:GiveUserAccess",
            give_user_access,
            [ua.VariantType.String, ua.VariantType.String],
            [ua.VariantType.Boolean],
        )
        method_id = method.nodeid
        service = server.iserver.attribute_service
        plain_write = service.write

        async def write(params, user=None):
            # setting data take a write only from a user with the SeaWrite right
            name = getattr(user, "name", None)
            allowed = (
                user is None or user is internal or SEA_WRITE in vcnc.rights.get(name or "", set())
            )
            denied = [wv.NodeId == sd_id and not allowed for wv in params.NodesToWrite]
            if not any(denied):
                return (
                    await plain_write(params, user=user)
                    if user is not None
                    else await plain_write(params)
                )
            vcnc.denied_writes += sum(denied)
            kept = [wv for wv, d in zip(params.NodesToWrite, denied) if not d]
            done = iter(
                await plain_write(ua.WriteParameters(NodesToWrite=kept), user=user) if kept else []
            )
            return [
                ua.StatusCode(ua.StatusCodes.BadUserAccessDenied) if d else next(done)
                for d in denied
            ]

        service.write = write
        iserver = server.iserver
        plain_session = iserver.create_session

        def create_session(*args, **kw):
            session = plain_session(*args, **kw)
            plain_call = session.call

            async def call(params):
                # GiveUserAccess: the administrators only (the session's user, once activated)
                if (
                    any(req.MethodId == method_id for req in params)
                    and getattr(session.user, "name", None) not in vcnc.admins
                ):
                    # as SINUMERIK documents it: a caller who is no administrator
                    return [
                        ua.CallMethodResult(
                            StatusCode=ua.StatusCode(ua.StatusCodes.BadInvalidArgument)
                        )
                        for _ in params
                    ]
                return await plain_call(params)

            session.call = call
            return session

        iserver.create_session = create_session

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        if self._server is not None:
            await self._server.stop()
            self._server = None

    async def _run(self, tick_s: float) -> None:
        while True:
            await self.tick()
            await asyncio.sleep(tick_s)

    async def tick(self) -> None:
        """Take the offset a client wrote, advance the plant to the clock, publish."""
        m = self.machine
        if self.control is None:
            written = await self._nodes["thermal_offset"].read_value()
            if written != m.offset_um and not m.apply_offset(written):
                await self._nodes["thermal_offset"].write_value(m.offset_um)
        else:
            node = self._nodes[self._offset_key]
            written = await node.read_value()
            if written != self._seen_raw:  # a client wrote: the control takes it, or refuses it
                if not self.control.write_raw(written):
                    await node.write_value(float(self.control.held_raw))
                self._seen_raw = float(self.control.held_raw)
            self.control.sync()  # the axis moves to the held value at the control's rate
        # the sign of life as written since the last tick: at the plant's time, like the offset
        life = "sinumerik_" if self.sinumerik else ""
        m.life_beat(
            await self._nodes[f"{life}life_counter"].read_value(),
            await self._nodes[f"{life}compensation_valid"].read_value(),
        )
        if await self._nodes["reset"].read_value() is True:
            m.reset()
            await self._nodes["reset"].write_value(False)
        if (m.pending is not None or m.watch.held) and await self._nodes[
            "cycle_start"
        ].read_value():
            m.advance()  # the program starts now, not at the last tick
            m.cycle_start()  # refused while the watch's alarm or feed hold stands: a press is spent
            await self._nodes["cycle_start"].write_value(False)
        m.advance()
        if m.watch.fading:  # the control rewrites its own variable as the offset fades
            await self._follow_fade()
        await self._publish()

    async def _follow_fade(self) -> None:
        """The fading offset is the variable's value: a read-back sees it, and a client's next
        write starts from it."""
        m = self.machine
        if self.control is None:
            await self._nodes["thermal_offset"].write_value(float(m.offset_um))
            return
        c, units = self.control, self.control.profile.units
        c.applied_um = m.offset_um
        # the control fades in its own arithmetic, not in whole counts: a count's rounding each
        # tick would hold a slow fade where it is
        c.held_raw = m.offset_um * units.scale * units.sign
        self._seen_raw = float(c.held_raw)
        await self._nodes[self._offset_key].write_value(float(c.held_raw))

    async def _publish(self) -> None:
        from asyncua import ua

        m = self.machine
        true = m.plant.true_elongation_um()
        values = {
            "act_speed": m.speed_rpm,
            "cmd_speed": m.commanded_rpm(m.plant.time_s),
            "displacement": m.measured_um,
            "sim_time": m.plant.time_s,
            "true_elongation": true,
            "tool_tip_error": true + m.offset_um,
        }
        values.update(m.sensor_values())
        if self.sinumerik:
            values["sinumerik_speed"] = m.speed_rpm

        def with_status(key: str, variant: Any) -> Any:
            bad = self.failed.get(key)
            return (
                variant
                if bad is None
                else ua.DataValue(variant, ua.StatusCode(getattr(ua.StatusCodes, bad)))
            )

        for key, v in values.items():
            await self._nodes[key].write_value(
                with_status(key, ua.Variant(float(v), ua.VariantType.Double))
            )
        for key, flag in (("at_speed", m.at_speed), ("cutting", m.cutting)):
            await self._nodes[key].write_value(
                with_status(key, ua.Variant(bool(flag), ua.VariantType.Boolean))
            )
        # as a probe cycle writes them: the value, then the counter
        seq, value, sigma = m.probe_sequence, m.probe_value_um, m.probe_sigma_um
        await self._nodes["probe_measurement"].write_value(
            ua.Variant(float(value), ua.VariantType.Double)
        )
        await self._nodes["probe_sigma"].write_value(
            ua.Variant(float(sigma), ua.VariantType.Double)
        )
        await self._nodes["probe_sequence"].write_value(ua.Variant(int(seq), ua.VariantType.UInt32))
        w = m.watch
        for key, variant in (
            ("compensation_watch", ua.Variant(w.state, ua.VariantType.String)),
            ("compensation_reaction", ua.Variant(w.reaction_text(), ua.VariantType.String)),
            ("compensation_alarm", ua.Variant(w.alarm, ua.VariantType.String)),
            ("compensation_trips", ua.Variant(int(w.trips), ua.VariantType.UInt32)),
            (
                "compensation_tripped_at",
                ua.Variant(
                    -1.0 if w.tripped_at_s is None else float(w.tripped_at_s),
                    ua.VariantType.Double,
                ),
            ),
        ):
            await self._nodes[key].write_value(variant)


def call(vcnc: VirtualCNC, coro_fn) -> None:
    """Run ``vcnc.stop``, ``vcnc.start`` or ``vcnc.tick`` on its own loop (under :func:`running`)."""
    assert vcnc.loop is not None
    asyncio.run_coroutine_threadsafe(coro_fn(), vcnc.loop).result(30)


def step(vcnc: VirtualCNC) -> None:
    """One server tick now, from another thread: take the offset a client wrote, advance the
    plant to the clock, publish (lock-step with a :class:`~compensator.clock.SteppedClock`)."""
    call(vcnc, vcnc.tick)


@contextlib.contextmanager
def running(vcnc: VirtualCNC) -> Iterator[VirtualCNC]:
    """Run ``vcnc`` on an event loop in a background thread, for synchronous callers."""
    loop = asyncio.new_event_loop()
    ready = threading.Event()
    error: list[BaseException] = []

    def main() -> None:
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(vcnc.start())
        except BaseException as err:  # noqa: BLE001 - handed to the caller
            error.append(err)
            ready.set()
            return
        ready.set()
        loop.run_forever()

    thread = threading.Thread(target=main, name="virtual-cnc", daemon=True)
    thread.start()
    ready.wait(30)
    if error:
        raise error[0]
    vcnc.loop = loop
    try:
        yield vcnc
    finally:
        asyncio.run_coroutine_threadsafe(vcnc.stop(), loop).result(30)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(30)
        loop.close()
