"""LinuxCNC link: a HAL userspace component that drives the Z axis's external offsets.

Started the LinuxCNC way, from a HAL file::

    loadusr -Wn thermocomp thermocomp run --config thermocomp.toml
    net spindle-rps-filtered => thermocomp.speed-in        # the spindle's *actual* speed
    net tc-counts  thermocomp.eoffset-counts => axis.z.eoffset-counts
    net tc-scale   thermocomp.eoffset-scale  => axis.z.eoffset-scale
    net tc-enable  thermocomp.eoffset-enable => axis.z.eoffset-enable
    net tc-clear   thermocomp.eoffset-clear  => axis.z.eoffset-clear

Pins of the component (``component``, default ``thermocomp``):

==================== ====== === ===========================================================
pin                  type   dir
==================== ====== === ===========================================================
speed-in             float  in  actual spindle speed (``speed_unit``: rps, as spindle.N.speed-in, or rpm)
eoffset-counts       s32    out to axis.L.eoffset-counts
eoffset-scale        float  out to axis.L.eoffset-scale (machine units per count)
eoffset-enable       bit    out to axis.L.eoffset-enable
eoffset-clear        bit    out to axis.L.eoffset-clear
offset-um            float  out the offset requested now [um] (thermocomp's sign: A = -S)
ready                bit    out machine on and homed: external offsets are honoured
input.<name>         float  in  extra channels (``inputs = [...]``) for a model with inputs
machine-on, homed    bit    in  only with ``machine_state = "pins"`` (else from linuxcnc.stat)
measurement.value    float  in  only with ``measurement = true``: the probe cycle's measurement
measurement.sequence float  in  its counter (``measurement_sequence_type``: float, s32 or u32)
measurement.sigma    float  in  only with ``measurement_sigma = true``: the measurement's sigma
cutting              bit    in  only with ``cutting = "pin"``: the tool is in the part
at-speed             bit    in  with ``cutting = "at-speed"`` or ``"feed"``: net to spindle.N.at-speed
motion-type          s32    in  with ``cutting = "feed"``: net motion.motion-type
life-counter         s32    out the sign of life: 1 .. 32767, one step each cycle thermocomp writes
life-toggle          bit    out flips with each step of the counter (for HAL's ``watchdog``)
comp-valid           bit    out true while thermocomp compensates (false: holding, not writing, stopped)
==================== ====== === ===========================================================

The sign of life: each cycle that writes or confirms the offset moves ``life-counter`` on and
flips ``life-toggle``, in the same call that sets the offset pins (the offset first, so a beat
never runs ahead of its offset). ``comp-valid`` is false while the runtime holds or cannot write,
and after a clean stop (its last beat). A killed thermocomp leaves every pin where it was: the
toggle stops, and that is what the control watches. The HAL recipe that watches it and its
reactions (an alarm that stops the next cycle start, a feed hold, a fade of the offset to zero)
are ``examples/linuxcnc/thermocomp-watchdog.hal`` and its companions (docs/controls/linuxcnc.md).

External offsets are accumulated count deltas times the scale, zeroed at every machine-on and
honoured only once all joints are homed (LinuxCNC's external-offsets chapter). So while the
machine is off, in E-stop or not homed the counts are held at zero and the runtime is told that
the controller applies no offset (:meth:`not_ready_offset_um`); once it is on and homed the
runtime re-seeds the offset from zero through its slew limit. Motion holds the change of its
counts pin since machine-on times the scale, so at that moment thermocomp takes over from what
motion holds (``held_pin``) and what its pin sees (``axis.L.eoffset-counts`` beside it): 0 and 0
after a machine-on; after a restart of thermocomp the offset motion still applies (faded, maybe,
by the control's watchdog), and a counts signal that kept an old value through a machine-on is
allowed for. Taking over never moves the offset by itself.

Sign: thermocomp's offset is ``A = -S`` with positive ``S`` toward the workpiece. On a vertical
spindle that is -Z, so the Z external offset is ``+S``: ``offset_sign = -1`` (the default).

Reading the offset back: the component's own pins only say what thermocomp wrote, which is no
check at all. What motion holds is LinuxCNC's ``axis.L.eoffset-request`` (the accumulated counts
times the scale, in machine units), read by name (``held_pin``, default
``axis.z.eoffset-request``; name the axis the counts are netted to, or ``""`` for no read-back).
While the machine is not ready it applies no external offset, so the read-back is 0 then.

The closed loop: with ``measurement = true`` a tool-setter or probe cycle hands its
measurement over through ``measurement.value`` and ``measurement.sequence`` (the value first,
then a changed counter; each value is used once, the counter found at the first read is stale).
The value is in machine units like the offset (``measurement_scale = 1`` for a cycle that hands
over um), positive when the tool grew toward the workpiece. From the G-code, through motion's
analog outputs (``motion.analog-out-NN``, float; four unless ``num_aio`` says more)::

    net tc-meas     motion.analog-out-00 => thermocomp.measurement.value
    net tc-meas-seq motion.analog-out-01 => thermocomp.measurement.sequence

    M68 E0 Q#<growth>               (the value first ...)
    M68 E1 Q[#<count>]              (... then the new counter)

M68 sets the output at once; M67 with the next move. A sequence pin of type s32 or u32
(``measurement_sequence_type``) takes a counter from an integer source (a ladder, a comp).

The cutting signal, so that the elastic step of a speed change is applied fast while
the tool is clear of the part and slowly while it cuts (``cutting``):

- ``"feed"``: the tool cuts while the spindle is at speed and motion makes a feed move:
  ``at-speed`` and ``motion-type`` in ``cutting_values`` (default 2 and 3, linear and arc feed;
  motion(9): 0 idle, 1 traverse, 2 linear feed, 3 arc feed, 4 tool change, 5 probing)::

      net spindle-at-speed => spindle.0.at-speed thermocomp.at-speed
      net motion-type motion.motion-type => thermocomp.motion-type

- ``"at-speed"``: the tool is taken to cut whenever the spindle is at speed (motion waits for
  ``spindle.N.at-speed`` before the first feed move after a speed change);
- ``"pin"``: a ``cutting`` bit from the machine's own logic (a ladder, a comp);
- ``"none"`` (default): no signal; the runtime infers it from the speed.
"""

from __future__ import annotations

import logging
import math
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, ClassVar
from urllib.parse import urlsplit

from pydantic import BeforeValidator, Field, model_validator

from .base import (
    Adapter,
    AdapterError,
    AdapterSettings,
    Allowed,
    BadValueError,
    CuttingValues,
    Life,
    NonZero,
    Positive,
    RawMeasurement,
    Sign,
    UnreachableError,
    one_of,
    query_params,
    read_handshake,
)

log = logging.getLogger("thermocomp.adapters.linuxcnc")

LINUXCNC_PYTHON = ("/usr/lib/python3/dist-packages", "/usr/lib/linuxcnc/python")
S32 = 2**31 - 1


def import_linuxcnc(module: str):
    """LinuxCNC's own Python modules (``hal``, ``linuxcnc``), also from a virtual environment."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        pass
    for path in LINUXCNC_PYTHON:
        if path not in sys.path:
            sys.path.append(path)  # after the venv's own packages: they keep precedence
    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise UnreachableError(
            f"linuxcnc: cannot import LinuxCNC's {module!r} module ({err}); "
            "is linuxcnc-uspace installed?"
        ) from err


HAL_NAME = r"^[A-Za-z0-9][A-Za-z0-9_.-]*$"


def _component_pid(name: str) -> int | None:
    """The process that owns userspace HAL component ``name`` (halcmd's PID column)."""
    try:
        r = subprocess.run(
            ["halcmd", "-s", "show", "comp", name], capture_output=True, text=True, timeout=10
        )
    except (OSError, subprocess.SubprocessError):
        return None
    for line in r.stdout.splitlines():
        parts = line.split()
        if len(parts) >= 4 and parts[1] == "User" and parts[2] == name and parts[3].isdigit():
            return int(parts[3])
    return None


def _process_alive(pid: int) -> bool:
    """True unless ``pid`` is gone or a zombie (killed, not yet reaped by its parent)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    except OSError:
        return True  # cannot tell: say it runs, never call a live process dead
    return stat.rsplit(")", 1)[-1].split()[:1] != ["Z"]


def _names(v: Any) -> Any:
    # a URL gives the names as one comma-separated string
    return [n.strip() for n in v.split(",") if n.strip()] if isinstance(v, str) else v


InputName = Annotated[
    str, Field(pattern=r"^[A-Za-z0-9_-]+$"), Allowed("letters, digits, '_' and '-'")
]
ComponentName = Annotated[str, Field(pattern=HAL_NAME), Allowed("a HAL component name")]
PinName = Annotated[
    str, Field(pattern=r"^$|" + HAL_NAME), Allowed("a HAL pin name, or '' for none")
]
if TYPE_CHECKING:  # a plain string to the type checker; pydantic checks the choice
    SpeedUnit = str
    AxisUnits = str
    MachineState = str
    SequenceType = str
    CuttingSource = str
else:
    SpeedUnit = one_of("rps", "rpm")
    AxisUnits = one_of("mm", "inch")
    MachineState = one_of("stat", "pins")
    SequenceType = one_of("float", "s32", "u32")
    CuttingSource = one_of("none", "pin", "at-speed", "feed")
FEED_MOTION_TYPES = (2, 3)
"""motion.motion-type of a feed move: linear (G1) and arc (G2/G3) feed (motion(9))."""


class LinuxCncSettings(AdapterSettings):
    """The options of :class:`LinuxCncAdapter`."""

    component: ComponentName = "thermocomp"
    speed_unit: SpeedUnit = Field("rps", description="of speed-in: rps, as spindle.N.speed-in")
    axis_units: AxisUnits = Field("mm", description="[TRAJ]LINEAR_UNITS")
    count_um: Positive = Field(0.01, description="um per external-offset count")
    machine_state: MachineState = Field(
        "stat", description="linuxcnc.stat, or pins machine-on/homed"
    )
    inputs: Annotated[
        list[InputName],
        BeforeValidator(_names),
        Allowed("names of letters, digits, '_' and '-' ('a,b' in a URL)"),
    ] = Field(default_factory=list, description="extra channels: float IN pins input.<name>")
    held_pin: PinName = Field(
        "axis.z.eoffset-request",
        description="the pin holding the external "
        "offset motion applies (machine units); '' for no read-back",
    )
    offset_sign: Sign = Field(-1, description="-1 for a vertical Z spindle (the default)")
    measurement: bool = Field(
        False,
        description="closed loop: IN pins measurement.value and "
        "measurement.sequence for a probe cycle's measurement",
    )
    measurement_sigma: bool = Field(False, description="an IN pin measurement.sigma too")
    measurement_sequence_type: SequenceType = Field(
        "float",
        description="of measurement.sequence: float (netted to motion.analog-out-NN), s32, u32",
    )
    measurement_scale: NonZero = Field(  # type: ignore[assignment]
        None, description="machine units per um of the measurement; default the offset's"
    )
    cutting: CuttingSource = Field(
        "none",
        description="the cutting signal: pin (a bit), at-speed, "
        "feed (at-speed and motion-type), or none (inferred from the speed)",
    )
    cutting_values: CuttingValues = Field(
        list(FEED_MOTION_TYPES),  # type: ignore[arg-type]  # a list, as documented
        description="feed: the motion types that count as cutting",
    )

    @model_validator(mode="after")
    def _measurement(self) -> LinuxCncSettings:
        if self.measurement_sigma and not self.measurement:
            raise ValueError(
                "measurement_sigma needs measurement = true (the value and its counter)"
            )
        if "cutting_values" in self.model_fields_set and self.cutting != "feed":
            raise ValueError(
                'cutting_values goes with cutting = "feed" (the motion types that cut); '
                "a bit (pin, at-speed) is true while cutting"
            )
        return self


class LinuxCncAdapter(Adapter):
    name = "linuxcnc"
    Settings: ClassVar[type[AdapterSettings]] = LinuxCncSettings
    can_read_offset: ClassVar[bool] = True  # an instance with held_pin = "" cannot
    can_read_measurement: ClassVar[bool] = True  # an instance without measurement = true cannot
    writes_life = True  # the life pins are always exported: a HAL file nets them or not

    def __init__(
        self,
        *,
        component: str = "thermocomp",
        speed_unit: str = "rps",
        axis_units: str = "mm",
        count_um: float = 0.01,
        machine_state: str = "stat",
        inputs: list[str] | tuple[str, ...] = (),
        held_pin: str = "axis.z.eoffset-request",
        measurement: bool = False,
        measurement_sigma: bool = False,
        measurement_sequence_type: str = "float",
        measurement_scale: float | None = None,
        cutting: str = "none",
        cutting_values: tuple[Any, ...] = FEED_MOTION_TYPES,
        **kw: Any,
    ):
        if speed_unit not in ("rps", "rpm"):
            raise AdapterError("linuxcnc: speed_unit is 'rps' (spindle.N.speed-in) or 'rpm'")
        if axis_units not in ("mm", "inch"):
            raise AdapterError("linuxcnc: axis_units is 'mm' or 'inch' ([TRAJ]LINEAR_UNITS)")
        if machine_state not in ("stat", "pins"):
            raise AdapterError("linuxcnc: machine_state is 'stat' (linuxcnc.stat) or 'pins'")
        if not count_um > 0:
            raise AdapterError("linuxcnc: count_um must be > 0")
        if measurement_sigma and not measurement:
            raise AdapterError("linuxcnc: measurement_sigma needs measurement = true")
        if measurement_sequence_type not in ("float", "s32", "u32"):
            raise AdapterError("linuxcnc: measurement_sequence_type is 'float', 's32' or 'u32'")
        if cutting not in ("none", "pin", "at-speed", "feed"):
            raise AdapterError("linuxcnc: cutting is 'none', 'pin', 'at-speed' or 'feed'")
        kw.setdefault("offset_sign", -1)
        kw.setdefault("speed_scale", 60.0 if speed_unit == "rps" else 1.0)
        kw.setdefault("offset_scale", 0.001 if axis_units == "mm" else 1 / 25400.0)
        super().__init__(**kw)
        self.component = component
        # extra channels for models with inputs: float IN pins `input.<name>` to net sensors to
        self.inputs = tuple(inputs)
        for name in self.inputs:
            if not name.replace("_", "").replace("-", "").isalnum():
                raise AdapterError(
                    f"linuxcnc: input name {name!r}: letters, digits, '_' and '-' only"
                )
        self.machine_state = machine_state
        self.held_pin = held_pin or None
        self.can_read_offset = self.held_pin is not None  # type: ignore[misc]
        self.count = count_um * self.offset_scale  # machine units per count
        self.can_read_measurement = bool(measurement)  # type: ignore[misc]
        self.measurement_sigma = bool(measurement and measurement_sigma)
        self.measurement_sequence_type = measurement_sequence_type
        self.measurement_scale = measurement_scale
        self.cutting = cutting
        self.can_read_cutting = cutting != "none"  # type: ignore[misc]
        # a bit is compared with True; the feed source hands over the motion type
        self.cutting_values = tuple(cutting_values) if cutting == "feed" else (True,)
        # HAL's component, the status channel and the linuxcnc module: untyped C extensions
        self._comp: Any = None
        self._stat: Any = None
        self._lcnc: Any = None
        self._ready = False
        self._toggle = False  # life-toggle as last written
        self._counter = 0  # life-counter as last written
        # the counts this process stands for while ready (None: none yet), set again with each
        # write: a pin netted after it was set takes the signal's old value
        self._counts_now: int | None = None
        # motion's pin at machine-on, in counts: 0 unless thermocomp took over a machine that
        # was switched on while its counts signal held an old value
        self._base = 0

    @classmethod
    def url_options(cls, url: str) -> dict[str, Any]:
        """``linuxcnc://thermocomp?speed_unit=rps&axis_units=mm``."""
        return {"component": urlsplit(url).netloc or "thermocomp", **query_params(url)}

    def _connect(self) -> None:
        hal = import_linuxcnc("hal")
        if self._comp is None:  # a HAL component lives as long as the process
            try:
                c = hal.component(self.component)
            except hal.error as err:
                raise UnreachableError(
                    self._name_taken(hal)
                    or (
                        f"linuxcnc create HAL component {self.component!r}: {err} "
                        "(is LinuxCNC running?)"
                    )
                ) from err
            c.newpin("speed-in", hal.HAL_FLOAT, hal.HAL_IN)
            c.newpin("eoffset-counts", hal.HAL_S32, hal.HAL_OUT)
            c.newpin("eoffset-scale", hal.HAL_FLOAT, hal.HAL_OUT)
            c.newpin("eoffset-enable", hal.HAL_BIT, hal.HAL_OUT)
            c.newpin("eoffset-clear", hal.HAL_BIT, hal.HAL_OUT)
            c.newpin("offset-um", hal.HAL_FLOAT, hal.HAL_OUT)
            c.newpin("ready", hal.HAL_BIT, hal.HAL_OUT)
            for name in self.inputs:
                c.newpin(f"input.{name}", hal.HAL_FLOAT, hal.HAL_IN)
            if self.machine_state == "pins":
                c.newpin("machine-on", hal.HAL_BIT, hal.HAL_IN)
                c.newpin("homed", hal.HAL_BIT, hal.HAL_IN)
            if self.can_read_measurement:
                seq_type = {"float": hal.HAL_FLOAT, "s32": hal.HAL_S32, "u32": hal.HAL_U32}
                c.newpin("measurement.value", hal.HAL_FLOAT, hal.HAL_IN)
                c.newpin(
                    "measurement.sequence", seq_type[self.measurement_sequence_type], hal.HAL_IN
                )
                if self.measurement_sigma:
                    c.newpin("measurement.sigma", hal.HAL_FLOAT, hal.HAL_IN)
            if self.cutting == "pin":
                c.newpin("cutting", hal.HAL_BIT, hal.HAL_IN)
            if self.cutting in ("at-speed", "feed"):
                c.newpin("at-speed", hal.HAL_BIT, hal.HAL_IN)
            if self.cutting == "feed":
                c.newpin("motion-type", hal.HAL_S32, hal.HAL_IN)
            c.newpin("life-counter", hal.HAL_S32, hal.HAL_OUT)
            c.newpin("life-toggle", hal.HAL_BIT, hal.HAL_OUT)
            c.newpin("comp-valid", hal.HAL_BIT, hal.HAL_OUT)
            c["eoffset-scale"] = self.count
            c["eoffset-counts"] = 0
            c["eoffset-enable"] = True
            c.ready()
            self._comp = c
            log.info(
                "linuxcnc: HAL component %s ready (%.6g machine units per count)",
                self.component,
                self.count,
            )
        if self.machine_state == "stat":
            self._lcnc = import_linuxcnc("linuxcnc")
            try:
                self._stat = self._lcnc.stat()
            except self._lcnc.error as err:
                raise UnreachableError(
                    f"linuxcnc open status channel (linuxcnc.stat): {err}"
                ) from err

    def _name_taken(self, hal: Any) -> str | None:
        """Why the component's name is taken, in one line; None: it is not (HAL refused for
        another reason)."""
        try:
            if not hal.component_exists(self.component):
                return None
        except (AttributeError, hal.error):
            return None
        name = self.component
        pid = _component_pid(name)
        if pid is None:
            return (
                f"linuxcnc: HAL component {name!r} exists already: another thermocomp, or one "
                "killed (HAL keeps its name until LinuxCNC restarts); see halcmd show comp"
            )
        if _process_alive(pid):
            return (
                f"linuxcnc: HAL component {name!r} belongs to process {pid}, which runs: stop "
                "it first, or give this thermocomp another component name"
            )
        # HAL frees a userspace component only when its own process says so: a killed one's
        # name stays taken, and halcmd unload only signals the process, which is gone
        return (
            f"linuxcnc: HAL component {name!r} is left from process {pid}, which ended "
            "without removing it (killed or crashed): LinuxCNC keeps the name until it "
            "restarts; restart LinuxCNC"
        )

    def _machine_ready(self) -> bool:
        c = self._comp
        if self.machine_state == "pins":
            return bool(c["machine-on"]) and bool(c["homed"])
        try:
            self._stat.poll()
        except self._lcnc.error as err:
            raise self._link_lost(f"linuxcnc poll status channel (linuxcnc.stat): {err}") from err
        s = self._stat
        on = s.task_state == self._lcnc.STATE_ON and not s.estop
        return on and all(s.homed[: s.joints])

    def _update(self) -> None:
        ready = self._machine_ready()
        c = self._comp
        if ready != self._ready:
            took = self._take_over() if ready else None
            if took is not None:
                # motion holds (pin - pin at machine-on) x scale: the counts go on from what its
                # pin sees now, the offset from what it holds (0 after a machine-on; after a
                # restart of thermocomp, what it still applies, faded maybe by the watchdog)
                held, at_pin = took
                self._base = at_pin - held
                c["eoffset-counts"] = self._counts_now = at_pin
            log.info(
                "linuxcnc: machine %s",
                (
                    "on and homed: external offsets honoured, re-seeding from "
                    + ("0" if took is None or not took[0] else f"the {took[0]} counts motion holds")
                    + (f" (counts offset by {self._base})" if took and self._base else "")
                )
                if ready
                else "off, in E-stop or not homed: counts held at 0",
            )
            self._ready = ready
        if not ready:
            c["eoffset-counts"] = 0  # zeroed at machine-on anyway: no jump when it comes back
            self._counts_now = 0
        c["ready"] = ready

    def _take_over(self) -> tuple[int, int] | None:
        """The external offset motion holds, in counts, and the counts its pin sees now
        (``axis.L.eoffset-counts`` beside ``held_pin``; the held ones where the held pin is
        another). None: no read-back configured, or it failed (the read-back reports that)."""
        if self.held_pin is None:
            return None
        held = self._pin_counts(self.held_pin, self.count)
        if held is None:
            return None
        if not self.held_pin.endswith(".eoffset-request"):
            return held, held
        at_pin = self._pin_counts(self.held_pin.removesuffix("-request") + "-counts", 1)
        return held, held if at_pin is None else at_pin

    @staticmethod
    def _pin_counts(pin: str, per_count: float) -> int | None:
        hal = import_linuxcnc("hal")
        try:
            value = float(hal.get_value(pin))
        except (AttributeError, RuntimeError, TypeError, ValueError):
            return None
        counts = round(value / per_count) if math.isfinite(value) else None
        return counts if counts is not None and abs(counts) <= S32 else None

    def _read_speed_raw(self) -> float:
        self._update()
        return self._comp["speed-in"]

    def _read_offset_raw(self) -> float:
        self._update()
        if not self._ready:
            return 0.0  # off, in E-stop or not homed: motion applies none (and zeroes it at machine-on)
        hal = import_linuxcnc("hal")
        try:
            return hal.get_value(self.held_pin)
        except AttributeError as err:  # hal.get_value came with LinuxCNC 2.8
            raise AdapterError(
                "linuxcnc: this LinuxCNC's hal module cannot read other pins; "
                'set held_pin = "" (no read-back)'
            ) from err
        except RuntimeError as err:
            raise AdapterError(
                f"linuxcnc read offset pin {self.held_pin}: {err} (held_pin names "
                "axis.<L>.eoffset-request of the axis the counts drive)"
            ) from err

    def _counts(self, value: float) -> int:
        counts = round(value / self.count) + self._base
        if abs(counts) > S32:
            raise BadValueError(
                f"linuxcnc write offset pin {self.component}.eoffset-counts: {value:g} "
                f"does not fit the s32 counts at this scale"
            )
        return counts

    def _write_offset_raw(self, value: float) -> None:
        self._write_raw(value, None)

    def _write_raw(self, raw: float | None, life: Life | None) -> None:
        # the offset checked before any pin moves: a refused offset writes no beat either
        counts = None if raw is None else self._counts(raw)
        c = self._comp
        if counts is not None:
            c["offset-um"] = self.offset_um_requested
            if self._ready:
                self._counts_now = counts
        if self._ready and self._counts_now is not None:
            # a confirm too: a thermocomp restarted under a running LinuxCNC is netted after its
            # first cycle, and its pin then holds the signal's old counts until set again
            c["eoffset-counts"] = self._counts_now
        if life is not None:
            self._write_life_raw(life)

    def _write_life_raw(self, life: Life) -> None:
        c = self._comp
        if life.counter != self._counter:  # the same beat again is no new beat
            self._toggle = not self._toggle
        self._counter = life.counter
        c["life-counter"] = life.counter
        c["life-toggle"] = self._toggle
        c["comp-valid"] = life.valid

    def input_channels(self) -> tuple[str, ...]:
        return self.inputs

    def _read_inputs_raw(self) -> dict[str, float]:
        return {name: self._comp[f"input.{name}"] for name in self.inputs}

    def _read_measurement_raw(self) -> RawMeasurement | None:
        c = self._comp
        # two M68 land in different servo periods: the counter is read twice, around the value
        return read_handshake(
            self.name,
            lambda: c["measurement.sequence"],
            lambda: c["measurement.value"],
            (lambda: c["measurement.sigma"]) if self.measurement_sigma else None,
        )

    def _read_cutting_raw(self) -> Any:
        c = self._comp
        if self.cutting == "pin":
            return bool(c["cutting"])
        if self.cutting == "at-speed":
            return bool(c["at-speed"])
        return int(c["motion-type"]) if c["at-speed"] else 0  # not at speed: idle, never a cut

    def not_ready_offset_um(self) -> float | None:
        """0 while the machine is off, in E-stop or not homed (the controller applies no
        external offset then, and zeroes it at machine-on); None when offsets are honoured."""
        return None if self._ready else 0.0

    def _disconnect(self) -> None:
        # the counts stay: stopping thermocomp must not pull the offset from under a running job
        self._stat = None
