"""Vectorised reading of clean ``name v1 … vN`` text tables (poses, intrinsics, submissions).

Parsing a benchmark's worth of text line by line in Python costs more than scoring it, so clean files
are read with numpy over their bytes. A file is *clean* when it is ASCII, every line holds exactly N+1
fields separated by single spaces, no line is blank or a comment (``#``), and every name has five digits
at ``name[-9:-4]`` (the frame number). Anything else makes ``scan_table`` return None and the
caller falls back to its line-by-line path, which reports problems precisely.
Numbers are parsed with ``float()`` (as the public evaluator does), and only for the rows asked for.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["RawTable", "scan_table", "parse_numbers"]



@dataclass
class RawTable:
    """Line and field offsets of a clean table; values are parsed on demand, only for the rows asked for."""

    data: np.ndarray  # uint8 view of the file
    starts: np.ndarray  # (n,) offset of each line
    ends: np.ndarray  # (n,) offset of each line's end (exclusive)
    spaces: np.ndarray  # offsets of every space in the file
    first_space: np.ndarray  # (n,) index into ``spaces`` of each line's first space
    keys: np.ndarray  # (n,) frame numbers, ``int(name[-9:-4])``
    nvalues: int
    _raw: bytes | None = None

    def __len__(self) -> int:
        return len(self.starts)

    @property
    def line_numbers(self) -> np.ndarray:
        return np.arange(1, len(self) + 1)

    @property
    def raw(self) -> bytes:
        return self.data.tobytes() if self._raw is None else self._raw

    def names(self, rows: np.ndarray | None = None) -> list[str]:
        starts, name_ends = self.starts, self.spaces[self.first_space]
        if rows is not None:
            starts, name_ends = starts[rows], name_ends[rows]
        raw = self.raw
        return [raw[a:b].decode("ascii") for a, b in zip(starts.tolist(), name_ends.tolist())]

    def values(self, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(len(rows), nvalues) float64 values and a mask of tokens ``float()`` rejects (left as NaN)."""
        if rows is None:
            tokens = self.raw.split()
            del tokens[:: self.nvalues + 1]  # the names
        else:
            starts, ends = self.spaces[self.first_space[rows]] + 1, self.ends[rows]
            raw = self.raw
            tokens = b" ".join([raw[a:b] for a, b in zip(starts.tolist(), ends.tolist())]).split(b" ") if len(starts) else []
        vals, bad = parse_numbers(tokens)
        return vals.reshape(-1, self.nvalues), bad.reshape(-1, self.nvalues)


def scan_table(data: bytes, nvalues: int) -> RawTable | None:
    """Offsets and frame numbers of a clean table with ``nvalues`` numbers per line, else None."""
    if not data:
        return RawTable(np.zeros(0, np.uint8), *(np.zeros(0, np.int64) for _ in range(5)), nvalues, b"")
    if not data.isascii() or b"#" in data:
        return None
    if not data.endswith(b"\n"):
        data += b"\n"
    b = np.frombuffer(data, dtype=np.uint8)
    ends = np.flatnonzero(b == 10)
    n = len(ends)
    if np.count_nonzero(b < 32) != n:
        return None  # tabs, carriage returns, other control characters
    starts = np.concatenate([[0], ends[:-1] + 1])
    if np.any(ends == starts):
        return None  # blank line
    spaces = np.flatnonzero(b == 32)
    if len(spaces) != n * nvalues or np.any(np.searchsorted(spaces, ends) != nvalues * np.arange(1, n + 1)):
        return None  # wrong field count somewhere
    if np.any(np.diff(spaces) == 1) or np.any(b[starts] == 32) or np.any(b[ends - 1] == 32):
        return None  # double, leading or trailing space
    first = nvalues * np.arange(n)
    name_end = spaces[first]
    if np.any(name_end - starts < 9):
        return None
    digits = b[name_end[:, None] - 9 + np.arange(5)].astype(np.int64) - 48
    if np.any((digits < 0) | (digits > 9)):
        return None
    keys = digits @ np.array([10000, 1000, 100, 10, 1], dtype=np.int64)
    return RawTable(b, starts, ends, spaces, first, keys, nvalues, data)


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
