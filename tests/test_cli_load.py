"""A command whose module cannot be imported is an error with its real cause: one line naming the command, the
exception and where it was raised (``MAPFREE_DEBUG=1`` adds the traceback), never a silently missing command."""

from __future__ import annotations

from pathlib import Path

import pytest

import mapfree.cli as cli
from mapfree.cli import CommandLoadError, build_parser, main


@pytest.fixture
def broken_command(tmp_path, monkeypatch) -> Path:
    """A command module ``broken`` beside the real ones whose second line imports a module that does not exist."""
    module = tmp_path / "broken.py"
    module.write_text(
        "from __future__ import annotations\nfrom mapfree.no_such_module import thing\n\n\n"
        "def register(subparsers):\n    subparsers.add_parser('broken')\n"
    )
    monkeypatch.setattr(cli, "__path__", [*cli.__path__, str(tmp_path)])
    monkeypatch.setattr(cli, "COMMANDS", [*cli.COMMANDS, "broken"])
    monkeypatch.delenv("MAPFREE_DEBUG", raising=False)
    return module


def test_a_command_that_cannot_be_imported_is_one_line_with_its_cause(broken_command, capsys):
    assert main(["broken"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert err.startswith(
        "mapfree broken: error: the command cannot be loaded: ModuleNotFoundError: "
        "No module named 'mapfree.no_such_module'"
    )
    assert f"({broken_command}, line 2)" in err and "MAPFREE_DEBUG=1" in err and "Traceback" not in err


def test_help_of_all_commands_names_the_broken_one_and_the_others_still_run(broken_command, capsys):
    assert main(["--help"]) == 1
    assert capsys.readouterr().err.startswith("mapfree broken: error: the command cannot be loaded")
    with pytest.raises(SystemExit) as e:  # a command of its own imports only its own module
        main(["evaluate", "--help"])
    assert e.value.code == 0 and "usage: mapfree evaluate" in capsys.readouterr().out


def test_debug_prints_the_traceback_under_the_line(broken_command, capsys, monkeypatch):
    monkeypatch.setenv("MAPFREE_DEBUG", "1")
    assert main(["broken"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("Traceback (most recent call last):")
    assert f'File "{broken_command}", line 2' in err
    assert err.rstrip().splitlines()[-1].startswith("mapfree broken: error: the command cannot be loaded")


def test_build_parser_raises_with_the_cause_chained(broken_command):
    with pytest.raises(CommandLoadError) as e:
        build_parser("broken")
    assert e.value.command == "broken" and isinstance(e.value.__cause__, ModuleNotFoundError)
    assert e.value.__cause__.name == "mapfree.no_such_module"
