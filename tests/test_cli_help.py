"""Every ``mapfree`` subcommand's --help explains itself: examples, and the default of every option that has one."""

from __future__ import annotations

import argparse

import pytest

from mapfree.cli import COMMANDS, build_parser


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    p = build_parser()
    return next(a for a in p._actions if isinstance(a, argparse._SubParsersAction)).choices


@pytest.mark.parametrize("name", COMMANDS)
def test_help_has_examples_and_defaults(name):
    sp = _subparsers()[name]
    text = sp.format_help()
    assert "examples:" in text and f"mapfree {name} " in text.split("examples:", 1)[1], text
    if issubclass(sp.formatter_class, argparse.ArgumentDefaultsHelpFormatter):
        return  # argparse prints every default itself
    for a in sp._actions:
        if not a.option_strings or a.default in (None, False, "", [], argparse.SUPPRESS) or a.help == argparse.SUPPRESS:
            continue
        assert "default" in (a.help or ""), (
            f"{name} {a.option_strings[-1]}: help does not say its default {a.default!r}"
        )
