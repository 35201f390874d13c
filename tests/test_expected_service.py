"""The error to expect, in the service: the figure the model's fit stated for the speed and the
inputs of each cycle, in the status, the metrics and on the broker; the configured bound
(``max_expected_error_um``) and its alarm, which never moves the offset; a model that states
none. In process, on the virtual machine and a fake clock; nothing sleeps (the broker test waits
for messages, with a timeout)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families
from test_runtime_statespace import WALL0, Bench, events, speed_only, with_inputs, write_config

from compensator.expected import MIN_FORWARD_FOLDS, Band, ExpectedError, Figure
from compensator.io import read_run_log, save_model
from thermocomp.commands.status import table
from thermocomp.runtime import Alarm, Service
from thermocomp.runtime.status import metrics_text, snapshot, spindle_status

MID = "3333-6667 rpm"  # the band of the bench's 5000 rpm


def statement(
    mid_p95: float = 9.3,
    outside: Figure | None = None,
    validated: float = 0.0,
    scale: float = 1.0,
    folds: int = MIN_FORWARD_FOLDS,
) -> ExpectedError:
    """A fit's statement over the test models' 0..10000 rpm: at rest and three bands, from
    ``folds`` folds predicted forward."""

    def band(lo, hi, rms, p95, out=None):
        return Band(
            speed_rpm=(lo, hi),
            source="forward",
            samples=120,
            rms_um=rms * scale,
            p95_abs_um=p95 * scale,
            outside=out,
        )

    return ExpectedError(
        bands=(
            band(0.0, 1.0, 0.2, 0.5),
            band(1.0, 3333.3, 1.0, 2.0),
            band(3333.3, 6666.7, 4.1, mid_p95, outside),
            band(6666.7, 10000.0, 5.0, 11.0),
        ),
        outside_validated=validated,
        forward_folds=folds,
    )


def stating(model, expected: ExpectedError | None):
    """``model`` with ``expected`` in its fit record (the way a fit stores it)."""
    fit = (
        {**model.fit, "expected_error": expected.model_dump(mode="json")}
        if expected
        else dict(model.fit)
    )
    return model.model_copy(update={"fit": fit})


def spindle_model(expected: ExpectedError | None = None):
    return stating(speed_only(spindle_id="sp-A"), expected)


def metrics(b: Bench) -> dict:
    snap = snapshot(
        version="test",
        pid=1,
        time_s=WALL0 + b.t,
        uptime_s=b.t,
        text="",
        reload_failed=False,
        spindles=[spindle_status(b.rt, b.t)],
        cooling=None,
    )
    json.dumps(snap, allow_nan=False)  # what /status and MQTT send
    fams = {f.name: f for f in text_string_to_metric_families(metrics_text(snap).decode())}
    return {
        name: {s.labels.get("spindle"): s.value for s in fams[name].samples}
        for name in (
            "thermocomp_expected_error_p95_micrometres",
            "thermocomp_expected_error_rms_micrometres",
            "thermocomp_expected_error_bound_micrometres",
            "thermocomp_expected_error_validated",
        )
    }


def high(rows: list[dict]) -> list[bool]:
    return [bool(r["alarms"] & Alarm.EXPECTED_ERROR_HIGH) for r in rows]


def test_the_stated_error_is_in_the_status_and_the_metrics(tmp_path):
    b = Bench(tmp_path, spindle_model(statement()))
    row = b.run(3)[-1]
    assert row["expected_error"] == {
        "band": MID,
        "rms_um": 4.1,
        "p95_abs_um": 9.3,
        "source": "forward",
        "outside": False,
        "outside_spans": 0.0,
        "validated": True,
        "bound_um": None,
        "claim": "expect ±9.3 µm (95 %)",
    }
    assert not any(high([row]))  # no bound configured: no alarm
    assert spindle_status(b.rt, b.t)["expected_error"] == row["expected_error"]
    m = metrics(b)
    assert m["thermocomp_expected_error_p95_micrometres"] == {"s1": 9.3}
    assert m["thermocomp_expected_error_rms_micrometres"] == {"s1": 4.1}
    assert m["thermocomp_expected_error_bound_micrometres"] == {}  # none configured: absent, not 0
    assert m["thermocomp_expected_error_validated"] == {"s1": 1.0}
    assert "; error: expect ±9.3 µm (95 %)" in table({"spindles": [spindle_status(b.rt, b.t)]})
    # the figure follows the speed: at rest the next cycle
    b.vm.override_speed(0.0)
    rows = b.run(5)
    assert rows[-1]["speed_rpm"] == 0.0
    assert (
        rows[-1]["expected_error"]["band"] == "at rest"
        and rows[-1]["expected_error"]["p95_abs_um"] == 0.5
    )
    assert metrics(b)["thermocomp_expected_error_p95_micrometres"] == {"s1": 0.5}
    b.rt.close()


def test_a_bound_below_the_stated_error_raises_the_alarm_and_never_moves_the_offset(
    tmp_path, caplog
):
    caplog.set_level(logging.INFO, logger="thermocomp.runtime")
    model = spindle_model(statement())
    bounded = Bench(tmp_path / "bounded", model, extra="max_expected_error_um = 5.0")
    free = Bench(tmp_path / "free", model)  # the same machine and model, no bound
    rows, plain = bounded.run(600), free.run(600)
    assert all(high(rows)) and not any(high(plain))
    assert rows[-1]["expected_error"]["bound_um"] == 5.0
    # advice only: every offset and estimate as without the bound
    assert [r["offset_um"] for r in rows] == [r["offset_um"] for r in plain]
    assert [r["predicted_um"] for r in rows] == [r["predicted_um"] for r in plain]
    (entered,) = events(caplog, "expected_error_high")
    assert entered.getMessage() == (
        "s1: EXPECTED_ERROR_HIGH: expected error 9.3 um (95 %) over the bound "
        "5 um at 3333-6667 rpm: probe or recalibrate"
    )
    assert entered.fields["p95_abs_um"] == 9.3 and entered.fields["band"] == MID
    assert "EXPECTED_ERROR_HIGH" in spindle_status(bounded.rt, bounded.t)["alarms"]
    assert metrics(bounded)["thermocomp_expected_error_bound_micrometres"] == {"s1": 5.0}
    # at rest the stated 0.5 um is within the bound: cleared, one event
    bounded.vm.override_speed(0.0)
    rows = bounded.run(10)
    assert not high(rows)[-1]
    (left,) = events(caplog, "expected_error_within_bound")
    assert "0.5 um (95 %) at rest, within the bound 5 um" in left.getMessage()
    assert len(events(caplog, "expected_error_high")) == 1
    for b in (bounded, free):
        b.rt.close()
    journal = read_run_log(min((tmp_path / "bounded" / "state" / "journal").glob("s1-*.csv")))
    flagged = (journal.extras["alarms"].astype(int) & int(Alarm.EXPECTED_ERROR_HIGH)) != 0
    assert Alarm.EXPECTED_ERROR_HIGH == 8388608
    assert 600 <= int(flagged.sum()) < 610  # the bound held at 5000 rpm, not at rest


def test_a_bound_above_the_stated_error_holds_back(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="thermocomp.runtime")
    b = Bench(tmp_path, spindle_model(statement()), extra="max_expected_error_um = 10.0")
    rows = b.run(300)
    assert not any(high(rows)) and rows[-1]["expected_error"]["p95_abs_um"] == 9.3
    assert not events(caplog, "expected_error_high")
    b.rt.close()


def test_inputs_outside_the_trained_range_use_the_outside_figure_and_alarm_beyond_validation(
    tmp_path, caplog
):
    caplog.set_level(logging.INFO, logger="thermocomp.runtime")
    outside = Figure(source="forward, outside", samples=40, rms_um=2.0, p95_abs_um=4.0)
    model = with_inputs()
    model = stating(model, statement(mid_p95=3.0, outside=outside, validated=0.5)).model_copy(
        update={"fallback": stating(model.fallback, statement(scale=0.5, mid_p95=3.0))}
    )
    b = Bench(
        tmp_path, model, extra="max_expected_error_um = 5.0"
    )  # trained 20..30 degC, valid 10..40
    ex = b.run(5)[-1]["expected_error"]
    assert (ex["p95_abs_um"], ex["outside"], ex["validated"]) == (3.0, False, True)
    # 0.2 spans out: the outside figure, which validation scored and the bound takes: no alarm
    b.inputs["temp1_c"] = 32.0
    row = b.run(5)[-1]
    ex = row["expected_error"]
    assert (ex["p95_abs_um"], ex["outside"], ex["validated"]) == (4.0, True, True)
    assert ex["outside_spans"] == pytest.approx(0.2)
    assert (
        row["alarms"] & Alarm.INPUTS_EXTRAPOLATED and not row["alarms"] & Alarm.EXPECTED_ERROR_HIGH
    )
    # 0.8 spans out, validation scored 0.5: the figure is a floor, and the bound alarms
    b.inputs["temp1_c"] = 38.0
    rows = b.run(5)
    ex = rows[-1]["expected_error"]
    assert (ex["p95_abs_um"], ex["validated"]) == (4.0, False) and all(high(rows))
    (entered,) = events(caplog, "expected_error_high")
    assert entered.getMessage() == (
        "s1: EXPECTED_ERROR_HIGH: expected error at least 4.0 um (95 %) at 3333-6667 rpm (bound 5 um), "
        "not validated here: inputs 0.80 spans outside the trained range, further than validation "
        "scored (0.50): probe or recalibrate"
    )
    # beyond the valid range: a sensor fault, the fallback stands in with its own statement
    b.inputs["temp1_c"] = 45.0
    row = b.run(1)[0]
    assert row["alarms"] & Alarm.INPUT_FALLBACK and not row["alarms"] & Alarm.EXPECTED_ERROR_HIGH
    ex = row["expected_error"]
    assert (ex["p95_abs_um"], ex["rms_um"], ex["outside"], ex["outside_spans"]) == (
        1.5,
        2.05,
        False,
        0.0,
    )
    assert len(events(caplog, "expected_error_within_bound")) == 1
    b.rt.close()


def test_a_floor_alarms_under_a_bound_whatever_its_figure(tmp_path, caplog):
    """Where validation scored nothing like the prediction the stated figure is only a floor: a
    speed above the calibrated range, or a statement from too few folds predicted forward."""
    caplog.set_level(logging.INFO, logger="thermocomp.runtime")
    b = Bench(tmp_path / "speed", spindle_model(statement()), extra="max_expected_error_um = 20.0")
    assert not any(high(b.run(10)))
    b.vm.override_speed(12000.0)  # the model was calibrated to 10000 rpm
    row = b.run(3)[-1]
    assert row["alarms"] & Alarm.OVER_RANGE and row["alarms"] & Alarm.EXPECTED_ERROR_HIGH
    assert (
        row["expected_error"]["validated"] is False and row["expected_error"]["p95_abs_um"] == 11.0
    )
    # a floor is no promise: the metrics publish no figure there, and say why not; the
    # command line says what the status page says
    lines = table({"spindles": [spindle_status(b.rt, b.t)]}).splitlines()
    claim = row["expected_error"]["claim"]
    assert claim.startswith("not validated") and any(f"; error: {claim}" in x for x in lines)
    m = metrics(b)
    assert m["thermocomp_expected_error_validated"] == {"s1": 0.0}
    assert m["thermocomp_expected_error_p95_micrometres"] == {}
    assert m["thermocomp_expected_error_rms_micrometres"] == {}
    (entered,) = events(caplog, "expected_error_high")
    assert entered.getMessage().endswith(
        "at least 11.0 um (95 %) at 6667-10000 rpm (bound 20 um), not "
        "validated here: 12000 rpm is above the calibrated 10000 rpm: "
        "probe or recalibrate"
    )
    b.vm.override_speed(5000.0)
    assert not any(high(b.run(3)))
    b.rt.close()
    caplog.clear()
    b = Bench(
        tmp_path / "folds", spindle_model(statement(folds=1)), extra="max_expected_error_um = 20.0"
    )
    assert any("rests on 1 fold(s) predicted forward" in r.getMessage() for r in caplog.records)
    rows = b.run(5)
    assert all(high(rows)) and rows[-1]["expected_error"]["p95_abs_um"] == 9.3
    assert (
        "the fit predicted 1 fold(s) forward, fewer than 2"
        in events(caplog, "expected_error_high")[0].getMessage()
    )
    b.rt.close()


def test_a_model_that_states_nothing_gives_null_and_no_alarm(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="thermocomp.runtime")
    for k, fit in enumerate(
        ({}, {"expected_error": {"bands": "not a list"}}, {"expected_error": 3.0})
    ):
        model = speed_only(spindle_id="sp-A").model_copy(update={"fit": fit})
        b = Bench(tmp_path / str(k), model, extra="max_expected_error_um = 0.001")
        rows = b.run(60)
        assert all(r["expected_error"] is None for r in rows) and not any(high(rows))
        assert spindle_status(b.rt, b.t)["expected_error"] is None
        assert all(v == {} for v in metrics(b).values())  # no gauge, not a 0
        b.rt.close()
    assert not events(caplog, "expected_error_high")
    said = [r for r in caplog.records if "states no expected error" in r.getMessage()]
    assert len(said) == 3 and said[0].levelno == logging.WARNING  # the bound cannot be checked


def test_an_older_statement_of_bands_alone_still_gives_its_figure_as_a_floor(tmp_path):
    old = {
        "bands": [
            {
                "speed_rpm": [0.0, 1.0],
                "source": "held out",
                "samples": 30,
                "rms_um": 0.3,
                "p95_abs_um": 0.6,
            },
            {
                "speed_rpm": [1.0, 10000.0],
                "source": "forward",
                "samples": 90,
                "rms_um": 1.1,
                "p95_abs_um": 2.4,
            },
        ]
    }
    model = speed_only(spindle_id="sp-A").model_copy(update={"fit": {"expected_error": old}})
    b = Bench(tmp_path, model, extra="max_expected_error_um = 2.0")
    row = b.run(3)[-1]
    assert (
        row["expected_error"]["band"] == "1-10000 rpm"
        and row["expected_error"]["p95_abs_um"] == 2.4
    )
    assert (
        row["expected_error"]["validated"] is False
    )  # it names no fold predicted forward: a floor
    assert row["alarms"] & Alarm.EXPECTED_ERROR_HIGH
    b.rt.close()


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_a_reload_keeps_the_alarm_and_takes_a_new_bound(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="thermocomp.runtime")
    path = tmp_path / "model.json"
    save_model(path, spindle_model(statement(scale=2.0)))  # 1 um (95 %) at rest and more above
    cfg = write_config(
        tmp_path,
        path,
        "max_expected_error_um = 0.5",
        adapter='url = "sim://motorized-27k?program=&seed=4"',
    )
    clock = FakeClock()
    svc = Service(cfg, clock=clock, wall=lambda: WALL0 + clock.t, lock=False)

    def run(seconds: float) -> None:
        end = clock.t + seconds
        while clock.t < end:
            clock.t += max(svc.tick(), 0.25)

    try:
        run(120)
        assert svc.spindles["s1"].alarms & Alarm.EXPECTED_ERROR_HIGH
        svc.reload()  # the same model and bound: the alarm carries on, no second entry
        run(60)
        assert svc.spindles["s1"].alarms & Alarm.EXPECTED_ERROR_HIGH
        assert len(events(caplog, "expected_error_high")) == 1
        cfg.write_text(
            cfg.read_text().replace("max_expected_error_um = 0.5", "max_expected_error_um = 50.0")
        )
        svc.reload()
        run(60)
        assert not svc.spindles["s1"].alarms & Alarm.EXPECTED_ERROR_HIGH
        assert svc.spindles["s1"].last["expected_error"]["bound_um"] == 50.0
        assert len(events(caplog, "expected_error_within_bound")) == 1
    finally:
        svc.close()


MOSQUITTO = Path("/usr/sbin/mosquitto")


@pytest.mark.skipif(
    not MOSQUITTO.exists(), reason="mosquitto is not installed (scripts/system-deps.sh)"
)
def test_the_expected_error_is_published_with_the_spindle(tmp_path):
    from test_mqtt import TOPIC, Brokers, Subscriber, tick_until_published, wait_for

    brokers = Brokers(tmp_path)
    port = brokers.start()
    path = tmp_path / "model.json"
    save_model(path, spindle_model(statement(scale=2.0)))
    cfg = tmp_path / "mqtt.toml"
    cfg.write_text(
        f'state_dir = "{tmp_path / "state"}"\nwatchdog = false\n[status]\nenabled = false\n'
        f'[mqtt]\ntopic = "{TOPIC}"\nhost = "127.0.0.1"\nport = {port}\npublish_every_s = 10\n'
        f'[[spindle]]\nname = "s1"\nmodel = "{path}"\nmax_expected_error_um = 0.5\n'
        'adapter = {url = "sim://motorized-27k?program=&seed=4"}\n'
        "[spindle.shaping]\nmax_offset_um = 40.0\nmax_rate_um_per_s = 2.0\n"
    )
    clock = FakeClock()
    svc = Service(cfg, clock=clock, wall=lambda: WALL0 + clock.t, lock=False)
    svc.start_status()
    sub = Subscriber(port)
    try:
        wait_for(lambda: svc.mqtt.connected, 10, "the service's connection")
        for _ in range(200):
            clock.t += max(svc.tick(), 0.25)
        tick_until_published(svc, clock)
        want = svc.snapshot["spindles"][0]
        assert want["expected_error"]["bound_um"] == 0.5 and "EXPECTED_ERROR_HIGH" in want["alarms"]
        sp = json.loads(
            sub.wait("spindle/s1", lambda p, r: json.loads(p)["time_s"] == want["time_s"])
        )
        assert (
            sp["expected_error"] == want["expected_error"] and "EXPECTED_ERROR_HIGH" in sp["alarms"]
        )
    finally:
        sub.close()
        svc.close()
        brokers.stop()
