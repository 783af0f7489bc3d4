"""The ``mapfree`` command: thin subcommands over the library, one module each."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import traceback
from typing import NoReturn


class HelpFormatter(argparse.HelpFormatter):
    """The description wrapped as usual; an epilog that starts with ``examples:`` kept line by line."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        if text.startswith("examples:"):
            return "".join(indent + line for line in text.splitlines(keepends=True))
        return super()._fill_text(text, width, indent)


class DefaultsHelpFormatter(HelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """``HelpFormatter`` that also prints every option's default."""


class Parser(argparse.ArgumentParser):
    """argparse's parser, but a command line it cannot parse is one line (which argument, what is wrong, where the
    help is) with exit status 2, not the whole usage block before it."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (`{self.prog} --help` shows the usage)\n")


#: Exit statuses of every command: results written; an error (a message on stderr says what); argparse's own
#: usage errors; the command ran but estimated nothing (with ``--strict``: not everything).
EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_NOTHING = 0, 1, 2, 3
#: The reader of the output went away (``mapfree … | head``): the shell's status of a command ended by SIGPIPE.
EXIT_BROKEN_PIPE = 141


def fail(command: str, error: BaseException | str) -> int:
    """Print the one line every command words an error with, ``mapfree COMMAND: error: MESSAGE`` (a KeyError's
    message without the quotes its ``str`` adds), on stderr; returns ``EXIT_ERROR``."""
    msg = error.args[0] if isinstance(error, KeyError) and error.args else error
    print(f"mapfree {command}: error: {msg}", file=sys.stderr)
    return EXIT_ERROR


def output_file_problem(flag: str, path, suffixes: tuple[str, ...] = ()) -> str | None:
    """Why ``path`` (given with ``flag``) cannot be written as an output file, before any work: it names a folder,
    or its name does not end in one of ``suffixes`` (the formats it is written in); None when it can be tried."""
    from pathlib import Path

    path = Path(path)
    if path.is_dir():
        return f"{flag} {path}: a folder; give a file name" + (
            f" (e.g. {path / ('out' + suffixes[0])})" if suffixes else ""
        )
    if suffixes and path.suffix.lower() not in suffixes:
        return f"{flag} {path}: the name must end in {' or '.join(suffixes)} (the format it is written in)"
    return None


def output_folder_problem(flag: str, path) -> str | None:
    """Why folder ``path`` (given with ``flag``) cannot be made or written into, before any work: it is a file, or a
    file stands where one of its parents should be; None when it can be tried."""
    from pathlib import Path

    path = Path(path)
    blocker = next((p for p in (path, *path.parents) if p.exists()), None)
    if blocker is not None and not blocker.is_dir():
        return f"{flag} {path}: {blocker} is a file, not a folder"
    return None


def plural(n: int, word: str, words: str | None = None) -> str:
    """``1 scene``, ``2 scenes`` (``words``: an irregular plural)."""
    return f"{n} {word if n == 1 else words or word + 's'}"


# Each module defines ``register(subparsers)``, which adds its parser and sets ``func`` on it.
COMMANDS = [
    "demo",
    "synth",
    "check",
    "evaluate",
    "calibrate",
    "relocalize",
    "match",
    "export",
    "run",
    "train",
    "serve",
    "admin",
    "sevenscenes",
    "scannet",
    "build",
    "weights",
]
#: Commands that relocalize images in this process: glibc's heap is kept warm for their per-pair buffers
#: (``mapfree.relocalize.allocator``), a process-wide setting made once, here where the process starts.
RELOCALIZING = frozenset({"run", "relocalize", "calibrate", "demo", "scannet", "sevenscenes", "serve"})
#: Set (to anything but 0) to have a command that cannot be loaded print the full traceback under its one line.
DEBUG_ENV = "MAPFREE_DEBUG"


class CommandLoadError(RuntimeError):
    """A command's module failed to import: a broken install or checkout, never a missing optional extra (a
    command imports its heavy dependencies only when it runs). ``command`` names it; the cause is chained."""

    def __init__(self, command: str, cause: BaseException):
        super().__init__(
            f"the command cannot be loaded: {type(cause).__name__}: {cause}{_raised_at(cause)} "
            f"(a broken install or checkout; {DEBUG_ENV}=1 prints the traceback)"
        )
        self.command = command


def _raised_at(error: BaseException) -> str:
    """`` (FILE, line N)`` of the innermost frame of ``error`` in a real file ("" for a SyntaxError, whose message
    names them already)."""
    if isinstance(error, SyntaxError):
        return ""
    frames = [f for f in traceback.extract_tb(error.__traceback__) if not f.filename.startswith("<")]
    return f" ({frames[-1].filename}, line {frames[-1].lineno})" if frames else ""


def _command_module(name: str):
    try:
        return importlib.import_module(f"{__name__}.{name}")
    except Exception as e:  # noqa: BLE001 - whatever stops the import, the command cannot run
        raise CommandLoadError(name, e) from e


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The ``mapfree`` parser; with ``only`` (a command name) just that subcommand's parser is built, so a
    command imports and builds nothing of the others."""
    from .. import __version__

    parser = Parser(
        prog="mapfree",
        description="Map-free visual relocalization: metric pose of a query photo relative to one reference photo.",
    )
    parser.add_argument("--version", action="version", version=f"mapfree {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in [only] if only in COMMANDS else COMMANDS:
        _command_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        parser = build_parser(argv[0] if argv else None)
    except CommandLoadError as e:
        if os.environ.get(DEBUG_ENV, "0") not in ("", "0"):
            traceback.print_exception(e.__cause__, file=sys.stderr)
        return fail(e.command, e)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    if args.command in RELOCALIZING:
        from ..relocalize.allocator import keep_heap_warm

        keep_heap_warm()
    try:
        code = int(args.func(args) or EXIT_OK)
        sys.stdout.flush()  # a closed pipe shows here, not as a traceback when the interpreter exits
        return code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `mapfree … | head`: the reader has gone; nothing to tell it
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    except OSError as e:  # an output that cannot be written (read-only, full disk, a file in the way): one line
        return fail(args.command, os_error_text(e))


def os_error_text(e: OSError) -> str:
    """``PATH: permission denied`` rather than Python's ``[Errno 13] Permission denied: 'PATH'``."""
    if isinstance(e, (FileExistsError, NotADirectoryError)) and e.filename and os.path.isfile(e.filename):
        return f"{e.filename} is a file, not a folder"
    if e.strerror and e.filename:
        return f"{e.filename}: {e.strerror[0].lower()}{e.strerror[1:]}"
    return e.strerror or str(e)
