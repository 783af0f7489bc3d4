"""Submission ZIPs read defensively, with every problem reported (``writing`` writes them).

A submission is a ZIP whose root holds ``pose_sNNNNN.txt``, one per scene, with lines
``seq1/frame_00000.jpg qw qx qy qz tx ty tz confidence`` (world-to-camera).
Reading never crashes and never extracts anything to disk: each bad line, file or entry becomes a
``Problem(scene, line, reason)`` and reading goes on; only an unreadable archive is fatal.
"""

from __future__ import annotations

import io
import os
import re
import struct
import zipfile
import zlib
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass, field
from itertools import repeat
from typing import BinaryIO

import numpy as np

from ..geometry import Pose, rotmat_to_quat
from .tables import parse_numbers, scan_table

__all__ = [
    "Problem",
    "SceneEstimates",
    "SubmissionLimits",
    "read_submission",
    "from_estimates",
    "COMPAT_MODES",
]

COMPAT_MODES = ("default", "official")
_ENTRY_RE = re.compile(r"^pose_(s\d{5})\.txt$")
_BOM = b"\xef\xbb\xbf"
_FIELDS = ("name", "qw", "qx", "qy", "qz", "tx", "ty", "tz", "confidence")
_UNSET_KEYS = np.zeros(0, np.int64)  # SceneEstimates.keys' default, replaced by the names' frame numbers
_EMPTY = (np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64))


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a submission, named by scene and line.

    Attributes:
        scene: The scene (``sNNNNN``), or None for the whole archive.
        line: 1-based line in ``pose_SCENE.txt``, or None for the file as a whole.
        reason: What is wrong, in one line.
        fatal: The submission cannot be scored (the public evaluator would abort).
    """

    scene: str | None
    line: int | None
    reason: str
    fatal: bool = False

    def __str__(self) -> str:
        where = self.scene or "submission"
        if self.line is not None:
            where += f":{self.line}"
        return f"{where}: {self.reason}"


@dataclass(frozen=True)
class SubmissionLimits:
    """Bounds that keep a hostile ZIP harmless (sizes in bytes, uncompressed where it matters).

    Attributes:
        max_zip_bytes: Size of the archive.
        max_entries: Entries in the archive.
        max_file_bytes: Uncompressed size of one pose file.
        max_total_bytes: Uncompressed size of all pose files together.
        max_problems: Problems worded; further ones are only counted.
    """

    max_zip_bytes: int = 1 << 30
    max_entries: int = 10_000
    max_file_bytes: int = 64 << 20
    max_total_bytes: int = 512 << 20
    max_problems: int = 1_000


@dataclass
class SceneEstimates:
    """The estimates of one scene as arrays.

    Attributes:
        names: (n) frame names.
        q: (n, 4) world-to-camera quaternions ``w x y z``, as written.
        t: (n, 3) translations, metres.
        confidence: (n,) confidences.
        lines: (n,) 1-based line numbers in the pose file (0 when not from a file).
        keys: (n,) frame numbers, ``int(name[-9:-4])``; read from the names when not given.
    """

    names: list[str]
    q: np.ndarray  # (n,4) world-to-camera wxyz, as written
    t: np.ndarray  # (n,3)
    confidence: np.ndarray  # (n,)
    lines: np.ndarray  # (n,)
    keys: np.ndarray = field(default_factory=lambda: _UNSET_KEYS)  # (n,) frame numbers, int(name[-9:-4])

    def __post_init__(self) -> None:
        if self.keys is _UNSET_KEYS:  # not given: read from the names
            self.keys = np.array([_frame_key(n) for n in self.names], dtype=np.int64)

    def __len__(self) -> int:
        return len(self.names)

    def take(self, idx: np.ndarray) -> SceneEstimates:
        """A subset of the rows.

        Args:
            idx: (k,) row indices.

        Returns:
            The k estimates, in ``idx`` order.
        """
        idx = np.asarray(idx, dtype=np.int64)
        return SceneEstimates(
            [self.names[i] for i in idx.tolist()],
            self.q[idx],
            self.t[idx],
            self.confidence[idx],
            self.lines[idx],
            self.keys[idx],
        )

    @classmethod
    def concat(cls, parts: list[SceneEstimates]) -> SceneEstimates:
        """Join the estimates of one scene read piece by piece.

        Args:
            parts: The pieces, in order (at least one).

        Returns:
            One table with every row.
        """
        if len(parts) == 1:
            return parts[0]
        return cls(
            [n for p in parts for n in p.names],
            *(np.concatenate([getattr(p, f) for p in parts]) for f in ("q", "t", "confidence", "lines", "keys")),
        )

    def to_list(self) -> list[tuple[str, Pose, float]]:
        """The estimates as ``(frame_name, world-to-camera Pose, confidence)`` tuples."""
        return [(n, Pose.from_qt(q, t), float(c)) for n, q, t, c in zip(self.names, self.q, self.t, self.confidence)]


def _frame_key(name: str) -> int:
    try:
        return int(name[-9:-4])
    except ValueError:
        return -1


class _Problems(list):
    """A problem list that stops growing at a limit and counts what it dropped."""

    def __init__(self, limit: int):
        super().__init__()
        self.limit, self.dropped = limit, 0

    def add(self, scene, line, reason, fatal=False) -> None:
        if len(self) < self.limit or fatal:
            self.append(Problem(scene, line, reason, fatal))
        else:
            self.dropped += 1

    @property
    def full(self) -> bool:
        """Further (non-fatal) problems are only counted."""
        return len(self) >= self.limit

    def merge(self, other: _Problems) -> None:
        for p in other:
            self.add(p.scene, p.line, p.reason, p.fatal)
        self.dropped += other.dropped

    def finish(self) -> list[Problem]:
        out = sorted(self, key=lambda p: (p.scene or "", p.line or 0))
        if self.dropped:
            out.append(Problem(None, None, f"{self.dropped} more problems not listed"))
        return out


# --------------------------------------------------------------------------- one pose file


def _split_lines(text: str) -> list[str]:
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    if lines and lines[-1] == "":
        lines.pop()
    return lines


def _parse_file_slow(scene: str, data: bytes, compat: str, problems: _Problems, line0: int = 0):
    """Line-by-line parse of a file (or a piece of one after ``line0`` lines) that is not clean:
    (names, keys, vals, bad, lines, number of lines)."""
    text = data.decode("utf-8", errors="surrogateescape")
    names: list[str] = []
    tokens: list[bytes] = []
    lines: list[int] = []
    all_lines = _split_lines(text)
    for lineno, line in enumerate(all_lines, line0 + 1):
        try:
            line.encode("utf-8")
        except UnicodeEncodeError:
            problems.add(scene, lineno, "not UTF-8 text; line skipped", fatal=compat == "official")
            continue
        fields = line.strip().split(" ") if compat == "official" else line.split()
        if not fields or fields == [""]:
            continue
        if "#" in fields[0]:
            continue  # comment
        if len(fields) != 9:
            problems.add(
                scene, lineno, f"expected 9 fields (name qw qx qy qz tx ty tz confidence), found {len(fields)}"
            )
            continue
        if _frame_key(fields[0]) < 0:
            problems.add(
                scene, lineno, f"frame name {fields[0]!r} does not end in a 5-digit number (like seq1/frame_00012.jpg)"
            )
            continue
        names.append(fields[0])
        tokens.extend(f.encode("utf-8") for f in fields[1:])
        lines.append(lineno)
    vals, bad = parse_numbers(tokens)
    keys = np.array([_frame_key(n) for n in names], dtype=np.int64)
    return names, keys, vals.reshape(-1, 8), bad.reshape(-1, 8), np.array(lines, dtype=np.int64), len(all_lines)


def _parse_file(scene: str, data: bytes, compat: str, problems: _Problems, line0: int = 0):
    """(names, frame numbers, (n,8) values, (n,8) rejected-token mask, line numbers, number of lines) of a
    pose file, or of whole lines of one after its first ``line0`` lines. A UTF-8 byte-order mark (Windows
    editors write one) is not part of the first frame's name."""
    if line0 == 0 and data.startswith(_BOM):
        data = data[len(_BOM) :]
    table = scan_table(data, 8)
    if table is None:
        return _parse_file_slow(scene, data, compat, problems, line0)
    vals, bad = table.values()
    return table.names(), table.keys, vals, bad, table.line_numbers + line0, len(table)


def _validate_rows(
    scene: str,
    est: SceneEstimates,
    bad: np.ndarray | None,
    compat: str,
    known: Collection[str] | None,
    problems: _Problems,
) -> SceneEstimates:
    """Drop (and report) rows a scorer must not use, each on its own (duplicates are ``_drop_duplicates``')."""
    n = len(est)
    keep = np.ones(n, dtype=bool)

    def report(mask: np.ndarray, reason, drop: bool = True) -> None:
        rows = np.flatnonzero(mask & keep).tolist()
        for k, i in enumerate(rows):
            if problems.full:  # counted, not worded
                problems.dropped += len(rows) - k
                break
            problems.add(scene, int(est.lines[i]) or None, reason(i) if callable(reason) else reason)
        if drop:
            keep[mask] = False

    if bad is not None and bad.any():
        report(np.any(bad, axis=1), lambda i: f"unparseable number in field {_FIELDS[1 + int(np.argmax(bad[i]))]}")
    vals = np.concatenate([est.q, est.t, est.confidence[:, None]], axis=1)
    report(~np.all(np.isfinite(vals), axis=1), "non-finite number (NaN or inf)")
    report(~(np.linalg.norm(np.nan_to_num(est.q), axis=1) > 1e-8), "zero quaternion")  # np.isclose(norm, 0)
    if compat == "official":
        report(
            est.confidence < 0, "negative confidence (the public evaluator aborts if this frame is scored)", drop=False
        )
    else:
        report(est.confidence < 0, "negative confidence; line skipped")
    if known is not None:
        known = known if hasattr(known, "issuperset") else set(known)
        if not known.issuperset(est.names):
            unknown = np.array([n not in known for n in est.names], dtype=bool)
            if compat == "official":
                reason = lambda i: f"unknown frame {est.names[i]!r} (kept: the public evaluator keys frames by number)"  # noqa: E731
                report(unknown, reason, drop=False)
            else:
                report(unknown, lambda i: f"unknown frame {est.names[i]!r}")
        if compat != "official" and not all(map(str.startswith, est.names, repeat("seq1/"))):
            report(
                np.array([not n.startswith("seq1/") for n in est.names]),
                lambda i: f"{est.names[i]!r} is not a query frame",
            )
    return est if keep.all() else est.take(np.flatnonzero(keep))


def _drop_duplicates(scene: str, est: SceneEstimates, compat: str, problems: _Problems, used: dict) -> SceneEstimates:
    """Drop (and report) repeated frames: the first estimate wins (default); the public evaluator keys by
    number, the last wins. ``used`` maps each frame kept from earlier pieces of the file to its line
    (default mode, read piece by piece); it is updated."""
    ids = est.keys.tolist() if compat == "official" else est.names
    if len(set(ids)) == len(ids) and used.keys().isdisjoint(ids):
        used.update(zip(ids, est.lines.tolist()))
        return est
    order = range(len(est) - 1, -1, -1) if compat == "official" else range(len(est))
    dup = np.zeros(len(est), dtype=bool)
    for i in order:
        k = ids[i]
        if k in used:
            dup[i] = True
            if problems.full:
                problems.dropped += 1
            else:
                problems.add(
                    scene,
                    int(est.lines[i]) or None,
                    f"duplicate frame {est.names[i]!r} (line {used[k] or '?'} is used)",
                )
        else:
            used[k] = int(est.lines[i])
    return est.take(np.flatnonzero(~dup)) if dup.any() else est


# --------------------------------------------------------------------------- the archive


def _zip_entry_count(f: BinaryIO) -> int | None:
    """Entry count from the end-of-central-directory record, read before zipfile parses the directory."""
    f.seek(0, os.SEEK_END)
    size = f.tell()
    f.seek(max(0, size - (1 << 16) - 22))
    tail = f.read()
    at = tail.rfind(b"PK\x05\x06")
    if at < 0 or at + 22 > len(tail):
        return None
    return struct.unpack("<H", tail[at + 10 : at + 12])[0]


def _unsafe(name: str) -> bool:
    parts = name.replace("\\", "/").split("/")
    return name.startswith(("/", "\\")) or re.match(r"^[A-Za-z]:", name) is not None or ".." in parts


def read_submission(
    source: os.PathLike | str | bytes | BinaryIO,
    expected: Mapping[str, Collection[str]] | None = None,
    compat: str = "default",
    limits: SubmissionLimits | None = None,
) -> tuple[dict[str, SceneEstimates], list[Problem]]:
    """Read and validate a submission ZIP; never raises for bad content (each defect is a ``Problem``).

    Args:
        source: The ZIP: a path, its bytes, or a binary file.
        expected: Frame names by scene; enables the unknown-frame and outside-the-split checks.
        compat: ``default``, or ``official`` to keep what the public evaluator keeps (frames keyed by number,
            the last duplicate wins, negative confidences kept for the scorer to reject).
        limits: Size limits that keep a hostile ZIP harmless.

    Returns:
        The valid estimates by scene, and every problem found (line by line).

    Raises:
        ValueError: ``compat`` is unknown.
    """
    if compat not in COMPAT_MODES:
        raise ValueError(f"compat must be one of {COMPAT_MODES}, got {compat!r}")
    limits = limits or SubmissionLimits()
    problems = _Problems(limits.max_problems)
    out: dict[str, SceneEstimates] = {}
    try:
        f: BinaryIO
        if isinstance(source, (bytes, bytearray)):
            f = io.BytesIO(source)
        elif isinstance(source, (str, os.PathLike)):
            f = open(source, "rb")  # noqa: SIM115 - closed below, with the caller's own file left open
        else:
            f = source
    except OSError as e:
        problems.add(None, None, f"cannot open submission: {e.strerror or e}", fatal=True)
        return out, problems.finish()
    try:
        f.seek(0, os.SEEK_END)
        if f.tell() > limits.max_zip_bytes:
            problems.add(
                None, None, f"submission is {f.tell()} bytes, over the {limits.max_zip_bytes}-byte limit", fatal=True
            )
            return out, problems.finish()
        count = _zip_entry_count(f)
        if count is None:
            problems.add(None, None, "not a ZIP file", fatal=True)
            return out, problems.finish()
        if count > limits.max_entries:
            problems.add(None, None, f"ZIP has {count} entries, over the limit of {limits.max_entries}", fatal=True)
            return out, problems.finish()
        f.seek(0)
        try:
            zf = zipfile.ZipFile(f)
        except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError, struct.error) as e:
            problems.add(None, None, f"not a readable ZIP file ({e})", fatal=True)
            return out, problems.finish()
        with zf:
            _read_entries(zf, expected, compat, limits, problems, out)
    finally:
        if not isinstance(source, (bytes, bytearray)) and not hasattr(source, "read"):
            f.close()
    return out, problems.finish()


def _limit_name(limits: SubmissionLimits, budget: int) -> str:
    """Which limit an entry hit: the per-file one, or what is left of the total."""
    if limits.max_file_bytes <= budget:
        return f"the per-file limit of {limits.max_file_bytes} bytes"
    return f"the total limit of {limits.max_total_bytes} bytes for all files ({budget} left)"


def _read_entries(zf, expected, compat, limits, problems: _Problems, out: dict) -> None:
    infos = zf.infolist()
    if len(infos) > limits.max_entries:
        problems.add(None, None, f"ZIP has {len(infos)} entries, over the limit of {limits.max_entries}", fatal=True)
        return
    seen: set[str] = set()
    budget = limits.max_total_bytes
    for info in infos:
        name = info.filename
        if info.is_dir():
            continue
        if _unsafe(name):
            problems.add(None, None, f"entry {name!r} has an absolute or '..' path; ignored")
            continue
        base = name.replace("\\", "/").rsplit("/", 1)[-1]
        m = _ENTRY_RE.match(base)
        if "/" in name.replace("\\", "/"):
            if m and not name.startswith("__MACOSX/"):
                problems.add(
                    m.group(1), None, f"{name!r} is inside a folder: pose files must be at the ZIP root; ignored"
                )
            else:
                problems.add(None, None, f"unexpected entry {name!r} in a folder; ignored")
            continue
        if not m:
            problems.add(None, None, f"unexpected file {name!r} (expected pose_sNNNNN.txt); ignored")
            continue
        scene = m.group(1)
        if name in seen:
            problems.add(scene, None, f"duplicate ZIP entry {name!r}; the first is used")
            continue
        seen.add(name)
        if expected is not None and scene not in expected:
            problems.add(scene, None, "scene is not part of the evaluated split; ignored")
            continue
        cap = min(limits.max_file_bytes, budget)
        if info.file_size > cap:
            problems.add(
                scene,
                None,
                f"{name} unpacks to {info.file_size} bytes, over the limit ({_limit_name(limits, budget)}); ignored",
            )
            continue
        known = expected.get(scene) if expected is not None else None
        local = _Problems(max(0, problems.limit - len(problems)))  # kept only if the whole entry is read
        try:
            with zf.open(info) as member:
                est, size = _read_member(scene, member, cap, compat, known, local)
        except (zipfile.BadZipFile, zlib.error, RuntimeError, NotImplementedError, OSError, EOFError, ValueError) as e:
            problems.add(scene, None, f"cannot read {name} ({e}); ignored")
            continue
        if est is None:
            problems.add(
                scene,
                None,
                f"{name} unpacks to more than {cap} bytes, over the limit "
                f"({_limit_name(limits, budget)}; the size in the ZIP directory is wrong); ignored",
            )
            continue
        budget -= size
        problems.merge(local)
        out[scene] = est


#: A pose file is read and parsed this many bytes at a time (whole lines), so memory stays a small multiple of
#: this plus the rows kept (known frames, each once) however large the file is.
CHUNK_BYTES = 1 << 16


def _read_member(
    scene: str, member: BinaryIO, cap: int, compat: str, known: Collection[str] | None, problems: _Problems
) -> tuple[SceneEstimates | None, int]:
    """Read, parse and check one pose file piece by piece -> (its estimates, or None when it unpacks to more
    than ``cap`` bytes; the bytes read). Rows that are dropped (unknown frames, repeats) never accumulate."""
    parts: list[SceneEstimates] = []
    used: dict | None = None if compat == "official" else {}  # official: the last repeat wins, known at the end
    size, line0, carry = 0, 0, b""
    while True:
        block = member.read(min(CHUNK_BYTES, cap + 1 - size))
        size += len(block)
        if size > cap:
            return None, size
        if block:
            data = carry + block
            cut = data.rfind(b"\n") + 1
            if cut == 0:
                carry = data
                continue
            data, carry = data[:cut], data[cut:]
        else:
            data, carry = carry, b""
        if data:
            names, keys, vals, bad, lines, nlines = _parse_file(scene, data, compat, problems, line0)
            line0 += nlines
            est = SceneEstimates(names, vals[:, :4], vals[:, 4:7], vals[:, 7], lines, keys)
            est = _validate_rows(scene, est, bad, compat, known, problems)
            parts.append(est if used is None else _drop_duplicates(scene, est, compat, problems, used))
        if not block:
            break
    est = SceneEstimates.concat(parts) if parts else SceneEstimates([], *_EMPTY)
    return (est if used is not None else _drop_duplicates(scene, est, compat, problems, {})), size


def from_estimates(
    estimates: Mapping[str, Iterable | SceneEstimates],
    expected: Mapping[str, Collection[str]] | None = None,
    compat: str = "default",
) -> tuple[dict[str, SceneEstimates], list[Problem]]:
    """Validate in-memory estimates as ``read_submission`` validates a file.

    Args:
        estimates: ``{scene: [(frame_name, Pose | None, confidence), ...]}`` or ``{scene: SceneEstimates}``;
            a None pose means "no estimate" and is dropped silently.
        expected: Frame names by scene; enables the unknown-frame and outside-the-split checks.
        compat: ``default`` or ``official`` (see ``read_submission``).

    Returns:
        The valid estimates by scene, and every problem found.
    """
    problems = _Problems(SubmissionLimits().max_problems)
    out: dict[str, SceneEstimates] = {}
    for scene, items in estimates.items():
        if expected is not None and scene not in expected:
            problems.add(scene, None, "scene is not part of the evaluated split; ignored")
            continue
        if isinstance(items, SceneEstimates):
            est = items
        else:
            rows = [(str(n), p, c) for n, p, c in items if p is not None]
            if rows:
                R = np.stack([p.R for _, p, _ in rows])
                t = np.stack([p.t for _, p, _ in rows])
                finite = np.all(np.isfinite(R), axis=(1, 2))
                q = np.full((len(rows), 4), np.nan)
                if finite.any():
                    q[finite] = rotmat_to_quat(R[finite])
            else:
                q, t = np.zeros((0, 4)), np.zeros((0, 3))
            conf = np.array([float(c) for _, _, c in rows], dtype=np.float64)
            est = SceneEstimates([n for n, _, _ in rows], q, t, conf, np.zeros(len(rows), dtype=np.int64))
        known = expected.get(scene) if expected is not None else None
        out[scene] = _drop_duplicates(
            scene, _validate_rows(scene, est, None, compat, known, problems), compat, problems, {}
        )
    return out, problems.finish()
