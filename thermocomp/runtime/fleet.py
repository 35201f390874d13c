"""The spindles and the chiller loop of one configuration, built at start and again at a reload
(SIGHUP), beside the running ones: a reload that does not validate keeps them, with
``RELOAD_FAILED``."""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from compensator.errors import ConfigError, ThermocompError
from compensator.io import load_any_model

from .checks import plausible
from .config import RuntimeConfig, load_config
from .cooling import CoolingRuntime
from .events import event
from .spindle import SpindleRuntime

log = logging.getLogger("thermocomp.runtime")


@dataclass(frozen=True)
class Fleet:
    """One configuration's running parts."""

    cfg: RuntimeConfig
    spindles: dict[str, SpindleRuntime]
    cooling: CoolingRuntime | None


class Builder:
    """Builds a configuration's spindles and chiller loop on one clock and journal time base,
    and reloads them: the reload's bookkeeping (asked for, refused) is here."""

    def __init__(
        self,
        config_path: str | os.PathLike[str],
        *,
        clock: Callable[[], float],
        wall: Callable[[], float],
        anchor_s: float,
    ) -> None:
        self.config_path = config_path
        self.clock, self.wall, self.anchor_s = clock, wall, anchor_s
        self.requested = False  # SIGHUP: reload at the next tick
        self.failed = False  # the last reload was refused: RELOAD_FAILED until one is taken

    def spindles(
        self, cfg: RuntimeConfig, previous: Mapping[str, SpindleRuntime]
    ) -> dict[str, SpindleRuntime]:
        """Every spindle of ``cfg``, each starting from its ``previous`` runtime where there is
        one; every model is loaded and judged first, so that a refused reload leaves no trace."""
        for sc in cfg.spindle:
            loaded = load_any_model(sc.model)
            sc.refuse_other_spindle(loaded.spindle_id)
            plausible(loaded.fallback or loaded, sc.name, sc.faults.max_speed_rpm)
        out: dict[str, SpindleRuntime] = {}
        try:
            for sc in cfg.spindle:
                out[sc.name] = SpindleRuntime(
                    sc,
                    cfg.state_dir,
                    cfg.journal_path,
                    clock=self.clock,
                    wall=self.wall,
                    anchor_s=self.anchor_s,
                    journal_fsync_s=cfg.journal_fsync_s,
                    previous=previous.get(sc.name),
                )
        except BaseException:
            _discard(out)
            raise
        return out

    def cooling(
        self,
        cfg: RuntimeConfig,
        spindles: Mapping[str, SpindleRuntime],
        previous: CoolingRuntime | None,
    ) -> CoolingRuntime | None:
        """The chiller loop of ``[cooling]``, or None; in mode ``cooling`` its spindle writes no offset."""
        name = cfg.cooling_spindle
        for sname, rt in spindles.items():
            rt.writes_offset = not (
                name == sname and cfg.cooling is not None and cfg.cooling.mode == "cooling"
            )
        if name is None or cfg.cooling is None:
            return None
        return CoolingRuntime(
            cfg.cooling,
            spindles[name],
            cfg.journal_path,
            clock=self.clock,
            wall=self.wall,
            anchor_s=self.anchor_s,
            journal_fsync_s=cfg.journal_fsync_s,
            previous=previous,
        )

    def reload(self, running: Fleet) -> Fleet | None:
        """Re-read the configuration and the models and build the new parts beside the running
        ones, which then hand over their journals and close; None (and ``RELOAD_FAILED``) where
        anything does not validate: the running ones go on."""
        try:
            new = load_config(self.config_path)
            if new.state_dir.resolve() != running.cfg.state_dir.resolve():
                raise ConfigError("state_dir cannot change on reload; restart the service")
            built = self.spindles(new, running.spindles)
        except (ThermocompError, OSError) as err:
            self._refused(err)
            return None
        try:
            cooling = self.cooling(new, built, running.cooling)
        except (ThermocompError, OSError) as err:
            _discard(built)
            self._refused(err)
            return None
        for name, rt in running.spindles.items():
            if name in built:
                built[name].take_journal(rt)
            else:  # no longer compensated: its control is told so
                last_beat(rt)
            rt.close()
        if running.cooling is not None:
            running.cooling.close()
        if new.status != running.cfg.status or new.mqtt != running.cfg.mqtt:
            log.warning("[status] and [mqtt] changes take effect at the next restart")
        self.failed = False
        return Fleet(new, built, cooling)

    def _refused(self, err: Exception) -> None:
        self.failed = True
        event(
            "reload_refused",
            None,
            "reload refused, keeping the running configuration: %s",
            err,
            level=logging.ERROR,
            error=str(err)[:300],
        )


def last_beat(rt: SpindleRuntime) -> None:
    """Spindle ``rt``'s last sign of life at a clean stop (compensation not valid); never
    raises."""
    try:
        life = rt.offset.last_beat(rt.adapter.write, rt.link.up)
    except Exception as err:  # noqa: BLE001 - stopping goes on; the counter stops anyway
        log.warning("%s: last sign of life not written: %s", rt.cfg.name, err)
        return
    if life is not None:
        log.info(
            "%s: last sign of life %d: compensation no longer valid; the control holds %.3f um",
            rt.cfg.name,
            life.counter,
            rt.offset.held_um,
        )


def _discard(spindles: Mapping[str, SpindleRuntime]) -> None:
    """Runtimes built but never run: their journal and link closed, their state left alone."""
    for rt in spindles.values():
        rt.journal.close()
        rt.adapter.close()
