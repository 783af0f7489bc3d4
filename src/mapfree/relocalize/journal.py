"""A run's journal: one JSON line per finished frame beside the submission, read back by ``--resume``.

``out/submission.zip`` is journaled in ``out/submission.journal.jsonl``: a header line (``JournalHeader``: the
method, the split, which frames, a print of each scene's data) then one line per frame (``FrameRecord``), appended
the moment the frame is done, by whichever process computed it. The frames without an estimate are listed in
``out/submission.failures.jsonl`` (``Failure``). The records are dataclasses; their JSON keys are the file format.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..calibration import CALIBRATION_OPTION
from ..data.io import naming
from ..estimate import Estimate, Signals
from ..geometry import Pose

__all__ = [
    "JOURNAL_VERSION",
    "FrameRecord",
    "JournalHeader",
    "Journal",
    "Failure",
    "journal_path",
    "failures_path",
    "read_journal",
    "append_records",
    "write_header",
    "rewrite_journal",
    "write_failures",
    "estimate_scores",
    "scene_fingerprint",
    "check_resumable",
    "check_same_selection",
]

JOURNAL_VERSION = 1


def journal_path(output: os.PathLike | str) -> Path:
    """``out/submission.zip`` -> ``out/submission.journal.jsonl``."""
    p = Path(output)
    return p.with_name(f"{p.stem}.journal.jsonl")


def failures_path(output: os.PathLike | str) -> Path:
    """``out/submission.zip`` -> ``out/submission.failures.jsonl``."""
    p = Path(output)
    return p.with_name(f"{p.stem}.failures.jsonl")


# --------------------------------------------------------------------------- records


def estimate_scores(est: Estimate) -> dict[str, float]:
    """The finite scalar numbers of ``est.extras`` (alternative confidences, ratios) for the journal."""
    out: dict[str, float] = {}
    for k, v in est.extras.items():
        if isinstance(v, (bool, np.bool_)):
            continue
        if isinstance(v, (int, float, np.integer, np.floating)) and np.isfinite(v):
            out[k] = float(v)
    return out


@dataclass(frozen=True)
class FrameRecord:
    """One finished frame of a run (a ``"kind": "frame"`` line of the journal).

    Attributes:
        scene: The scene's name (``s00000``).
        frame: The query frame's name (``seq1/frame_00000.jpg``).
        ok: Whether it got an estimate.
        confidence: The method's own confidence.
        inliers: The solver's inlier count.
        reason: Why there is no estimate ("" when there is one).
        timings: Seconds per stage.
        scores: The estimate's finite scalar extras (``confidence_inliers``, ...), the choices of ``--confidence``.
        signals: The evidence a calibration reads.
        p_correct: The calibrated probability that the pose is right (None without a calibration).
        stage: The cascade stage that answered ("" for other methods).
        q: The world-to-camera rotation as a quaternion (w, x, y, z), when ``ok``.
        t: The world-to-camera translation (metres), when ``ok``.
    """

    scene: str
    frame: str
    ok: bool
    confidence: float = 0.0
    inliers: int = 0
    reason: str = ""
    timings: dict[str, float] = field(default_factory=dict)
    scores: dict[str, float] = field(default_factory=dict)
    signals: Signals = field(default_factory=Signals)
    p_correct: float | None = None
    stage: str = ""
    q: list[float] | None = None
    t: list[float] | None = None

    @classmethod
    def of(cls, scene: str, frame: str, est: Estimate, world_pose: Pose | None) -> FrameRecord:
        """The record of ``est`` (relative to the reference) whose world-to-camera pose is ``world_pose``."""
        q, t = world_pose.qt() if world_pose is not None else (None, None)
        return cls(
            scene=scene,
            frame=frame,
            ok=world_pose is not None,
            confidence=est.confidence,
            inliers=int(est.inliers),
            reason=est.reason,
            timings={k: round(float(v), 6) for k, v in est.timings.items()},
            scores=estimate_scores(est),
            signals=est.signals,
            p_correct=est.p_correct,
            stage=est.stage,
            q=None if q is None else q.tolist(),
            t=None if t is None else t.tolist(),
        )

    @property
    def key(self) -> tuple[str, str]:
        """(scene, frame): what a journal holds once."""
        return self.scene, self.frame

    def world_pose(self) -> Pose:
        """The world-to-camera pose of a record with an estimate."""
        if self.q is None or self.t is None:
            raise ValueError(f"{self.scene} {self.frame} has no estimate")
        return Pose.from_qt(self.q, self.t)

    def score(self, confidence: str | None) -> float:
        """The submission confidence: the score named ``confidence`` (default: the method's own), 0 when it is
        not a finite positive number."""
        conf = self.scores.get(confidence, self.confidence) if confidence else self.confidence
        return positive(conf)

    def to_json(self) -> dict[str, Any]:
        """The journal line (``p_correct``, ``stage`` and the pose only when there are)."""
        rec: dict[str, Any] = {
            "kind": "frame",
            "scene": self.scene,
            "frame": self.frame,
            "ok": self.ok,
            "confidence": self.confidence,
            "inliers": self.inliers,
            "reason": self.reason,
            "timings": self.timings,
            "scores": self.scores,
            "signals": self.signals.to_dict(),
        }
        if self.p_correct is not None:
            rec["p_correct"] = self.p_correct
        if self.stage:
            rec["stage"] = self.stage
        if self.q is not None and self.t is not None:
            rec["q"], rec["t"] = self.q, self.t
        return rec

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> FrameRecord:
        """The record of a journal line (fields an older journal lacks take their defaults)."""
        return cls(
            scene=str(d["scene"]),
            frame=str(d["frame"]),
            ok=bool(d.get("ok", False)),
            confidence=d.get("confidence", 0.0),
            inliers=int(d.get("inliers", 0)),
            reason=str(d.get("reason", "")),
            timings=dict(d.get("timings", {})),
            scores=dict(d.get("scores", {})),
            signals=Signals.from_dict(d.get("signals", {})),
            p_correct=d.get("p_correct"),
            stage=str(d.get("stage", "")),
            q=d.get("q"),
            t=d.get("t"),
        )


def positive(conf: float) -> float:
    """``conf`` as a float when finite and > 0, else 0 (a submission confidence)."""
    return float(conf) if np.isfinite(conf) and conf > 0 else 0.0


@dataclass(frozen=True)
class JournalHeader:
    """The journal's first line (``"kind": "header"``): what the run computes.

    Attributes:
        method: The method (``Method.to_dict()``).
        root: The dataset folder.
        split: The split.
        all_frames: Every query (``--all-frames``) rather than the scored ones.
        frames: Which frames: ``all``, ``scored`` or the name of a selection (None in journals written before it
            was recorded).
        data: Each scene's ``scene_fingerprint`` when its frames were computed.
        version: The journal format's version.
    """

    method: dict[str, Any]
    root: str = ""
    split: str = ""
    all_frames: bool = False
    frames: str | None = None
    data: dict[str, str] = field(default_factory=dict)
    version: int = JOURNAL_VERSION

    def to_json(self) -> dict[str, Any]:
        """The header line (``frames`` only when recorded)."""
        out: dict[str, Any] = {"kind": "header", "version": self.version, "method": self.method}
        out.update(root=self.root, split=self.split, all_frames=self.all_frames)
        if self.frames is not None:
            out["frames"] = self.frames
        out["data"] = self.data
        return out

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> JournalHeader:
        """The header of a journal's header line."""
        return cls(
            method=dict(d.get("method") or {}),
            root=str(d.get("root", "")),
            split=str(d.get("split", "")),
            all_frames=bool(d.get("all_frames", False)),
            frames=d.get("frames"),
            data=dict(d.get("data") or {}),
            version=int(d.get("version", JOURNAL_VERSION)),
        )


@dataclass
class Journal:
    """A journal as read back: its header (None without one), its frames, and the lines cut mid-write (a kill, a
    full disk), which are left out."""

    header: JournalHeader | None = None
    frames: list[FrameRecord] = field(default_factory=list)
    torn: int = 0

    @classmethod
    def read(cls, path: os.PathLike | str) -> Journal:
        """The journal at ``path`` (empty when there is none)."""
        header, lines, torn = _lines(Path(path))
        return cls(
            None if header is None else JournalHeader.from_json(header),
            [FrameRecord.from_json(r) for r in lines],
            torn,
        )

    def done(self) -> set[tuple[str, str]]:
        """The (scene, frame) pairs it holds."""
        return {r.key for r in self.frames}


@dataclass(frozen=True)
class Failure:
    """A frame without an estimate, as the failure log lists it."""

    scene: str
    frame: str
    reason: str

    def to_json(self) -> dict[str, str]:
        return {"scene": self.scene, "frame": self.frame, "reason": self.reason}


# --------------------------------------------------------------------------- reading and writing


def _lines(path: Path) -> tuple[dict | None, list[dict], int]:
    """(header line, frame lines, lines that are not a whole record) of a journal, as JSON objects."""
    if not path.is_file():
        return None, [], 0
    header, recs, torn = None, [], 0
    for line in path.read_text(errors="replace").splitlines():
        try:
            r = json.loads(line)
        except json.JSONDecodeError:
            torn += bool(line.strip())
            continue
        if not isinstance(r, dict):
            torn += 1
        elif r.get("kind") == "header":
            header = header or r
        elif r.get("kind") == "frame":
            recs.append(r)
    return header, recs, torn


def read_journal(path: os.PathLike | str) -> tuple[dict | None, list[dict]]:
    """(header, frame records) of a journal as the JSON objects of its lines (``Journal.read`` gives the typed
    records); a torn line (killed mid-write, a full disk) is left out (a resumed run counts them in
    ``RunResult.torn_lines``)."""
    header, recs, _ = _lines(Path(path))
    return header, recs


def _json_lines(items: Iterable[dict[str, Any]]) -> str:
    return "".join(json.dumps(r, allow_nan=False) + "\n" for r in items)


def append_records(path: Path, records: Sequence[FrameRecord]) -> None:
    """Append whole lines with one ``write`` on an O_APPEND descriptor (safe across worker processes)."""
    data = _json_lines(r.to_json() for r in records).encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        with naming(path):
            os.write(fd, data)
    finally:
        os.close(fd)


def write_header(path: Path, header: JournalHeader) -> None:
    """Start a journal: ``header`` alone."""
    with naming(path):
        path.write_text(json.dumps(header.to_json()) + "\n")


def rewrite_journal(path: Path, header: JournalHeader, recs: Sequence[FrameRecord]) -> None:
    """Replace the journal by ``header`` + ``recs`` (atomically: a kill meanwhile leaves the old one)."""
    tmp = path.with_name(path.name + ".tmp")
    with naming(path):
        tmp.write_text(_json_lines([header.to_json(), *(r.to_json() for r in recs)]))
    os.replace(tmp, path)


def write_failures(output: os.PathLike | str, failures: Iterable[Failure]) -> Path:
    """Write the failure log of the submission ``output`` (``failures_path``); returns its path."""
    path = failures_path(output)
    with naming(path):
        path.write_text("".join(json.dumps(f.to_json()) + "\n" for f in failures))
    return path


# --------------------------------------------------------------------------- resuming


def scene_fingerprint(scene_dir: os.PathLike | str) -> str:
    """What a scene's data looked like: a hash of its text files' bytes and of every other file's name, size and
    modification time (images and depth maps are not read). A resumed run recomputes a scene whose print changed."""
    h = hashlib.sha1()
    root = Path(scene_dir)
    for p in sorted(root.rglob("*")):
        if not p.is_file():
            continue
        rel = p.relative_to(root).as_posix()
        if p.suffix == ".txt":
            h.update(f"{rel}\0".encode() + p.read_bytes() + b"\0")
        else:
            st = p.stat()
            h.update(f"{rel}\0{st.st_size}\0{st.st_mtime_ns}\0".encode())
    return h.hexdigest()


def drop_stale(journal: Journal, fingerprints: Mapping[str, str]) -> list[str]:
    """Drop from ``journal`` the records of scenes whose data changed since they were computed (or have no
    recorded print: a journal of an older version); returns those scenes' names (the run's ``stale_scenes``:
    the CLI says so)."""
    known = journal.header.data if journal.header is not None else {}
    stale = sorted(
        {r.scene for r in journal.frames if r.scene in fingerprints and known.get(r.scene) != fingerprints[r.scene]}
    )
    journal.frames = [r for r in journal.frames if r.scene not in stale]
    return stale


def same_method(a: Mapping[str, Any], b: Mapping[str, Any]) -> bool:
    """Whether two journal headers' methods give the same estimates (a calibration file only sets ``p_correct``,
    recomputed from the journal's signals when the submission is written)."""
    keys = ("kind", "matcher", "matcher_opts", "depth", "solver", "solver_opts")
    options = [{k: v for k, v in (m.get("options") or {}).items() if k != CALIBRATION_OPTION} for m in (a, b)]
    return all(a.get(k) == b.get(k) for k in keys) and options[0] == options[1]


def check_resumable(
    path: Path, journal: Journal, method: Mapping[str, Any], selection: str, resume: bool, overwrite: bool
) -> bool:
    """Whether the run starts a fresh journal at ``path`` (True) or continues ``journal`` (False), refusing one
    it would clobber (results there, neither ``resume`` nor ``overwrite``) or mix with (another method, another
    selection of frames).

    Args:
        path: The journal's path (for the messages).
        journal: What it holds.
        method: This run's method (``Method.to_dict()``).
        selection: This run's frames (``preflight.selection_of``).
        resume: ``--resume``.
        overwrite: ``--overwrite``.

    Raises:
        FileExistsError: Results there without ``resume`` or ``overwrite``.
        ValueError: A journal of another method or selection, resumed.
    """
    if journal.frames and not resume and not overwrite:
        raise FileExistsError(
            f"{path} already holds {len(journal.frames)} results: run again with --resume to continue "
            f"that run or --overwrite to start again (in Python: resume=True, overwrite=True)"
        )
    header = journal.header
    if resume and header is not None and not overwrite:
        if not same_method(header.method, method):
            raise ValueError(
                f"{path} was written by method {header.method.get('name')!r}, not {method['name']!r}: "
                f"use another output path or --overwrite"
            )
        check_same_selection(path, header, selection)
    return overwrite or not resume or header is None


_SELECTION_WORDS = {"all": "every query (--all-frames)", "scored": "the scored queries (no --all-frames)"}


def check_same_selection(path: Path, header: JournalHeader, selection: str) -> None:
    """A resumed run must relocalize the frames the journal's run did: resuming a run of every query without
    --all-frames (or the other way round) would write a mix of both sets."""
    had = header.frames
    if had is None:  # a journal written before the selection was recorded: its all_frames flag says it
        if selection not in _SELECTION_WORDS:
            return
        had = "all" if header.all_frames else "scored"
    if had != selection:
        was, now = (_SELECTION_WORDS.get(x, x) for x in (had, selection))
        raise ValueError(
            f"{path} holds a run of {was}, this one asks for {now}: resuming would mix the two; "
            f"run it as it was, or use --overwrite or another output path"
        )
