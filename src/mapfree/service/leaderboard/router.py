"""JSON routes of the evaluation server, thin over the domain modules the web pages call too: submissions
(upload, list, read, visibility, figures, withdraw, ZIP, method description) and the leaderboards (board, CSV,
compare)."""

from __future__ import annotations

import logging
import re

from fastapi import APIRouter, Depends, File, Form, HTTPException, Query, Request, UploadFile
from fastapi.responses import Response, StreamingResponse
from pydantic import BaseModel, Field
from sqlalchemy import select
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from ..accounts.caller import db_session, identify, require_user, require_writer
from ..database.models import MethodInfo, Submission
from ..http.guard import client_address
from ..http.heavy import Heavy
from ..inputs import spooled_upload
from ..schemas import BoardOut, CompareOut, MethodMetaOut, SubmissionOut
from ..state import SessionsDep, SettingsDep
from .boards import (
    MAX_PER_PAGE,
    PER_PAGE,
    board,
    check_split,
    compare,
    meta_json,
    parse_meta,
    ranking,
    reference_rows,
    save_meta,
    stream_csv,
    visible_json,
)
from .own import own_submission, withdraw, zip_response
from .submissions import accept, needs_drawing, stored_plot, to_json, visible_submission
from .submissions import plot_png as render_plot

router = APIRouter()

log = logging.getLogger("mapfree.leaderboard")


@router.post(
    "/api/submissions",
    tags=["submissions"],
    status_code=202,
    response_model=SubmissionOut,
    response_model_exclude_unset=True,
)
def create_submission(
    request: Request,
    settings: SettingsDep,
    file: UploadFile = File(..., description="submission ZIP"),
    split: str = Form(..., description="val or test"),
    name: str = Form(""),
    public: bool = Form(False),
    csrf_token: str | None = Form(None),
    description: str = Form("", description="the method, shown on the leaderboard"),
    paper_url: str = Form("", description="http(s) link to the paper"),
    code_url: str = Form("", description="http(s) link to the code"),
    runtime_ms: str = Form("", description="runtime per query in ms"),
    extra_data: bool = Form(False, description="trained or tuned on data beyond the train split"),
    db: Session = Depends(db_session),
):
    """Upload a submission ZIP, optionally with its method's metadata (as ``PUT …/method``; a bad field is a
    422 naming it, before anything is stored). It is stored and queued before this answers 202; poll
    ``api_url``."""
    caller = require_writer(request, db, csrf_token)
    meta = parse_meta(description, paper_url, code_url, runtime_ms, extra_data)
    sub = accept(db, settings, caller.user, split, name, public, spooled_upload(file, "submission"))
    if not meta.empty():
        save_meta(db, sub.id, meta)
        db.commit()
    log.info("submission queued", extra={"submission": sub.id, "split": split, "user_id": caller.user.id})
    return {**to_json(db, sub, caller.user.name), "method": meta_json(db.get(MethodInfo, sub.id))}


@router.get(
    "/api/submissions", tags=["submissions"], response_model=list[SubmissionOut], response_model_exclude_unset=True
)
def my_submissions(request: Request, db: Session = Depends(db_session)):
    """The caller's own submissions (private history), newest first."""
    caller = require_user(request, db)
    subs = db.scalars(
        select(Submission).where(Submission.user_id == caller.user.id).order_by(Submission.created_at.desc()).limit(500)
    ).all()
    return [to_json(db, s, caller.user.name) for s in subs]


def _visible_submission(request: Request, db: Session, sid: str) -> Submission:
    return visible_submission(db, identify(request, db).user, sid)


@router.get(
    "/api/submissions/{sid}", tags=["submissions"], response_model=SubmissionOut, response_model_exclude_unset=True
)
def get_submission(sid: str, request: Request, db: Session = Depends(db_session)):
    """A submission you may see. Once withdrawn, its owner (and admins) still get it, as their list shows it:
    status ``withdrawn``, ``withdrawn_at``, no results; everyone else gets 404."""
    return to_json(db, visible_submission(db, identify(request, db).user, sid, withdrawn=True))


class Visibility(BaseModel):
    public: bool


@router.patch(
    "/api/submissions/{sid}", tags=["submissions"], response_model=SubmissionOut, response_model_exclude_unset=True
)
def set_visibility(sid: str, body: Visibility, request: Request, db: Session = Depends(db_session)):
    """Make one of your submissions public or private (409 once it is withdrawn: it stays hidden for good)."""
    caller = require_writer(request, db)
    sub = own_submission(db, caller.user, sid)
    sub.public = body.public
    db.commit()
    return to_json(db, sub)


@router.get(
    "/submissions/{sid}/plots/{name}.png",
    tags=["submissions"],
    response_class=Response,
    responses={200: {"content": {"image/png": {}}, "description": "the figure"}},
)
async def plot_png(sid: str, name: str, request: Request, pool: Heavy, db: Session = Depends(db_session)):
    sub = await run_in_threadpool(_visible_submission, request, db, sid)
    png = await run_in_threadpool(stored_plot, db, sub, name)
    if png is None and needs_drawing(sub, name):  # a first view: drawn on the heavy threads (429 past their
        # room), never on the shared pool, where 60 first renders stalled another user's /api/me for 22 s
        account = getattr(request.state, "user_id", None) or client_address(request)
        png = await pool.run(render_plot, db, sub, name, account=account)
    if png is None:
        raise HTTPException(404, "no such plot")
    return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=3600"})


@router.delete("/api/submissions/{sid}", tags=["submissions"], status_code=204, response_class=Response)
def withdraw_submission(sid: str, request: Request, db: Session = Depends(db_session)):
    """Withdraw one of your submissions: off the leaderboards, results and ZIP deleted. It still counts against
    the test quota of the day it was uploaded. Final: a withdrawn submission answers 409 to every later change."""
    caller = require_writer(request, db)
    withdraw(db, own_submission(db, caller.user, sid))
    return Response(status_code=204)


@router.get(
    "/api/submissions/{sid}/zip",
    tags=["submissions"],
    response_class=Response,
    responses={200: {"content": {"application/zip": {}}, "description": "the ZIP as uploaded"}},
)
def download_zip(sid: str, request: Request, sessions: SessionsDep, db: Session = Depends(db_session)):
    """The ZIP you uploaded (owner or admin only; 409 once withdrawn, 410 once past the retention time)."""
    caller = require_user(request, db)
    return zip_response(sessions, db, own_submission(db, caller.user, sid))


class MethodBody(BaseModel):
    description: str = Field("", max_length=4000)
    paper_url: str = Field("", max_length=1000)
    code_url: str = Field("", max_length=1000)
    runtime_ms: float | None = None
    extra_data: bool = False


@router.put("/api/submissions/{sid}/method", tags=["submissions"], response_model=MethodMetaOut)
def describe_method(sid: str, body: MethodBody, request: Request, db: Session = Depends(db_session)):
    """Describe the method behind one of your submissions (shown on the leaderboard): description, paper and
    code links (http/https), runtime per query in ms, and whether it uses data beyond the train split."""
    caller = require_writer(request, db)
    sub = own_submission(db, caller.user, sid)
    meta = parse_meta(body.description, body.paper_url, body.code_url, body.runtime_ms, body.extra_data)
    save_meta(db, sub.id, meta)
    db.commit()
    return meta_json(db.get(MethodInfo, sub.id))


@router.get(
    "/api/leaderboard/{split}.csv",
    tags=["leaderboard"],
    response_class=Response,
    responses={200: {"content": {"text/csv": {}}, "description": "the whole board"}},
)
def leaderboard_csv(
    split: str,
    settings: SettingsDep,
    sessions: SessionsDep,
    sort: str = Query("vcre_auc"),
    view: str = Query("all"),
    scene: str | None = Query(None),
    db: Session = Depends(db_session),
):
    """The whole leaderboard as a CSV file (same parameters as the JSON board, no paging), streamed."""
    check_split(settings, split)
    ranked = ranking(db, split, sort, view, scene)
    db.commit()
    fname = f"mapfree-{split}{'-' + scene if scene else ''}-{view}-{sort}.csv"
    return StreamingResponse(
        stream_csv(sessions, split, ranked, scene),  # a plain iterator: run in the thread pool
        media_type="text/csv; charset=utf-8",
        headers={"Content-Disposition": f'attachment; filename="{re.sub("[^A-Za-z0-9_.-]", "", fname)}"'},
    )


@router.get(
    "/api/leaderboard/{split}", tags=["leaderboard"], response_model=BoardOut, response_model_exclude_unset=True
)
def leaderboard(
    split: str,
    settings: SettingsDep,
    sort: str = Query("vcre_auc"),
    view: str = Query("all"),
    scene: str | None = Query(None),
    reference: bool = Query(True),
    page: int = Query(1, ge=1, description="page number, from 1"),
    per_page: int = Query(PER_PAGE, ge=1, le=MAX_PER_PAGE, description="rows per page"),
    db: Session = Depends(db_session),
):
    """Public results of a split, best first by ``sort`` (vcre_auc, vcre_prec, pose_auc, pose_prec, med_trans,
    med_rot, med_vcre, estimates); equal scores share a rank. ``view=best``: each account's best entry;
    ``scene``: one scene's scores (val only). Paged: ``page`` (from 1) of ``per_page`` rows (at most
    200); ``total`` and ``pages`` say how many there are. Published results on the real Map-free data come
    apart, under ``reference``."""
    check_split(settings, split)
    b = board(db, split, sort, view, scene, page, per_page)
    out = {
        "split": split,
        "sort": sort,
        "view": view,
        "scene": scene,
        "entries": b.entries,
        "page": b.page,
        "per_page": b.per_page,
        "total": b.total,
        "pages": b.pages,
    }
    if reference:
        out["reference"] = reference_rows()
    return out


@router.get("/api/compare", tags=["leaderboard"], response_model=CompareOut)
def compare_submissions(
    request: Request,
    a: str = Query(..., description="submission id"),
    b: str = Query(..., description="submission id"),
    db: Session = Depends(db_session),
):
    """Two submissions side by side: each metric, b − a, and which is better (per scene too, except test)."""
    return compare(visible_json(request, db, a), visible_json(request, db, b))
