"""Shared fixtures: hand-built models of each form."""

from __future__ import annotations

import fcntl
from pathlib import Path

import pytest

from compensator import ThermalModel, ThermalStateCoefficients

# The modules with the longest tests, collected first: pytest-xdist hands tests out in collection
# order and a worker can take over only tests not yet started, so a long test left to the end keeps
# the run waiting on one core. Each module's tests stay together (their module fixtures).
# LinuxCNC's first: about 100 s that mostly wait on its servo clock, one HAL at a time (a lock),
# so one worker runs them while the others have both cores.
LONG_MODULES = (
    "test_linuxcnc_watchdog.py",
    "test_linuxcnc.py",
    "test_cli.py",
    "test_learning.py",
    "test_cooling_paper.py",
    "test_service.py",
    "test_closed_loop.py",
    "test_wizard.py",
    "test_identify.py",
)


def pytest_collection_modifyitems(session, config, items):
    def rank(item) -> int:
        name = Path(str(item.fspath)).name
        return LONG_MODULES.index(name) if name in LONG_MODULES else len(LONG_MODULES)

    items.sort(key=rank)  # stable: the rest keep their order


@pytest.fixture(scope="session")
def computed_once(tmp_path_factory, worker_id):
    """``computed_once(name, make)``: the directory ``make`` filled, made by the first pytest-xdist
    worker that asks and read by the others, which wait for it (xdist's recipe for a fixture run
    once per session, with a lock file). Workers share a module's fixtures only this way: a slow
    one otherwise runs in every worker that takes one of its tests. Without xdist, this run's own."""
    root = tmp_path_factory.getbasetemp()
    if worker_id != "master":
        root = root.parent  # the run's directory, above each worker's own

    def get(name: str, make) -> Path:
        d = root / f"once-{name}"
        with open(root / f"once-{name}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not (d / ".done").exists():
                d.mkdir(exist_ok=True)
                make(d)
                (d / ".done").touch()
        return d

    return get


def first_order(**kw) -> ThermalModel:
    return ThermalModel(
        fitted_dt_s=60.0,
        speed_range_rpm=(0.0, 27000.0),
        states=(
            ThermalStateCoefficients(
                dissipation_per_s=(1 / 1200.0, 0.0),
                generation_um_per_s=(0.0005, 0.0004, 0.00003, 0.0000012),
            ),
        ),
        **kw,
    )


def rich_form() -> ThermalModel:
    """Two states, a speed x state term and an elastic part."""
    return ThermalModel(
        form="two-state+nS+elastic",
        fitted_dt_s=60.0,
        speed_range_rpm=(0.0, 27000.0),
        states=(
            ThermalStateCoefficients(
                dissipation_per_s=(1 / 300.0, 2e-5),
                generation_um_per_s=(0.0, 0.0008, 0.00004, 0.000002),
            ),
            ThermalStateCoefficients(
                dissipation_per_s=(1 / 3600.0, 0.0),
                generation_um_per_s=(0.0001, 0.0001, 0.00001, 0.0),
            ),
        ),
        elastic_um=(0.05, 0.02),
    )


@pytest.fixture
def model1() -> ThermalModel:
    return first_order()


@pytest.fixture
def model_rich() -> ThermalModel:
    return rich_form()


@pytest.fixture(scope="session")
def calibrated_model(computed_once) -> Path:
    """A model calibrated on the virtual plant's own data (as tests/test_service.py does): the
    workpiece error of an end-to-end test then shows the route, not a model that does not fit.
    Fitted once per run, whatever the number of workers (it takes seconds)."""

    def make(d: Path) -> None:
        from plantdata import identify_runs, plant_run

        from compensator.io import save_model

        model = identify_runs(
            [plant_run("calibration", 60.0, 0), plant_run("validation", 60.0, 1)]
        ).model
        save_model(d / "model.json", model)

    return computed_once("calibrated-model", make) / "model.json"
