"""Every option of every command has a help line (issue 22, point 6): crowd-demo's, and each crowd-bench
subcommand's, read from the parsers themselves and from their --help text."""

from __future__ import annotations

import argparse
import contextlib
import io

import pytest


def _parsers():
    from app.demo import _parser
    from bench.cli import build_parser

    yield "crowd-demo", _parser()
    bench = build_parser()
    yield "crowd-bench", bench
    for action in bench._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield f"crowd-bench {name}", sub


def _options(parser):
    return [a for a in parser._actions if a.option_strings and not isinstance(a, argparse._HelpAction)]


@pytest.mark.parametrize("command, parser", list(_parsers()), ids=lambda v: v if isinstance(v, str) else "")
def test_every_option_has_a_help_line(command, parser):
    missing = [a.option_strings[0] for a in _options(parser) if not (a.help and a.help.strip()) or a.help == argparse.SUPPRESS]
    assert not missing, f"{command}: no help for {', '.join(missing)}"
    text = io.StringIO()
    with contextlib.redirect_stdout(text), pytest.raises(SystemExit):
        parser.parse_args(["--help"])
    for action in _options(parser):
        assert action.option_strings[-1] in text.getvalue()


def test_every_bench_subcommand_says_what_it_does():
    from bench.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    helps = {c.dest: c.help for c in sub._choices_actions}
    assert set(helps) == set(sub.choices) and all(h and h.strip() for h in helps.values()), helps
