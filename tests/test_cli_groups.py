"""The command line's shape: commands grouped by audience in the help, one meaning per option
name, fixed value sets as choices, and the old spellings still working for one release with
one deprecation line each. Parsing only (in process), except where a command must run."""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys

import pytest
from conftest import first_order

from compensator.io import save_model
from thermocomp.cli import GROUPS, build_parser, main


def parsers(parser: argparse.ArgumentParser, prog: str = "thermocomp"):
    """(prog, parser) of the parser and every subcommand below it, each once."""
    yield prog, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            seen: set[int] = set()
            for name, sub in action.choices.items():
                if id(sub) not in seen:
                    seen.add(id(sub))
                    yield from parsers(sub, f"{prog} {name}")


def commands() -> set[str]:
    top = build_parser()
    return set(next(a for a in top._actions if isinstance(a, argparse._SubParsersAction)).choices)


def test_the_help_lists_every_command_once_in_its_audiences_group():
    text = build_parser().format_help()
    titles = [title for title, _ in GROUPS]
    assert [line[:-1] for line in text.splitlines() if line[:-1] in titles] == titles
    listed: dict[str, str] = {}
    group = None
    for line in text.splitlines():
        if line.endswith(":") and not line.startswith(" "):
            group = line[:-1]
        elif group in titles and (m := re.match(r"  (\S+)", line)):
            assert m.group(1) not in listed, f"{m.group(1)} listed twice"
            listed[m.group(1)] = group
    assert set(listed) == commands()
    assert listed["run"] == listed["status"] == listed["measure"] == listed["journal"] == titles[0]
    assert (
        listed["wizard"] == listed["fit"] == listed["model"] == listed["probe-program"] == titles[1]
    )
    assert (
        listed["simulate"]
        == listed["virtual-cnc"]
        == listed["hal-plant"]
        == listed["demo"]
        == titles[2]
    )
    assert "usage: thermocomp [-h] [--version] COMMAND ..." in text


def test_building_the_parser_imports_no_layer_below_the_cli():
    """What `thermocomp --help` and the docs build pay: the value sets are read on use."""
    code = (
        "import sys; from thermocomp.cli import build_parser; build_parser().format_help(); "
        "print(sorted(m for m in sys.modules if m.split('.')[0] in "
        "('calibration', 'machine_sim', 'compensator', 'cnc_adapters', 'numpy')))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr


def test_replay_fit_and_the_wizard_import_scipys_solvers_only_when_they_solve():
    """scipy.optimize and scipy.interpolate cost about 1.6 s of CPU to import: every `replay`, every
    `fit` that stops at a bad log and every wizard question paid it before the work began."""
    code = (
        "import sys, calibration.replay, calibration.fit, calibration.wizard; "
        "print(sorted(m for m in ('scipy.optimize', 'scipy.interpolate') if m in sys.modules))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr


def test_every_commands_help_formats_and_its_value_sets_are_the_codes():
    from calibration.nc_programs import DIALECTS
    from machine_sim.plant import PRESETS

    dialect_options = set()
    for prog, parser in parsers(build_parser()):
        assert parser.format_help(), prog
        for action in parser._actions:
            if "--dialect" in action.option_strings:
                assert tuple(action.choices) == DIALECTS, prog
                dialect_options.add(prog)
            if "--preset" in action.option_strings:
                assert tuple(action.choices) == tuple(PRESETS), prog
    assert dialect_options == {
        "thermocomp wizard",
        "thermocomp profile",
        "thermocomp probe-program",
    }


def test_an_option_name_has_one_meaning():
    """--spindle names a [[spindle]] of the runtime configuration wherever it is shown."""
    shown = 0
    for prog, parser in parsers(build_parser()):
        for action in parser._actions:
            if action.help == argparse.SUPPRESS:
                continue  # an old spelling
            assert "--spindle-id" not in action.option_strings, prog
            if "--spindle" in action.option_strings:
                shown += 1
                assert action.metavar == "NAME" and "[[spindle]]" in action.help, prog
    assert shown == 6  # replay, measure, journal export, refit, model history, model rollback


@pytest.fixture
def model_file(tmp_path):
    path = tmp_path / "m.json"
    save_model(path, first_order())
    return path


def parsed(capsys, argv: list[str]) -> tuple[dict, str]:
    args = build_parser().parse_args(argv)
    return vars(args), capsys.readouterr().err


OLD_AND_NEW = [
    (
        ["fit", "r.csv", "--output", "m.json", "--spindle-id", "s1"],
        ["fit", "r.csv", "--output", "m.json", "--model-spindle-id", "s1"],
        "'--spindle-id'",
        "'--model-spindle-id'",
    ),
    (
        ["wizard", "--spindle-id", "s1"],
        ["wizard", "--model-spindle-id", "s1"],
        "'--spindle-id'",
        "'--model-spindle-id'",
    ),
    (
        ["probe-program", "--dialect", "fanuc", "--spindle", "low"],
        ["probe-program", "--dialect", "fanuc", "--probe-spindle", "low"],
        "'--spindle'",
        "'--probe-spindle'",
    ),
    (
        ["model", "FILE"],
        ["model", "show", "FILE"],
        "'thermocomp model FILE'",
        "'thermocomp model show FILE'",
    ),
    (
        ["model", "--json", "FILE"],
        ["model", "show", "--json", "FILE"],
        "'thermocomp model FILE'",
        "model show",
    ),
    (
        ["model", "--schema", "--format", "all"],
        ["model", "schema", "--format", "all"],
        "'thermocomp model --schema'",
        "'thermocomp model schema'",
    ),
    (
        ["replay", "day.csv", "--model", "m.json", "--applied"],
        ["replay", "day.csv", "--model", "m.json"],
        "'--applied'",
        "does nothing",
    ),
    (
        ["fit", "r.csv", "--output", "m.json", "--method", "cycles"],
        ["fit", "r.csv", "--output", "m.json"],
        "'--method'",
        "does nothing",
    ),
]


@pytest.mark.parametrize(
    "old,new,said,instead", OLD_AND_NEW, ids=[" ".join(c[0]) for c in OLD_AND_NEW]
)
def test_an_old_spelling_parses_as_the_new_with_one_deprecation_line(
    capsys, model_file, old, new, said, instead
):
    old = [str(model_file) if w == "FILE" else w for w in old]
    new = [str(model_file) if w == "FILE" else w for w in new]
    now, quiet = parsed(capsys, new)
    then, err = parsed(capsys, old)
    assert quiet == ""
    assert then == now
    assert err.count("\n") == 1 and err.startswith("thermocomp: ") and "deprecated" in err
    assert said in err and instead in err and "removed in the next release" in err


def test_an_old_spelling_still_runs_the_command(capsys, model_file):
    assert main(["model", str(model_file)]) == 0
    out, err = capsys.readouterr()
    assert out.startswith(f"{model_file}: ") and err.count("\n") == 1 and "model show FILE" in err
    assert main(["model", "show", str(model_file)]) == 0
    assert capsys.readouterr() == (out, "")


def test_model_check_is_a_subcommand_that_passes_a_good_file_and_refuses_a_bad_one(
    capsys, model_file, tmp_path
):
    assert main(["model", "check", str(model_file)]) == 0
    out, err = capsys.readouterr()
    assert out.startswith(f"{model_file}: ok: ") and err == ""
    bad = tmp_path / "bad.json"
    bad.write_text(
        model_file.read_text().replace('"spindle_id": "unknown"', '"spindle_id": "other"')
    )
    assert main(["model", "check", str(bad)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and "checksum mismatch" in err
    # the option before the action, as earlier releases took it: the same spelling, no warning
    assert main(["model", "--json", "check", str(bad)]) == 2
    out, err = capsys.readouterr()
    assert json.loads(out)["ok"] is False and err == ""
    assert build_parser().parse_args(["model", "check", str(bad)]).model_command == "check"


@pytest.mark.parametrize(
    "argv",
    [
        ["wizard", "--dialect", "mazak"],
        ["profile", "--max-rpm", "12000", "--dialect", "mazak", "--output", "x.nc"],
        ["probe-program", "--dialect", "mazak"],
    ],
)
def test_an_unknown_dialect_is_argparses_one_line_refusal(capsys, argv):
    with pytest.raises(SystemExit) as stop:
        build_parser().parse_args(argv)
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if "error:" in line]
    assert stop.value.code == 2 and errors == [
        f"thermocomp {argv[0]}: error: argument --dialect: invalid choice: 'mazak' "
        "(choose from 'fanuc', 'sinumerik', 'heidenhain', 'linuxcnc')"
    ]


def test_the_wizards_time_scale_is_shown_and_checked(capsys):
    wizard = next(p for prog, p in parsers(build_parser()) if prog == "thermocomp wizard")
    text = " ".join(wizard.format_help().split())
    assert "--time-scale TIME_SCALE" in text and "Keep 1, the default, on a real machine" in text
    assert build_parser().parse_args(["wizard"]).time_scale == 1.0
    for bad in ("0", "-60", "nan", "inf", "fast"):
        with pytest.raises(SystemExit) as stop:
            build_parser().parse_args(["wizard", "--time-scale", bad])
        assert stop.value.code == 2 and "argument --time-scale" in capsys.readouterr().err, bad
    assert build_parser().parse_args(["virtual-cnc", "--time-scale", "600"]).time_scale == 600.0


def test_replay_applied_changes_nothing_in_what_replay_does(capsys):
    """The applied offset is in every replay report; the flag is accepted, said to do nothing,
    and leaves no trace in what the command is given."""
    args = build_parser().parse_args(["replay", "day.csv", "--model", "m.json", "--applied"])
    assert not hasattr(args, "applied") and "does nothing" in capsys.readouterr().err
    replay = next(p for prog, p in parsers(build_parser()) if prog == "thermocomp replay")
    assert "--applied" not in replay.format_help()


def test_a_value_set_the_slim_install_cannot_load_is_the_extras_one_line():
    """The plant's presets need scipy: without it, `simulate --preset` and `simulate --help` say
    which extra brings it, as the command itself would."""
    for argv in (
        ["simulate", "--preset", "motorized-27k", "--output", "x.csv"],
        ["simulate", "--help"],
    ):
        code = f"import sys; sys.modules['scipy'] = None; from thermocomp.cli import main; sys.exit(main({argv!r}))"
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
        assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
        assert "pip install 'thermocomp[calibration]'" in r.stderr and r.stdout == ""
