"""The relocalization web pages: trying a method on two photos, localizing a photo against a stored anchor, and
creating an anchor and adding or deleting its photos from the page (what the ``/anchors`` routes do, with the
same limits and messages). A form that fails comes back with its values and the error above it."""

from __future__ import annotations

import base64
import secrets
import shlex
from dataclasses import replace
from pathlib import Path

from fastapi import APIRouter, Depends, File, Form, HTTPException, Request, UploadFile
from fastapi.responses import HTMLResponse, RedirectResponse
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from ..accounts.caller import RowId, db_session, identify, require_writer, signed_in
from ..accounts.render import page
from ..config import Limits, Settings
from ..database.models import Anchor, AnchorPhoto
from ..http.heavy import heavy
from ..inputs import UploadError, problem
from ..state import SettingsDep
from .decode import IntrinsicsForm
from .domain import (
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
from .localizers import LocalizersDep, check_method, default_method, estimate_json, figure_png, needs_reference_depth
from .photos import Photo, Upload
from .photos import read_upload as read_photo_upload

router = APIRouter(include_in_schema=False)
#: Offered on the relocalization page; the note says what each needs.
RELOC_CHOICES = {
    "best-offline": "XFeat + 3D-3D; needs the reference depth (the query's too, else PnP runs)",
    "best-offline-pnp": "XFeat + PnP; needs the reference depth",
    "sift_pnp_sensor": "SIFT + PnP; needs the reference depth",
    "sift_emat_none": "SIFT + essential matrix; no depth, so direction only: no metric scale",
}


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


def _reloc_page(request: Request, db: Session, settings: Settings, status: int = 200, **ctx) -> HTMLResponse:
    ctx.setdefault("form", {})
    ctx.setdefault("method", default_method(settings.default_method))
    return page(
        request,
        "relocalize.html",
        db,
        status,
        choices=RELOC_CHOICES,
        anchors=_anchor_choices(request, db),
        max_photos=settings.limits.max_anchor_photos,
        **ctx,
    )


@router.get("/relocalize", response_class=HTMLResponse)
def relocalize_form(request: Request, settings: SettingsDep, db: Session = Depends(db_session)):
    return _reloc_page(request, db, settings)


def _form_intrinsics(form: dict, prefix: str) -> IntrinsicsForm:
    """The form's ``{prefix}fx`` ... fields."""
    return IntrinsicsForm(form[f"{prefix}fx"], form[f"{prefix}fy"], form[f"{prefix}cx"], form[f"{prefix}cy"])


def _query_photo(query: UploadFile, lim: Limits, form: dict) -> Photo:
    """The page's query photo with its ``q_*`` intrinsics (EXIF or the default camera when left empty), at the
    working size."""
    return read_photo_upload(
        query.file.read(lim.max_image_bytes + 1),
        lim,
        _form_intrinsics(form, "q_"),
        what="query photo",
        intr_what="query intrinsics",
    ).photo


@router.post("/relocalize", response_class=HTMLResponse)
@heavy
def relocalize_try(
    request: Request,
    settings: SettingsDep,
    localizers: LocalizersDep,
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
    lim = settings.limits
    m = method.strip() or default_method(settings.default_method)
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
            _form_intrinsics(form, "ref_"),
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
        return _reloc_page(request, db, settings, e.status, method=m, form=form, error=e.message)
    key = "try-" + secrets.token_hex(8)
    est = localizers.localize(key, m, ref.image, ref.intrinsics, ref.depth, q.image, q.intrinsics, owner=caller.user.id)
    localizers.forget(key)
    png = figure_png(ref.image, q.image, ref.intrinsics, q.intrinsics, est, title=m)
    return _reloc_page(
        request,
        db,
        settings,
        method=m,
        form=form,
        result=estimate_json(est, m),
        figure="data:image/png;base64," + base64.b64encode(png).decode(),
    )


@router.post("/relocalize/anchor", response_class=HTMLResponse)
@heavy
def relocalize_anchor(
    request: Request,
    settings: SettingsDep,
    localizers: LocalizersDep,
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
    lim = settings.limits
    try:
        q = _query_photo(query, lim, form)  # at the size the matches are in
    except UploadError as e:
        return _reloc_page(request, db, settings, e.status, method=a.method, form=form, error=e.message)
    est = localize_anchor(localizers, lim, a, rows, q, owner=caller.user.id)
    result = estimate_json(est, a.method)
    if not may_see_photos(a, caller.user):  # the figure would show the anchor's photo
        return _reloc_page(
            request, db, settings, method=a.method, form=form, result=result, anchor_name=a.name or a.id[:8]
        )
    photo = stored_photo(a, rows, result.get("photo") or 0, lim)  # only the one drawn, not every photo again
    shown = replace(est, pose=est.pose @ photo.pose.inverse()) if est.pose is not None else est  # vs that photo
    png = figure_png(
        photo.image, q.image, photo.intrinsics, q.intrinsics, shown, title=f"{a.method}, photo {result.get('photo', 0)}"
    )
    return _reloc_page(
        request,
        db,
        settings,
        method=a.method,
        form=form,
        result=result,
        anchor_name=a.name or a.id[:8],
        figure="data:image/png;base64," + base64.b64encode(png).decode(),
    )


# ------------------------------------------------------------------------------------ anchors from the page


#: One line of the "cameras" box: (line number, file name, intrinsics as written, pose or None).
CameraLine = tuple[int, str, IntrinsicsForm, str | None]


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
        intrinsics = IntrinsicsForm(parts[1], parts[2], parts[3], parts[4])
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
    lim: Limits, photos: list[UploadFile], depths: list[UploadFile], cameras: str
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
        photo_upload(lim, names[i], files[name], intr, depth_of.get(name), pose)
        for i, (_, name, intr, pose) in enumerate(lines)
    ]
    return ups, names


@router.post("/relocalize/anchors")
@heavy
def create_anchor_form(
    request: Request,
    settings: SettingsDep,
    localizers: LocalizersDep,
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
        ups, names = _form_photos(settings.limits, photos, depths, cameras)
        a, _ = make_anchor(settings, localizers, db, caller.user, name, method, ups, names, bool(private))
    except (UploadError, HTTPException) as e:
        db.rollback()
        status, message = problem(e)
        return _reloc_page(request, db, settings, status, form=form, error=message, error_box="anchor-error")
    return RedirectResponse(f"/relocalize/anchors/{a.id}", status_code=303)


def _anchor_page(
    request: Request,
    db: Session,
    settings: Settings,
    aid: str,
    status: int = 200,
    error: str = "",
    form: dict | None = None,
) -> HTMLResponse:
    user = signed_in(request, db)
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
        max_photos=settings.limits.max_anchor_photos,
    )


@router.get("/relocalize/anchors/{aid}", response_class=HTMLResponse)
def anchor_page(aid: str, request: Request, settings: SettingsDep, db: Session = Depends(db_session)):
    """An anchor's photos (images, intrinsics, depth, poses); its owner adds and deletes photos here."""
    return _anchor_page(request, db, settings, aid)


@router.post("/relocalize/anchors/{aid}/photos")
@heavy
def add_photo_form(
    aid: str,
    request: Request,
    settings: SettingsDep,
    localizers: LocalizersDep,
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
        add_photo(settings, localizers, db, caller.user, aid, image, IntrinsicsForm(fx, fy, cx, cy), depth, pose)
    except (UploadError, HTTPException) as e:
        db.rollback()
        status, message = problem(e)
        return _anchor_page(
            request, db, settings, aid, status, message, {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "pose": pose}
        )
    return RedirectResponse(f"/relocalize/anchors/{aid}", status_code=303)


@router.post("/relocalize/anchors/{aid}/photos/{k}/delete")
def delete_photo_form(
    aid: str,
    k: RowId,
    request: Request,
    settings: SettingsDep,
    localizers: LocalizersDep,
    csrf_token: str = Form(""),
    db: Session = Depends(db_session),
):
    """``DELETE /anchors/{id}/photos/{k}`` from the anchor's page; a refusal shows on the page."""
    caller = require_writer(request, db, csrf_token)
    try:
        remove_photo(localizers, db, caller.user, aid, k)
    except HTTPException as e:
        db.rollback()
        return _anchor_page(request, db, settings, aid, e.status_code, str(e.detail))
    return RedirectResponse(f"/relocalize/anchors/{aid}", status_code=303)
