"""The ``sim`` backend: an in-process virtual machine, like python-can's ``virtual`` bus.

``sim://motorized-27k?program=job-shop-day&seed=3&time_scale=60`` builds a plant, a speed
program and a simulated clock (``accel_rpm_per_s`` and ``approach_s`` change the preset's drive). Reading the speed advances the plant to the clock; the
written offset moves the virtual tool tip (``machine.history().tool_tip_error_um``) and is
read back from the machine (:attr:`VirtualMachine.offset_um`). The machine's tool setter
(:meth:`VirtualMachine.start_probe`) is read like a controller's probe variables, with the
sequence-counter handshake, and its cutting state (:attr:`VirtualMachine.cutting`: the tool in
the part) like a controller's cutting signal. The sign of life (life counter and "compensation
valid" flag) goes to the machine's watch (:meth:`VirtualMachine.life_beat`), which reacts as
its settings say when it stops.
"""

from __future__ import annotations

import numbers
from dataclasses import replace
from typing import TYPE_CHECKING, Annotated, Any, ClassVar
from urllib.parse import parse_qsl, urlsplit

from pydantic import Field

from cnc_adapters.base import (
    Adapter,
    AdapterError,
    AdapterSettings,
    Allowed,
    Life,
    Positive,
    RawMeasurement,
    WriteRejectedError,
    one_of,
)
from compensator.speed_programs import PROGRAMS
from compensator.speed_programs import program as make_program

from .plant import PRESETS, SpindlePlant
from .vcnc import SimClock, VirtualMachine

if TYPE_CHECKING:  # a plain string to the type checker; pydantic checks the choice
    PlantPreset = str
    ProgramName = str
else:
    PlantPreset = one_of(*PRESETS)
    ProgramName = one_of(*PROGRAMS)


class SimSettings(AdapterSettings):
    """The options of :class:`SimAdapter` (``machine``, an existing virtual machine, is a
    runtime-only keyword)."""

    preset: PlantPreset = "motorized-27k"
    program: ProgramName | None = Field("job-shop-day", description="speed program; none: idle")
    seed: Annotated[int, Field(ge=0), Allowed("a whole number >= 0")] = 0
    time_scale: Positive = Field(60.0, description="simulated seconds per second")
    accel_rpm_per_s: Positive = Field(  # type: ignore[assignment]
        None, description="how fast the drive changes speed; default the preset's"
    )
    approach_s: Annotated[float, Field(ge=0), Allowed("a number >= 0 (seconds)")] = Field(  # type: ignore[assignment]
        None, description="from at-speed to the first cut; default the preset's"
    )


class SimAdapter(Adapter):
    name = "sim"
    Settings: ClassVar[type[AdapterSettings]] = SimSettings
    can_read_offset: ClassVar[bool] = True
    can_read_measurement: ClassVar[bool] = True
    can_read_cutting: ClassVar[bool] = True
    writes_life = True  # the virtual machine's control watches it

    def __init__(
        self,
        preset: str = "motorized-27k",
        *,
        program: str | None = "job-shop-day",
        seed: int = 0,
        time_scale: float = 60.0,
        accel_rpm_per_s: float | None = None,
        approach_s: float | None = None,
        machine: VirtualMachine | None = None,
        **scaling: Any,
    ):
        super().__init__(**scaling)
        if machine is None:
            if preset not in PRESETS:
                raise AdapterError(f"unknown sim preset {preset!r}; known: {', '.join(PRESETS)}")
            drive: dict[str, Any] = {
                k: v
                for k, v in (("accel_rpm_per_s", accel_rpm_per_s), ("approach_s", approach_s))
                if v is not None
            }
            params = replace(PRESETS[preset], **drive)
            try:
                prog = make_program(program, params.max_rpm, seed=seed) if program else None
            except KeyError as err:
                raise AdapterError(str(err.args[0])) from err
            # a clock handed in (the runtime's) drives the plant too, so both share one time
            machine = VirtualMachine(
                SpindlePlant(params, seed=seed),
                prog,
                clock=scaling.get("clock") or SimClock(time_scale),
            )
        self.machine = machine

    @classmethod
    def url_options(cls, url: str) -> dict[str, Any]:
        """``sim://motorized-27k?program=job-shop-day&seed=3``; ``program=`` (empty): idle."""
        parts = urlsplit(url)
        kw: dict[str, Any] = {
            "preset": parts.netloc or "motorized-27k",
            **dict(parse_qsl(parts.query, keep_blank_values=True)),
        }
        if kw.get("program") == "":
            kw["program"] = None
        return kw

    def _connect(self) -> None:
        self.machine.advance()

    def _read_speed_raw(self) -> float:
        self.machine.advance()
        return self.machine.speed_rpm

    def _read_offset_raw(self) -> float:
        return self.machine.offset_um

    def _write_offset_raw(self, value: float) -> None:
        if not self.machine.apply_offset(value):
            raise WriteRejectedError(f"sim: offset {value!r} refused by the virtual CNC")

    def _write_life_raw(self, life: Life) -> None:
        self.machine.life_beat(life.counter, life.valid)

    def _read_measurement_raw(self) -> RawMeasurement:
        self.machine.advance()
        m = self.machine
        seq = m.probe_sequence  # the counter first: it changes after the value
        scale = self.measurement_scale or self.units.scale  # the controller's unit
        return RawMeasurement(
            seq, _scaled(m.probe_value_um, scale), _scaled(m.probe_sigma_um, scale)
        )

    def _read_cutting_raw(self) -> bool:
        self.machine.advance()
        return self.machine.cutting

    def input_channels(self) -> tuple[str, ...]:
        from .vcnc import SENSOR_KEYS

        return SENSOR_KEYS

    def _read_inputs_raw(self) -> dict[str, float]:
        self.machine.advance()
        return self.machine.sensor_values()

    def _disconnect(self) -> None:
        pass


def _scaled(value: Any, scale: float) -> Any:
    """A number in the controller's unit; anything else as it is (the base refuses it)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return value
    return float(value) * scale
