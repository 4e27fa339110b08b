"""``--help`` says what each option does and its default, once and truthfully (issue 14)."""

from __future__ import annotations

import argparse

from companion.cli import build_parser as companion_parser


def _sub(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices[name]


def _help(parser: argparse.ArgumentParser, dest: str) -> str:
    return next(a.help for a in parser._actions if a.dest == dest) or ""


def test_run_profile_default_is_detected_from_the_vehicle_not_a_recording():
    text = _help(_sub(companion_parser(), "run"), "profile")
    assert "recording" not in text and "detected from the vehicle" in text
    for name in ("replay", "diagnose"):
        assert "detected from the recording" in _help(_sub(companion_parser(), name), "profile")


def _options():
    """(command, subcommand, option, action) for every option of both command lines."""
    from simvehicle.cli import build_parser as simvehicle_parser

    for prog, parser in (("companion", companion_parser()), ("simvehicle", simvehicle_parser())):
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        for name, p in sub.choices.items():
            for a in p._actions:
                if not isinstance(a, argparse._HelpAction):
                    yield prog, name, (a.option_strings or [a.dest])[0], a


def test_every_option_says_what_it_does_and_its_default_once():
    """``serve --profile/--seed`` and the ``scenario`` name had no help; ``sweep --out`` did not show
    its default; ``replay --gyro`` stated two defaults ("auto (default)" and "the config's")."""
    problems = []
    for prog, name, flag, a in _options():
        text = a.help or ""
        if not text.strip():
            problems.append(f"{prog} {name} {flag}: no help")
        if a.default not in (None, False) and "default" not in text:
            problems.append(f"{prog} {name} {flag}: default {a.default!r} not shown")
        if text.count("default") > 1:
            problems.append(f"{prog} {name} {flag}: states {text.count('default')} defaults")
    assert not problems, "\n".join(problems)
