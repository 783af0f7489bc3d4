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


#: Exit statuses of every command: results written; an error (a message on stderr says what); argparse's own
#: usage errors; the command ran but estimated nothing (with ``--strict``: not everything).
EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_NOTHING = 0, 1, 2, 3


def fail(command: str, error: BaseException | str) -> int:
    """Print the one line every command words an error with, ``mapfree COMMAND: error: MESSAGE`` (a KeyError's
    message without the quotes its ``str`` adds), on stderr; returns ``EXIT_ERROR``."""
    msg = error.args[0] if isinstance(error, KeyError) and error.args else error
    print(f"mapfree {command}: error: {msg}", file=sys.stderr)
    return EXIT_ERROR


# Each module defines ``register(subparsers)``, which adds its parser and sets ``func`` on it.
COMMANDS = ["demo", "synth", "check", "evaluate", "relocalize", "match", "run", "train", "serve", "admin", "sevenscenes",
            "scannet", "build", "weights"]


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The ``mapfree`` parser; with ``only`` (a command name) just that subcommand's parser is built, so a
    command imports and builds nothing of the others."""
    from .. import __version__

    parser = argparse.ArgumentParser(
        prog="mapfree",
        description="Map-free visual relocalization: metric pose of a query photo relative to one reference photo.",
    )
    parser.add_argument("--version", action="version", version=f"mapfree {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in [only] if only in COMMANDS else COMMANDS:
        try:
            module = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"{__name__}.{name}":
                continue  # command not built yet
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv[0] if argv else None)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    try:
        return int(args.func(args) or EXIT_OK)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except OSError as e:  # an output that cannot be written (read-only, full disk, a file in the way): one line
        return fail(args.command, e)

