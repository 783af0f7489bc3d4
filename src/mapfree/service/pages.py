"""Web pages (server-rendered, Jinja2): sign-in, upload, submission pages, leaderboards, comparisons, history,
and a page to try relocalization. Every form carries a CSRF token; the session cookie is HttpOnly and
SameSite=Lax. A form that fails comes back as the same form with its values and the error above it (and with
JavaScript the page is not replaced at all, so chosen files stay chosen)."""

from __future__ import annotations

import base64
import secrets
import shlex
from dataclasses import replace
from pathlib import Path
from urllib.parse import urlencode

from fastapi import APIRouter, Depends, File, Form, HTTPException, Query, Request, UploadFile
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from .accounts import tokens as auth
from .accounts.caller import (
    LOGIN_CSRF_COOKIE,
    SESSION_COOKIE,
    RowId,
    db_session,
    identify,
    require_user,
    require_writer,
)
from .accounts.quota import test_quota
from .accounts.router import current_token_hash, list_sessions, list_tokens, session_json, token_json
from .anchors.domain import (
    add_photo,
    anchor_json,
    check_photo_count,
    find_anchor,
    localize_anchor,
    make_anchor,
    may_see_photos,
    photo_name,
    photo_rows,
    photo_upload,
    remove_photo,
    stored_photo,
)
from .anchors.localizers import check_method, default_method, estimate_json, figure_png, needs_reference_depth
from .anchors.photos import Photo, Upload
from .anchors.photos import read_upload as read_photo_upload
from .database.models import Anchor, AnchorPhoto, MethodInfo, Submission, User
from .http.heavy import heavy
from .http.render import error_page, page
from .inputs import UploadError, spooled_upload
from .leaderboard.boards import (
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
from .leaderboard.own import Withdrawn, own_submission, withdraw, zip_response
from .leaderboard.scoring import LOWER_IS_BETTER, SHORT, known_scenes
from .leaderboard.submissions import accept, to_json, visible_submission

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
#: Offered on the relocalization page; the note says what each needs.
RELOC_CHOICES = {
    "best-offline": "XFeat + 3D-3D; needs the reference depth (the query's too, else PnP runs)",
    "best-offline-pnp": "XFeat + PnP; needs the reference depth",
    "sift_pnp_sensor": "SIFT + PnP; needs the reference depth",
    "sift_emat_none": "SIFT + essential matrix; no depth, so direction only: no metric scale",
}


def _problem(exc: UploadError | HTTPException) -> tuple[int, str]:
    if isinstance(exc, UploadError):
        return exc.status, exc.message
    return exc.status_code, str(exc.detail)


@router.get("/", response_class=HTMLResponse)
def home(request: Request, db: Session = Depends(db_session)):
    return page(request, "index.html", db)


@router.get("/login", response_class=HTMLResponse)
def login_form(request: Request, db: Session = Depends(db_session)):
    return _login_page(request, db)


def _login_page(request: Request, db: Session, status: int = 200, error: str = "") -> HTMLResponse:
    token = secrets.token_urlsafe(24)  # double-submit: no session exists yet
    resp = page(request, "login.html", db, status, login_csrf=token, error=error)
    resp.set_cookie(
        LOGIN_CSRF_COOKIE,
        token,
        httponly=True,
        samesite="strict",
        secure=request.app.state.settings.secure_cookies,
        max_age=3600,
    )
    return resp


@router.post("/login")
def login(request: Request, token: str = Form(...), csrf_token: str = Form(""), db: Session = Depends(db_session)):
    if not auth.same_secret(csrf_token, request.cookies.get(LOGIN_CSRF_COOKIE)):
        raise HTTPException(403, "CSRF check failed: reload the sign-in page and try again")
    row, _ = auth.find_token(db, token.strip())
    if row is None:  # the sign-in form again, with the error above it
        try:
            request.app.state.auth_throttle.refuse(request)
        except HTTPException as e:
            resp = _login_page(request, db, e.status_code, str(e.detail))
            resp.headers.update(e.headers or {})
            return resp
        return _login_page(request, db, 401, "invalid or revoked API token")
    settings = request.app.state.settings
    sid, _ = auth.open_session(db, row, settings.session_hours)  # ends with the token, at the latest
    db.commit()
    signed_in = RedirectResponse("/me", status_code=303)
    signed_in.set_cookie(
        SESSION_COOKIE,
        sid,
        httponly=True,
        samesite="lax",
        secure=settings.secure_cookies,
        max_age=int(settings.session_hours * 3600),
    )
    signed_in.delete_cookie(LOGIN_CSRF_COOKIE)
    return signed_in


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
    return _history(request, db, _signed_in(request, db))


def _history(request: Request, db: Session, user: User, status: int = 200, error: str = "") -> HTMLResponse:
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
        quota=test_quota(db, request.app.state.settings, user),
        error=error,
    )


def withdrawn_page(request: Request, exc: Withdrawn) -> HTMLResponse:
    """A form that changes a withdrawn submission (say, from a page opened before withdrawing it): the owner's
    history, where it is listed as withdrawn, with the reason above it (409)."""
    with request.app.state.sessions() as db:
        user = identify(request, db).user
        if user is None:
            return error_page(request, exc.status_code, str(exc.detail))
        return _history(request, db, user, exc.status_code, str(exc.detail))


@router.get("/me/access", response_class=HTMLResponse)
def access_page(request: Request, db: Session = Depends(db_session)):
    """Your tokens and browser sessions, each with a button that revokes it."""
    caller = require_user(request, db)
    sid = request.cookies.get(SESSION_COOKIE)
    current = auth.hash_secret(sid) if sid else ""
    return page(
        request,
        "access.html",
        db,
        tokens=[token_json(t, current_token_hash(request)) for t in list_tokens(db, caller.user.id)],
        sessions=[session_json(s, current) for s in list_sessions(db, caller.user.id)],
    )


# ------------------------------------------------------------------------------------------- submissions


def _submit_page(
    request: Request, db: Session, user: User, status: int = 200, error: str = "", form: dict | None = None
) -> HTMLResponse:
    return page(
        request,
        "submit.html",
        db,
        status,
        error=error,
        form=form or {},
        quota=test_quota(db, request.app.state.settings, user),
    )


@router.get("/submit", response_class=HTMLResponse)
def submit_form(request: Request, db: Session = Depends(db_session)):
    return _submit_page(request, db, _signed_in(request, db))


@router.post("/submit")
def submit(
    request: Request,
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
    settings = request.app.state.settings
    try:
        meta = parse_meta(description, paper_url, code_url, runtime_ms, extra_data)
        sub = accept(db, settings, caller.user, split, name, public, spooled_upload(file, "submission"))
    except (UploadError, HTTPException) as e:
        db.rollback()
        status, message = _problem(e)
        return _submit_page(request, db, caller.user, status, message, form)
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
def download(sid: str, request: Request, db: Session = Depends(db_session)) -> Response:
    return zip_response(request, db, own_submission(db, _signed_in(request, db), sid))


# ------------------------------------------------------------------------------------------ leaderboards


@router.get("/leaderboard", response_class=HTMLResponse)
def leaderboard_default(request: Request):
    return RedirectResponse("/leaderboard/val", status_code=307)


@router.get("/leaderboard/{split}", response_class=HTMLResponse)
def leaderboard_page(
    split: str,
    request: Request,
    sort: str = Query("vcre_auc"),
    view: str = Query("all"),
    scene: str = Query(""),
    page_no: int = Query(1, ge=1, alias="page"),
    per_page: int = Query(PER_PAGE, ge=1, le=MAX_PER_PAGE),
    db: Session = Depends(db_session),
):
    check_split(request, split)
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
        scenes=[] if split == "test" else sorted(known_scenes(request.app.state.settings, split) or ()),
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


# ---------------------------------------------------------------------------------------- relocalization


def _anchor_choices(request: Request, db: Session) -> list[dict]:
    """The newest anchors (anyone signed in may localize against any), with their photo counts and whether the
    caller owns them, no blobs."""
    user = identify(request, db).user
    if user is None:
        return []
    rows = db.execute(
        select(Anchor.id, Anchor.name, Anchor.method, Anchor.user_id, func.count(AnchorPhoto.seq))
        .outerjoin(AnchorPhoto, AnchorPhoto.anchor_id == Anchor.id)
        .group_by(Anchor.id, Anchor.name, Anchor.method, Anchor.user_id, Anchor.created_at)
        .order_by(Anchor.created_at.desc())
        .limit(50)
    ).all()
    return [
        {"id": r[0], "name": r[1] or r[0][:8], "method": r[2], "photos": 1 + r[4], "mine": r[3] == user.id}
        for r in rows
    ]


def _reloc_page(request: Request, db: Session, status: int = 200, **ctx) -> HTMLResponse:
    ctx.setdefault("form", {})
    ctx.setdefault("method", default_method(request.app.state.settings.default_method))
    return page(
        request,
        "relocalize.html",
        db,
        status,
        choices=RELOC_CHOICES,
        anchors=_anchor_choices(request, db),
        max_photos=request.app.state.settings.limits.max_anchor_photos,
        **ctx,
    )


@router.get("/relocalize", response_class=HTMLResponse)
def relocalize_form(request: Request, db: Session = Depends(db_session)):
    return _reloc_page(request, db)


def _form_fields(form: dict, prefix: str) -> dict:
    """The form's ``{prefix}fx`` ... fields as ``fx`` ...."""
    return {k[len(prefix) :]: v for k, v in form.items() if k.startswith(prefix)}


def _query_photo(query: UploadFile, lim, form: dict) -> Photo:
    """The page's query photo with its ``q_*`` intrinsics (EXIF or the default camera when left empty), at the
    working size."""
    return read_photo_upload(
        query.file.read(lim.max_image_bytes + 1),
        lim,
        _form_fields(form, "q_"),
        what="query photo",
        intr_what="query intrinsics",
    ).photo


@router.post("/relocalize", response_class=HTMLResponse)
@heavy
def relocalize_try(
    request: Request,
    reference: UploadFile = File(...),
    query: UploadFile = File(...),
    reference_depth: UploadFile | None = File(None),
    method: str = Form(""),
    ref_fx: str = Form(""),
    ref_fy: str = Form(""),
    ref_cx: str = Form(""),
    ref_cy: str = Form(""),
    q_fx: str = Form(""),
    q_fy: str = Form(""),
    q_cx: str = Form(""),
    q_cy: str = Form(""),
    csrf_token: str = Form(""),
    db: Session = Depends(db_session),
):
    """Two photos in, the matches and the virtual grid at the estimated pose out (nothing is stored). A method
    that needs the reference depth is refused without one, before anything runs."""
    caller = require_writer(request, db, csrf_token)
    form = {
        "ref_fx": ref_fx,
        "ref_fy": ref_fy,
        "ref_cx": ref_cx,
        "ref_cy": ref_cy,
        "q_fx": q_fx,
        "q_fy": q_fy,
        "q_cx": q_cx,
        "q_cy": q_cy,
    }
    lim = request.app.state.settings.limits
    m = method.strip() or default_method(request.app.state.settings.default_method)
    try:
        m = check_method(m)
        ref_depth = (
            reference_depth.file.read(lim.max_image_bytes + 1)
            if reference_depth is not None and reference_depth.filename
            else None
        )
        ref = read_photo_upload(
            reference.file.read(lim.max_image_bytes + 1),
            lim,
            _form_fields(form, "ref_"),
            ref_depth,
            what="reference photo",
            intr_what="reference intrinsics",
            depth_what="reference depth",
        ).photo  # at the size the matches are in
        q = _query_photo(query, lim, form)
        if ref_depth is None and needs_reference_depth(m, scale_free_too=False):
            raise UploadError(
                422,
                f"method {m} needs the reference depth map (a uint16 PNG in millimetres, the "
                "size of the reference photo) for a metric pose; choose one, or a method "
                "without depth such as sift_emat_none (direction only, no metric scale)",
            )
    except UploadError as e:
        return _reloc_page(request, db, e.status, method=m, form=form, error=e.message)
    key = "try-" + secrets.token_hex(8)
    loc = request.app.state.localizers
    est = loc.localize(key, m, ref.image, ref.intrinsics, ref.depth, q.image, q.intrinsics, owner=caller.user.id)
    loc.forget(key)
    png = figure_png(ref.image, q.image, ref.intrinsics, q.intrinsics, est, title=m)
    return _reloc_page(
        request,
        db,
        method=m,
        form=form,
        result=estimate_json(est, m),
        figure="data:image/png;base64," + base64.b64encode(png).decode(),
    )


@router.post("/relocalize/anchor", response_class=HTMLResponse)
@heavy
def relocalize_anchor(
    request: Request,
    anchor: str = Form(...),
    query: UploadFile = File(...),
    q_fx: str = Form(""),
    q_fy: str = Form(""),
    q_cx: str = Form(""),
    q_cy: str = Form(""),
    csrf_token: str = Form(""),
    db: Session = Depends(db_session),
):
    """A query photo against a stored anchor (one or several photos): the pose in the anchor's frame, which
    photo answered, and the figure drawn against that photo."""
    caller = require_writer(request, db, csrf_token)
    form = {"q_fx": q_fx, "q_fy": q_fy, "q_cx": q_cx, "q_cy": q_cy, "anchor": anchor}
    a = find_anchor(db, anchor)
    rows = photo_rows(db, a.id)
    db.commit()  # release the read transaction before the long computation
    lim = request.app.state.settings.limits
    try:
        q = _query_photo(query, lim, form)  # at the size the matches are in
    except UploadError as e:
        return _reloc_page(request, db, e.status, method=a.method, form=form, error=e.message)
    est = localize_anchor(request, a, rows, q, owner=caller.user.id)
    result = estimate_json(est, a.method)
    if not may_see_photos(a, caller.user):  # the figure would show the anchor's photo
        return _reloc_page(request, db, method=a.method, form=form, result=result, anchor_name=a.name or a.id[:8])
    photo = stored_photo(a, rows, result.get("photo") or 0, lim)  # only the one drawn, not every photo again
    shown = replace(est, pose=est.pose @ photo.pose.inverse()) if est.pose is not None else est  # vs that photo
    png = figure_png(
        photo.image, q.image, photo.intrinsics, q.intrinsics, shown, title=f"{a.method}, photo {result.get('photo', 0)}"
    )
    return _reloc_page(
        request,
        db,
        method=a.method,
        form=form,
        result=result,
        anchor_name=a.name or a.id[:8],
        figure="data:image/png;base64," + base64.b64encode(png).decode(),
    )


# ------------------------------------------------------------------------------------ anchors from the page


#: One line of the "cameras" box: (line number, file name, fx fy cx cy, pose or None).
CameraLine = tuple[int, str, tuple[str, str, str, str], str | None]


def _camera_lines(text: str) -> list[CameraLine]:
    """The page's "cameras" box: one line per photo, in the anchor's order, ``NAME fx fy cx cy`` and, for every
    photo but the first, its pose ``qw qx qy qz tx ty tz`` -> (line number, file name, intrinsics, pose). A
    name with spaces is quoted; blank lines and ``#`` comments are skipped. Values are checked per photo later,
    with the API's messages."""
    out: list[CameraLine] = []
    for no, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            parts = shlex.split(line)
        except ValueError as e:
            raise UploadError(422, f"cameras line {no}: {e}") from None
        if len(parts) not in (5, 12) or (len(parts) == 12) != bool(out):
            want = (
                "NAME fx fy cx cy qw qx qy qz tx ty tz"
                if out
                else "NAME fx fy cx cy (no pose: its camera is the anchor's frame)"
            )
            raise UploadError(
                422,
                f"cameras line {no}: expected {want!r} for {'a further' if out else 'the first'} "
                f"photo; got {len(parts)} value(s)",
            )
        intrinsics = (parts[1], parts[2], parts[3], parts[4])
        out.append((no, parts[0], intrinsics, " ".join(parts[5:]) if len(parts) == 12 else None))
    if not out:
        raise UploadError(
            422,
            "cameras: give one line per photo, the first 'NAME fx fy cx cy', each further one "
            "'NAME fx fy cx cy qw qx qy qz tx ty tz'",
        )
    return out


def _stem(name: str) -> str:
    """A file name up to its first dot: ``frame_00000.sensor.png`` goes with ``frame_00000.jpg``."""
    return Path(name).name.split(".", 1)[0]


def _form_photos(
    lim, photos: list[UploadFile], depths: list[UploadFile], cameras: str
) -> tuple[list[Upload], list[str]]:
    """The create-anchor form's photos (a multiple file input), depth maps (another, matched by file name) and
    cameras lines, checked as ``POST /anchors`` checks its fields, errors naming the photo the same way."""
    files = {Path(f.filename or "").name: f for f in photos if f.filename or f.size}
    if not files:
        raise UploadError(400, "photos: choose at least one photo")
    if len(files) < len([f for f in photos if f.filename or f.size]):
        raise UploadError(422, "photos: two chosen photos have the same file name; rename one")
    check_photo_count(lim, len(files))  # before decoding any
    lines = _camera_lines(cameras)
    seen: set[str] = set()
    for no, name, _, _ in lines:
        if name not in files:
            raise UploadError(
                422, f"cameras line {no}: no chosen photo is named {name!r} (chosen: {', '.join(sorted(files))[:300]})"
            )
        if name in seen:
            raise UploadError(422, f"cameras line {no}: {name!r} has a line already")
        seen.add(name)
    if len(seen) < len(files):
        missing = sorted(set(files) - seen)
        raise UploadError(422, f"cameras: no line for the chosen photo(s) {', '.join(map(repr, missing))[:300]}")
    by_stem: dict[str, list[str]] = {}
    for n in files:
        by_stem.setdefault(_stem(n), []).append(n)
    depth_of: dict[str, UploadFile] = {}
    for d in depths:
        if not (d.filename or d.size):
            continue
        owners = by_stem.get(_stem(d.filename or ""), [])
        if len(owners) > 1:
            raise UploadError(
                422,
                f"depths: {Path(d.filename or '').name!r} could go with any of "
                f"{', '.join(map(repr, sorted(owners)))[:300]} (a depth map is matched by the "
                "part of its name before the first dot); rename the photos apart",
            )
        owner = owners[0] if owners else None
        if owner is None:
            raise UploadError(
                422,
                f"depths: {Path(d.filename or '').name!r} goes with no chosen photo (a depth map "
                "is matched by the part of its name before the first dot: frame_00000.sensor.png "
                "goes with frame_00000.jpg)",
            )
        if owner in depth_of:
            raise UploadError(422, f"depths: two depth maps for {owner!r}")
        depth_of[owner] = d
    several = len(lines) > 1  # one photo: the API's messages for a lone photo, without "photo 0"
    names = [photo_name(i, files[name]) if several else "" for i, (_, name, _, _) in enumerate(lines)]
    ups = [
        photo_upload(lim, names[i], files[name], *intr, depth_of.get(name), pose)
        for i, (_, name, intr, pose) in enumerate(lines)
    ]
    return ups, names


@router.post("/relocalize/anchors")
@heavy
def create_anchor_form(
    request: Request,
    photos: list[UploadFile] = File([]),
    depths: list[UploadFile] = File([]),
    cameras: str = Form(""),
    name: str = Form(""),
    method: str = Form(""),
    private: str = Form(""),
    csrf_token: str = Form(""),
    db: Session = Depends(db_session),
):
    """Create an anchor from the page (what ``POST /anchors`` does, same limits and errors): on success its page;
    on a problem the relocalize page with the error above this form, its values kept."""
    caller = require_writer(request, db, csrf_token)
    form = {"new_name": name, "new_method": method, "cameras": cameras, "new_private": bool(private)}
    try:
        ups, names = _form_photos(request.app.state.settings.limits, photos, depths, cameras)
        a, _ = make_anchor(request, db, caller.user, name, method, ups, names, bool(private))
    except (UploadError, HTTPException) as e:
        db.rollback()
        status, message = _problem(e)
        return _reloc_page(request, db, status, form=form, error=message, error_box="anchor-error")
    return RedirectResponse(f"/relocalize/anchors/{a.id}", status_code=303)


def _anchor_page(
    request: Request, db: Session, aid: str, status: int = 200, error: str = "", form: dict | None = None
) -> HTMLResponse:
    user = _signed_in(request, db)
    a = find_anchor(db, aid)
    data = anchor_json(a, photo_rows(db, a.id))
    return page(
        request,
        "anchor.html",
        db,
        status,
        anchor=data,
        error=error,
        form=form or {},
        owner=user.id == a.user_id or user.is_admin,
        show_photos=may_see_photos(a, user),
        max_photos=request.app.state.settings.limits.max_anchor_photos,
    )


@router.get("/relocalize/anchors/{aid}", response_class=HTMLResponse)
def anchor_page(aid: str, request: Request, db: Session = Depends(db_session)):
    """An anchor's photos (images, intrinsics, depth, poses); its owner adds and deletes photos here."""
    return _anchor_page(request, db, aid)


@router.post("/relocalize/anchors/{aid}/photos")
@heavy
def add_photo_form(
    aid: str,
    request: Request,
    image: UploadFile | None = File(None),
    depth: UploadFile | None = File(None),
    fx: str = Form(""),
    fy: str = Form(""),
    cx: str = Form(""),
    cy: str = Form(""),
    pose: str = Form(""),
    csrf_token: str = Form(""),
    db: Session = Depends(db_session),
):
    """``POST /anchors/{id}/photos`` from the anchor's page; a problem shows above the form, values kept."""
    caller = require_writer(request, db, csrf_token)
    try:
        add_photo(request, db, caller.user, aid, image, fx, fy, cx, cy, depth, pose)
    except (UploadError, HTTPException) as e:
        db.rollback()
        status, message = _problem(e)
        return _anchor_page(request, db, aid, status, message, {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "pose": pose})
    return RedirectResponse(f"/relocalize/anchors/{aid}", status_code=303)


@router.post("/relocalize/anchors/{aid}/photos/{k}/delete")
def delete_photo_form(
    aid: str, k: RowId, request: Request, csrf_token: str = Form(""), db: Session = Depends(db_session)
):
    """``DELETE /anchors/{id}/photos/{k}`` from the anchor's page; a refusal shows on the page."""
    caller = require_writer(request, db, csrf_token)
    try:
        remove_photo(request, db, caller.user, aid, k)
    except HTTPException as e:
        db.rollback()
        return _anchor_page(request, db, aid, e.status_code, str(e.detail))
    return RedirectResponse(f"/relocalize/anchors/{aid}", status_code=303)
