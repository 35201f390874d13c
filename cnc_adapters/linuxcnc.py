"""LinuxCNC link: a HAL userspace component that drives the Z axis's external offsets.

Started the LinuxCNC way, from a HAL file::

    loadusr -Wn thermocomp thermocomp run --config thermocomp.toml
    net spindle-rps-filtered => thermocomp.speed-in        # the spindle's *actual* speed
    net tc-counts  thermocomp.eoffset-counts => axis.z.eoffset-counts
    net tc-scale   thermocomp.eoffset-scale  => axis.z.eoffset-scale
    net tc-enable  thermocomp.eoffset-enable => axis.z.eoffset-enable
    net tc-clear   thermocomp.eoffset-clear  => axis.z.eoffset-clear

Pins of the component (``component``, default ``thermocomp``):

=================== ====== === ===========================================================
pin                 type   dir
=================== ====== === ===========================================================
speed-in            float  in  actual spindle speed (``speed_unit``: rps, as spindle.N.speed-in, or rpm)
eoffset-counts      s32    out to axis.L.eoffset-counts
eoffset-scale       float  out to axis.L.eoffset-scale (machine units per count)
eoffset-enable      bit    out to axis.L.eoffset-enable
eoffset-clear       bit    out to axis.L.eoffset-clear
offset-um           float  out the offset requested now [um] (thermocomp's sign: A = -S)
ready               bit    out machine on and homed: external offsets are honoured
input.<name>        float  in  extra channels (``inputs = [...]``) for a model with inputs
machine-on, homed   bit    in  only with ``machine_state = "pins"`` (else from linuxcnc.stat)
=================== ====== === ===========================================================

External offsets are accumulated count deltas times the scale, zeroed at every machine-on and
honoured only once all joints are homed (LinuxCNC's external-offsets chapter). So while the
machine is off, in E-stop or not homed the counts are held at zero and the runtime is told that
the controller applies no offset (:meth:`not_ready_offset_um`); once it is on and homed the
runtime re-seeds the offset from zero through its slew limit.

Sign: thermocomp's offset is ``A = -S`` with positive ``S`` toward the workpiece. On a vertical
spindle that is -Z, so the Z external offset is ``+S``: ``offset_sign = -1`` (the default).
"""

from __future__ import annotations

import logging
import sys
from typing import Any
from urllib.parse import urlsplit

from .base import Adapter, AdapterError, BadValueError, UnreachableError, typed_params

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
        raise UnreachableError(f"linuxcnc: cannot import LinuxCNC's {module!r} module ({err}); "
                               "is linuxcnc-uspace installed?") from err


class LinuxCncAdapter(Adapter):
    name = "linuxcnc"

    def __init__(self, *, component: str = "thermocomp", speed_unit: str = "rps",
                 axis_units: str = "mm", count_um: float = 0.01, machine_state: str = "stat",
                 inputs: list[str] | tuple[str, ...] = (), **kw: Any):
        if speed_unit not in ("rps", "rpm"):
            raise AdapterError("linuxcnc: speed_unit is 'rps' (spindle.N.speed-in) or 'rpm'")
        if axis_units not in ("mm", "inch"):
            raise AdapterError("linuxcnc: axis_units is 'mm' or 'inch' ([TRAJ]LINEAR_UNITS)")
        if machine_state not in ("stat", "pins"):
            raise AdapterError("linuxcnc: machine_state is 'stat' (linuxcnc.stat) or 'pins'")
        if not count_um > 0:
            raise AdapterError("linuxcnc: count_um must be > 0")
        kw.setdefault("offset_sign", -1)
        kw.setdefault("speed_scale", 60.0 if speed_unit == "rps" else 1.0)
        kw.setdefault("offset_scale", 0.001 if axis_units == "mm" else 1 / 25400.0)
        super().__init__(**kw)
        self.component = component
        # extra channels for models with inputs: float IN pins `input.<name>` to net sensors to
        self.inputs = tuple(inputs)
        for name in self.inputs:
            if not name.replace("_", "").replace("-", "").isalnum():
                raise AdapterError(f"linuxcnc: input name {name!r}: letters, digits, '_' and '-' only")
        self.machine_state = machine_state
        self.count = count_um * self.offset_scale  # machine units per count
        self._comp = None
        self._stat = None
        self._lcnc = None
        self._ready = False

    @classmethod
    def from_url(cls, url: str, **overrides: Any) -> LinuxCncAdapter:
        """``linuxcnc://thermocomp?speed_unit=rps&axis_units=mm``."""
        kw: dict[str, Any] = {"component": urlsplit(url).netloc or "thermocomp",
                              **typed_params(url, ints=frozenset({"offset_sign"}),
                                             floats=frozenset({"count_um", "offset_scale", "speed_scale"}))}
        kw.update(overrides)
        return cls(**kw)

    def _connect(self) -> None:
        hal = import_linuxcnc("hal")
        if self._comp is None:  # a HAL component lives as long as the process
            try:
                c = hal.component(self.component)
            except hal.error as err:
                raise UnreachableError(f"linuxcnc: cannot create HAL component {self.component!r}: {err} "
                                       "(is LinuxCNC running, and the name free?)") from err
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
            c["eoffset-scale"] = self.count
            c["eoffset-counts"] = 0
            c["eoffset-enable"] = True
            c.ready()
            self._comp = c
            log.info("linuxcnc: HAL component %s ready (%.6g machine units per count)", self.component, self.count)
        if self.machine_state == "stat":
            self._lcnc = import_linuxcnc("linuxcnc")
            try:
                self._stat = self._lcnc.stat()
            except self._lcnc.error as err:
                raise UnreachableError(f"linuxcnc: no status channel: {err}") from err

    def _machine_ready(self) -> bool:
        c = self._comp
        if self.machine_state == "pins":
            return bool(c["machine-on"]) and bool(c["homed"])
        try:
            self._stat.poll()
        except self._lcnc.error as err:
            raise self._link_lost(f"linuxcnc: status poll failed: {err}") from err
        s = self._stat
        on = s.task_state == self._lcnc.STATE_ON and not s.estop
        return on and all(s.homed[: s.joints])

    def _update(self) -> None:
        ready = self._machine_ready()
        c = self._comp
        if ready != self._ready:
            log.info("linuxcnc: machine %s", "on and homed: external offsets honoured, re-seeding from 0"
                     if ready else "off, in E-stop or not homed: counts held at 0")
            self._ready = ready
        if not ready:
            c["eoffset-counts"] = 0  # zeroed at machine-on anyway: no jump when it comes back
        c["ready"] = ready

    def _read_speed_raw(self) -> float:
        self._update()
        return self._comp["speed-in"]

    def _write_offset_raw(self, value: float) -> None:
        counts = round(value / self.count)
        if abs(counts) > S32:
            raise BadValueError(f"linuxcnc: offset {value:g} does not fit the s32 counts at this scale")
        c = self._comp
        c["offset-um"] = self.offset_um_requested
        if self._ready:
            c["eoffset-counts"] = counts

    def input_channels(self) -> tuple[str, ...]:
        return self.inputs

    def _read_inputs_raw(self) -> dict[str, float]:
        return {name: self._comp[f"input.{name}"] for name in self.inputs}

    def not_ready_offset_um(self) -> float | None:
        """0 while the machine is off, in E-stop or not homed (the controller applies no
        external offset then, and zeroes it at machine-on); None when offsets are honoured."""
        return None if self._ready else 0.0

    def _disconnect(self) -> None:
        # the counts stay: stopping thermocomp must not pull the offset from under a running job
        self._stat = None
