"""The controller boundary is not chatty: a cycle asks the link once (``read``) and writes at most
once (``write``), with the observer on, a model with inputs, a journal that records every input
channel, and a link that goes down and comes back. Nothing else of the link is called while the
service runs (the capabilities are a value, read without asking the controller)."""

from __future__ import annotations

import collections
from pathlib import Path
from typing import Any

from cnc_adapters import UnreachableError
from compensator.io import save_model
from compensator.model import ThermalModel
from compensator.speed_programs import job_shop_day
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import VirtualMachine
from thermocomp.runtime import SpindleRuntime
from thermocomp.runtime.config import load_config

WALL0 = 1.77e9


class Counted:
    """The sim link, every call from the runtime counted by name (a proxy, not a mock: each call
    goes to the real link)."""

    def __init__(self, link: SimAdapter):
        self._link = link
        self.calls: collections.Counter[str] = collections.Counter()

    def __getattr__(self, name: str) -> Any:
        value = getattr(self._link, name)
        if not callable(value):
            return value

        def call(*args: Any, **kw: Any) -> Any:
            self.calls[name] += 1
            return value(*args, **kw)

        return call


def test_a_cycle_reads_once_and_writes_at_most_once(tmp_path: Path) -> None:
    model = tmp_path / "model.json"
    save_model(
        model,
        ThermalModel.from_discrete(0.99, (0.0, 0.002, 0.0, 0.0), 1.0, speed_range_rpm=(0, 24000)),
    )
    cfg_path = tmp_path / "machine.toml"
    cfg_path.write_text(
        f'state_dir = "{tmp_path / "state"}"\nwatchdog = false\n[[spindle]]\nname = "s1"\n'
        f'model = "{model}"\nperiod_s = 1.0\nadapter = {{url = "sim://"}}\n'
        "[spindle.observer]\nenabled = true\n[spindle.faults]\nreadback_every = 1\n"
    )
    cfg = load_config(cfg_path)
    t = [0.0]
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k"), seed=3), None, clock=lambda: t[0])
    vm.load_program(job_shop_day(preset("motorized-27k").max_rpm, seed=3, hours=1))
    sim = SimAdapter(machine=vm)
    link = Counted(sim)
    rt = SpindleRuntime(
        cfg.spindle[0],
        cfg.state_dir,
        cfg.journal_path,
        clock=lambda: t[0],
        wall=lambda: WALL0 + t[0],
        adapter=link,  # type: ignore[arg-type]
    )
    link.calls.clear()  # what the start asked (none but the capabilities)
    real = sim._read_speed_raw
    down = range(100, 130)
    writes = 0
    try:
        for k in range(300):
            t[0] += 1.0
            if k in down:  # the controller goes away for 30 s, then comes back
                sim._read_speed_raw = lambda: (_ for _ in ()).throw(UnreachableError("gone"))  # type: ignore[method-assign]
            else:
                sim._read_speed_raw = real  # type: ignore[method-assign]
            before = dict(link.calls)
            out = rt.cycle()
            made = {k: v - before.get(k, 0) for k, v in link.calls.items() if v != before.get(k, 0)}
            assert made.get("read") == 1, made
            assert made.get("write", 0) <= 1 and set(made) <= {"read", "write"}, made
            writes += made.get("write", 0)
            # the one write carries the offset, or only the sign of life that confirms it
            assert not out.written or made.get("write") == 1
            if k not in down:  # every cycle the link is up: the sign of life
                assert made.get("write") == 1, (k, made)
            assert sim.writes_life and (rt.offset.life is not None)
    finally:
        rt.close()
    assert writes >= 10 and link.calls["read"] == 300  # it compensated through it all
    assert rt.offset.life is not None and rt.offset.life.counter == 300 - len(down)
