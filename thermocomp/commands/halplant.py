"""``thermocomp hal-plant``: the virtual spindle as a LinuxCNC HAL userspace component.

For LinuxCNC's simulated machines: it reads the simulated spindle's actual speed, grows like a
real motorized spindle (the ``SpindlePlant``), and shows what the part would see::

    loadusr -Wn thermocomp-plant thermocomp hal-plant --name thermocomp-plant --time-scale 60
    net spindle-rps-filtered => thermocomp-plant.speed-in
    net z-eoffset axis.z.eoffset => thermocomp-plant.eoffset-mm

Pins: ``speed-in`` (float in, rps), ``eoffset-mm`` (float in, the applied Z external offset),
``growth-um`` (out: the spindle's true growth toward the work), ``tip-error-um`` (out: growth
less the compensation the Z offset applies), ``sim-time-s`` (out).
"""

from __future__ import annotations

import argparse
import signal
import time

from cnc_adapters.linuxcnc import import_linuxcnc
from compensator.errors import ConfigError
from machine_sim.plant import SpindlePlant, preset
from machine_sim.vcnc import SimClock


def hal_plant(args: argparse.Namespace) -> int:
    try:
        params = preset(args.preset)
    except KeyError as err:
        raise ConfigError(str(err.args[0])) from err
    if not args.time_scale > 0:
        raise ConfigError("--time-scale must be > 0")
    hal = import_linuxcnc("hal")
    c = hal.component(args.name)
    c.newpin("speed-in", hal.HAL_FLOAT, hal.HAL_IN)
    c.newpin("eoffset-mm", hal.HAL_FLOAT, hal.HAL_IN)
    c.newpin("growth-um", hal.HAL_FLOAT, hal.HAL_OUT)
    c.newpin("tip-error-um", hal.HAL_FLOAT, hal.HAL_OUT)
    c.newpin("sim-time-s", hal.HAL_FLOAT, hal.HAL_OUT)
    c.ready()
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
    plant = SpindlePlant(params, seed=args.seed)
    clock = SimClock(args.time_scale)
    h = args.step_s
    try:
        while not stop:
            target = clock()
            rpm = abs(float(c["speed-in"])) * 60.0
            while plant.time_s + h <= target:
                plant.advance(rpm, h)  # a fixed step keeps the plant's matrix exponentials cached
            growth = plant.true_elongation_um()
            c["growth-um"] = growth
            # +Z external offset moves the tool away from the work: it cancels growth
            c["tip-error-um"] = growth - 1000.0 * float(c["eoffset-mm"])
            c["sim-time-s"] = plant.time_s
            time.sleep(0.02)
    except KeyboardInterrupt:
        pass
    return 0
