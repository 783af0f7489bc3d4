"""Typed option dataclasses, checked in one place for the command line, YAML configs and Python alike.

Every component's options (a matcher's, a solver's, a depth network's) are a dataclass deriving from ``Options``.
Constructing one checks each value against its annotation (``int``, ``float``, ``bool``, ``str``, ``X | None``)
and against the range, choices or device rule declared with ``option(...)``::

    @dataclass
    class SIFTOptions(Options):
        max_features: int = option(2048, min=1)
        ratio: float = option(0.8, min=0, max=1, min_open=True)

``Options.build(values, owner="matcher 'sift'")`` is how the registries make one from user input: an unknown key
is refused with the nearest known one, a bad value with what was expected, both as one ``OptionError`` line
naming the option and its owner (and the file it came from, ``where=``). This module imports nothing of ours.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import types
import typing
from collections.abc import Mapping
from typing import Any, TypeVar

__all__ = ["Options", "OptionError", "option", "device_problem", "check_device", "check_keys"]

T = TypeVar("T", bound="Options")

_DEVICE = re.compile(r"(cuda|mps)(?::(\d+))?")


class OptionError(ValueError, TypeError):
    """A refused option; ``str()`` is the one line a user sees (the option, its value, what was expected).

    A ``ValueError``, and a ``TypeError`` as the dataclass's own refusal of an unknown keyword was.

    Args:
        message: The line shown to the user.
        key: The option's name.
        value: The refused value.
        expected: What would have been accepted, in words.
    """

    def __init__(self, message: str, key: str = "", value: Any = None, expected: str = "") -> None:
        super().__init__(message)
        self.key, self.value, self.expected = key, value, expected


def option(
    default: Any,
    *,
    min: float | None = None,
    max: float | None = None,
    min_open: bool = False,
    max_open: bool = False,
    choices: tuple | None = None,
    device: bool = False,
    doc: str = "",
) -> Any:
    """A dataclass field with the rule ``Options`` checks its value against.

    ``None`` is always allowed where the field's type allows it.

    Args:
        default: The default value.
        min: Lowest accepted number (inclusive unless ``min_open``).
        max: Highest accepted number (inclusive unless ``max_open``).
        min_open: Exclude ``min`` itself.
        max_open: Exclude ``max`` itself.
        choices: The accepted values.
        device: The value names a device this machine has (cpu, cuda, cuda:N, mps, auto).
        doc: One line describing the option.

    Returns:
        A ``dataclasses.field`` carrying the rule.
    """
    meta = {
        "min": min,
        "max": max,
        "min_open": min_open,
        "max_open": max_open,
        "choices": choices,
        "device": device,
        "doc": doc,
    }
    return dataclasses.field(default=default, metadata={"mapfree": meta})


def device_problem(value: Any) -> str | None:
    """Why a value is not a device to run on here, for a one-line refusal.

    Args:
        value: A device name; None and ``auto`` (cuda when available, else cpu) are always fine.

    Returns:
        None when the device is usable; else why not (a name torch does not know, CUDA or MPS on a machine
            without it, a CUDA index beyond the devices).
    """
    if value is None:
        return None
    if not isinstance(value, str):
        return "expected cpu, cuda, cuda:N, mps or auto"
    s = value.strip().lower()
    if s in ("auto", "cpu"):
        return None
    m = _DEVICE.fullmatch(s)
    if m is None:
        return "expected cpu, cuda, cuda:N, mps or auto"
    try:
        import torch
    except ImportError:
        return f"{m[1]} needs torch (pip install 'mapfree[learned]')"
    if m[1] == "mps":
        mps = getattr(torch.backends, "mps", None)
        return None if mps is not None and mps.is_available() else "MPS is not available on this machine"
    if not torch.cuda.is_available():
        return f"CUDA is not available on this machine (torch {torch.__version__}): use cpu, or leave it out"
    n = torch.cuda.device_count()
    if m[2] is not None and int(m[2]) >= n:
        return f"this machine has {n} CUDA device(s): cuda:0" + (f" … cuda:{n - 1}" if n > 1 else "")
    return None


def check_device(value: Any, name: str = "--device") -> None:
    """Refuse a device this machine cannot run on.

    Args:
        value: A device name (see ``device_problem``).
        name: How the user gave it, e.g. ``--device``, named in the error.

    Raises:
        OptionError: ``NAME VALUE: why``.
    """
    why = device_problem(value)
    if why:
        raise OptionError(f"{name} {value}: {why}", "device", value, why)


def _literal_base(tp: Any) -> Any:
    """``str`` for a ``Literal`` of strings (its values are the field's ``choices``), else ``tp``."""
    if typing.get_origin(tp) is typing.Literal and all(isinstance(a, str) for a in typing.get_args(tp)):
        return str
    return tp


def _type_name(tp: Any) -> str:
    tp = _literal_base(tp)
    return {int: "an integer", float: "a number", bool: "true or false", str: "a string"}.get(
        tp, getattr(tp, "__name__", str(tp))
    )


def _split_optional(tp: Any) -> tuple[tuple, bool]:
    """The member types of ``tp`` and whether ``None`` is one of them."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        return tuple(a for a in args if a is not type(None)), type(None) in args
    return (tp,), tp is type(None)


def _type_ok(value: Any, tp: Any) -> bool:
    tp = _literal_base(tp)
    if tp is bool:
        return isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if tp is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if tp is str:
        return isinstance(value, str)
    return True  # a type this check does not know (a tuple, a path): left to the component


def _range_text(meta: dict) -> str:
    lo, hi = meta["min"], meta["max"]
    if lo is not None and hi is not None:
        return f"in {'(' if meta['min_open'] else '['}{lo:g}, {hi:g}{')' if meta['max_open'] else ']'}"
    if lo is not None:
        return f"{'>' if meta['min_open'] else '>='} {lo:g}"
    if hi is not None:
        return f"{'<' if meta['max_open'] else '<='} {hi:g}"
    return ""


def _problem(value: Any, tp: Any, meta: dict) -> str | None:
    """What is wrong with ``value`` for a field of type ``tp`` with rule ``meta`` (None when nothing)."""
    members, nullable = _split_optional(tp)
    if value is None:
        return None if nullable else f"expected {' or '.join(_type_name(t) for t in members)}, not null"
    if meta.get("device"):
        return device_problem(value)
    kinds = " or ".join(_type_name(t) for t in members)
    rng = _range_text(meta) if meta else ""
    if not any(_type_ok(value, t) for t in members):
        return f"expected {kinds}{' or null' if nullable else ''}{' ' + rng if rng else ''}"
    if not meta:
        return None
    if meta["choices"] is not None and value not in meta["choices"]:
        return f"expected one of {', '.join(map(str, meta['choices']))}"
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        lo, hi = meta["min"], meta["max"]
        bad_lo = lo is not None and (value <= lo if meta["min_open"] else value < lo)
        bad_hi = hi is not None and (value >= hi if meta["max_open"] else value > hi)
        if bad_lo or bad_hi:
            return f"expected {kinds} {rng}"
    return None


def check_keys(cls: type, values: Mapping[str, Any], *, owner: str = "", where: str = "", prefix: str = "") -> None:
    """Refuse a key that an options dataclass has no field for, naming the nearest known one.

    Works for any dataclass, ``Options`` or not (whose values are then left to the component).

    Args:
        cls: The options dataclass.
        values: The user's options by name.
        owner: What the options are for, e.g. ``matcher 'sift'``, named in the error.
        where: Where they came from (a file), named first in the error.
        prefix: Prefix of the key as the user wrote it, e.g. ``matcher.``.

    Raises:
        OptionError: ``[WHERE: ]unknown option PREFIXKEY for OWNER: did you mean …``.
    """
    known = [f.name for f in dataclasses.fields(cls)]
    for key in values:
        if key not in known:
            close = difflib.get_close_matches(str(key), known, n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            lead, of = (f"{where}: " if where else ""), (f" for {owner}" if owner else "")
            raise OptionError(
                f"{lead}unknown option {prefix}{key}{of}: {hint}known: {', '.join(sorted(known))}", str(key)
            )


_HINTS: dict[type, dict[str, Any]] = {}


def _hints(cls: type) -> dict[str, Any]:
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


@dataclasses.dataclass
class Options:
    """Base of every options dataclass: each value is checked on construction, and ``build`` makes one from input.

    Raises:
        OptionError: A value does not match its field's type or rule.
    """

    def __post_init__(self) -> None:
        hints = _hints(type(self))
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            why = _problem(value, hints.get(f.name, Any), f.metadata.get("mapfree", {}))
            if why:
                raise OptionError(f"option {f.name}={value!r}: {why}", f.name, value, why)

    @classmethod
    def names(cls) -> list[str]:
        """The option names (the dataclass's fields)."""
        return [f.name for f in dataclasses.fields(cls)]

    @classmethod
    def build(
        cls: type[T],
        values: Mapping[str, Any] | None = None,
        *,
        owner: str = "",
        where: str = "",
        prefix: str = "",
        base: Options | None = None,
    ) -> T:
        """Make options from user input (command line, YAML, Python), checked.

        Args:
            values: Options by name, over ``base``'s values, else over the defaults.
            owner: What the options are for, e.g. ``matcher 'sift'``, named in an error.
            where: Where they came from (a file), named first in an error.
            prefix: Prefix of the keys as the user wrote them, e.g. ``matcher.``.
            base: Options whose values stand where ``values`` has none.

        Returns:
            The options.

        Raises:
            OptionError: An unknown key (``[WHERE: ]unknown option PREFIXKEY for OWNER: did you mean …``) or a
                bad value (``[WHERE: ]option PREFIXKEY=VALUE for OWNER: expected …``).
        """
        values = dict(values or {})
        check_keys(cls, values, owner=owner, where=where, prefix=prefix)
        lead = f"{where}: " if where else ""
        of = f" for {owner}" if owner else ""
        start = {f.name: getattr(base, f.name) for f in dataclasses.fields(cls)} if base is not None else {}
        try:
            return cls(**{**start, **values})
        except OptionError as e:
            raise OptionError(
                f"{lead}option {prefix}{e.key}={e.value!r}{of}: {e.expected}", e.key, e.value, e.expected
            ) from None
