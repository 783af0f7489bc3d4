"""The leaderboard's web pages: uploading a submission, your history, a submission's page (its figures, and for
its owner the method form, the ZIP and withdrawing), the boards and a comparison of two submissions. A form
that fails comes back as the same form with its values and the error above it."""

from __future__ import annotations

from urllib.parse import urlencode

from fastapi import APIRouter, Depends, File, Form, HTTPException, Query, Request, UploadFile
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from sqlalchemy import select
from sqlalchemy.orm import Session

from ..accounts.caller import db_session, identify, require_writer, signed_in
from ..accounts.quota import test_quota
from ..accounts.render import error_page, page
from ..config import Settings
from ..database.models import MethodInfo, Submission, User
from ..inputs import UploadError, problem, spooled_upload
from ..state import SessionsDep, SettingsDep, sessions_of, settings_of
from .boards import (
    MAX_PER_PAGE,
    PER_PAGE,
    VIEWS,
    board,
    check_sort,
    check_split,
    compare,
    meta_json,
    ordered_metrics,
    parse_meta,
    reference_rows,
    save_meta,
    visible_json,
)
from .own import Withdrawn, own_submission, withdraw, zip_response
from .scoring import LOWER_IS_BETTER, SHORT, known_scenes
from .submissions import accept, to_json, visible_submission

router = APIRouter(include_in_schema=False)
LABELS = {
    "vcre_auc": "VCRE AUC",
    "vcre_prec": "VCRE prec.",
    "pose_auc": "Pose AUC",
    "pose_prec": "Pose prec.",
    "med_trans": "Med. trans. (m)",
    "med_rot": "Med. rot. (°)",
    "med_vcre": "Med. VCRE (px)",
    "estimates": "Estimates (frac.)",
}


@router.get("/me", response_class=HTMLResponse)
def history(request: Request, settings: SettingsDep, db: Session = Depends(db_session)):
    return _history(request, db, settings, signed_in(request, db))


def _history(
    request: Request, db: Session, settings: Settings, user: User, status: int = 200, error: str = ""
) -> HTMLResponse:
    subs = db.scalars(
        select(Submission).where(Submission.user_id == user.id).order_by(Submission.created_at.desc()).limit(500)
    ).all()
    return page(
        request,
        "history.html",
        db,
        status,
        subs=[to_json(db, s, user.name) for s in subs],
        labels=LABELS,
        quota=test_quota(db, settings, user),
        error=error,
    )


def withdrawn_page(request: Request, exc: Withdrawn) -> HTMLResponse:
    """A form that changes a withdrawn submission (say, from a page opened before withdrawing it): the owner's
    history, where it is listed as withdrawn, with the reason above it (409)."""
    with sessions_of(request)() as db:
        user = identify(request, db).user
        if user is None:
            return error_page(request, exc.status_code, str(exc.detail))
        return _history(request, db, settings_of(request), user, exc.status_code, str(exc.detail))


# ------------------------------------------------------------------------------------------- submissions


def _submit_page(
    request: Request,
    db: Session,
    settings: Settings,
    user: User,
    status: int = 200,
    error: str = "",
    form: dict | None = None,
) -> HTMLResponse:
    return page(
        request,
        "submit.html",
        db,
        status,
        error=error,
        form=form or {},
        quota=test_quota(db, settings, user),
    )


@router.get("/submit", response_class=HTMLResponse)
def submit_form(request: Request, settings: SettingsDep, db: Session = Depends(db_session)):
    return _submit_page(request, db, settings, signed_in(request, db))


@router.post("/submit")
def submit(
    request: Request,
    settings: SettingsDep,
    file: UploadFile = File(...),
    split: str = Form(...),
    name: str = Form(""),
    public: bool = Form(False),
    description: str = Form(""),
    paper_url: str = Form(""),
    code_url: str = Form(""),
    runtime_ms: str = Form(""),
    extra_data: bool = Form(False),
    csrf_token: str = Form(""),
    db: Session = Depends(db_session),
):
    """Upload from the form; on a problem the form comes back filled in, with the error above it."""
    form = {
        "split": split,
        "name": name,
        "public": public,
        "description": description,
        "paper_url": paper_url,
        "code_url": code_url,
        "runtime_ms": runtime_ms,
        "extra_data": extra_data,
    }
    caller = require_writer(request, db, csrf_token)
    try:
        meta = parse_meta(description, paper_url, code_url, runtime_ms, extra_data)
        sub = accept(db, settings, caller.user, split, name, public, spooled_upload(file, "submission"))
    except (UploadError, HTTPException) as e:
        db.rollback()
        status, message = problem(e)
        return _submit_page(request, db, settings, caller.user, status, message, form)
    if not meta.empty():
        save_meta(db, sub.id, meta)
        db.commit()
    return RedirectResponse(f"/submissions/{sub.id}", status_code=303)


@router.get("/submissions/{sid}", response_class=HTMLResponse)
def submission_page(sid: str, request: Request, db: Session = Depends(db_session)):
    return _submission(request, db, sid)


def _submission(request: Request, db: Session, sid: str, status: int = 200, error: str = "") -> HTMLResponse:
    """A submission's page: every figure of its result, per-scene table, plots; for its owner also the method
    form, the ZIP download and withdrawing."""
    user = identify(request, db).user
    sub = visible_submission(db, user, sid, withdrawn=True)
    data = to_json(db, sub)
    first_scene = next(iter((data.get("per_scene") or {}).values()), None) or {}
    return page(
        request,
        "submission.html",
        db,
        status,
        sub=data,
        labels=LABELS,
        short=SHORT,
        metric_keys=ordered_metrics(data["metrics"]),
        scene_keys=ordered_metrics(first_scene),
        method=meta_json(db.get(MethodInfo, sub.id)),
        error=error,
        owner=user is not None and user.id == sub.user_id,
    )


@router.post("/submissions/{sid}/visibility")
def visibility(
    sid: str,
    request: Request,
    public: bool = Form(False),
    csrf_token: str = Form(""),
    db: Session = Depends(db_session),
):
    caller = require_writer(request, db, csrf_token)
    sub = own_submission(db, caller.user, sid)
    sub.public = public
    db.commit()
    return RedirectResponse(f"/submissions/{sid}", status_code=303)


@router.post("/submissions/{sid}/method")
def edit_method(
    sid: str,
    request: Request,
    description: str = Form(""),
    paper_url: str = Form(""),
    code_url: str = Form(""),
    runtime_ms: str = Form(""),
    extra_data: bool = Form(False),
    csrf_token: str = Form(""),
    db: Session = Depends(db_session),
):
    caller = require_writer(request, db, csrf_token)
    sub = own_submission(db, caller.user, sid)
    try:
        save_meta(db, sub.id, parse_meta(description, paper_url, code_url, runtime_ms, extra_data))
    except UploadError as e:
        db.rollback()
        return _submission(request, db, sid, e.status, e.message)
    db.commit()
    return RedirectResponse(f"/submissions/{sid}", status_code=303)


@router.post("/submissions/{sid}/withdraw")
def withdraw_form(sid: str, request: Request, csrf_token: str = Form(""), db: Session = Depends(db_session)):
    caller = require_writer(request, db, csrf_token)
    withdraw(db, own_submission(db, caller.user, sid))
    return RedirectResponse("/me", status_code=303)


@router.get("/submissions/{sid}/zip")
def download(sid: str, request: Request, sessions: SessionsDep, db: Session = Depends(db_session)) -> Response:
    return zip_response(sessions, db, own_submission(db, signed_in(request, db), sid))


# ------------------------------------------------------------------------------------------ leaderboards


@router.get("/leaderboard", response_class=HTMLResponse)
def leaderboard_default(request: Request):
    return RedirectResponse("/leaderboard/val", status_code=307)


@router.get("/leaderboard/{split}", response_class=HTMLResponse)
def leaderboard_page(
    split: str,
    request: Request,
    settings: SettingsDep,
    sort: str = Query("vcre_auc"),
    view: str = Query("all"),
    scene: str = Query(""),
    page_no: int = Query(1, ge=1, alias="page"),
    per_page: int = Query(PER_PAGE, ge=1, le=MAX_PER_PAGE),
    db: Session = Depends(db_session),
):
    check_split(settings, split)
    check_sort(sort)
    b = board(db, split, sort, view, scene or None, page_no, per_page)
    query = urlencode({"sort": sort, "view": view, **({"scene": scene} if scene else {})})
    pages = {
        "prev": b.page - 1 if b.page > 1 else None,
        "next": b.page + 1 if b.page < b.pages else None,
        "first": 1,
        "last": b.pages,
    }
    page_url = {
        k: f"?{query}&page={n}" + (f"&per_page={b.per_page}" if b.per_page != PER_PAGE else "")
        for k, n in pages.items()
        if n is not None
    }
    return page(
        request,
        "leaderboard.html",
        db,
        split=split,
        sort=sort,
        view=view,
        views=VIEWS,
        scene=scene,
        scenes=[] if split == "test" else sorted(known_scenes(settings, split) or ()),
        entries=b.entries,
        board=b,
        page_url=page_url,
        labels=LABELS,
        lower=LOWER_IS_BETTER,
        reference=reference_rows(),
        csv_url=f"/api/leaderboard/{split}.csv?{query}",
    )


@router.get("/compare", response_class=HTMLResponse)
def compare_page(request: Request, id: list[str] = Query([]), db: Session = Depends(db_session)):
    """Two submissions side by side (chosen with the leaderboard's check boxes)."""
    if len(id) != 2:
        raise HTTPException(422, f"choose exactly two submissions to compare (got {len(id)})")
    a, b = (visible_json(request, db, x) for x in id)
    return page(request, "compare.html", db, cmp=compare(a, b))
