"""JSON API: submissions, leaderboards, the relocalization anchors, health."""

from __future__ import annotations

import logging
import os
import socket
from typing import BinaryIO

from fastapi import APIRouter, Depends, File, Form, HTTPException, Request, UploadFile
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel
from sqlalchemy import select, text
from sqlalchemy.orm import Session

from . import jobs
from .db import READ_ONLY, Anchor, Submission, WorkerRow, new_id, now
from .deps import db_session, identify, require_writer
from .reloc import check_method, check_runnable, default_method, estimate_json, intrinsics_of
from .submissions import accept, daily_test_limit, to_json, visible
from .submissions import plot_png as render_plot
from .uploads import UploadError, check_name, decode_depth, decode_image, parse_intrinsics
from .worker import SEEN_SECONDS

log = logging.getLogger("mapfree.api")
router = APIRouter()


def read_upload(f: UploadFile | None, limit: int, what: str) -> bytes | None:
    """An uploaded file's bytes, refusing more than ``limit`` without reading it all. Endpoints that touch the
    database are plain ``def`` (run in the thread pool): a blocking database wait never stalls the event loop."""
    if f is None or (not f.filename and not f.size):
        return None
    data = f.file.read(limit + 1)
    if len(data) > limit:
        raise UploadError(413, f"{what}: larger than the limit of {limit} bytes")
    return data


def spooled_upload(f: UploadFile | None, what: str) -> BinaryIO:
    """The spooled file of an upload (on disk past 1 MB), never read whole: the body limit bounds its size."""
    if f is None or (not f.filename and not f.size):
        raise UploadError(400, f"{what}: no file uploaded")
    return f.file


# ----------------------------------------------------------------------------------------------- health


def _alive(w: WorkerRow) -> bool:
    """A worker on this host is alive only if its process is (a SIGKILLed one leaves its row behind)."""
    if w.host != socket.gethostname()[:128]:
        return True
    try:
        os.kill(w.pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@router.get("/health", tags=["operations"])
def health(request: Request):
    """Liveness and readiness: database reachable, queue length, live workers. ``degraded`` when no worker is
    alive (submissions would wait forever); workers count as alive while they report every few seconds."""
    engine = request.app.state.engine
    try:
        with engine.connect().execution_options(**{READ_ONLY: True}) as conn, Session(conn) as rdb:
            rdb.execute(text("SELECT 1"))
            counts = jobs.counts(rdb)
            rows = rdb.scalars(select(WorkerRow).where(WorkerRow.last_seen > now() - 3 * SEEN_SECONDS)).all()
            workers = [{"id": w.id, "pid": w.pid, "host": w.host, "jobs_done": w.jobs_done} for w in rows if _alive(w)]
            rdb.rollback()
    except Exception as e:
        log.warning("health check failed", extra={"error": type(e).__name__})
        return JSONResponse({"status": "error", "db": "unreachable"}, status_code=503)
    return {"status": "ok" if workers else "degraded", "db": engine.dialect.name, "jobs": counts, "workers": workers}


# ------------------------------------------------------------------------------------------ submissions


@router.get("/api/me", tags=["accounts"])
def me(request: Request, db: Session = Depends(db_session)):
    caller = identify(request, db)
    if caller.user is None:
        raise HTTPException(401, "authentication required", headers={"WWW-Authenticate": "Bearer"})
    u = caller.user
    used = db.scalars(select(Submission.created_at).where(
        Submission.user_id == u.id, Submission.split == "test", Submission.created_at > now() - 86400)).all()
    limit = daily_test_limit(request.app.state.settings, u)
    return {"name": u.name, "admin": u.is_admin, "test_evaluations_left_today": max(0, limit - len(used)),
            "test_daily_limit": limit}


@router.post("/api/submissions", status_code=202, tags=["submissions"])
def create_submission(request: Request, file: UploadFile = File(..., description="submission ZIP"),
                            split: str = Form(..., description="val or test"), name: str = Form(""),
                            public: bool = Form(False), csrf_token: str | None = Form(None),
                            db: Session = Depends(db_session)):
    """Upload a submission ZIP. It is stored and queued before this answers 202; poll ``api_url``."""
    caller = require_writer(request, db, csrf_token)
    settings = request.app.state.settings
    sub = accept(db, settings, caller.user, split, name, public, spooled_upload(file, "submission"))
    log.info("submission queued", extra={"submission": sub.id, "split": split, "user_id": caller.user.id})
    return to_json(db, sub, caller.user.name)


@router.get("/api/submissions", tags=["submissions"])
def my_submissions(request: Request, db: Session = Depends(db_session)):
    """The caller's own submissions (private history), newest first."""
    caller = identify(request, db)
    if caller.user is None:
        raise HTTPException(401, "authentication required", headers={"WWW-Authenticate": "Bearer"})
    subs = db.scalars(select(Submission).where(Submission.user_id == caller.user.id)
                      .order_by(Submission.created_at.desc()).limit(500)).all()
    return [to_json(db, s, caller.user.name) for s in subs]


def _visible_submission(request: Request, db: Session, sid: str) -> Submission:
    sub = db.get(Submission, sid) if len(sid) <= 32 else None
    if not visible(sub, identify(request, db).user):
        raise HTTPException(404, "no such submission (or it is private)")
    return sub


@router.get("/api/submissions/{sid}", tags=["submissions"])
def get_submission(sid: str, request: Request, db: Session = Depends(db_session)):
    return to_json(db, _visible_submission(request, db, sid))


class Visibility(BaseModel):
    public: bool


@router.patch("/api/submissions/{sid}", tags=["submissions"])
def set_visibility(sid: str, body: Visibility, request: Request, db: Session = Depends(db_session)):
    """Make one of your submissions public or private."""
    caller = require_writer(request, db)
    sub = db.get(Submission, sid) if len(sid) <= 32 else None
    if sub is None or sub.user_id != caller.user.id:
        raise HTTPException(404, "no such submission of yours")
    sub.public = body.public
    db.commit()
    return to_json(db, sub, caller.user.name)


@router.get("/submissions/{sid}/plots/{name}.png", tags=["submissions"], response_class=Response)
def plot_png(sid: str, name: str, request: Request, db: Session = Depends(db_session)):
    sub = _visible_submission(request, db, sid)
    png = render_plot(db, sub, name)
    if png is None:
        raise HTTPException(404, "no such plot")
    return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=3600"})


# --------------------------------------------------------------------------------------------- anchors


def _anchor_json(a: Anchor) -> dict:
    return {"id": a.id, "name": a.name, "method": a.method, "intrinsics": a.intrinsics,
            "has_depth": a.depth is not None, "created_at": a.created_at, "url": f"/anchors/{a.id}"}


def _intr(fx, fy, cx, cy, img, what) -> dict:
    return parse_intrinsics({"fx": fx, "fy": fy, "cx": cx, "cy": cy}, img.shape[1], img.shape[0], what)


@router.post("/anchors", status_code=201, tags=["relocalization"])
def create_anchor(request: Request, image: UploadFile = File(..., description="reference photo (JPEG/PNG)"),
                        fx: float = Form(...), fy: float = Form(...), cx: float = Form(...), cy: float = Form(...),
                        depth: UploadFile | None = File(None, description="optional uint16 PNG depth, millimetres"),
                        method: str = Form(""), name: str = Form(""), csrf_token: str | None = Form(None),
                        db: Session = Depends(db_session)):
    """Register a reference photo (user A) that anyone signed in can localize against."""
    caller = require_writer(request, db, csrf_token)
    settings = request.app.state.settings
    lim = settings.limits
    img_bytes = read_upload(image, lim.max_image_bytes, "image")
    if img_bytes is None:
        raise UploadError(400, "image: no file uploaded")
    img = decode_image(img_bytes, lim, "image")
    intr = _intr(fx, fy, cx, cy, img, "intrinsics")
    depth_bytes = read_upload(depth, lim.max_image_bytes, "depth")
    ref_depth = decode_depth(depth_bytes, lim, img.shape[:2]) if depth_bytes is not None else None
    name = check_name(name, lim.max_name_chars)
    m = check_method(method) if method.strip() else default_method(settings.default_method)
    check_runnable(m, ref_depth is not None)
    aid = new_id()
    request.app.state.localizers.check(aid, m, img, intrinsics_of(intr), ref_depth)  # 422 if it cannot run here
    a = Anchor(id=aid, user_id=caller.user.id, name=name, method=m, intrinsics=intr, image=img_bytes,
               depth=depth_bytes, created_at=now())
    db.add(a)
    db.commit()
    return _anchor_json(a)


def _anchor(db: Session, aid: str) -> Anchor:
    a = db.get(Anchor, aid) if len(aid) <= 32 else None
    if a is None:
        raise HTTPException(404, "no such anchor")
    return a


@router.get("/anchors/{aid}", tags=["relocalization"])
def get_anchor(aid: str, request: Request, db: Session = Depends(db_session)):
    caller = identify(request, db)
    if caller.user is None:
        raise HTTPException(401, "authentication required", headers={"WWW-Authenticate": "Bearer"})
    return _anchor_json(_anchor(db, aid))


@router.delete("/anchors/{aid}", status_code=204, tags=["relocalization"], response_class=Response)
def delete_anchor(aid: str, request: Request, db: Session = Depends(db_session)):
    caller = require_writer(request, db)
    a = _anchor(db, aid)
    if a.user_id != caller.user.id and not caller.user.is_admin:
        raise HTTPException(403, "only the anchor's owner can delete it")
    db.delete(a)
    db.commit()
    request.app.state.localizers.forget(aid)
    return Response(status_code=204)


@router.post("/anchors/{aid}/localize", tags=["relocalization"])
def localize(aid: str, request: Request, image: UploadFile = File(..., description="query photo (JPEG/PNG)"),
             fx: float = Form(...), fy: float = Form(...), cx: float = Form(...), cy: float = Form(...),
             depth: UploadFile | None = File(None), csrf_token: str | None = Form(None),
             db: Session = Depends(db_session)):
    """Metric pose of the query camera relative to the anchor's camera (``X_query = R X_ref + t``), with
    confidence and timings. ``ok: false`` with a ``reason`` when the method finds no pose."""
    require_writer(request, db, csrf_token)
    a = _anchor(db, aid)
    db.commit()  # release the read transaction before the long computation
    lim = request.app.state.settings.limits
    q_bytes = image.file.read(lim.max_image_bytes + 1)
    if len(q_bytes) > lim.max_image_bytes:
        raise UploadError(413, f"image: larger than the limit of {lim.max_image_bytes} bytes")
    q_img = decode_image(q_bytes, lim, "image")
    q_K = intrinsics_of(_intr(fx, fy, cx, cy, q_img, "intrinsics"))
    q_depth = None
    if depth is not None and depth.filename:
        q_depth = decode_depth(depth.file.read(lim.max_image_bytes + 1), lim, q_img.shape[:2])
    ref_img = decode_image(a.image, lim, "anchor image")
    ref_depth = decode_depth(a.depth, lim, ref_img.shape[:2], "anchor depth") if a.depth is not None else None
    est = request.app.state.localizers.localize(a.id, a.method, ref_img, intrinsics_of(a.intrinsics), ref_depth,
                                                q_img, q_K, q_depth)
    out = estimate_json(est, a.method)
    out["anchor"] = a.id
    return out
