"""``/metrics``: the status snapshot in Prometheus' text format (``prometheus_client``)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from typing import TYPE_CHECKING, Any, cast

if TYPE_CHECKING:  # prometheus_client is imported when /metrics is first served
    from prometheus_client.metrics_core import GaugeMetricFamily, Metric
    from prometheus_client.registry import Collector

from .states import ALARM_NAMES, STATES, finite


def metrics_text(snap: Mapping[str, Any] | None) -> bytes:
    """The snapshot in Prometheus' text format, through ``prometheus_client``'s own exposition
    (a registry of one collector that reads this snapshot)."""
    from prometheus_client import CollectorRegistry, generate_latest
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, InfoMetricFamily

    # any object with collect() is a collector: the Collector base is newer than the oldest
    # prometheus_client this project supports
    class _Snapshot:
        def collect(self) -> Iterator[Metric]:
            up = GaugeMetricFamily("thermocomp_up", "1 while the service runs and has a snapshot")
            up.add_metric([], 0.0 if snap is None else 1.0)
            yield up
            if snap is None:
                return
            info = InfoMetricFamily("thermocomp_build", "the service's version")
            info.add_metric([], {"version": str(snap.get("version"))})
            yield info
            yield _gauge(
                "thermocomp_uptime_seconds",
                "seconds since the service started",
                [],
                [([], snap.get("uptime_s"))],
            )
            yield _gauge(
                "thermocomp_reload_failed",
                "1 while a refused reload keeps the old configuration",
                [],
                [([], 1.0 if snap.get("reload_failed") else 0.0)],
            )
            sp = snap.get("spindles") or []
            gauges = {
                "speed_rpm": ("thermocomp_spindle_speed_rpm", "spindle speed read [rpm]"),
                "elongation_um": (
                    "thermocomp_elongation_micrometres",
                    "estimated thermal elongation S [um]",
                ),
                "offset_target_um": (
                    "thermocomp_offset_target_micrometres",
                    "offset the shaper aims at [um]",
                ),
                "offset_held_um": (
                    "thermocomp_offset_held_micrometres",
                    "offset the controller holds [um]",
                ),
                "last_write_age_s": (
                    "thermocomp_last_write_age_seconds",
                    "seconds since an offset was written",
                ),
            }
            for key, (name, doc) in gauges.items():
                yield _gauge(name, doc, ["spindle"], [([s["name"]], s.get(key)) for s in sp])
            yield _gauge(
                "thermocomp_compensating",
                "1 while the spindle's state is compensating (0: holding "
                "or not writing; the reason is in /status)",
                ["spindle"],
                [([s["name"]], 1.0 if s.get("state") == "compensating" else 0.0) for s in sp],
            )
            state = GaugeMetricFamily(
                "thermocomp_spindle_state",
                "1 for the spindle's state, 0 for the others (every state is listed)",
                labels=["spindle", "state"],
            )
            for s in sp:
                for word in STATES:
                    state.add_metric([s["name"], word], 1.0 if s.get("state") == word else 0.0)
            yield state
            yield _gauge(
                "thermocomp_link_up",
                "1 while the controller link is up",
                ["spindle"],
                [([s["name"]], 1.0 if s.get("link") == "connected" else 0.0) for s in sp],
            )
            yield _gauge(
                "thermocomp_cutting",
                "1 while the tool is taken to cut",
                ["spindle"],
                [([s["name"]], 1.0 if s.get("cutting") else 0.0) for s in sp],
            )
            alarm = GaugeMetricFamily(
                "thermocomp_alarm",
                "1 while the alarm is raised (every alarm is listed, so a 0 means clear)",
                labels=["spindle", "alarm"],
            )
            for s in sp:
                bits = int(s.get("alarm_bits") or 0)
                for bit, aname in ALARM_NAMES.items():
                    alarm.add_metric([s["name"], aname], 1.0 if bits & bit else 0.0)
            yield alarm
            yield _gauge(
                "thermocomp_observer_bias_micrometres",
                "the probe observer's bias [um]",
                ["spindle"],
                [
                    ([s["name"]], (s.get("observer") or {}).get("bias_um"))
                    for s in sp
                    if s.get("observer")
                ],
            )
            # absent for a spindle whose model states no expected error; the figures only where
            # validation measured (elsewhere a floor, never to be read as a promise)
            stated = [(s["name"], s["expected_error"]) for s in sp if s.get("expected_error")]
            vouched = [(name, e) for name, e in stated if e.get("validated")]
            yield _gauge(
                "thermocomp_expected_error_validated",
                "1 while the error to expect now is validated, 0 where validation never measured "
                "(at a speed, or after running faster, or with inputs further out than "
                "calibration saw: no figure is then published)",
                ["spindle"],
                [([name], 1.0 if e.get("validated") else 0.0) for name, e in stated],
            )
            yield _gauge(
                "thermocomp_expected_error_p95_micrometres",
                "the error to expect now, as the fit stated it: 95th percentile of |error| [um]",
                ["spindle"],
                [([name], e.get("p95_abs_um")) for name, e in vouched],
            )
            yield _gauge(
                "thermocomp_expected_error_rms_micrometres",
                "the error to expect now, as the fit stated it: RMS [um]",
                ["spindle"],
                [([name], e.get("rms_um")) for name, e in vouched],
            )
            yield _gauge(
                "thermocomp_expected_error_bound_micrometres",
                "max_expected_error_um: above it EXPECTED_ERROR_HIGH [um]",
                ["spindle"],
                [([name], e.get("bound_um")) for name, e in stated],
            )
            yield _gauge(
                "thermocomp_input_value",
                "the link's extra inputs (temperatures, load)",
                ["spindle", "input"],
                [([s["name"], k], v) for s in sp for k, v in (s.get("inputs") or {}).items()],
            )
            names = sorted({k for s in sp for k in (s.get("counters") or {})})
            for key in names:
                c = CounterMetricFamily(
                    f"thermocomp_{key}", f"count of {key.replace('_', ' ')}", labels=["spindle"]
                )
                for s in sp:
                    if key in (s.get("counters") or {}):
                        c.add_metric([s["name"]], float(s["counters"][key]))
                yield c
            cool = snap.get("cooling")
            if cool:
                yield _gauge(
                    "thermocomp_chiller_setpoint_celsius",
                    "set point sent to the chiller [degC]",
                    [],
                    [([], cool.get("setpoint_c"))],
                )
                yield _gauge(
                    "thermocomp_chiller_supply_celsius",
                    "chiller supply temperature read [degC]",
                    [],
                    [([], cool.get("supply_c"))],
                )
                yield _gauge(
                    "thermocomp_chiller_alarm",
                    "1 while the chiller loop has an alarm",
                    [],
                    [([], 1.0 if cool.get("alarm") else 0.0)],
                )

    registry = CollectorRegistry(auto_describe=False)
    registry.register(cast("Collector", _Snapshot()))
    return generate_latest(registry)


def _gauge(
    name: str, doc: str, labels: list[str], values: Iterable[tuple[list[str], Any]]
) -> GaugeMetricFamily:
    from prometheus_client.core import GaugeMetricFamily

    g = GaugeMetricFamily(name, doc, labels=labels)
    for lab, v in values:
        x = finite(v)
        if x is not None:  # an unknown value is absent, not 0
            g.add_metric(lab, x)
    return g
