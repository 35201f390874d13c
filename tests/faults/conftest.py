"""Fixtures of the fault-injection suite: model files, one virtual CNC process shared by the
cases (each case leaves it running; the next one makes sure it listens and holds 0), a case
factory that writes configurations and cleans up its services, and the summary table."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from compensator.io import model_to_json, save_model
from compensator.io.checksum import digest

from .harness import (
    SUMMARY,
    ServiceProcess,
    Setup,
    VirtualCncProcess,
    read_only_dir,
    spindle_model,
    summary_table,
)


@pytest.fixture(scope="session")
def models(tmp_path_factory) -> dict[str, Path]:
    """Model files. ``quick`` (tau 0.1 s) is at its steady 30 um within a cycle or two;
    ``medium`` (tau 2 s) cools visibly during an outage; ``slow`` (tau 8 s) is still heating
    for half a minute, so the offset keeps changing while a fault lasts. The bad ones: not
    JSON, an unstable pole (with a valid checksum), a stable model predicting 4 cm."""
    d = tmp_path_factory.mktemp("models")
    out = {}
    for name, tau in (("quick", 0.1), ("medium", 2.0), ("slow", 8.0)):
        out[name] = d / f"{name}.json"
        save_model(out[name], spindle_model(tau))
    out["garbage"] = d / "garbage.json"
    out["garbage"].write_bytes(b"\x00\xffnot a model {{{\n")
    body = json.loads(model_to_json(spindle_model(0.1)))
    body.pop("sha256")
    body["states"][0]["dissipation_per_s"] = [-0.5, 0.0]  # a pole outside the unit circle
    body["sha256"] = digest(body)
    out["unstable"] = d / "unstable.json"
    out["unstable"].write_text(json.dumps(body))
    out["implausible"] = d / "implausible.json"
    save_model(out["implausible"], spindle_model(0.1, steady_um=40000.0))
    return out


@pytest.fixture(scope="session")
def vcnc(tmp_path_factory):
    """One ``thermocomp virtual-cnc`` process for the suite (an OPC UA server takes seconds
    to start on a slow machine). Started at once; a case waits for it with ``ensure()``."""
    proc = VirtualCncProcess(tmp_path_factory.mktemp("vcnc"))
    proc.start()
    yield proc
    proc.close()


@pytest.fixture(autouse=True, scope="session")
def _boot_vcnc_early(vcnc):
    """Starts the virtual CNC when the suite starts, so it boots while the in-process
    cases run."""
    return vcnc


class Case:
    def __init__(self, root: Path, vcnc: VirtualCncProcess, models: dict[str, Path]):
        self.root = root
        self.vcnc = vcnc
        self.models = models
        self.services: list[ServiceProcess] = []
        self.undo: list = []  # e.g. chattr -i, before the temporary directory is removed

    def setup(self, model: str = "quick", timeout_s: float = 1.0, **kw) -> Setup:
        s = Setup(
            root=self.root,
            model=self.models[model],
            adapter={
                "url": self.vcnc.url,
                "preset": "virtual-cnc",
                "timeout_s": timeout_s,
                "backoff_s": 0.1,
                "max_backoff_s": 0.5,
            },
            **kw,
        )
        s.write()
        return s

    def start(self, setup: Setup, ensure: bool = True, **kw) -> ServiceProcess:
        if ensure:
            self.vcnc.ensure()
        svc = ServiceProcess(setup, **kw)
        self.services.append(svc)
        return svc

    def read_only(self, path: Path) -> bool:
        undo = read_only_dir(path)
        if undo is None:
            return False
        self.undo.append(undo)
        return True

    def writable_again(self) -> None:
        while self.undo:
            self.undo.pop()()

    def close(self) -> None:
        for svc in self.services:
            svc.kill()
        self.writable_again()
        if self.vcnc.stopped:
            self.vcnc.cont()


@pytest.fixture
def case(tmp_path, vcnc, models):
    c = Case(tmp_path, vcnc, models)
    yield c
    c.close()


def pytest_terminal_summary(terminalreporter):
    if not SUMMARY:
        return
    terminalreporter.section("fault-injection summary")
    for line in summary_table():
        terminalreporter.write_line(line)
