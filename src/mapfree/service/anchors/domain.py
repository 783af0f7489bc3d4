"""Anchors: a place's photos stored once, localized against by anyone signed in. The operations here (make, add or
delete a photo, localize) are shared by the JSON API (``anchors.router``) and the web pages (``pages``)."""

from __future__ import annotations

from dataclasses import replace

from fastapi import HTTPException, UploadFile
from sqlalchemy import select
from sqlalchemy.orm import Session

from ...estimate import Estimate
from ...geometry import Pose
from ..accounts.quota import check_quota
from ..config import Limits, Settings
from ..database.models import Anchor, AnchorPhoto, RetiredPhotoIndex, User, new_id, now
from ..inputs import UploadError, check_name, read_upload
from .calibration import calibration_json, uploaded
from .decode import IntrinsicsForm, parse_pose
from .localizers import Localizers, check_method, check_runnable, default_method
from .photos import Photo, Upload, decode_stored
from .photos import read_upload as read_photo_upload

#: The pose of an anchor's first photo in the anchor's frame (``[qw, qx, qy, qz, tx, ty, tz]``).
IDENTITY = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]


def photo_rows(db: Session, aid: str) -> list[AnchorPhoto]:
    """The further photos of an anchor (all but photo 0, which is the anchor row's own).

    Args:
        db: The request's database session.
        aid: The anchor's id.

    Returns:
        Its photo rows by index (1, 2, …; a deleted photo leaves a gap).
    """
    return list(db.scalars(select(AnchorPhoto).where(AnchorPhoto.anchor_id == aid).order_by(AnchorPhoto.seq)))


def anchor_version(rows: list[AnchorPhoto]) -> tuple:
    """What identifies the current set of an anchor's photos, the same in every API process: each further
    photo's index and creation time (photo 0 never changes). A photo added or deleted through any process
    changes it, so no process answers from an anchor it prepared before."""
    return tuple((r.seq, r.created_at) for r in rows)


def photo_indices(rows: list[AnchorPhoto]) -> list[int]:
    """The indices of an anchor's photos, in order: 0 (the anchor's frame), then each further photo's."""
    return [0, *(r.seq for r in rows)]


def _photo_json(index: int, intrinsics: dict, has_depth: bool, pose: list[float]) -> dict:
    """One photo of an anchor as the API shows it; its intrinsics' ``source`` (given, exif or default) stored
    with them is shown beside them (rows stored before sources were: given)."""
    intr = {k: v for k, v in intrinsics.items() if k != "source"}
    return {
        "index": index,
        "intrinsics": intr,
        "intrinsics_source": intrinsics.get("source", "given"),
        "has_depth": has_depth,
        "pose": pose,
    }


def anchor_json(a: Anchor, rows: list[AnchorPhoto]) -> dict:
    """An anchor and its photos as the API shows them (``AnchorOut``).

    Photo 0 is the anchor's own: its camera is the anchor's frame. Each further photo's ``pose`` is
    world-to-camera from that frame as ``[qw, qx, qy, qz, tx, ty, tz]`` (metres). A photo keeps its ``index`` for
    life (deleting one leaves a gap).

    Args:
        a: The anchor.
        rows: Its further photos (``photo_rows``).

    Returns:
        ``id``, ``name``, ``method``, ``intrinsics``, ``private``, ``has_depth``, ``num_photos``, ``photos``
        (``index``, ``intrinsics``, ``intrinsics_source``, ``has_depth``, ``pose`` each), ``created_at`` (UNIX seconds),
        ``url``, ``calibrations`` and ``accept`` (``calibration.calibration_json``).
    """
    photos = [
        _photo_json(0, a.intrinsics, a.depth is not None, IDENTITY),
        *(_photo_json(r.seq, r.intrinsics, r.depth is not None, r.pose) for r in rows),
    ]
    return {
        "id": a.id,
        "name": a.name,
        "method": a.method,
        "intrinsics": photos[0]["intrinsics"],
        "private": bool(a.private),
        "has_depth": a.depth is not None,
        "num_photos": len(photos),
        "photos": photos,
        "created_at": a.created_at,
        "url": f"/anchors/{a.id}",
        **calibration_json(a),
    }


def photo_upload(
    lim: Limits,
    what: str,
    image: UploadFile | None,
    intrinsics: IntrinsicsForm,
    depth: UploadFile | None,
    pose: str | None,
) -> Upload:
    """Read and check one uploaded photo of an anchor, with what is stored of it (``photos.read_upload``).

    Args:
        lim: The server's limits (file sizes, pixels, the working size).
        what: How errors name the photo (``photo_name``; "" for a lone photo).
        image: The photo file (JPEG or PNG); turned upright by its EXIF orientation.
        intrinsics: Its ``fx fy cx cy`` as sent, pixels of the uploaded image (all left out: its EXIF focal
            length, else the default camera).
        depth: Optional depth map: a single-channel uint16 PNG in millimetres, of the photo's size.
        pose: ``"qw qx qy qz tx ty tz"``, world-to-camera from the anchor's frame (metres); None for the
            anchor's first photo, whose camera is that frame.

    Returns:
        The checked photo at the working size, and what is stored of it.

    Raises:
        UploadError: A missing or undecodable image (400, 422), a file or image over the limits (413), bad
            intrinsics or pose, or a depth map without a single measurement (422); the message starts with
            ``what``.
    """
    try:
        img_bytes = read_upload(image, lim.max_image_bytes, "image")
        if img_bytes is None:
            raise UploadError(400, "image: no file uploaded")
        up = read_photo_upload(
            img_bytes,
            lim,
            intrinsics,
            read_upload(depth, lim.max_image_bytes, "depth"),
            store=True,
        )
        if up.depth is not None and not up.depth_measured:
            raise UploadError(
                422,
                "depth: every pixel is 0 (no measurement), so the photo could never give a "
                "metric pose; send its real depth map, or none with a method that needs none",
            )
        q = IDENTITY if pose is None else parse_pose(pose)
    except UploadError as e:
        raise UploadError(e.status, f"{what}: {e.message}" if what else e.message) from None
    return replace(up, photo=replace(up.photo, pose=Pose.from_qt(q[:4], q[4:])), pose=q)


def photo_name(i: int, f: UploadFile | None) -> str:
    """How errors name a photo.

    Args:
        i: Its index in the anchor (0: the first).
        f: The uploaded file, whose name is added when it has one.

    Returns:
        ``"photo 2 ('kitchen.jpg')"``, or ``"photo 2"`` without a file name.
    """
    fname = check_name((f.filename or "") if f is not None else "", 80, "file name") if f is not None else ""
    return f"photo {i}" + (f" ({fname!r})" if fname else "")


def _runnable(m: str, ups: list[Upload], names: list[str]) -> None:
    """``check_runnable`` for every photo, naming the one without the depth the method needs."""
    for i, u in enumerate(ups):
        try:
            check_runnable(m, u.depth is not None)
        except UploadError as e:
            if not names[i]:
                raise
            raise UploadError(
                e.status,
                f"{names[i]}: method {m} takes its metric scale from each photo's depth map "
                "and this photo has none: upload its depth (a single-channel uint16 PNG in "
                "millimetres)",
            ) from None


def extra_photos(
    lim: Limits,
    images: list[UploadFile],
    fx: list[str],
    fy: list[str],
    cx: list[str],
    cy: list[str],
    poses: list[str],
    depths: list[UploadFile],
    first: int,
) -> tuple[list[Upload], list[str]]:
    """The further photos of ``POST /anchors``: its repeated ``photo_*`` fields, one value per ``photo_image``
    in the same order, each photo read and checked (``photo_upload``).

    Depth maps are all or none (an empty file part is dropped, so it cannot stand for a missing one): photos of
    which only some have depth are added one by one (``POST /anchors/{id}/photos``).

    Args:
        lim: The server's limits.
        images: The photo files; empty parts are skipped.
        fx: One focal length along x per photo, in pixels.
        fy: One focal length along y per photo, in pixels.
        cx: One principal point x per photo, in pixels.
        cy: One principal point y per photo, in pixels.
        poses: One ``"qw qx qy qz tx ty tz"`` per photo, world-to-camera from the anchor's frame (metres).
        depths: No depth maps, or one per photo.
        first: The index of the first of these photos in the anchor (errors name photos by it).

    Returns:
        The checked photos, and how errors name each one.

    Raises:
        UploadError: A field with a count other than the photos' (422), or a photo ``photo_upload`` refuses.
    """
    images = [f for f in images if f.filename or f.size]
    n = len(images)
    for field_name, vals in (
        ("photo_fx", fx),
        ("photo_fy", fy),
        ("photo_cx", cx),
        ("photo_cy", cy),
        ("photo_pose", poses),
    ):
        if len(vals) != n and not (vals == [] and field_name != "photo_pose"):  # intrinsics: all, or none
            raise UploadError(
                422,
                f"{field_name}: {len(vals)} value(s) for {n} photo_image file(s); give one per "
                "photo, in the same order",
            )
    if depths and len(depths) != n:
        raise UploadError(
            422,
            f"photo_depth: {len(depths)} file(s) for {n} photo_image file(s); give none, or one "
            "per photo in the same order (or add the photos one by one: POST "
            "/anchors/{id}/photos)",
        )
    names = [photo_name(first + i, f) for i, f in enumerate(images)]
    fx, fy, cx, cy = (v or [""] * n for v in (fx, fy, cx, cy))  # none given: each photo's EXIF, else the default
    ups = [
        photo_upload(
            lim, names[i], f, IntrinsicsForm(fx[i], fy[i], cx[i], cy[i]), depths[i] if depths else None, poses[i]
        )
        for i, f in enumerate(images)
    ]
    return ups, names


def _photo_rows_of(aid: str, ups: list[Upload], first_seq: int) -> list[AnchorPhoto]:
    return [
        AnchorPhoto(
            anchor_id=aid,
            seq=first_seq + i,
            intrinsics=u.stored_intrinsics,
            pose=u.pose,
            image=u.image,
            depth=u.depth,
            created_at=now(),
        )
        for i, u in enumerate(ups)
    ]


def check_photo_count(lim: Limits, n: int) -> None:
    """Refuse an anchor of more photos than the limit. Called before any photo is decoded too: a small PNG can
    decode to tens of MB, so a request of a thousand of them must be refused unread.

    Args:
        lim: The server's limits (``max_anchor_photos``).
        n: The photos the anchor would hold, the first included.

    Raises:
        UploadError: 413 past the limit.
    """
    if n > lim.max_anchor_photos:
        raise UploadError(413, f"an anchor holds at most {lim.max_anchor_photos} photos; got {n}")


def anchor_method(configured: str, method: str) -> str:
    """The method a new anchor gets: ``method`` as a client may send it (``localizers.check_method``), or when
    empty the server's default (``configured``, else the registry's).

    Raises:
        UploadError: An unknown method (422).
    """
    return check_method(method) if method.strip() else default_method(configured)


def make_anchor(
    settings: Settings,
    localizers: Localizers,
    db: Session,
    user: User,
    name: str,
    method: str,
    ups: list[Upload],
    names: list[str],
    private: bool = False,
    calibration: list[dict] | None = None,
    accept: float | None = None,
) -> tuple[Anchor, list[AnchorPhoto]]:
    """Store a new anchor of ``user``, after its method has prepared it here (so that an anchor that could never
    localize is refused now, not at its first query). Shared by ``POST /anchors`` and the relocalize page.

    Args:
        settings: The deployment's settings (limits, quota, default method).
        localizers: The app's prepared methods (``localizers.LocalizersDep``).
        db: The request's database session; committed.
        user: The owner.
        name: The anchor's name (checked; may be empty).
        method: A method name a client may send (``localizers.check_method``); empty: the server's default.
        ups: The checked photos (``photo_upload``); ``ups[0]``'s camera is the anchor's frame.
        names: How errors name each photo ("" for a lone photo).
        private: Serve its photos to its owner and admins only (anyone signed in may still localize).
        calibration: Its uploaded calibrations (``calibration.read_calibrations``, for ``anchor_method``'s
            method); None: the method's shipped ones.
        accept: Its threshold on ``p_correct`` (``calibration.check_accept``); None: none.

    Returns:
        The stored anchor and its further photo rows.

    Raises:
        UploadError: Past the photo limit or the owner's storage quota (413), an unknown method (422), or a
            method that cannot run on these photos here (``MethodUnavailable``, 422).
    """
    lim = settings.limits
    check_photo_count(lim, len(ups))
    name = check_name(name, lim.max_name_chars)
    m = anchor_method(settings.default_method, method)
    _runnable(m, ups, names)
    nbytes = sum(u.nbytes for u in ups)
    check_quota(db, settings, user.id, nbytes, "this anchor's photos")  # refused before the costly preparation
    db.commit()  # no transaction (SQLite: the write lock; PostgreSQL: the user's row) held while preparing
    aid = new_id()
    rows = _photo_rows_of(aid, ups[1:], 1)
    # 422 when it cannot run; what it prepares counts against the owner's share of the cache
    localizers.check(aid, m, [u.photo for u in ups], anchor_version(rows), user.id)
    try:  # counted again, locked, in the transaction that stores them: another upload may have come meanwhile
        check_quota(db, settings, user.id, nbytes, "this anchor's photos")
    except UploadError:
        db.rollback()
        localizers.forget(aid)
        raise
    first = ups[0]
    a = Anchor(
        id=aid,
        user_id=user.id,
        name=name,
        method=m,
        intrinsics=first.stored_intrinsics,
        image=first.image,
        depth=first.depth,
        private=bool(private),
        calibration=calibration,
        accept=accept,
        created_at=now(),
    )
    db.add(a)
    db.flush()
    db.add_all(rows)
    db.commit()
    return a, rows


def find_anchor(db: Session, aid: str, lock: bool = False) -> Anchor:
    """The anchor of an id.

    Args:
        db: The request's database session.
        aid: The anchor's id.
        lock: Lock its row for the transaction, which serialises changes to its photos (the next index) on
            PostgreSQL too.

    Returns:
        The anchor.

    Raises:
        HTTPException: 404 when there is none.
    """
    a = None
    if len(aid) <= 32:
        a = (
            db.scalars(select(Anchor).where(Anchor.id == aid).with_for_update()).first()
            if lock
            else db.get(Anchor, aid)
        )
    if a is None:
        raise HTTPException(404, "no such anchor")
    return a


def may_see_photos(a: Anchor, user: User | None) -> bool:
    """Whether an account may see the anchor's photos: anyone signed in, unless the anchor is private (then its
    owner and admins).

    Args:
        a: The anchor.
        user: The caller's account; None: nobody signed in.
    """
    return user is not None and (not a.private or a.user_id == user.id or user.is_admin)


def own_anchor(a: Anchor, user: User, what: str) -> None:
    """Refuse a change to an anchor by anyone but its owner or an admin (anyone signed in may see and use it).

    Args:
        a: The anchor.
        user: The caller's account.
        what: The change, for the message ("delete it").

    Raises:
        HTTPException: 403 for anyone else.
    """
    if a.user_id != user.id and not user.is_admin:
        raise HTTPException(403, f"only the anchor's owner can {what}")


def next_photo_index(db: Session, aid: str, rows: list[AnchorPhoto]) -> int:
    """The index the anchor's next photo gets: after the highest one it ever had, deleted ones included, so that
    an index always names the same photo."""
    retired = db.scalar(select(RetiredPhotoIndex.highest).where(RetiredPhotoIndex.anchor_id == aid)) or 0
    return max(retired, rows[-1].seq if rows else 0) + 1


def retire_photo_index(db: Session, aid: str, k: int) -> None:
    """Remember that index ``k`` of the anchor was given (its photo is being deleted), if it is the highest."""
    row = db.get(RetiredPhotoIndex, aid)
    if row is None:
        db.add(RetiredPhotoIndex(anchor_id=aid, highest=k))
    elif row.highest < k:
        row.highest = k


def add_photo(
    settings: Settings,
    localizers: Localizers,
    db: Session,
    user: User,
    aid: str,
    image: UploadFile | None,
    intrinsics: IntrinsicsForm,
    depth: UploadFile | None,
    pose: str,
) -> tuple[Anchor, list[AnchorPhoto]]:
    """Check and store one more photo of an anchor, at the index after the highest one it ever had
    (``next_photo_index``), with the same limits and errors as at creation. Every API process then prepares
    the anchor afresh. Shared by the API and the anchor's page.

    Args:
        settings: The deployment's settings (limits, quota).
        localizers: The app's prepared methods (``localizers.LocalizersDep``).
        db: The request's database session; committed.
        user: The caller's account: the anchor's owner or an admin.
        aid: The anchor's id.
        image: The photo file (JPEG or PNG).
        intrinsics: Its ``fx fy cx cy`` as sent, pixels of the uploaded image (``photo_upload``).
        depth: Optional depth map: a single-channel uint16 PNG in millimetres.
        pose: ``"qw qx qy qz tx ty tz"``, world-to-camera from the anchor's frame (metres).

    Returns:
        The anchor and its further photo rows, the new one included.

    Raises:
        HTTPException: No such anchor (404), or not the caller's (403).
        UploadError: A photo ``photo_upload`` refuses, an anchor at its photo limit or its owner's storage
            quota (413), or a photo without the depth map the anchor's method needs (422).
    """
    lim = settings.limits

    def checks(lock: bool) -> tuple[Anchor, int, str]:
        a = find_anchor(db, aid, lock=lock)
        own_anchor(a, user, "add photos to it")
        rows = photo_rows(db, a.id)
        seq = next_photo_index(db, a.id, rows)
        what = photo_name(seq, image)
        if len(rows) + 1 >= lim.max_anchor_photos:
            raise UploadError(413, f"{what}: anchor {a.id} already holds the limit of {lim.max_anchor_photos} photos")
        return a, seq, what

    a, _, what = checks(lock=False)
    method = a.method
    # Decode (up to 16 MB) outside any transaction: on SQLite every transaction holds the database's write lock.
    db.commit()
    up = photo_upload(lim, what, image, intrinsics, depth, pose)
    _runnable(method, [up], [what])
    a, seq, what = checks(lock=True)  # again, locked: the anchor may have changed (or gone) while decoding
    check_quota(db, settings, a.user_id, up.nbytes, "this photo")
    db.add_all(_photo_rows_of(a.id, [up], seq))
    db.commit()
    localizers.forget(a.id)  # older versions of this anchor are of no further use here
    return a, photo_rows(db, a.id)


def remove_photo(localizers: Localizers, db: Session, user: User, aid: str, k: int) -> tuple[Anchor, list[AnchorPhoto]]:
    """Delete a photo of an anchor with its stored bytes; every API process then prepares the anchor afresh from
    the photos left. Its index is never given again.

    Args:
        localizers: The app's prepared methods (``localizers.LocalizersDep``).
        db: The request's database session; committed.
        user: The caller's account: the anchor's owner or an admin.
        aid: The anchor's id.
        k: The photo's index (1 or more: photo 0 is the anchor's frame and stays).

    Returns:
        The anchor and the further photo rows left.

    Raises:
        HTTPException: No such anchor or photo (404), not the caller's (403), or photo 0 (409).
    """
    a = find_anchor(db, aid, lock=True)
    own_anchor(a, user, "delete its photos")
    rows = photo_rows(db, a.id)
    if k == 0:
        raise HTTPException(
            409,
            f"photo 0 of anchor {a.id} cannot be deleted: its camera is the anchor's frame, "
            "the one every photo's pose and every localize answer is given in; delete the "
            "whole anchor instead (DELETE /anchors/{id}) and create a new one from the photos "
            "to keep",
        )
    row = next((r for r in rows if r.seq == k), None)
    if row is None:
        raise HTTPException(
            404, f"anchor {a.id} has no photo {k} (its photos: {', '.join(map(str, photo_indices(rows)))})"
        )
    db.delete(row)
    retire_photo_index(db, a.id, k)
    db.commit()
    localizers.forget(a.id)
    return a, photo_rows(db, a.id)


def stored_photo(a: Anchor, rows: list[AnchorPhoto], k: int, lim: Limits) -> Photo:
    """A stored photo of an anchor, decoded from the database at the working size.

    Args:
        a: The anchor.
        rows: Its further photos (``photo_rows``).
        k: The photo's index (0: the anchor row's own).
        lim: The server's limits (the working size).

    Returns:
        The photo with its intrinsics, depth map (if stored) and pose in the anchor's frame.
    """
    row = next(r for r in rows if r.seq == k) if k else None
    if row is None:
        return decode_stored(a.image, a.intrinsics, a.depth, IDENTITY, lim, f"anchor photo {k}")
    return decode_stored(row.image, row.intrinsics, row.depth, row.pose, lim, f"anchor photo {k}")


def localize_anchor(
    localizers: Localizers,
    lim: Limits,
    a: Anchor,
    rows: list[AnchorPhoto],
    query: Photo,
    owner: int | None = None,
) -> Estimate:
    """Localize a query photo against an anchor with the anchor's method: its metric pose in the anchor's frame.

    The stored photos are decoded only when this process has not prepared this version of the anchor; what it
    prepares counts against ``owner``'s share of the cache. With several photos the most similar one answers.

    Args:
        localizers: The app's prepared methods (``localizers.LocalizersDep``).
        lim: The server's limits (the working size, the decode limits).
        a: The anchor.
        rows: Its further photos (``photo_rows``), as they are now.
        query: The query photo at the working size (``photos.read_upload``), with its intrinsics and optional
            depth map.
        owner: The account asking (its share of the prepared-anchor cache).

    Returns:
        The estimate: world-to-camera pose of the query in the anchor's frame (metres), confidence, timings;
        no pose, with a reason, when the method finds none. ``est.photo`` is the answering photo's index,
        ``extras["method"]`` the method that ran.

    Raises:
        MethodUnavailable: The anchor's method cannot run here (weights missing, depth it needs absent).
    """
    indices = photo_indices(rows)
    est = localizers.localize_photos(
        a.id,
        a.method,
        anchor_version(rows),
        lambda: (stored_photo(a, rows, k, lim) for k in indices),
        query.image,
        query.intrinsics,
        query.depth,
        owner,
        uploaded(a),
    )
    if est.photo is not None:  # the position among the photos prepared -> its index
        est.photo = indices[est.photo]
    return est
