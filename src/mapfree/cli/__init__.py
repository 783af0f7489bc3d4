"""The ``mapfree`` command: thin subcommands over the library, one module each."""

from __future__ import annotations

import argparse
import importlib
import sys

class HelpFormatter(argparse.HelpFormatter):
    """The description wrapped as usual; an epilog that starts with ``examples:`` kept line by line."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        if text.startswith("examples:"):
            return "".join(indent + line for line in text.splitlines(keepends=True))
        return super()._fill_text(text, width, indent)


class DefaultsHelpFormatter(HelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """``HelpFormatter`` that also prints every option's default."""


# Each module defines ``register(subparsers)``, which adds its parser and sets ``func`` on it.
COMMANDS = ["demo", "synth", "check", "evaluate", "relocalize", "run", "train", "serve", "admin", "sevenscenes", "scannet",
            "build"]


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__

    parser = argparse.ArgumentParser(
        prog="mapfree",
        description="Map-free visual relocalization: metric pose of a query photo relative to one reference photo.",
    )
    parser.add_argument("--version", action="version", version=f"mapfree {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"{__name__}.{name}":
                continue  # command not built yet
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except OSError as e:  # an output that cannot be written (read-only, full disk, a file in the way): one line
        print(f"mapfree {args.command}: error: {e}", file=sys.stderr)
        return 1

