"""Reference pages generated from the code at build time (an MkDocs hook, ``hooks:`` in
mkdocs.yml): the configuration keys from the pydantic models of ``thermocomp.runtime.config``
and of each controller link, the command line from ``thermocomp.cli.build_parser()``, and the
annotated example files. Nothing generated here is committed, so the pages follow the code.

Run on its own, ``python docs/gen_reference.py config|cli|examples`` prints one page.
"""

from __future__ import annotations

import argparse
import re
import sys
import types
import typing
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

PAGES = {
    "reference/configuration.md": "config",
    "reference/cli.md": "cli",
    "reference/examples.md": "examples",
}


# -- configuration ---------------------------------------------------------------------------


def _type_name(annotation: Any) -> str:
    """A short readable type: ``float``, ``float | None``, ``"clamp" | "extrapolate"``."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Annotated:
        return _type_name(args[0])
    if origin is typing.Literal:
        return " \\| ".join(f'`"{a}"`' if isinstance(a, str) else f"`{a}`" for a in args)
    if origin in (typing.Union, types.UnionType):
        return " \\| ".join(_type_name(a) for a in args)
    if origin in (list, tuple, set, frozenset):
        inner = ", ".join(_type_name(a) for a in args if a is not Ellipsis)
        return f"list of {inner}" if inner else "list"
    if origin is dict:
        return "table"
    if annotation is type(None):
        return "none"
    if isinstance(annotation, type):
        return {
            "str": "string",
            "Path": "path",
            "bool": "boolean",
            "int": "integer",
            "float": "number",
            "PosixPath": "path",
        }.get(annotation.__name__, annotation.__name__)
    return str(annotation).replace("typing.", "")


def _models_in(annotation: Any) -> list[type]:
    """The pydantic models a field's annotation holds as a section (itself, in a list, or
    optional); not those inside a table of named entries (``dict[str, Model]``)."""
    from pydantic import BaseModel

    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    if typing.get_origin(annotation) is dict:
        return []
    found: list[type] = []
    for arg in typing.get_args(annotation):
        found += _models_in(arg)
    return found


def _entry_model(annotation: Any) -> type | None:
    """The model of a table of named entries (``dict[str, Model]``, optional or not)."""
    from pydantic import BaseModel

    if typing.get_origin(annotation) is dict:
        args = typing.get_args(annotation)
        if len(args) == 2 and isinstance(args[1], type) and issubclass(args[1], BaseModel):
            return args[1]
        return None
    for arg in typing.get_args(annotation):
        found = _entry_model(arg)
        if found is not None:
            return found
    return None


def _default(field: Any) -> str:
    from pydantic import BaseModel
    from pydantic_core import PydanticUndefined

    if field.is_required():
        return "required"
    if field.default_factory is not None:
        try:
            value = field.default_factory()
        except TypeError:
            return "(computed)"
    else:
        value = field.default
    if value is PydanticUndefined:
        return "required"
    if isinstance(value, BaseModel):
        return "(section)"
    if value is None:
        return "–"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, str):
        return f'`"{value}"`'
    if isinstance(value, Path):
        return f'`"{value}"`'
    if isinstance(value, (list, tuple)):
        return "`[" + ", ".join(f'"{v}"' if isinstance(v, str) else str(v) for v in value) + "]`"
    return f"`{value}`"


def _number(v: Any) -> str:
    """A bound as written: 31536000, 0.5, 1e-06 (never 3.1536e+07)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return str(v)
    if float(v).is_integer() and abs(v) < 1e15:
        return str(int(v))
    return f"{v:g}"


def _bounds(field: Any) -> str:
    parts = []
    for m in field.metadata:
        for attr, sign in (("ge", "≥"), ("gt", ">"), ("le", "≤"), ("lt", "<")):
            v = getattr(m, attr, None)
            if v is not None:
                parts.append(f"{sign} {_number(v)}")
        pattern = getattr(m, "pattern", None)
        if pattern:
            parts.append(f"matches `{pattern}`")
    return ", ".join(parts)


_HISTORY = re.compile(r"\s*\((?:since |see )?issues? \d+[^)]*\)|;?\s*\bissues? \d+\b", re.I)


def _plain(text: str) -> str:
    """Docstring text for a page: one line, reStructuredText's ``code`` as Markdown's, no
    development history, and ``<`` ``>`` outside code escaped (Markdown would take them as tags)."""
    text = " ".join(str(text).split()).replace("``", "`")
    text = _HISTORY.sub("", text)
    parts = text.split("`")
    for i in range(0, len(parts), 2):  # outside code spans
        parts[i] = parts[i].replace("<", "&lt;").replace(">", "&gt;")
    return "`".join(parts)


def _cell(text: str) -> str:
    return _plain(text).replace("|", "\\|")


def _doc_of(model: type) -> str:
    doc = (model.__doc__ or "").strip()
    if not doc or doc.startswith(("Usage docs:", "!!! abstract")):
        return ""
    return _plain(doc.split("\n\n")[0])


def _table(model: type, section: str, out: list[str], seen: set[str]) -> list[tuple[str, type]]:
    """One section's keys as a table; returns the sub-sections to document after it."""
    subs: list[tuple[str, type]] = []
    rows = []
    for name, field in model.model_fields.items():
        key = field.alias or name
        inner = _models_in(field.annotation)
        entry = _entry_model(field.annotation)
        if entry is not None:
            keys = ", ".join(f"`{k}`" for k in entry.model_fields)
            desc = field.description or _doc_of(entry)
            rows.append(
                f"| `{key}` | table of name = {{{keys}}} | {_default(field)} | {_cell(desc)} |"
            )
            continue
        if inner:
            many = typing.get_origin(field.annotation) in (list, tuple)
            sub = f"{section}.{key}" if section else key
            subs.append((f"[[{sub}]]" if many else f"[{sub}]", inner[0]))
            rows.append(
                f"| `{key}` | section [{sub}](#{_anchor(sub)}) | {_default(field)} | "
                f"{_cell(field.description or _doc_of(inner[0]))} |"
            )
            continue
        desc = field.description or ""
        bounds = _bounds(field)
        if bounds:
            desc = f"{desc} ({bounds})" if desc else bounds
        rows.append(
            f"| `{key}` | {_type_name(field.annotation)} | {_default(field)} | {_cell(desc)} |"
        )
    out += ["| key | type | default | meaning |", "| --- | --- | --- | --- |", *rows, ""]
    return subs


def _anchor(section: str) -> str:
    return "section-" + section.replace(".", "-").replace("_", "-").lower()


def config_page() -> str:
    from thermocomp.runtime.config import RuntimeConfig

    out = [
        "# Configuration keys",
        "",
        "Generated from the runtime configuration's own models at every build of this site, so it",
        "is the list `thermocomp run` checks a file against. Every section refuses a key it does not",
        "know; numbers must be finite and within the bounds given. An annotated file to start from:",
        "[`machine.toml`](examples.md#machinetoml).",
        "",
        "A table's name is its place in the TOML file: `[[spindle]]` is one spindle (repeat it for",
        "more), `[spindle.shaping]` belongs to the spindle above it.",
        "",
    ]
    queue: list[tuple[str, str, type]] = [("the top level", "", RuntimeConfig)]
    seen: set[str] = set()
    while queue:
        title, section, model = queue.pop(0)
        if section in seen:
            continue
        seen.add(section)
        anchor = _anchor(section) if section else "top-level"
        out += [f"## {title} {{#{anchor}}}", ""]
        doc = _doc_of(model)
        if doc:
            out += [doc, ""]
        for sub_title, sub_model in _table(model, section, out, seen):
            sub = sub_title.strip("[]")
            queue.append((f"`{sub_title}`", sub, sub_model))
    out += _links_page_part()
    return "\n".join(out) + "\n"


def _links_page_part() -> list[str]:
    """The options of each controller link, sensor-less: the `[spindle.adapter]` table."""
    from cnc_adapters.chiller import CHILLERS
    from cnc_adapters.registry import BACKENDS, settings_model

    out = [
        "## `[spindle.adapter]`: the controller link {#section-spindle-adapter}",
        "",
        "A `type` key names the backend (or a `url` carries it, with the options as its query),",
        "and the backend's own options follow. A `profile` key (see [Controls](../controls/index.md))",
        "fixes the offset's unit, sign and resolution. Each backend's options:",
        "",
    ]
    for name in BACKENDS:
        try:
            model = settings_model(name)
        except Exception as err:  # noqa: BLE001 - a backend whose module cannot be imported here
            out += [f'### `type = "{name}"`', "", f"(not importable at build time: {err})", ""]
            continue
        out += [f'### `type = "{name}"` {{#adapter-{name}}}', ""]
        if model is None:
            out += ["No options of its own.", ""]
            continue
        _table(model, "", out, set())
    out += [
        "## `[cooling.chiller]`: the chiller link {#section-cooling-chiller}",
        "",
        "A `type` key names the backend; its options follow.",
        "",
    ]
    for name, cls in CHILLERS.items():
        out += [f'### `type = "{name}"` {{#chiller-{name}}}', ""]
        _table(cls.Settings, "", out, set())
    return out


# -- command line ----------------------------------------------------------------------------


def _subparsers(parser: argparse.ArgumentParser) -> list[tuple[str, str, argparse.ArgumentParser]]:
    """(name, help, parser) of each visible subcommand, in the order argparse lists them."""
    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: (a.help or "") for a in action._choices_actions}
            seen: set[int] = set()
            for name, sub in action.choices.items():
                if id(sub) in seen:  # an alias
                    continue
                seen.add(id(sub))
                if name not in helps:  # hidden (help=SUPPRESS): a deprecated spelling
                    continue
                found.append((name, helps[name], sub))
    return found


def _option_rows(parser: argparse.ArgumentParser) -> list[str]:
    rows = []
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        if action.help == argparse.SUPPRESS:
            continue
        if action.option_strings:
            names = ", ".join(f"`{o}`" for o in action.option_strings)
            if action.nargs != 0:
                metavar = action.metavar or action.dest.upper()
                if isinstance(metavar, tuple):
                    metavar = " ".join(metavar)
                names += f" `{metavar}`"
        else:
            metavar = action.metavar or action.dest
            names = f"`{metavar if isinstance(metavar, str) else ' '.join(metavar)}`"
        raw = action.help or ""
        try:  # argparse's own expansion of %(default)s, %(choices)s, %(prog)s
            text = parser._get_formatter()._expand_help(action) if "%(" in raw else raw
        except (KeyError, TypeError, ValueError, AttributeError):
            text = raw
        if action.choices and not isinstance(action.choices, dict) and "%(choices)" not in raw:
            text += " (one of: " + ", ".join(f"`{c}`" for c in action.choices) + ")"
        default = action.default
        if (
            action.option_strings
            and default not in (None, False, argparse.SUPPRESS)
            and action.nargs != 0
            and "default" not in text
        ):
            text += f" (default: `{default}`)"
        rows.append(f"| {names} | {_cell(text)} |")
    return rows


def _cli_section(
    name: str, help_: str, parser: argparse.ArgumentParser, depth: int, out: list[str]
) -> None:
    anchor = parser.prog.replace(" ", "-")
    out += [f"{'#' * depth} `{parser.prog}` {{#{anchor}}}", ""]
    text = parser.description or help_
    if text:
        out += [_plain(text), ""]
    usage = " ".join(parser.format_usage().split())
    out += ["```text", usage.removeprefix("usage: "), "```", ""]
    rows = _option_rows(parser)
    if rows:
        out += ["| argument | meaning |", "| --- | --- |", *rows, ""]
    if parser.epilog:
        out += [_plain(parser.epilog), ""]
    for sub_name, sub_help, sub in _subparsers(parser):
        _cli_section(sub_name, sub_help, sub, min(depth + 1, 4), out)


def cli_page() -> str:
    from thermocomp import cli

    parser = cli.build_parser()
    out = [
        "# Command line",
        "",
        "Generated from the command's own parser at every build of this site: each command,",
        "its usage and its arguments, as `thermocomp COMMAND --help` prints them. Errors are one",
        "line on stderr with exit status 2.",
        "",
    ]
    commands = _subparsers(parser)
    # the audiences `thermocomp --help` groups the commands by, where the parser declares them
    groups = [(title, list(names)) for title, names in getattr(cli, "GROUPS", ())]
    grouped = {n for _, names in groups for n in names}
    rest = [name for name, _, _ in commands if name not in grouped]
    if rest:
        groups.append(("other commands" if groups else "", rest))
    by_name = {name: (help_, sub) for name, help_, sub in commands}
    for title, names in groups:
        if title:
            out += [f"**{title[0].upper()}{title[1:]}**", ""]
        out += ["| command | what it does |", "| --- | --- |"]
        for name in names:
            if name in by_name:
                help_, sub = by_name[name]
                out.append(f"| [`{name}`](#{sub.prog.replace(' ', '-')}) | {_cell(help_)} |")
        out.append("")
    for name, help_, sub in _subparsers(parser):
        _cli_section(name, help_, sub, 2, out)
    return "\n".join(out) + "\n"


# -- the example files -----------------------------------------------------------------------


def examples_page() -> str:
    ex = ROOT / "examples"
    out = [
        "# Example files",
        "",
        "The annotated examples as they ship: `thermocomp init DIR` writes them into `DIR`.",
        "",
    ]
    files = sorted(ex.glob("*.toml")) + sorted(ex.glob("*.service")) + sorted(ex.glob("*.timer"))
    files += sorted((ex / "linuxcnc").glob("*.hal")) + sorted((ex / "linuxcnc").glob("*.toml"))
    files += sorted((ex / "linuxcnc").glob("*.ini"))
    lang = {".toml": "toml", ".service": "ini", ".timer": "ini", ".ini": "ini", ".hal": "text"}
    for path in files:
        rel = path.relative_to(ex)
        anchor = str(rel).replace("/", "-").replace(".", "").replace("_", "-").lower()
        out += [
            f"## `{rel}` {{#{anchor}}}",
            "",
            f"```{lang.get(path.suffix, 'text')}",
            path.read_text().rstrip("\n"),
            "```",
            "",
        ]
    return "\n".join(out) + "\n"


GENERATORS = {"config": config_page, "cli": cli_page, "examples": examples_page}


# -- the MkDocs hook ---------------------------------------------------------------------------


def on_files(files: Any, config: Any) -> Any:
    """Add the generated pages to the site."""
    from mkdocs.structure.files import File

    for uri, kind in PAGES.items():
        files.append(File.generated(config, uri, content=GENERATORS[kind]()))
    return files


if __name__ == "__main__":
    print(GENERATORS[sys.argv[1]](), end="")
