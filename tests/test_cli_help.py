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
