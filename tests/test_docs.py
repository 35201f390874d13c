"""The documentation site builds in strict mode (a broken link or anchor fails), and the
user-facing text keeps its rules: no link out of the repository but to public references, no
development history, every alarm explained, the README a short front door."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
sys.path.insert(0, str(DOCS))

# the text a user reads: the README, the site's pages and scripts, the site's configuration, the
# examples `thermocomp init` ships, and the modules whose docstrings cite the papers
USER_FILES = sorted(
    [ROOT / "README.md", ROOT / "mkdocs.yml"]
    + [p for p in DOCS.rglob("*") if p.suffix in (".md", ".py")]
    + [p for p in (ROOT / "examples").rglob("*") if p.is_file() and p.suffix != ".py"]
    + [
        ROOT / "compensator" / "cooling_law.py",
        ROOT / "calibration" / "stability.py",
        ROOT / "calibration" / "tuning.py",
    ]
)


def _generated_pages() -> dict[str, str]:
    import gen_reference

    return {uri: gen_reference.GENERATORS[kind]() for uri, kind in gen_reference.PAGES.items()}


def test_the_site_builds_strict_without_a_warning(tmp_path):
    """`mkdocs build --strict`, as `make docs` runs it: a link to a missing page or anchor, a page
    left out of the navigation, or a missing image aborts it; no warning may pass either."""
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1", "PYTHONWARNINGS": "ignore::DeprecationWarning"}
    run = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(tmp_path / "site")],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
    )
    out = run.stdout + run.stderr
    assert run.returncode == 0, out[-4000:]
    warnings = [line for line in out.splitlines() if re.match(r"\s*(WARNING|ERROR)\b", line)]
    assert not warnings, "\n".join(warnings)
    site = tmp_path / "site"
    for page in (
        "index.html",
        "reference/configuration.html",
        "reference/cli.html",
        "reference/examples.html",
        "sign-convention.html",
        "troubleshooting.html",
    ):
        assert (site / page).is_file(), page
    assert "spindle.shaping" in (site / "reference" / "configuration.html").read_text()
    assert "thermocomp run" in (site / "reference" / "cli.html").read_text()


def test_no_link_leaves_the_repository_but_to_public_references():
    """No path into the developers' machines or a shared folder beside the checkout."""
    found = []
    for path in USER_FILES:
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if "../shared" in line or "/work/" in line:
                found.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    for uri, text in _generated_pages().items():
        if "../shared" in text or "/work/" in text:
            found.append(uri)
    assert not found, "\n".join(found)


HISTORY = re.compile(r"\b[Ii]ssue [0-9]|\b[Rr]e-measured\b")


def test_no_development_history_in_user_facing_text():
    """Issue numbers and re-measurement diaries go to CHANGELOG.md, not to what a user reads
    (a public project's own issue tracker, cited as '#N', is a reference, not history)."""
    found = []
    for path in USER_FILES:
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if HISTORY.search(line):
                found.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    for uri, text in _generated_pages().items():
        for line in text.splitlines():
            if HISTORY.search(line):
                found.append(f"{uri}: {line.strip()[:160]}")
    assert not found, "\n".join(found)


def test_every_alarm_has_a_troubleshooting_entry():
    """One entry per alarm: what it means, what the service does, what you do."""
    from thermocomp.runtime.spindle import Alarm

    text = (DOCS / "troubleshooting.md").read_text()
    entries = set(re.findall(r"^### ([A-Z_]+)\s*$", text, re.M))
    names = {a.name for a in Alarm if a.name and a.value}
    assert names <= entries, f"no entry for: {sorted(names - entries)}"
    for alarm in Alarm:
        if alarm.value:
            body = text.split(f"### {alarm.name}\n", 1)[1].split("\n### ", 1)[0]
            assert f"Bit {alarm.value} in" in body, alarm.name
            assert "**Means:**" in body and "**Does:**" in body and "**You:**" in body, alarm.name


def test_the_journal_columns_are_documented():
    from compensator.io.journal import CoolingJournal, Journal, MeasurementJournal

    text = (DOCS / "reference" / "file-formats.md").read_text()
    for cls in (Journal, MeasurementJournal, CoolingJournal):
        missing = [c for c in cls.COLUMNS if f"`{c}`" not in text]
        assert not missing, f"{cls.__name__}: {missing}"


def test_the_readme_is_a_short_front_door():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) < 150
    assert "docs/demo.png" in text and "make demo" in text and "make test" in text
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if "://" in target:
            continue
        assert (ROOT / target).exists(), f"README links to {target}, which does not exist"


@pytest.mark.parametrize("kind", ["config", "cli", "examples"])
def test_the_generated_reference_pages_run_on_their_own(kind):
    """`python docs/gen_reference.py KIND` prints the page (what the hook adds at build time)."""
    run = subprocess.run(
        [sys.executable, str(DOCS / "gen_reference.py"), kind],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.startswith("# ")
