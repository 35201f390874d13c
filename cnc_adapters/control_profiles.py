"""Controller profiles: what each control family does with the offset thermocomp writes.

A profile is a named preset of the adapter settings for one control family (``sinumerik``,
``fanuc``, ``heidenhain``, ``haas``, ``linuxcnc``, ``beckhoff``, and ``virtual``, the virtual
CNC's own). It fixes what the control side decides, so that an integrator does not have to:

- the unit and resolution of the written value (mm, 0.1 um, detection units) and its sign;
- the largest value and the largest single step the control takes;
- whether the control itself rate-limits the value, and how fast;
- how the value the control holds is read back;
- the NC/PLC snippet that applies it (the whole recipe is in ``docs/controls/<family>.md``);
- the routes from the PC to the control (OPC UA, S7, FOCAS, MDC, ADS, HAL), each an adapter
  configuration with what is left for the user to give.

An adapter configuration names one with ``profile`` (and ``route``, default the profile's
first): ``{profile = "sinumerik", route = "s7", host = "10.0.0.5", ...}``. The registry merges
the route's adapter settings and the profile's units under the user's own keys
(:func:`adapter_settings`). Pure data: no I/O, no library import.

Where a figure is the control's and public documentation does not fix it (a SINUMERIK's rate
factor is machine data the builder sets), the profile carries a documented default that the
emulated control uses and ``docs/controls/<family>.md`` says how to read the real one.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

from compensator.errors import ConfigError, unknown
from compensator.units import ControllerUnits

from .reading import LIFE_OPTION_PAIRS

__all__ = [
    "PROFILES",
    "ControllerProfile",
    "Route",
    "adapter_settings",
    "control_count_um",
    "life_options",
    "profile",
]

_FROZEN = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Route(BaseModel):
    """One way from the PC to a control: the adapter settings it presets, and what it takes."""

    model_config = _FROZEN

    adapter: dict[str, Any] = Field(description="adapter settings this route presets (a 'type')")
    library: str = Field(description="the Python library that speaks the protocol")
    tested: str = Field(description="how this route is tested here")
    control_side: str = Field(description="what the integrator must do on the control")
    requires: tuple[str, ...] = Field((), description="adapter options the user must give")
    fixed: dict[str, Any] = Field(
        default_factory=dict,
        description="options the profile's units hold for: a user's other value is refused",
    )


class ControllerProfile(BaseModel):
    """What a control family does with the written offset (see the module docstring).

    ``raw = offset_um * scale * sign`` is the value in the control's unit, with thermocomp's
    offset ``A = -S`` (positive S: the tool tip moved toward the workpiece)."""

    model_config = _FROZEN

    name: str
    title: str
    unit: str = Field(description="the written value's unit, in words")
    scale: float = Field(gt=0, description="control units per um")
    sign: int = Field(description="+1 or -1: the control's value is sign * A")
    resolution: float = Field(ge=0, description="control units of one count; 0: continuous")
    integer: bool = Field(False, description="the control takes whole counts only")
    limit: float = Field(gt=0, description="largest |value| the control takes, in its units")
    max_step: float | None = Field(
        None,
        gt=0,
        description="largest change per write the control "
        "takes without an alarm, in its units; None: no such limit",
    )
    control_rate_um_per_s: float | None = Field(
        None,
        gt=0,
        description="the control moves its applied value at most this fast; None: "
        "it applies each value at once",
    )
    rate_source: str = Field("", description="where the control's rate limit comes from")
    readback: str = Field(description="how the held value is read back")
    snippet: str = Field(description="the NC/PLC code that applies the value (the short form)")
    life_sign: str = Field(
        "",
        description="the sign of life: what the control watches, and where the routes write it",
    )
    doc: str = Field(description="the full recipe, relative to the repository")
    routes: dict[str, Route]

    @field_validator("sign")
    @classmethod
    def _sign(cls, v: int) -> int:
        if v not in (1, -1):
            raise ValueError("+1 or -1")
        return v

    @property
    def limit_um(self) -> float:
        """The control's limit as an offset [um]."""
        return self.limit / self.scale

    @property
    def resolution_um(self) -> float:
        """One count as an offset [um] (0: continuous)."""
        return self.resolution / self.scale

    @property
    def max_step_um(self) -> float | None:
        return None if self.max_step is None else self.max_step / self.scale

    @property
    def units(self) -> ControllerUnits:
        """The control's unit and sign as the adapters convert them (raw = A * scale * sign)."""
        return ControllerUnits(self.scale, self.sign, self.resolution)

    def route_name(self, name: str | None = None) -> str:
        """``name``, or the profile's first route (the family's usual one)."""
        return name or next(iter(self.routes), "")

    def route(self, name: str | None = None) -> Route:
        """The route ``name`` (None: the first, the family's usual one); ConfigError naming the
        known ones otherwise."""
        if not self.routes:
            raise ConfigError(
                f"profile {self.name!r} has no route thermocomp can drive: see {self.doc}"
            )
        key = self.route_name(name)
        try:
            return self.routes[key]
        except KeyError:
            raise ConfigError(
                f"profile {self.name!r} has no route {key!r}; known: {', '.join(self.routes)}"
            ) from None

    def life_text(
        self,
        route: str | None = None,
        settings: Mapping[str, Any] | None = None,
        writes_life: bool = True,
    ) -> str:
        """The sign of life, in words: the route's defaults; or, given a link's ``settings``
        (:func:`adapter_settings`' result) and ``writes_life`` (whether that link writes one),
        what the link writes, or ``off``."""
        r = self.route(route)
        default = life_options(r.adapter)
        text = self.life_sign or "none"
        if settings is None:
            return f"{text} ({_shown(default)})" if default else text
        if not writes_life:
            return "off (the control cannot tell when thermocomp stops)"
        given = life_options(settings)
        if not given or given == default:  # the profile's own (or HAL pins, always there)
            return f"{text} ({_shown(given)})" if given else text
        return f"{_shown(given)} (the control's check must watch these)"

    def describe(
        self,
        route: str | None = None,
        settings: Mapping[str, Any] | None = None,
        writes_life: bool = True,
    ) -> str:
        """One paragraph: what the profile will do (``thermocomp run --check`` prints it, with
        the link's ``settings``: see :meth:`life_text`)."""
        r = self.route(route)
        key = self.route_name(route)
        res = (
            f"resolution {self.resolution:g} ({self.resolution_um:g} um)"
            if self.resolution
            else "continuous"
        )
        rate = (
            f"the control itself moves it at most {self.control_rate_um_per_s:g} um/s "
            f"({self.rate_source})"
            if self.control_rate_um_per_s
            else "the control applies each value at once (the shaper's slew is the only rate limit)"
        )
        step = f", an alarm at a step of more than {self.max_step:g}" if self.max_step else ""
        sign = "+S (the growth itself)" if self.sign == -1 else "-S (the offset A)"
        return (
            f"profile {self.name} ({self.title}), route {key} via {r.library}: writes {sign} "
            f"in {self.unit}, {res}, |value| <= {self.limit:g} ({self.limit_um:g} um){step}; "
            f"{rate}; read-back: {self.readback}; on the control: {r.control_side}; "
            f"sign of life: {self.life_text(route, settings, writes_life)}; recipe: {self.doc}"
        )


def _life_groups() -> list[tuple[str, ...]]:
    """Each backend's sign-of-life options, the counter's and the flag's together."""
    return [counters + flags for counters, flags in LIFE_OPTION_PAIRS]


def life_options(settings: Mapping[str, Any]) -> dict[str, Any]:
    """The sign-of-life options an adapter's settings (:func:`adapter_settings`' result, or a
    route's) name: ``{"life_macro": 502, "valid_macro": 503}``; ``{}`` for none (``""``
    turns a default off)."""
    for counters, flags in LIFE_OPTION_PAIRS:
        found = {k: settings[k] for k in (*counters, *flags) if settings.get(k) is not None}
        if found:
            return found if all(v != "" for v in found.values()) else {}
    return {}


def _shown(options: Mapping[str, Any]) -> str:
    return ", ".join(f"{k} = {v!r}" for k, v in options.items())


_SINUMERIK_SNIPPET = """\
; MD32750 $MA_TEMP_COMP_TYPE[Z] = 1 (bit 0: position-independent), MD32760 limits the rate
; S7 route: the PLC writes the growth [mm] as a REAL that the NC reads as $A_DBR[0]
IDS=1 WHENEVER TRUE DO $$SA_TEMP_COMP_ABS_VALUE[Z]=$A_DBR[0]
; OPC UA route: thermocomp writes SD43900 $SA_TEMP_COMP_ABS_VALUE[Z] itself (right SeaWrite)"""

_FANUC_SNIPPET = """\
(thermocomp writes the growth in detection units to common variable #500 over FOCAS)
(the builder's ladder: on a change of #500 -> THD00-15, THSTB up; wait THREND; THSTB down)
(macro alternative: #1133 = #500 + 32768 to the UO signals; the ladder subtracts 32768)
(and does the THD handshake: check #1133 and its F addresses on your control)"""

_HEIDENHAIN_SNIPPET = """\
; TNC 426/430: PLC module 9231 takes the compensation in 0.1 um per axis
; older controls: PLC words W576-W582, followed at 1 um/s
; TNC 640 / TNC7: a TEMPCOMP formula in the kinematics that reads PLC data (the builder's)"""

_HAAS_SNIPPET = """\
(thermocomp writes the growth [mm] to macro #10500 over MDC: ?E10500 0.0123)
(O08500 after each tool change and before each pass; #10600+T: growth already in T's wear)
G103 P1
#[2200 + #3026] = #[2200 + #3026] + #10500 - #[10600 + #3026]
#[10600 + #3026] = #10500
G43 H#3026 (re-apply: the wear takes effect at G43)
G103 P0"""

_BECKHOFF_SNIPPET = """\
(* thermocomp writes the growth in 0.1 um (DINT) to a PLC variable over ADS; the PLC checks
   range and rate and writes TEMPC::offset_0 with ADSWRITE (GEO task, port 551), with
   P-AXIS-00271 temp_comp = 1 and the slope P-AXIS-00274 = 0; TEMPC::actual_offset comes back *)"""

_LINUXCNC_SNIPPET = """\
net tc-counts thermocomp.eoffset-counts => axis.z.eoffset-counts
net tc-scale  thermocomp.eoffset-scale  => axis.z.eoffset-scale
net tc-enable thermocomp.eoffset-enable => axis.z.eoffset-enable
# [AXIS_Z] OFFSET_AV_RATIO = 0.1 (the share of velocity and acceleration external offsets may use)"""

PROFILES: dict[str, ControllerProfile] = {
    p.name: p
    for p in (
        ControllerProfile(
            name="sinumerik",
            title="Siemens SINUMERIK 840D sl / ONE",
            unit="mm (SD43900, a REAL)",
            scale=0.001,
            sign=-1,
            resolution=0.0,
            limit=1.0,
            control_rate_um_per_s=5000.0,
            rate_source="MD32760 $MA_COMP_ADD_VELO_FACTOR x MD32000 $MA_MAX_AX_VELO: the default "
            "factor 0.01 of an example 30 m/min; read yours off the machine",
            readback="SD43900 read back (OPC UA), or the DB word the NC reports (S7)",
            snippet=_SINUMERIK_SNIPPET,
            life_sign="a synchronized action checks that a counter moves and a valid flag is 1: "
            "R98/R99 (OPC UA) or DB100.DBW14/DBW16 (S7)",
            doc="docs/controls/sinumerik.md",
            routes={
                "opcua": Route(
                    adapter={
                        "type": "opcua",
                        "preset": "sinumerik-sea",
                        "life_node": "ns=2;s=/Channel/Parameter/R[u1,98]",
                        "valid_node": "ns=2;s=/Channel/Parameter/R[u1,99]",
                    },
                    library="asyncua",
                    tested="the virtual CNC's SINUMERIK-like address space (asyncua "
                    "server): SD43900 node, writes refused without the SeaWrite right",
                    control_side="MD32750 bit 0 on the axis; the OPC UA option; a user with the SeaWrite "
                    "right (GiveUserAccess)",
                    requires=("url", "offset_node|offset_path"),
                ),
                "s7": Route(
                    adapter={
                        "type": "plc",
                        "protocol": "s7",
                        "rack": 0,
                        "slot": 2,
                        "life_address": "DB100.DBW14",
                        "valid_address": "DB100.DBW16",
                    },
                    library="python-snap7",
                    tested="python-snap7's own S7 server (snap7.server) on "
                    "loopback, the synchronized action emulated",
                    control_side="MD32750 bit 0; a DB with PUT/GET access; the synchronized action "
                    "IDS=1 WHENEVER TRUE DO $$SA_TEMP_COMP_ABS_VALUE[Z]=$A_DBR[0]",
                    requires=("host", "offset_address", "speed_address"),
                ),
            },
        ),
        ControllerProfile(
            name="fanuc",
            title="FANUC 0i-F / 30i-B",
            unit="detection units (1 um: IS-B, metric)",
            scale=1.0,
            sign=-1,
            resolution=1.0,
            integer=True,
            limit=32767.0,
            max_step=9998.0,
            readback="#500 read back over FOCAS, or ack_macro: the value the ladder reports after THREND",
            snippet=_FANUC_SNIPPET,
            life_sign="a macro or the ladder checks that #502 (counter) moves and #503 "
            "(valid) is 1",
            doc="docs/controls/fanuc.md",
            routes={
                "focas": Route(
                    adapter={"type": "focas", "life_macro": 502, "valid_macro": 503},
                    library="socket (own FOCAS client, pyfocas's documented packet format)",
                    tested="a loopback FOCAS server built from the documented packet format; pyfocas, "
                    "an independent client, talks to it",
                    control_side="the option 'thermal growth compensation along tool vector'; the "
                    "builder's ladder (THD00-15, THSTB, THREND) or a macro copying the variable",
                    requires=("host",),
                ),
            },
        ),
        ControllerProfile(
            name="heidenhain",
            title="HEIDENHAIN TNC",
            unit="0.1 um (module 9231, TNC 426/430; W576-W582 of older TNCs take 1 um: the PLC divides by 10)",
            scale=10.0,
            sign=-1,
            resolution=1.0,
            integer=True,
            limit=30000.0,
            control_rate_um_per_s=1.0,
            rate_source="the TNC follows W576-W582 at 1 um/s; module "
            "9231's rate is not documented publicly, taken the same",
            readback="the PLC word read back (any PLC route)",
            snippet=_HEIDENHAIN_SNIPPET,
            life_sign="the PLC checks that a counter word moves and a valid word is 1: give "
            "life_address and valid_address on the gateway (no default)",
            doc="docs/controls/heidenhain.md",
            routes={
                "plc": Route(
                    adapter={"type": "plc"},
                    library="python-snap7 / pymodbus / pyads (the builder's PLC gateway)",
                    tested="docs only: nothing here speaks to a TNC (pylsv2 reads PLC memory but "
                    "cannot write it); the PLC route's own code is tested against S7, Modbus and ADS",
                    control_side="the machine builder maps a PLC word from a gateway to W576-W582, "
                    "module 9231, or the TEMPCOMP formula's PLC data",
                    requires=("protocol", "host", "offset_address", "speed_address"),
                ),
            },
        ),
        ControllerProfile(
            name="haas",
            title="Haas NGC",
            unit="mm (a macro variable; tool-length wear)",
            scale=0.001,
            sign=-1,
            resolution=0.0001,
            limit=0.5,
            readback="the macro variable read back with ?Q600",
            snippet=_HAAS_SNIPPET,
            life_sign="the program's macro checks that #10501 (counter) moves and #10502 "
            "(valid) is 1",
            doc="docs/controls/haas.md",
            routes={
                "mdc": Route(
                    adapter={"type": "haas-mdc", "life_var": 10501, "valid_var": 10502},
                    library="socket (MDC over TCP)",
                    tested="a loopback MDC server (threaded TCP) "
                    "emulating the reply forms reported for NGC over TCP and RS-232, the two-connection "
                    "limit and the wear applied at G43 safe points",
                    control_side="Setting 143 (MDC port); a macro that re-applies the wear with G43 at "
                    "safe points",
                    requires=("host",),
                    fixed={"offset_decimals": 4},
                ),
                "serial": Route(
                    adapter={"type": "haas", "life_var": 10501, "valid_var": 10502},
                    library="pyserial",
                    tested="pseudo-terminals: real serial links to an emulated Haas",
                    control_side="the RS-232 port; the same macro as the MDC route",
                    requires=("port",),
                    fixed={"offset_decimals": 4},
                ),
            },
        ),
        ControllerProfile(
            name="linuxcnc",
            title="LinuxCNC 2.9",
            unit="mm (external-offset counts of 0.01 um)",
            scale=0.001,
            sign=-1,
            resolution=0.00001,
            limit=1.0,
            control_rate_um_per_s=None,
            rate_source="",
            readback="axis.z.eoffset-request (the external offset motion is asked to apply; "
            "axis.z.eoffset, what it has reached, lags and stops at a soft limit)",
            snippet=_LINUXCNC_SNIPPET,
            life_sign="HAL logic watches thermocomp.life-counter (or life-toggle) and "
            "thermocomp.comp-valid, always exported",
            doc="docs/controls/linuxcnc.md",
            routes={
                "hal": Route(
                    adapter={"type": "linuxcnc"},
                    library="LinuxCNC's hal module",
                    tested="a real LinuxCNC (halrun and a simulator configuration)",
                    control_side="[AXIS_Z] OFFSET_AV_RATIO; net the eoffset pins",
                    fixed={"axis_units": "mm", "count_um": 0.01},
                ),
            },
        ),
        ControllerProfile(
            name="beckhoff",
            title="Beckhoff TwinCAT CNC",
            unit="0.1 um (P-AXIS-00273 temp_comp_offset_0, a DINT)",
            scale=10.0,
            sign=-1,
            resolution=1.0,
            integer=True,
            limit=10000.0,
            readback="the PLC's copy of TEMPC::actual_offset (held_address), or the variable read back",
            snippet=_BECKHOFF_SNIPPET,
            life_sign="a TON timer checks that GVL_Thermo.nLifeCounter moves and "
            "GVL_Thermo.bCompValid is TRUE",
            doc="docs/controls/beckhoff.md",
            routes={
                "ads": Route(
                    adapter={
                        "type": "plc",
                        "protocol": "ads",
                        "offset_type": "DINT",
                        "life_address": "GVL_Thermo.nLifeCounter",
                        "valid_address": "GVL_Thermo.bCompValid",
                    },
                    library="pyads",
                    tested="pyads's own ADS test server on loopback",
                    control_side="an ADS route to the PC; temp_comp = 1, slope 0; the PLC checks "
                    "range and rate and writes TEMPC::offset_0",
                    requires=("host", "offset_address", "speed_address"),
                    fixed={"offset_type": "DINT"},
                ),
            },
        ),
        ControllerProfile(
            name="virtual",
            title="thermocomp virtual CNC",
            unit="um (ThermalOffset)",
            scale=1.0,
            sign=1,
            resolution=0.0,
            limit=1000.0,
            readback="ThermalOffset read back",
            snippet="(none: the virtual CNC applies ThermalOffset)",
            life_sign="its watcher checks that LifeCounter moves and CompensationValid is true",
            doc="docs/reference/virtual-machine-tool.md",
            routes={
                "opcua": Route(
                    adapter={
                        "type": "opcua",
                        "preset": "virtual-cnc",
                        # the preset's own, named here so that run --check can show them
                        "life_node": "ns={ns};s=/CncInterface/CncSpindleList/Spindle1/LifeCounter",
                        "valid_node": "ns={ns};s=/CncInterface/CncSpindleList/Spindle1/"
                        "CompensationValid",
                    },
                    library="asyncua",
                    tested="the virtual CNC (asyncua server)",
                    control_side="nothing",
                    requires=("url",),
                ),
            },
        ),
    )
}


def profile(name: str) -> ControllerProfile:
    """The profile ``name``; ConfigError naming the known ones otherwise."""
    try:
        return PROFILES[name]
    except (KeyError, TypeError):
        raise ConfigError(unknown("controller profile", name, PROFILES)) from None


def adapter_settings(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """An adapter configuration with ``profile`` (and ``route``) resolved: the route's settings
    and the profile's units (``offset_scale``, ``offset_sign``, ``offset_resolution``) under the
    user's own keys; the profile's own keys taken out. A configuration without ``profile`` comes
    back unchanged. ConfigError for a user key that would change the control's units (the
    profile fixes them), and for a required option left out."""
    if "profile" not in cfg:
        if "route" in cfg:
            raise ConfigError("adapter: 'route' goes with 'profile'")
        return dict(cfg)
    user = dict(cfg)
    p = profile(user.pop("profile"))
    route_name = user.pop("route", None)
    r = p.route(route_name)
    for key in ("offset_scale", "offset_sign", "offset_resolution"):
        if key in user:
            raise ConfigError(
                f"adapter: {key} is fixed by profile {p.name!r} ({p.unit}); "
                "leave it out, or drop the profile"
            )
    if "type" in user and user["type"] != r.adapter.get("type"):
        raise ConfigError(
            f"adapter: profile {p.name!r}, route {p.route_name(route_name)!r} "
            f"uses type {r.adapter.get('type')!r}, not {user['type']!r}"
        )
    for key, value in r.fixed.items():
        if key in user and user[key] != value:
            raise ConfigError(
                f"adapter: profile {p.name!r} is for {key} = {value!r} ({p.unit}), not "
                f"{user[key]!r}: drop the profile and give the units yourself"
            )
    # "a|b": either will do
    missing = [
        k.replace("|", " or ") for k in r.requires if not any(a in user for a in k.split("|"))
    ]
    if missing:
        raise ConfigError(
            f"adapter: profile {p.name!r}, route {p.route_name(route_name)!r} "
            f"needs {', '.join(missing)} ({p.doc})"
        )
    units: dict[str, Any] = {"offset_scale": p.scale, "offset_sign": p.sign}
    if p.resolution:
        units["offset_resolution"] = p.resolution
    # a sign of life given by half keeps none of the route's: the settings refuse the half
    route = {
        k: v
        for k, v in r.adapter.items()
        if not any(k in pair and any(u in user for u in pair) for pair in _life_groups())
    }
    merged = {**route, **units, **user}
    if not math.isfinite(float(merged["offset_scale"])):
        raise ConfigError("adapter: offset_scale must be finite")
    return merged


def control_count_um(settings: Any) -> float:
    """One count of the controller's offset value [um], from an adapter's validated settings:
    ``offset_resolution`` (a profile's, or the user's), a Haas link's ``offset_decimals``, a
    LinuxCNC link's ``count_um``; 0 where the value is continuous. The shaper must move in whole
    multiples of it, or the rounding at the controller could cross the clamp or the slew limit."""
    scale = float(abs(getattr(settings, "offset_scale", None) or 1.0))
    resolution = getattr(settings, "offset_resolution", None)
    if resolution:
        return float(resolution) / scale
    decimals = getattr(settings, "offset_decimals", None)
    if decimals is not None:
        return 10.0 ** -int(decimals) / scale
    count = getattr(settings, "count_um", None)
    return float(count) if count else 0.0
