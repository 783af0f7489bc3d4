"""Vectorised reading of clean ``name v1 … vN`` text tables (poses, intrinsics, submissions).

Parsing a benchmark's worth of text line by line in Python costs more than scoring it, so clean files
are read with numpy over their bytes. A file is *clean* when it is ASCII, every line holds exactly N+1
fields separated by single spaces, no line is blank or a comment (``#``), and every name has five digits
at ``name[-9:-4]`` (the frame number). Anything else makes ``scan_table`` return None and the
caller falls back to its line-by-line path, which reports problems precisely.
Numbers are parsed with ``float()`` (as the public evaluator does), and only for the rows and columns asked for.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["RawTable", "scan_table", "parse_numbers"]

_KEY_DIGITS = np.array([10000, 1000, 100, 10, 1], dtype=np.int64)


@dataclass
class RawTable:
    """Separator offsets of a clean table; values are parsed on demand, only for the rows asked for."""

    raw: bytes  # the file, ending in a newline
    sep: np.ndarray  # (n, nvalues + 1) offset of every space, then of the line's newline
    keys: np.ndarray  # (n,) frame numbers, ``int(name[-9:-4])``
    nvalues: int

    def __len__(self) -> int:
        return len(self.sep)

    @property
    def line_numbers(self) -> np.ndarray:
        return np.arange(1, len(self) + 1)

    @property
    def starts(self) -> np.ndarray:
        """(n,) offset of each line."""
        return _line_starts(self.sep)

    def names(self, rows: np.ndarray | None = None) -> list[str]:
        starts, name_ends = self.starts, self.sep[:, 0]
        if rows is not None:
            starts, name_ends = starts[rows], name_ends[rows]
        raw = self.raw
        return [raw[a:b].decode("ascii") for a, b in zip(starts.tolist(), name_ends.tolist())]

    def values(self, rows: np.ndarray | None = None, ncols: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(len(rows), ncols) float64 values (the first ``ncols``, default all) and a mask of tokens ``float()``
        rejects (left as NaN)."""
        ncols = self.nvalues if ncols is None else ncols
        if rows is None and ncols == self.nvalues:
            text, count = self._numbers(), len(self) * ncols
        else:
            sep = self.sep if rows is None else self.sep[rows]
            raw = self.raw
            spans = zip((sep[:, 0] + 1).tolist(), sep[:, ncols].tolist())
            text, count = b" ".join([raw[a:b] for a, b in spans]), len(sep) * ncols
        vals = _fast_numbers(text, count)
        if vals is not None:
            return vals.reshape(-1, ncols), np.zeros((len(vals) // max(ncols, 1), ncols), bool)
        vals, bad = parse_numbers(text.split())  # which token is wrong, and float()'s own verdict on each
        return vals.reshape(-1, ncols), bad.reshape(-1, ncols)

    def _numbers(self) -> bytes:
        """The file with every name blanked out: only the numbers, separated by whitespace."""
        b = np.frombuffer(self.raw, dtype=np.uint8).copy()
        marks = np.zeros(len(b) + 1, dtype=np.int8)
        marks[self.starts] = 1
        marks[self.sep[:, 0]] = -1
        b[np.cumsum(marks[:-1], dtype=np.int8).view(bool)] = 32
        return b.tobytes()


def _line_starts(sep: np.ndarray) -> np.ndarray:
    """(n,) offset of each line of a table, from its separator offsets (each line starts after the last one's
    newline)."""
    starts = np.empty(len(sep), dtype=np.int64)
    starts[:1] = 0
    starts[1:] = sep[:-1, -1] + 1
    return starts


def _fast_numbers(text: bytes, count: int) -> np.ndarray | None:
    """``count`` whitespace-separated finite numbers parsed in C with Python's own correctly rounded
    conversion (the values of ``float()``), without a Python object per token; None when there are not
    exactly ``count`` or one is not a finite number (the caller then looks at each token)."""
    if count == 0:
        return np.zeros(0) if not text.strip() else None
    try:
        vals = np.fromstring(text, sep=" ")
    except ValueError:
        return None
    return vals if len(vals) == count and np.isfinite(vals).all() else None


def scan_table(data: bytes, nvalues: int) -> RawTable | None:
    """Separator offsets and frame numbers of a clean table with ``nvalues`` numbers per line, else None."""
    fields = nvalues + 1
    if not data:
        return RawTable(b"", np.zeros((0, fields), np.int64), np.zeros(0, np.int64), nvalues)
    if not data.isascii() or b"#" in data:
        return None
    if not data.endswith(b"\n"):
        data += b"\n"
    b = np.frombuffer(data, dtype=np.uint8)
    sep: np.ndarray = np.flatnonzero(b <= 32)  # every space, newline and other control character, in one pass
    n = len(sep) // fields
    if len(sep) != n * fields:
        return None  # wrong field count somewhere
    sep = sep.reshape(n, fields)
    kinds = b[sep]
    if not ((kinds[:, -1] == 10).all() and (kinds[:, :-1] == 32).all()):
        return None  # wrong field count, tabs, carriage returns, other control characters
    if sep[0, 0] == 0 or np.any(np.diff(sep.ravel()) == 1):
        return None  # an empty field: double, leading or trailing space, blank line
    starts = _line_starts(sep)
    name_end = sep[:, 0]
    if np.any(name_end - starts < 9):
        return None
    digits = b[name_end[:, None] - 9 + np.arange(5)].astype(np.int64) - 48
    if np.any((digits < 0) | (digits > 9)):
        return None
    return RawTable(data, sep, digits @ _KEY_DIGITS, nvalues)


def parse_numbers(tokens: list[bytes]) -> tuple[np.ndarray, np.ndarray]:
    """``float()`` of each token; returns (values, rejected mask), rejected tokens left as NaN."""
    try:
        return np.fromiter(map(float, tokens), np.float64, count=len(tokens)), np.zeros(len(tokens), bool)
    except ValueError:
        pass
    out = np.full(len(tokens), np.nan)
    bad = np.zeros(len(tokens), dtype=bool)
    for i, tok in enumerate(tokens):
        try:
            out[i] = float(tok)
        except ValueError:
            bad[i] = True
    return out, bad
