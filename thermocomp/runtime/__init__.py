"""The compensation runtime: the service an edge box runs (``thermocomp run``).

- :mod:`.config`: the TOML configuration (pydantic, ``extra="forbid"``);
- :mod:`.spindle`: one spindle's cycle, read -> step -> shape -> write -> journal;
- :mod:`.link`: link health (connected, retrying, outage);
- :mod:`.offset`: the offset (tracking, ramping, holding), owning the shaper;
- :mod:`.service`: all spindles in one process, signals, the reload, over its parts: the
  spindles built and reloaded (:mod:`.fleet`), their schedule (:mod:`.watch`), the status
  published (:mod:`.publish`, :mod:`.status`), the control socket (:mod:`.inbox`), journal
  retention (:mod:`.sweep`), systemd and logging (:mod:`.host`).
"""

from .config import FaultPolicy, RuntimeConfig, SpindleConfig, load_config
from .link import LinkHealth, LinkState
from .offset import OffsetMode, OffsetTracker
from .service import Service, check
from .spindle import Alarm, SpindleRuntime

__all__ = [
    "Alarm",
    "FaultPolicy",
    "LinkHealth",
    "LinkState",
    "OffsetMode",
    "OffsetTracker",
    "RuntimeConfig",
    "Service",
    "SpindleConfig",
    "SpindleRuntime",
    "check",
    "load_config",
]
