"""The CLI reference (`docs/reference/cli.md`) from the `ddvs` argparse parsers (`ddvs.cli.build_parser`)."""

from __future__ import annotations

import argparse

from ddvs.cli import SUBCOMMANDS, build_parser
from scripts.docsgen.markdown import GENERATED, cell, code, table


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The sub-commands of `parser` (name → parser), in declaration order."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _usage(parser: argparse.ArgumentParser) -> str:
    """The usage line, wrapped at a fixed width so the page does not depend on the terminal."""
    formatter = argparse.HelpFormatter(parser.prog, width=100)
    formatter.add_usage(parser.usage, parser._actions, parser._mutually_exclusive_groups, prefix="")
    return formatter.format_help().strip()


def _default(action: argparse.Action) -> str:
    if action.default in (None, argparse.SUPPRESS, False, []) or isinstance(action, argparse._StoreTrueAction):
        return ""
    return code(action.default)


def _help(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    """The help text as `--help` prints it: `%(default)s`, `%(prog)s` and the like expanded (argparse's own
    expansion)."""
    if not action.help:
        return ""
    return argparse.HelpFormatter(parser.prog)._expand_help(action)


def _name(action: argparse.Action) -> str:
    names = ", ".join(action.option_strings) if action.option_strings else action.dest
    metavar = action.metavar
    if isinstance(metavar, tuple):
        metavar = " ".join(metavar)
    if action.nargs == 0:
        return code(names)
    if metavar is None and action.choices is not None:
        metavar = "{" + ",".join(str(c) for c in action.choices) + "}"
    if action.option_strings:
        return code(f"{names} {metavar or action.dest.upper()}")
    return code(metavar or names)


def _section(parser: argparse.ArgumentParser, level: int) -> str:
    """A parser's section: heading, description, usage, argument table, then its sub-commands."""
    out = [f"{'#' * level} `{parser.prog}`\n"]
    if parser.description:
        out.append(parser.description.strip() + "\n")
    out.append(f"```text\n{_usage(parser)}\n```\n")
    rows = [
        [_name(a), _default(a), cell(_help(parser, a))]
        for a in parser._actions
        if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)) and a.help != argparse.SUPPRESS
    ]
    if rows:
        out.append(table(["argument", "default", "meaning"], rows))
    for child in _subparsers(parser).values():
        out.append(_section(child, min(level + 1, 4)))
    return "\n".join(out)


def render() -> str:
    """The whole page: one section per `ddvs` subcommand, with its own sub-commands nested."""
    out = [
        GENERATED.format(source="ddvs/cli.py and every subcommand's add_arguments"),
        "# Command line reference\n",
        "Every program of ddvs is a subcommand of one command, `ddvs`; `ddvs COMMAND --help` prints the same "
        "information as this page. Options that take Zenoh endpoints also read the `DDVS_ZENOH_*` environment "
        "variables named in their help.\n",
        table(["command", "what it does"], [[f"[`{n}`](#ddvs-{n})", cell(h)] for n, (_, h) in SUBCOMMANDS.items()]),
    ]
    for name in SUBCOMMANDS:
        out.append(_section(_subparsers(build_parser(name))[name], 2))
    return "\n".join(out)
