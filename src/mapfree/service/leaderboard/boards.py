"""Leaderboards: the public finished submissions of a split ranked by one metric (equal scores share a rank),
all of them or each account's best, on the whole split or one scene; the method each author describes; CSV
export; two submissions side by side. Published results stay in a table of their own (``published.py``); the
JSON routes are in ``router.py``."""

from __future__ import annotations

import csv
import io
import math
import re
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from urllib.parse import urlsplit

from fastapi import HTTPException, Request
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from ..accounts.caller import identify
from ..config import Settings
from ..database.models import MethodInfo, Result, Submission, User
from ..inputs import UploadError
from .disclosure import TEST_RANK_BY
from .published import REFERENCE_ROWS
from .scoring import LOWER_IS_BETTER, METRIC_KEYS, SHORT
from .submissions import shown_metrics, to_json, visible_submission

VIEWS = ("all", "best")
#: Characters refused in free text: C0/C1 controls (but tab/newline in descriptions) and bidirectional overrides.
_BAD_TEXT = re.compile("[\x00-\x08\x0b-\x1f\x7f-\x9f\u200e\u200f\u202a-\u202e\u2066-\u2069]")
MAX_DESCRIPTION = 2000
MAX_URL = 500


# --------------------------------------------------------------------------------------- method metadata


@dataclass
class MethodMeta:
    """What an author states about the method behind a submission."""

    description: str = ""
    paper_url: str = ""
    code_url: str = ""
    runtime_ms: float | None = None  # per query pair
    extra_data: bool = False  # trained or tuned on data beyond the benchmark's train split

    def empty(self) -> bool:
        return self == MethodMeta()


def _text(value: str | None, limit: int, what: str) -> str:
    value = (value or "").strip()
    if len(value) > limit:
        raise UploadError(422, f"{what}: longer than {limit} characters")
    if _BAD_TEXT.search(value):
        raise UploadError(422, f"{what}: contains control or bidirectional-override characters")
    return value


def _url(value: str | None, what: str) -> str:
    value = _text(value, MAX_URL, what)
    if not value:
        return ""
    parts = urlsplit(value)
    if parts.scheme not in ("http", "https") or not parts.netloc or any(c.isspace() for c in value):
        raise UploadError(422, f"{what}: must be an http(s) URL such as https://arxiv.org/abs/…; got {value[:80]!r}")
    return value


def _runtime(value: str | float | None) -> float | None:
    if value is None or str(value).strip() == "":
        return None
    try:
        ms = float(value)
    except ValueError:
        raise UploadError(422, f"runtime_ms: not a number: {str(value)[:40]!r}") from None
    if not math.isfinite(ms) or not 0 < ms < 1e7:
        raise UploadError(422, "runtime_ms: must be a finite number of milliseconds per query, 0 < ms < 1e7")
    return ms


def parse_meta(
    description: str | None = "",
    paper_url: str | None = "",
    code_url: str | None = "",
    runtime_ms: str | float | None = None,
    extra_data: bool = False,
) -> MethodMeta:
    """What an author states about the method behind a submission, checked: plain text, and http(s) links only
    (no ``javascript:``).

    Args:
        description: Free text, at most ``MAX_DESCRIPTION`` characters.
        paper_url: A link to the paper (http or https).
        code_url: A link to the code (http or https).
        runtime_ms: Runtime per query, in milliseconds (a number or its text; empty: not stated).
        extra_data: Whether the method was trained or tuned on data beyond the benchmark's train split.

    Returns:
        The metadata.

    Raises:
        UploadError: 422 naming the field: too long, control or bidirectional-override characters, a link
            that is not http(s), a runtime that is not a positive number.
    """
    return MethodMeta(
        _text(description, MAX_DESCRIPTION, "description"),
        _url(paper_url, "paper_url"),
        _url(code_url, "code_url"),
        _runtime(runtime_ms),
        bool(extra_data),
    )


def save_meta(db: Session, submission_id: str, meta: MethodMeta) -> None:
    """Store (or replace) the method description of a submission; the caller commits.

    Args:
        db: The request's database session.
        submission_id: The submission's id.
        meta: The checked description (``parse_meta``).
    """
    row = db.get(MethodInfo, submission_id)
    if row is None:
        db.add(MethodInfo(submission_id=submission_id, **asdict(meta)))
    else:
        for k, v in asdict(meta).items():
            setattr(row, k, v)


def meta_json(row: MethodInfo | None) -> dict:
    """A submission's method description as the API shows it (``MethodMetaOut``); the empty one when none
    was given.

    Args:
        row: The stored description, or None.
    """
    if row is None:
        return asdict(MethodMeta())
    return {k: getattr(row, k) for k in asdict(MethodMeta())}


# ------------------------------------------------------------------------------------------------ boards


def check_sort(key: str) -> str:
    """A board's sort key, checked.

    Args:
        key: A short metric name (``scoring.SHORT``: ``vcre_auc``, ``pose_auc``, ``med_trans``, …).

    Returns:
        The key.

    Raises:
        UploadError: 422 naming the keys for any other.
    """
    if key not in SHORT:
        raise UploadError(422, f"unknown sort key {key!r}; use one of {', '.join(SHORT)}")
    return key


def competition_ranks(values: list[float | None]) -> list[int | None]:
    """Ranks of already sorted values, "1224" style: equal values share the best rank; missing ones get none."""
    ranks: list[int | None] = []
    for i, v in enumerate(values):
        if v is None:
            ranks.append(None)
        elif i > 0 and values[i - 1] == v:
            ranks.append(ranks[-1])
        else:
            ranks.append(i + 1)
    return ranks


#: Rows per leaderboard page: the default, and the most a request may ask for.
PER_PAGE, MAX_PER_PAGE = 50, 200


def ranking(
    db: Session, split: str, sort: str = "vcre_auc", view: str = "all", scene: str | None = None
) -> list[tuple[str, int | None]]:
    """The public scored submissions of a split, ranked. Equal scores share a rank; ties are ordered by age.
    Only ids, dates and the one sort value are read (the database extracts it from the stored JSON), so that a
    board of 20,000 entries costs milliseconds, not the decoding of every result.

    Args:
        db: The request's database session.
        split: The split.
        sort: The metric to rank by (``check_sort``); lower is better for the medians. On ``test`` an AUC
            ranks by the precision at the same threshold (AUCs are not published there).
        view: ``"all"``, or ``"best"``: each account's best entry only.
        scene: Rank by this scene's scores instead of the split's (not for ``test``: it has no per-scene
            results).

    Returns:
        ``(submission id, rank)`` pairs, best first; entries without the metric come last, without a rank.

    Raises:
        UploadError: 422 for an unknown sort key or view, or a scene of ``test``.
    """
    check_sort(sort)
    if view not in VIEWS:
        raise UploadError(422, f"view must be one of {', '.join(VIEWS)}; got {view!r}")
    if scene is not None and split == "test":
        raise UploadError(422, "the test split has no per-scene results")
    if split == "test":  # AUCs are withheld on test: rank by the precision at the same threshold
        sort = TEST_RANK_BY.get(sort, sort)
    key = SHORT[sort]
    query = (
        select(
            Submission.id,
            Submission.created_at,
            Submission.user_id,
            (Result.metrics[key] if scene is None else Result.per_scene[(scene, key)]).as_float(),
        )
        .join(Result, Result.submission_id == Submission.id)
        .where(Submission.split == split, Submission.public.is_(True), Submission.status == "done")
    )
    if scene is not None:  # submissions with results for that scene (every scored scene has an estimate ratio)
        query = query.where(Result.per_scene[(scene, SHORT["estimates"])].as_float().is_not(None))
    rows = [
        (sid, created, uid, shown_metrics(split, {key: v})[key] if v is not None else None)
        for sid, created, uid, v in db.execute(query).all()
    ]
    lower = sort in LOWER_IS_BETTER
    rows.sort(key=lambda r: (r[3] is None, 0.0 if r[3] is None else (r[3] if lower else -r[3]), r[1], r[0]))
    if view == "best":
        best: dict[int, tuple] = {}
        for r in rows:
            best.setdefault(r[2], r)  # an author's first row in this order is their best
        rows = list(best.values())
    return list(zip((r[0] for r in rows), competition_ranks([r[3] for r in rows])))


def entries_of(db: Session, split: str, ranked: list[tuple[str, int | None]], scene: str | None = None) -> list[dict]:
    """The board rows of ``ranked`` (a slice of ``ranking``), in its order: name, author, method, metrics."""
    scores = Result.metrics if scene is None else Result.per_scene  # only the column needed (per_scene is big)
    rows = db.execute(
        select(Submission.id, Submission.name, Submission.created_at, User.name, scores, MethodInfo)
        .join(Result, Result.submission_id == Submission.id)
        .join(User, User.id == Submission.user_id)
        .outerjoin(MethodInfo, MethodInfo.submission_id == Submission.id)
        .where(Submission.id.in_([sid for sid, _ in ranked]))
    ).all()
    by_id = {r[0]: r for r in rows}
    entries = []
    for sid, rank in ranked:
        if sid not in by_id:  # withdrawn meanwhile
            continue
        _, name, created_at, uname, values, info = by_id[sid]
        values = (shown_metrics(split, values) if scene is None else (values or {}).get(scene)) or {}
        entries.append(
            {
                "id": sid,
                "name": name,
                "user": uname,
                "created_at": created_at,
                "rank": rank,
                "url": f"/submissions/{sid}",
                "method": meta_json(info),
                "metrics": {short: values.get(long) for short, long in SHORT.items()},
            }
        )
    return entries


@dataclass
class Page:
    """One page of a board: its entries, and where it sits among ``total`` entries."""

    entries: list[dict]
    total: int
    page: int
    per_page: int

    @property
    def pages(self) -> int:
        return max(1, -(-self.total // self.per_page))


def board(
    db: Session,
    split: str,
    sort: str = "vcre_auc",
    view: str = "all",
    scene: str | None = None,
    page: int = 1,
    per_page: int = PER_PAGE,
) -> Page:
    """One page of a leaderboard (``ranking``), each row with its name, author, method and metrics.

    Args:
        db: The request's database session.
        split: The split.
        sort: The metric to rank by (``check_sort``).
        view: ``"all"``, or ``"best"``: each account's best entry only.
        scene: Rank and show this scene's scores instead of the split's (not for ``test``).
        page: The page, from 1.
        per_page: Rows per page, at most ``MAX_PER_PAGE``.

    Returns:
        The page's rows and where it sits among all the entries.

    Raises:
        UploadError: 422 for an unknown sort key or view, or a scene of ``test``.
    """
    per_page = max(1, min(MAX_PER_PAGE, per_page))
    ranked = ranking(db, split, sort, view, scene)
    first = (max(1, page) - 1) * per_page
    return Page(entries_of(db, split, ranked[first : first + per_page], scene), len(ranked), max(1, page), per_page)


def reference_rows() -> list[dict]:
    """The published results of the literature shown beside a board (never ranked with submissions), best VCRE
    AUC first within each dataset.

    Returns:
        Rows of ``name``, ``dataset``, ``note`` and ``metrics`` (by short name).
    """
    rows = [
        {
            "name": r["name"],
            "dataset": r["dataset"],
            "note": r["note"],
            "metrics": {k: r["metrics"].get(k) for k in SHORT},
        }
        for r in REFERENCE_ROWS
    ]
    return sorted(rows, key=lambda r: (r["dataset"], -(r["metrics"]["vcre_auc"] or 0)))


CSV_HEADER = [
    "rank",
    "name",
    "user",
    "submitted_utc",
    *METRIC_KEYS,
    "runtime_ms",
    "extra_data",
    "paper_url",
    "code_url",
    "url",
]


def csv_rows(entries: list[dict]) -> str:
    """Board rows as CSV lines (full metric names as headers: ``CSV_HEADER``). Text cells that a spreadsheet
    would run as a formula get a leading apostrophe."""

    def cell(v: object) -> object:
        if isinstance(v, str) and v[:1] in ("=", "+", "-", "@", "\t", "\r"):
            return "'" + v
        return "" if v is None else v

    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    for e in entries:
        date = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(e["created_at"]))
        w.writerow(
            [
                cell(x)
                for x in (
                    e["rank"],
                    e["name"],
                    e["user"],
                    date,
                    *(e["metrics"][s] for s in SHORT),
                    e["method"]["runtime_ms"],
                    e["method"]["extra_data"],
                    e["method"]["paper_url"],
                    e["method"]["code_url"],
                    e["url"],
                )
            ]
        )
    return out.getvalue()


def stream_csv(
    sessions: sessionmaker, split: str, ranked: list[tuple[str, int | None]], scene: str | None, chunk: int = 500
) -> Iterator[str]:
    """The CSV export of a ranked board, streamed: a header (``CSV_HEADER``), then ``chunk`` rows at a time, each
    chunk read in a short transaction of its own. Text cells a spreadsheet would run as a formula are quoted.

    Args:
        sessions: The app's session factory.
        split: The split.
        ranked: The board's ``(submission id, rank)`` pairs (``ranking``).
        scene: The scene whose scores the rows show (None: the split's).
        chunk: Rows read per transaction.

    Yields:
        The CSV text, a chunk of lines at a time.
    """
    yield ",".join(CSV_HEADER) + "\n"
    for i in range(0, len(ranked), chunk):
        with sessions() as db:
            yield csv_rows(entries_of(db, split, ranked[i : i + chunk], scene))


# ----------------------------------------------------------------------------------------------- compare


def ordered_metrics(metrics: dict | None) -> list[str]:
    """Every metric a result holds: the benchmark's eight headline keys first, then the rest (50 cm / 10°,
    45 px, …) in a stable order."""
    metrics = metrics or {}
    return [k for k in METRIC_KEYS if k in metrics] + sorted(k for k in metrics if k not in METRIC_KEYS)


def compare(a: dict, b: dict) -> dict:
    """Two submissions of one split side by side: every metric either has, the difference b − a and which is
    better; per scene as well where they have per-scene results.

    Args:
        a: A submission the caller may see (``submissions.to_json``).
        b: Another one.

    Returns:
        ``split``; ``a`` and ``b`` (``id``, ``name``, ``user``, ``url``); ``metrics``: rows of ``metric``, ``a``,
        ``b``, ``diff`` and ``better`` (``"a"``, ``"b"`` or None); ``per_scene``: such rows by scene.

    Raises:
        UploadError: 422 for submissions of different splits.
    """
    if a["split"] != b["split"]:
        raise UploadError(422, f"compare submissions of the same split (got {a['split']} and {b['split']})")
    lower = {SHORT[k] for k in LOWER_IS_BETTER}

    def rows(ma: dict, mb: dict) -> list[dict]:
        out = []
        for k in ordered_metrics({**ma, **mb}):
            va, vb = ma.get(k), mb.get(k)
            diff = vb - va if isinstance(va, (int, float)) and isinstance(vb, (int, float)) else None
            better = None if not diff else (("b" if diff < 0 else "a") if k in lower else ("b" if diff > 0 else "a"))
            out.append({"metric": k, "a": va, "b": vb, "diff": diff, "better": better})
        return out

    result = {
        "split": a["split"],
        "a": {k: a[k] for k in ("id", "name", "user", "url")},
        "b": {k: b[k] for k in ("id", "name", "user", "url")},
        "metrics": rows(a["metrics"] or {}, b["metrics"] or {}),
        "per_scene": {},
    }
    sa, sb = a.get("per_scene") or {}, b.get("per_scene") or {}
    for scene in sorted({*sa, *sb}):
        result["per_scene"][scene] = rows(sa.get(scene) or {}, sb.get(scene) or {})
    return result


def check_split(settings: Settings, split: str) -> None:
    """Refuse a board of a split this server does not take submissions for.

    Args:
        settings: The deployment's settings (its ``splits``).
        split: The split named in the path.

    Raises:
        HTTPException: 404 for any split not in ``Settings.splits``.
    """
    if split not in settings.splits:
        raise HTTPException(404, f"no leaderboard for split {split!r}")


def visible_json(request: Request, db: Session, sid: str) -> dict:
    """A submission the caller may see (``submissions.visible_submission``), as the API shows it (``to_json``).

    Args:
        request: The request (who is calling).
        db: The request's database session.
        sid: The submission's id.

    Raises:
        HTTPException: 404 when there is none the caller may see.
    """
    return to_json(db, visible_submission(db, identify(request, db).user, sid, f"no such submission {sid[:40]!r}"))
