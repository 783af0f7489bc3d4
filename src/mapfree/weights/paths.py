"""The weights folders, in the rule's order, and the one shape of every missing-weights message."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

WEIGHTS_ENV = "MAPFREE_WEIGHTS_DIR"
OFFLINE_ENV = "MAPFREE_OFFLINE"
_LIST_HINT = "`mapfree weights` lists every model, where it looks and how to get it"


class MissingWeightsError(FileNotFoundError):
    """Weights are not on this machine and cannot be downloaded; the message says what to place where."""


class BrokenWeightsError(ValueError):
    """A weights file is there but cannot be read whole (an interrupted download, a wrong file); names the file."""


# --------------------------------------------------------------------------- the folders


def weights_dir() -> Path | None:
    """The folder named by ``$MAPFREE_WEIGHTS_DIR``, or None when it is not set."""
    env = os.environ.get(WEIGHTS_ENV)
    return Path(env).expanduser() if env else None


def weights_dir_problem() -> str | None:
    """Why ``$MAPFREE_WEIGHTS_DIR`` cannot be a weights folder (it names a file), or None (unset, a folder, or not
    made yet)."""
    env = weights_dir()
    if env is not None and env.exists() and not env.is_dir():
        return f"${WEIGHTS_ENV}={env} is a file, not a folder: point it at the folder that holds the weights"
    return None


def default_dir() -> Path:
    """The default weights folder: ``$XDG_CACHE_HOME/mapfree/weights`` (``~/.cache/mapfree/weights``)."""
    cache = os.environ.get("XDG_CACHE_HOME")
    return (Path(cache).expanduser() if cache else Path.home() / ".cache") / "mapfree" / "weights"


def search_dirs() -> list[tuple[str, Path]]:
    """The weights folders in search order: ``$MAPFREE_WEIGHTS_DIR`` (when set), then the default folder.

    Returns:
        ``(label, folder)`` pairs, the label naming the folder in messages.
    """
    out = [(f"${WEIGHTS_ENV}", weights_dir()), ("the default folder", default_dir())]
    seen: list[Path] = []
    res = []
    for label, d in out:
        if d is not None and d not in seen:
            seen.append(d)
            res.append((label, d))
    return res


def target_dir() -> Path:
    """Where a user should place weights: ``$MAPFREE_WEIGHTS_DIR`` when set, else the default folder."""
    return weights_dir() or default_dir()


def torch_hub_dir() -> Path:
    """torch's hub cache of checkpoints (``$TORCH_HOME/hub/checkpoints``), found without importing torch."""
    home = os.environ.get("TORCH_HOME")
    if not home:
        cache = os.environ.get("XDG_CACHE_HOME")
        home = str((Path(cache).expanduser() if cache else Path.home() / ".cache") / "torch")
    return Path(home).expanduser() / "hub" / "checkpoints"


def looked_in(name: str, extra: tuple[str, ...] = ()) -> str:
    """Where a model was looked for, in words, for the missing-weights messages.

    Args:
        name: The model's name in a weights folder.
        extra: Further places, already worded.

    Returns:
        E.g. ``$MAPFREE_WEIGHTS_DIR (not set), the default folder (~/.cache/mapfree/weights/NAME)``.
    """
    env = weights_dir()
    places = [
        f"${WEIGHTS_ENV}/{name} ({env / name})" if env is not None else f"${WEIGHTS_ENV} (not set)",
        *([f"(but ${WEIGHTS_ENV} {env} is a file, not a folder)"] if weights_dir_problem() else []),
        f"the default folder ({default_dir() / name})",
        *extra,
    ]
    return ", ".join(places)


def missing_message(what: str, item: str, name: str, how: str, why: str = "", extra: tuple[str, ...] = ()) -> str:
    """The one shape of every missing-weights message: ``WHAT: ITEM not found (WHY); looked in …. HOW.``

    Args:
        what: What the model is for, e.g. ``LightGlue matcher``.
        item: The model, e.g. ``weights file 'x.pth'``.
        name: Its name in a weights folder.
        how: How to get it, one sentence.
        why: Why it was not downloaded, when that is known.
        extra: Further places looked in, already worded.

    Returns:
        The message.
    """
    return f"{what}: {item} not found{f' ({why})' if why else ''}; looked in {looked_in(name, extra)}. {how}. {_LIST_HINT}."


def find_in_dirs(*names: str) -> tuple[Path, str] | None:
    """Find the first of several names in the weights folders (folder by folder, then name by name).

    Args:
        *names: File or folder names relative to a weights folder.

    Returns:
        The path and the folder's label, or None.
    """
    for label, d in search_dirs():
        for n in names:
            if (d / n).exists():
                return d / n, label
    return None


@dataclass(frozen=True)
class Found:
    """Where a model was found.

    Attributes:
        path: The file or folder.
        where: Which place of the rule it came from, in words (``the default folder``, ``the path given``).
    """

    path: Path
    where: str


class Model(Protocol):
    """What every published model declares (``WeightFile``, ``HubModel``, the MASt3R checkpoints): its name in the
    weights folders, what it is, where the rule finds it, how to get it, and its missing-weights error."""

    @property
    def name(self) -> str:
        """Its file or folder name relative to a weights folder."""
        ...

    @property
    def what(self) -> str:
        """What it is for, in words (the start of every message about it)."""
        ...

    @property
    def licence(self) -> str:
        """The weights' licence, named in messages ("" when none is stated)."""
        ...

    def item(self) -> str:
        """The model itself in words, e.g. ``weights file 'x.pth'``, ``model 'org/name'``."""
        ...

    def locate(self, explicit: str | os.PathLike | None = None) -> Found | None:
        """Find the model by the rule.

        Args:
            explicit: A path the user gave for it: then only there.

        Returns:
            Where it was found, or None.
        """
        ...

    def how(self) -> str:
        """How to get it, in a sentence."""
        ...

    def fetch_command(self) -> str:
        """A shell command that puts it where the rule finds it (``mapfree weights``)."""
        ...

    def missing(self, why: str = "", explicit: str | os.PathLike | None = None) -> MissingWeightsError:
        """The error raised when the model is not found.

        Args:
            why: Why it was not downloaded, when that is known.
            explicit: The path the user gave, when any.

        Returns:
            The error, its message saying what to place where.
        """
        ...
