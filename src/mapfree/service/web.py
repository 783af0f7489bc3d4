"""Web pages (server-rendered, Jinja2): sign-in, upload, submission pages, leaderboards, history, and a page to
try relocalization. Every form carries a CSRF token; the session cookie is HttpOnly and SameSite=Lax."""

from __future__ import annotations

import base64
import secrets
from pathlib import Path

from fastapi import APIRouter, Depends, File, Form, HTTPException, Query, Request, UploadFile
from fastapi.responses import HTMLResponse, RedirectResponse
from fastapi.templating import Jinja2Templates
from sqlalchemy import select
from sqlalchemy.orm import Session

from . import auth
from .api import read_upload
from .db import Submission, User
from .deps import LOGIN_CSRF_COOKIE, SESSION_COOKIE, db_session, identify, require_writer
from .evaluation import LOWER_IS_BETTER, SHORT
from .reloc import check_method, default_method, estimate_json, figure_png, intrinsics_of
from .submissions import accept, leaderboard, to_json, visible
from .uploads import UploadError, decode_depth, decode_image, parse_intrinsics

router = APIRouter(include_in_schema=False)
templates = Jinja2Templates(directory=str(Path(__file__).parent / "templates"))
LABELS = {"vcre_auc": "VCRE AUC", "vcre_prec": "VCRE prec.", "pose_auc": "Pose AUC", "pose_prec": "Pose prec.",
          "med_trans": "Med. trans. (m)", "med_rot": "Med. rot. (°)", "med_vcre": "Med. VCRE (px)",
          "estimates": "Estimates (frac.)"}


def _fmt_time(t):
    import time

    return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(t)) if t else ""


def _fmt_num(v):
    if v is None:
        return "–"
    return f"{v:.3f}" if isinstance(v, float) else str(v)


templates.env.filters["time"] = _fmt_time
templates.env.filters["num"] = _fmt_num


def page(request: Request, name: str, db: Session, status: int = 200, **ctx) -> HTMLResponse:
    caller = identify(request, db)
    return templates.TemplateResponse(request, name, {"user": caller.user, "csrf": caller.csrf,
                                                      "splits": request.app.state.settings.splits, **ctx},
                                      status_code=status)


@router.get("/", response_class=HTMLResponse)
def home(request: Request, db: Session = Depends(db_session)):
    return page(request, "index.html", db)


@router.get("/login", response_class=HTMLResponse)
def login_form(request: Request, db: Session = Depends(db_session)):
    token = secrets.token_urlsafe(24)  # double-submit: no session exists yet
    resp = page(request, "login.html", db, login_csrf=token)
    resp.set_cookie(LOGIN_CSRF_COOKIE, token, httponly=True, samesite="strict",
                    secure=request.app.state.settings.secure_cookies, max_age=3600)
    return resp


@router.post("/login")
def login(request: Request, token: str = Form(...), csrf_token: str = Form(""), db: Session = Depends(db_session)):
    if not auth.same_secret(csrf_token, request.cookies.get(LOGIN_CSRF_COOKIE)):
        raise HTTPException(403, "CSRF check failed: reload the sign-in page and try again")
    user = auth.user_for_token(db, token.strip())
    if user is None:
        raise HTTPException(401, "invalid or revoked API token")
    settings = request.app.state.settings
    sid, _ = auth.open_session(db, user, settings.session_hours)
    db.commit()
    resp = RedirectResponse("/me", status_code=303)
    resp.set_cookie(SESSION_COOKIE, sid, httponly=True, samesite="lax", secure=settings.secure_cookies,
                    max_age=int(settings.session_hours * 3600))
    resp.delete_cookie(LOGIN_CSRF_COOKIE)
    return resp


@router.post("/logout")
def logout(request: Request, csrf_token: str = Form(""), db: Session = Depends(db_session)):
    require_writer(request, db, csrf_token)
    auth.close_session(db, request.cookies.get(SESSION_COOKIE))
    db.commit()
    resp = RedirectResponse("/", status_code=303)
    resp.delete_cookie(SESSION_COOKIE)
    return resp


def _signed_in(request: Request, db: Session) -> User:
    user = identify(request, db).user
    if user is None:
        raise HTTPException(401, "sign in first (/login)")
    return user


@router.get("/me", response_class=HTMLResponse)
def history(request: Request, db: Session = Depends(db_session)):
    user = _signed_in(request, db)
    subs = db.scalars(select(Submission).where(Submission.user_id == user.id)
                      .order_by(Submission.created_at.desc()).limit(500)).all()
    return page(request, "history.html", db, subs=[to_json(db, s, user.name) for s in subs], labels=LABELS)


@router.get("/submit", response_class=HTMLResponse)
def submit_form(request: Request, db: Session = Depends(db_session)):
    _signed_in(request, db)
    return page(request, "submit.html", db)


@router.post("/submit")
def submit(request: Request, file: UploadFile = File(...), split: str = Form(...), name: str = Form(""),
                 public: bool = Form(False), csrf_token: str = Form(""), db: Session = Depends(db_session)):
    caller = require_writer(request, db, csrf_token)
    settings = request.app.state.settings
    data = read_upload(file, settings.limits.max_submission_bytes, "submission")
    if data is None:
        raise UploadError(400, "submission: no file chosen")
    sub = accept(db, settings, caller.user, split, name, public, data)
    return RedirectResponse(f"/submissions/{sub.id}", status_code=303)


@router.get("/submissions/{sid}", response_class=HTMLResponse)
def submission_page(sid: str, request: Request, db: Session = Depends(db_session)):
    user = identify(request, db).user
    sub = db.get(Submission, sid) if len(sid) <= 32 else None
    if not visible(sub, user):
        raise HTTPException(404, "no such submission (or it is private)")
    return page(request, "submission.html", db, sub=to_json(db, sub), labels=LABELS, short=SHORT,
                owner=user is not None and user.id == sub.user_id)


@router.post("/submissions/{sid}/visibility")
def visibility(sid: str, request: Request, public: bool = Form(False), csrf_token: str = Form(""),
               db: Session = Depends(db_session)):
    caller = require_writer(request, db, csrf_token)
    sub = db.get(Submission, sid) if len(sid) <= 32 else None
    if sub is None or sub.user_id != caller.user.id:
        raise HTTPException(404, "no such submission of yours")
    sub.public = public
    db.commit()
    return RedirectResponse(f"/submissions/{sid}", status_code=303)


@router.get("/leaderboard", response_class=HTMLResponse)
def leaderboard_default(request: Request):
    return RedirectResponse("/leaderboard/val", status_code=307)


@router.get("/leaderboard/{split}", response_class=HTMLResponse)
def leaderboard_page(split: str, request: Request, sort: str = Query("vcre_auc"),
                     db: Session = Depends(db_session)):
    if split not in request.app.state.settings.splits:
        raise HTTPException(404, f"no leaderboard for split {split!r}")
    entries = leaderboard(db, split, sort)
    return page(request, "leaderboard.html", db, split=split, sort=sort, entries=entries, labels=LABELS,
                lower=LOWER_IS_BETTER)


@router.get("/relocalize", response_class=HTMLResponse)
def relocalize_form(request: Request, db: Session = Depends(db_session)):
    return page(request, "relocalize.html", db, method=default_method(request.app.state.settings.default_method))


def _guess_intrinsics(fields: dict, img, what: str) -> dict:
    """Intrinsics from the form, or a guess (focal 0.8 x longest side, centred) when left empty."""
    h, w = img.shape[:2]
    if all(str(fields.get(k, "")).strip() == "" for k in ("fx", "fy", "cx", "cy")):
        f = 0.8 * max(w, h)
        fields = {"fx": f, "fy": f, "cx": (w - 1) / 2, "cy": (h - 1) / 2}
    return parse_intrinsics(fields, w, h, what)


@router.post("/relocalize", response_class=HTMLResponse)
def relocalize_try(request: Request, reference: UploadFile = File(...), query: UploadFile = File(...),
                   reference_depth: UploadFile | None = File(None), method: str = Form(""),
                   ref_fx: str = Form(""), ref_fy: str = Form(""), ref_cx: str = Form(""), ref_cy: str = Form(""),
                   q_fx: str = Form(""), q_fy: str = Form(""), q_cx: str = Form(""), q_cy: str = Form(""),
                   csrf_token: str = Form(""), db: Session = Depends(db_session)):
    """Two photos in, the matches and the virtual grid at the estimated pose out (nothing is stored)."""
    require_writer(request, db, csrf_token)
    lim = request.app.state.settings.limits
    ref_img = decode_image(reference.file.read(lim.max_image_bytes + 1), lim, "reference photo")
    q_img = decode_image(query.file.read(lim.max_image_bytes + 1), lim, "query photo")
    ref_K = intrinsics_of(_guess_intrinsics({"fx": ref_fx, "fy": ref_fy, "cx": ref_cx, "cy": ref_cy}, ref_img,
                                            "reference intrinsics"))
    q_K = intrinsics_of(_guess_intrinsics({"fx": q_fx, "fy": q_fy, "cx": q_cx, "cy": q_cy}, q_img,
                                          "query intrinsics"))
    ref_depth = None
    if reference_depth is not None and reference_depth.filename:
        ref_depth = decode_depth(reference_depth.file.read(lim.max_image_bytes + 1), lim, ref_img.shape[:2],
                                 "reference depth")
    m = check_method(method) if method.strip() else default_method(request.app.state.settings.default_method)
    key = "try-" + secrets.token_hex(8)
    loc = request.app.state.localizers
    est = loc.localize(key, m, ref_img, ref_K, ref_depth, q_img, q_K)
    loc.forget(key)
    png = figure_png(ref_img, q_img, ref_K, q_K, est, title=m)
    result = estimate_json(est, m)
    return page(request, "relocalize.html", db, method=m, result=result,
                figure="data:image/png;base64," + base64.b64encode(png).decode())
