"""JSON routes of submissions: upload, list, read, make public or private, figures."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Depends, File, Form, HTTPException, Request, UploadFile
from fastapi.responses import Response
from pydantic import BaseModel
from sqlalchemy import select
from sqlalchemy.orm import Session

from ..database.models import MethodInfo, Submission
from ..http.caller import db_session, identify, require_user, require_writer
from ..inputs import spooled_upload
from ..schemas import SubmissionOut
from .boards import meta_json, parse_meta, save_meta
from .own import own_submission
from .submissions import accept, to_json, visible_submission
from .submissions import plot_png as render_plot

router = APIRouter(tags=["submissions"])

log = logging.getLogger("mapfree.leaderboard")


@router.post("/api/submissions", status_code=202, response_model=SubmissionOut,
             response_model_exclude_unset=True)
def create_submission(request: Request, file: UploadFile = File(..., description="submission ZIP"),
                            split: str = Form(..., description="val or test"), name: str = Form(""),
                            public: bool = Form(False), csrf_token: str | None = Form(None),
                            description: str = Form("", description="the method, shown on the leaderboard"),
                            paper_url: str = Form("", description="http(s) link to the paper"),
                            code_url: str = Form("", description="http(s) link to the code"),
                            runtime_ms: str = Form("", description="runtime per query in ms"),
                            extra_data: bool = Form(False, description="trained or tuned on data beyond the train "
                                                                       "split"),
                            db: Session = Depends(db_session)):
    """Upload a submission ZIP, optionally with its method's metadata (as ``PUT …/method``; a bad field is a
    422 naming it, before anything is stored). It is stored and queued before this answers 202; poll
    ``api_url``."""
    caller = require_writer(request, db, csrf_token)
    settings = request.app.state.settings
    meta = parse_meta(description, paper_url, code_url, runtime_ms, extra_data)
    sub = accept(db, settings, caller.user, split, name, public, spooled_upload(file, "submission"))
    if not meta.empty():
        save_meta(db, sub.id, meta)
        db.commit()
    log.info("submission queued", extra={"submission": sub.id, "split": split, "user_id": caller.user.id})
    return {**to_json(db, sub, caller.user.name), "method": meta_json(db.get(MethodInfo, sub.id))}


@router.get("/api/submissions", response_model=list[SubmissionOut],
            response_model_exclude_unset=True)
def my_submissions(request: Request, db: Session = Depends(db_session)):
    """The caller's own submissions (private history), newest first."""
    caller = require_user(request, db)
    subs = db.scalars(select(Submission).where(Submission.user_id == caller.user.id)
                      .order_by(Submission.created_at.desc()).limit(500)).all()
    return [to_json(db, s, caller.user.name) for s in subs]


def _visible_submission(request: Request, db: Session, sid: str) -> Submission:
    return visible_submission(db, identify(request, db).user, sid)


@router.get("/api/submissions/{sid}", response_model=SubmissionOut,
            response_model_exclude_unset=True)
def get_submission(sid: str, request: Request, db: Session = Depends(db_session)):
    """A submission you may see. Once withdrawn, its owner (and admins) still get it, as their list shows it:
    status ``withdrawn``, ``withdrawn_at``, no results; everyone else gets 404."""
    return to_json(db, visible_submission(db, identify(request, db).user, sid, withdrawn=True))


class Visibility(BaseModel):
    public: bool


@router.patch("/api/submissions/{sid}", response_model=SubmissionOut,
              response_model_exclude_unset=True)
def set_visibility(sid: str, body: Visibility, request: Request, db: Session = Depends(db_session)):
    """Make one of your submissions public or private (409 once it is withdrawn: it stays hidden for good)."""
    caller = require_writer(request, db)
    sub = own_submission(db, caller.user, sid)
    sub.public = body.public
    db.commit()
    return to_json(db, sub)


@router.get("/submissions/{sid}/plots/{name}.png", tags=["submissions"], response_class=Response,
            responses={200: {"content": {"image/png": {}}, "description": "the figure"}})
def plot_png(sid: str, name: str, request: Request, db: Session = Depends(db_session)):
    sub = _visible_submission(request, db, sid)
    png = render_plot(db, sub, name)
    if png is None:
        raise HTTPException(404, "no such plot")
    return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=3600"})
