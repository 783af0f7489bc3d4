"""JSON routes of the relocalization anchors: thin, over ``anchors.domain`` (the web pages call the same functions)."""

from __future__ import annotations

from fastapi import APIRouter, Depends, File, Form, HTTPException, Request, UploadFile
from fastapi.responses import Response
from sqlalchemy import select
from sqlalchemy.orm import Session

from ..accounts.caller import RowId, db_session, require_user, require_writer
from ..database.models import AnchorPhoto
from ..http.heavy import heavy
from ..inputs import read_upload
from ..schemas import AnchorOut, LocalizeOut
from ..state import SettingsDep
from .calibration import accepted, check_accept, read_calibrations, set_calibration
from .decode import IntrinsicsForm
from .domain import (
    add_photo,
    anchor_json,
    anchor_method,
    check_photo_count,
    extra_photos,
    find_anchor,
    localize_anchor,
    make_anchor,
    may_see_photos,
    own_anchor,
    photo_name,
    photo_rows,
    photo_upload,
    remove_photo,
)
from .exif import clean_photo
from .localizers import LocalizersDep, estimate_json
from .photos import read_upload as read_photo_upload

router = APIRouter(tags=["relocalization"])

#: How the optional calibration fields are read.
_CALIBRATION = (
    "optional .calib.json files (mapfree calibrate) for the anchor's method, or one per stage of a cascade (repeat); "
    "none: the method's shipped calibration, if it has one"
)
_ACCEPT = "optional threshold on p_correct: localize answers then say accepted (true when p_correct >= accept)"

#: How the optional intrinsics fields are read.
_INTRINSICS = (
    "pixels of the uploaded image, with fy, cx, cy: all four, or none to take the photo's EXIF focal length "
    "(else a default 64° camera); the response's intrinsics_source says which"
)


@router.post("/anchors", status_code=201, response_model=AnchorOut)
@heavy
def create_anchor(
    request: Request,
    settings: SettingsDep,
    localizers: LocalizersDep,
    image: UploadFile = File(..., description="reference photo (JPEG/PNG)"),
    fx: float | None = Form(None, description=_INTRINSICS),
    fy: float | None = Form(None),
    cx: float | None = Form(None),
    cy: float | None = Form(None),
    depth: UploadFile | None = File(None, description="optional uint16 PNG depth, millimetres"),
    method: str = Form(""),
    name: str = Form(""),
    csrf_token: str | None = Form(None),
    photo_image: list[UploadFile] = File([], description="further photos of the place (repeat)"),
    photo_fx: list[str] = Form([], description="one per photo_image, or none at all (EXIF or the default)"),
    photo_fy: list[str] = Form([]),
    photo_cx: list[str] = Form([]),
    photo_cy: list[str] = Form([]),
    photo_pose: list[str] = Form(
        [],
        description="one per photo_image: 'qw qx qy qz tx ty tz', "
        "world-to-camera from the first photo's camera, metres",
    ),
    photo_depth: list[UploadFile] = File([], description="none, or one per photo_image, in order"),
    private: bool = Form(
        False, description="its photos are served to you (and admins) only; others may still localize against it"
    ),
    calibration: list[UploadFile] = File([], description=_CALIBRATION),
    accept: float | None = Form(None, description=_ACCEPT),
    db: Session = Depends(db_session),
):
    """Register a place (user A) that anyone signed in can localize against: its first photo (``image``, whose
    camera is the anchor's frame) and optionally further photos (``photo_*``, repeated, one per photo, each
    with its own intrinsics, optional depth and pose in the anchor's frame). Errors name the photo: photo 0 is
    ``image``, photo 1 the first ``photo_image``, and so on. The photos count against the storage quota."""
    caller = require_writer(request, db, csrf_token)
    lim = settings.limits
    calibrations = read_calibrations(calibration, anchor_method(settings.default_method, method))
    accept = check_accept(accept)
    n_extra = sum(1 for f in photo_image if f.filename or f.size)
    check_photo_count(lim, 1 + n_extra)  # before decoding any
    several = n_extra > 0  # one photo: messages as before, without "photo 0"
    name0 = photo_name(0, image) if several else ""
    first = photo_upload(lim, name0, image, IntrinsicsForm(fx, fy, cx, cy), depth, None)
    extra, names = extra_photos(lim, photo_image, photo_fx, photo_fy, photo_cx, photo_cy, photo_pose, photo_depth, 1)
    a, rows = make_anchor(
        settings,
        localizers,
        db,
        caller.user,
        name,
        method,
        [first, *extra],
        [name0, *names],
        private,
        calibrations,
        accept,
    )
    return anchor_json(a, rows)


@router.get("/anchors/{aid}", response_model=AnchorOut)
def get_anchor(aid: str, request: Request, db: Session = Depends(db_session)):
    require_user(request, db)
    a = find_anchor(db, aid)
    return anchor_json(a, photo_rows(db, a.id))


@router.put("/anchors/{aid}/calibration", response_model=AnchorOut)
def put_anchor_calibration(
    aid: str,
    request: Request,
    calibration: list[UploadFile] = File([], description=_CALIBRATION),
    accept: float | None = Form(None, description=_ACCEPT),
    csrf_token: str | None = Form(None),
    db: Session = Depends(db_session),
):
    """Give one of your anchors (its owner, or an admin) its calibrations and accept threshold, replacing both:
    ``.calib.json`` files fitted by ``mapfree calibrate`` for the anchor's method (a cascade: one per stage), or
    none to use the method's shipped calibration. A file for another method, of an older format or corrupt is a
    422 naming it. The next localize answers with ``p_correct`` from them (``calibration`` says uploaded or
    shipped) and, with ``accept``, ``accepted``."""
    caller = require_writer(request, db, csrf_token)
    a = find_anchor(db, aid)
    own_anchor(a, caller.user, "change its calibration")
    set_calibration(db, a, calibration, accept)
    return anchor_json(a, photo_rows(db, a.id))


@router.post("/anchors/{aid}/photos", status_code=201, response_model=AnchorOut)
@heavy
def add_anchor_photo(
    aid: str,
    request: Request,
    settings: SettingsDep,
    localizers: LocalizersDep,
    image: UploadFile = File(..., description="photo (JPEG/PNG)"),
    fx: float | None = Form(None, description=_INTRINSICS),
    fy: float | None = Form(None),
    cx: float | None = Form(None),
    cy: float | None = Form(None),
    pose: str = Form(..., description="'qw qx qy qz tx ty tz': world-to-camera from the anchor's first photo, metres"),
    depth: UploadFile | None = File(None, description="optional uint16 PNG depth, millimetres"),
    csrf_token: str | None = Form(None),
    db: Session = Depends(db_session),
):
    """Add a photo of the place to one of your anchors (its owner, or an admin). Localizing then retrieves the
    most similar photo for each query; poses stay in the anchor's frame. It gets the index after the highest
    one the anchor ever had (a deleted photo's index is never given again) and counts against the owner's
    storage quota."""
    caller = require_writer(request, db, csrf_token)
    intrinsics = IntrinsicsForm(fx, fy, cx, cy)
    return anchor_json(*add_photo(settings, localizers, db, caller.user, aid, image, intrinsics, depth, pose))


@router.delete("/anchors/{aid}/photos/{k}", response_model=AnchorOut)
def delete_anchor_photo(
    aid: str, k: RowId, request: Request, localizers: LocalizersDep, db: Session = Depends(db_session)
):
    """Delete photo ``k`` of one of your anchors (its owner, or an admin) -> the anchor. Indices stay as they
    are (deleting photo 1 of 0, 1, 2 leaves 0, 2); the next localize uses the photos left; the bytes no longer
    count against the storage quota. Photo 0, the anchor's frame, cannot be deleted (409): delete the anchor."""
    caller = require_writer(request, db)
    return anchor_json(*remove_photo(localizers, db, caller.user, aid, k))


@router.get(
    "/anchors/{aid}/photos/{k}",
    tags=["relocalization"],
    response_class=Response,
    responses={200: {"content": {"image/jpeg": {}, "image/png": {}}, "description": "the photo"}},
)
def anchor_photo_image(aid: str, k: RowId, request: Request, db: Session = Depends(db_session)):
    """The stored image of photo ``k`` (JPEG or PNG, upright, without EXIF metadata), for anyone signed in; a
    private anchor's for its owner and admins only."""
    caller = require_user(request, db)
    a = find_anchor(db, aid)
    if not may_see_photos(a, caller.user):
        raise HTTPException(403, "this anchor's photos are private to its owner")
    data = a.image if k == 0 else None
    if k > 0:
        data = db.scalar(select(AnchorPhoto.image).where(AnchorPhoto.anchor_id == a.id, AnchorPhoto.seq == k))
    if data is None:
        raise HTTPException(404, f"anchor {a.id} has no photo {k}")
    kind = "image/png" if data.startswith(b"\x89PNG") else "image/jpeg"  # decoded as one of them at upload
    data = clean_photo(data)  # rows stored before photos were cleaned at upload still hold their metadata
    return Response(data, media_type=kind, headers={"Cache-Control": "private, max-age=3600"})


@router.delete("/anchors/{aid}", status_code=204, tags=["relocalization"], response_class=Response)
def delete_anchor(aid: str, request: Request, localizers: LocalizersDep, db: Session = Depends(db_session)):
    caller = require_writer(request, db)
    a = find_anchor(db, aid)
    own_anchor(a, caller.user, "delete it")
    db.delete(a)
    db.commit()
    localizers.forget(aid)
    return Response(status_code=204)


@router.post("/anchors/{aid}/localize", response_model=LocalizeOut, response_model_exclude_unset=True)
@heavy
def localize(
    aid: str,
    request: Request,
    settings: SettingsDep,
    localizers: LocalizersDep,
    image: UploadFile = File(..., description="query photo (JPEG/PNG)"),
    fx: float | None = Form(None, description=_INTRINSICS),
    fy: float | None = Form(None),
    cx: float | None = Form(None),
    cy: float | None = Form(None),
    depth: UploadFile | None = File(None),
    csrf_token: str | None = Form(None),
    db: Session = Depends(db_session),
):
    """Metric pose of the query camera in the anchor's frame, the camera of its first photo
    (``X_query = R X_anchor + t``), with confidence, timings and ``p_correct`` where the anchor's method has a
    calibration (``calibration`` says whose; ``accepted`` with the anchor's threshold). With several photos the most similar one
    (DenseVLAD) answers: ``photo`` says which (its index), ``retrieval_similarity`` how similar. ``ok: false``
    with a ``reason`` when the method finds no pose."""
    caller = require_writer(request, db, csrf_token)
    a = find_anchor(db, aid)
    rows = photo_rows(db, a.id)
    db.commit()  # release the read transaction before the long computation
    lim = settings.limits
    q = read_photo_upload(
        read_upload(image, lim.max_image_bytes, "image") or b"",
        lim,
        IntrinsicsForm(fx, fy, cx, cy),
        read_upload(depth, lim.max_image_bytes, "depth"),
    ).photo
    est = localize_anchor(localizers, lim, a, rows, q, caller.user.id)
    out = estimate_json(est, a.method)
    if a.accept is not None:
        out["accepted"] = accepted(est, a.accept)
    out["anchor"] = a.id
    out["intrinsics_source"] = q.intrinsics_source
    return out
