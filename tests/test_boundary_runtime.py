"""The controller boundary under the service's cycle: whatever an OPC UA controller puts in any
node the cycle reads (speed, cutting, held offset, an input, the probe's value, sigma and
sequence), of any variant type and with any status, the cycle never raises, the offset it
writes is finite, within the clamp and within the slew limit, and the journal never records a
value beyond the clamp as the held offset (it records the clamp's edge, with OFFSET_MISMATCH).

A real asyncua server (tests/test_boundary_opcua.py's), the runtime in lock-step on its clock.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import pytest
from asyncua import ua
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_boundary_opcua import GOOD, STATUSES, VARIANTS, Controller, Sequence, controller

from compensator.io import read_run_log, save_model
from compensator.model import ThermalModel
from thermocomp.runtime import Alarm, SpindleRuntime
from thermocomp.runtime.config import load_config

__all__ = ["controller"]  # the module's server, shared by the examples

WALL0 = 1.77e9
CLAMP_UM, RATE, FAST = 40.0, 0.5, 5.0

# the held offset's node beyond the clamp, and values a controller could hold there
BEYOND = [
    ua.Variant(999.0, ua.VariantType.Double),
    ua.Variant(-1e308, ua.VariantType.Double),
    ua.Variant(2**63 - 1, ua.VariantType.Int64),
]


class Bench:
    """One spindle's runtime reading the boundary controller, in lock-step."""

    def __init__(self, ctl: Controller, directory: Path):
        directory.mkdir(parents=True, exist_ok=True)
        model = directory / "model.json"
        save_model(
            model,
            ThermalModel.from_discrete(
                0.99, (0.0, 0.002, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 24000.0)
            ),
        )
        node = ctl.node_id
        adapter = (
            f'{{type = "opcua", url = "{ctl.url}", speed_node = "{node("speed")}", '
            f'offset_node = "{node("offset")}", cutting_node = "{node("cutting")}", '
            f'input_nodes = {{bearing_temp_c = "{node("input")}"}}, '
            f'measurement_node = "{node("probe_value")}", '
            f'measurement_sequence_node = "{node("probe_sequence")}", '
            f'measurement_sigma_node = "{node("probe_sigma")}", timeout_s = 5.0}}'
        )
        path = directory / "machine.toml"
        path.write_text(
            "\n".join(
                [
                    f'state_dir = "{directory / "state"}"',
                    "watchdog = false",
                    "journal_fsync_s = 3600.0",
                    "[[spindle]]",
                    'name = "s1"',
                    f'model = "{model}"',
                    "period_s = 1.0",
                    f"adapter = {adapter}",
                    "[spindle.shaping]",
                    f"max_offset_um = {CLAMP_UM}",
                    f"max_rate_um_per_s = {RATE}",
                    f"not_cutting_rate_um_per_s = {FAST}",
                    "deadband_um = 0.0",
                    "[spindle.observer]",
                    "enabled = true",
                ]
            )
            + "\n"
        )
        cfg = load_config(path)
        self.t = 0.0
        self.rt = SpindleRuntime(
            cfg.spindle[0],
            cfg.state_dir,
            cfg.journal_path,
            journal_fsync_s=cfg.journal_fsync_s,
            clock=lambda: self.t,
            wall=lambda: WALL0 + self.t,
        )
        self.held = 0.0  # the offset the journal said the controller held, last cycle

    def cycle(self) -> None:
        """One cycle, 1 s on; the offset invariants checked on what it did."""
        self.t += 1.0
        out = self.rt.cycle()  # never raises
        assert math.isfinite(out.predicted_um) and abs(out.predicted_um) < 1e4
        assert math.isfinite(out.offset_um) and abs(out.offset_um) <= CLAMP_UM
        if out.written and not out.alarms & Alarm.OFFSET_MISMATCH:
            # a read-back that found another value moves on from that one (its own test);
            # otherwise at most the fast rate over the cycle from the last value held
            assert abs(out.offset_um - self.held) <= FAST * out.dt_s + 1e-6
        self.held = out.offset_um


@pytest.fixture(scope="module")
def bench(controller: Controller, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Bench]:
    controller.keep_offset.clear()
    controller.reset(Sequence.next())
    b = Bench(controller, tmp_path_factory.mktemp("runtime-boundary"))
    try:
        for _ in range(3):
            b.cycle()
        yield b
    finally:
        b.rt.close()


@settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    faults=st.lists(
        st.tuples(
            st.sampled_from(sorted(GOOD)),
            st.sampled_from(sorted(VARIANTS)),
            st.sampled_from(STATUSES),
        ),
        min_size=1,
        max_size=3,
    ),
    cycles=st.integers(1, 3),
)
def test_no_controller_value_breaks_the_cycle_or_the_offset(
    controller: Controller, bench: Bench, faults: list[tuple[str, str, int]], cycles: int
) -> None:
    controller.reset(Sequence.next())
    for name, variant, status in faults:
        if name == "probe_sequence":
            controller.set("probe_sequence", ua.Variant(Sequence.next(), ua.VariantType.UInt32))
        controller.set(name, VARIANTS[variant], status)
    for _ in range(cycles):
        bench.cycle()
    controller.reset(Sequence.next())
    bench.cycle()  # and it goes on when the controller is well again
    assert bench.rt.link.up


def test_a_held_offset_beyond_the_clamp_is_journaled_at_the_clamps_edge(
    controller: Controller, bench: Bench
) -> None:
    """A controller that keeps a value beyond the clamp, whatever is written: every cycle says
    OFFSET_MISMATCH, and neither the journal nor the status ever holds the foreign value."""
    seen = Alarm.NONE
    for variant in BEYOND:
        controller.reset(Sequence.next())
        controller.keep_offset[:] = [float(variant.Value)]  # it reverts every write to this
        controller.set("offset", variant)
        for _ in range(3):
            bench.cycle()
            seen |= bench.rt.alarms
            assert abs(bench.rt.offset.held_um) <= CLAMP_UM
    controller.keep_offset.clear()
    controller.reset(Sequence.next())
    for _ in range(3):
        bench.cycle()
    assert seen & Alarm.OFFSET_MISMATCH
    bench.rt.journal.flush(bench.t)
    log = read_run_log(bench.rt.journal.path)
    held = log.extras["offset_um"]
    assert len(held) > 9 and all(math.isfinite(v) and abs(v) <= CLAMP_UM for v in held)
    assert any(abs(v) == CLAMP_UM for v in held)  # the edge, where the foreign value was
