"""Anchors holding several photos of a place (issue 12): created in one request or grown photo by photo, each
photo with its own intrinsics, depth and pose in the anchor's frame; a query is answered by the most similar
photo (DenseVLAD) with its pose in the anchor's frame. Real HTTP, real photos (realmini-dev, sensor depth)."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select, text

from mapfree.data import Dataset
from mapfree.geometry import Pose
from mapfree.service import Limits, Settings, create_app
from mapfree.service.accounts.quota import check_quota
from mapfree.service.database.models import Anchor, User, make_engine, session_factory
from mapfree.service.inputs import UploadError

from .conftest import BACKENDS, create_users, db_url_for
from .test_browser import CHROMIUM, PHONE, _sign_in, browser, phone, shot  # noqa: F401 (fixtures)

METHOD = "sift_pnp_sensor"
SCENE = "s00000"
#: A second photo from the query scan near its end, and queries: one only that photo sees well (the anchor's
#: first photo alone gives no pose for it on this scene), one near the first photo.
SECOND, FAR_QUERY, NEAR_QUERY = "seq1/frame_00022.jpg", "seq1/frame_00024.jpg", "seq1/frame_00010.jpg"
THIRD = "seq1/frame_00005.jpg"  # a third photo, near the first


def _form(K, prefix: str = "") -> dict:
    return {f"{prefix}fx": str(K.fx), f"{prefix}fy": str(K.fy), f"{prefix}cx": str(K.cx), f"{prefix}cy": str(K.cy)}


def _pose_text(p: Pose) -> str:
    q, t = p.qt()
    return " ".join(f"{x:.9f}" for x in [*q, *t])


def _files(frame, key: str = "image", depth_key: str = "depth") -> list:
    return [
        (key, (frame.image_path.name, frame.image_path.read_bytes(), "image/jpeg")),
        (depth_key, (frame.depth_path("sensor").name, frame.depth_path("sensor").read_bytes(), "image/png")),
    ]


def _errors(est: dict, gt: Pose) -> tuple[float, float]:
    pose = Pose(np.array(est["R"]), np.array(est["t"]))
    rot = np.degrees(np.arccos(np.clip((np.trace(pose.R.T @ gt.R) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(pose.center - gt.center)), float(rot)


def _localize(client, aid: str, frame) -> dict:
    r = client.post(
        f"/anchors/{aid}/localize",
        data=_form(frame.intrinsics),
        files={"image": (frame.image_path.name, frame.image_path.read_bytes(), "image/jpeg")},
    )
    assert r.status_code == 200, r.text
    return r.json()


@pytest.fixture(scope="module")
def scene(realmini_dir):
    return Dataset(realmini_dir).scene("val", SCENE)


def test_two_photo_anchor_retrieves_the_right_photo_in_the_anchor_frame(server, scene):
    ref, second = scene.reference, scene.frame(SECOND)
    far, near = scene.frame(FAR_QUERY), scene.frame(NEAR_QUERY)
    with server.client("alice") as alice:
        # one request: photo 0 (the anchor's frame) and photo 1 with its pose relative to photo 0
        r = alice.post(
            "/anchors",
            files=_files(ref) + _files(second, "photo_image", "photo_depth"),
            data={
                **_form(ref.intrinsics),
                **_form(second.intrinsics, "photo_"),
                "photo_pose": _pose_text(second.pose),
                "method": METHOD,
                "name": "office, 2 photos",
            },
        )
        assert r.status_code == 201, r.text
        anchor = r.json()
        assert anchor["num_photos"] == 2 and [p["index"] for p in anchor["photos"]] == [0, 1]
        assert all(p["has_depth"] for p in anchor["photos"]) and anchor["photos"][0]["pose"][0] == 1.0
        assert np.allclose(anchor["photos"][1]["pose"], [float(x) for x in _pose_text(second.pose).split()], atol=1e-6)
        one = alice.post("/anchors", files=_files(ref), data={**_form(ref.intrinsics), "method": METHOD}).json()
        api = alice.get("/openapi.json").json()  # the API docs describe the photo fields and the new endpoint
        assert "post" in api["paths"]["/anchors/{aid}/photos"]
        assert "photo_pose" in str(api["components"]["schemas"])
    with server.client("bob") as bob:
        est = _localize(bob, anchor["id"], far)
        assert est["ok"] and est["photo"] == 1, est
        dist, rot = _errors(est, far.pose)  # ground truth is in the first photo's frame
        assert dist < 0.15 and rot < 5, (dist, rot)
        est = _localize(bob, anchor["id"], near)
        assert est["ok"] and est["photo"] == 0, est
        dist, rot = _errors(est, near.pose)
        assert dist < 0.15 and rot < 5, (dist, rot)
        # the first photo alone does not localize the far query within that error: the second photo is what did
        alone = _localize(bob, one["id"], far)
        assert not alone["ok"] or _errors(alone, far.pose)[0] > 0.5, alone
        assert (
            bob.post(
                f"/anchors/{one['id']}/photos",
                files=_files(second),
                data={**_form(second.intrinsics), "pose": _pose_text(second.pose)},
            ).status_code
            == 403
        )
    with server.client("alice") as alice:
        # growing the single-photo anchor photo by photo gives the same answers (a new version, not the cache)
        r = alice.post(
            f"/anchors/{one['id']}/photos",
            files=_files(second),
            data={**_form(second.intrinsics), "pose": _pose_text(second.pose)},
        )
        assert r.status_code == 201 and r.json()["num_photos"] == 2, r.text
        assert alice.get(f"/anchors/{one['id']}").json()["photos"][1]["has_depth"]
        est = _localize(alice, one["id"], far)
        assert est["ok"] and est["photo"] == 1 and _errors(est, far.pose)[0] < 0.15, est
        # the relocalize page lists the anchor and localizes a query against it (a token needs no CSRF field)
        assert "office, 2 photos · 2 photos · sift_pnp_sensor" in alice.get("/relocalize").text
        r = alice.post(
            "/relocalize/anchor",
            data={"anchor": anchor["id"], **_form(far.intrinsics, "q_")},
            files={"query": (far.image_path.name, far.image_path.read_bytes(), "image/jpeg")},
        )
        assert r.status_code == 200 and "answered by photo 1" in r.text and 'id="figure"' in r.text, r.text[-2000:]
        assert "Pose found" in r.text
        for a in (anchor, one):
            assert alice.delete(f"/anchors/{a['id']}").status_code == 204  # its photos go with it
            assert alice.get(f"/anchors/{a['id']}").status_code == 404


@pytest.mark.parametrize(
    "bad, words",
    [
        ({"photo_pose": "1 0 0 0 0.1 0.2"}, "photo 1 ('frame_00022.jpg'): pose: expected 7 numbers"),
        ({"photo_pose": "2 0 0 0 0.1 0.2 0.3"}, "photo 1 ('frame_00022.jpg'): pose: the quaternion"),
        ({"photo_pose": "1 0 0 0 nan 0 0"}, "photo 1 ('frame_00022.jpg'): pose: every value must be finite"),
        ({"photo_fx": "-5"}, "photo 1 ('frame_00022.jpg'): intrinsics: focal lengths must lie between"),
        ({"photo_cx": "99999"}, "photo 1 ('frame_00022.jpg'): intrinsics: principal point"),
        ({"photo_fy": "abc"}, "photo 1 ('frame_00022.jpg'): intrinsics: fy must be a number"),
    ],
)
def test_a_bad_photo_is_a_422_naming_it(server, scene, bad, words):
    ref, second = scene.reference, scene.frame(SECOND)
    data = {
        **_form(ref.intrinsics),
        **_form(second.intrinsics, "photo_"),
        "photo_pose": _pose_text(second.pose),
        "method": METHOD,
        **bad,
    }
    with server.client("carol") as c:
        r = c.post("/anchors", files=_files(ref) + _files(second, "photo_image", "photo_depth"), data=data)
    assert r.status_code == 422 and words in r.json()["detail"], r.text


def test_photo_fields_must_line_up_and_depth_is_checked_per_photo(server, scene):
    ref, second, third = scene.reference, scene.frame(SECOND), scene.frame(NEAR_QUERY)
    base = {**_form(ref.intrinsics), "method": METHOD}
    two = {k: [v, v] for k, v in _form(second.intrinsics, "photo_").items()}
    pose2 = [_pose_text(second.pose), _pose_text(third.pose)]
    imgs = [("photo_image", (f.image_path.name, f.image_path.read_bytes(), "image/jpeg")) for f in (second, third)]
    with server.client("carol") as c:
        r = c.post("/anchors", files=_files(ref) + imgs, data={**base, **two, "photo_pose": pose2[:1]})
        assert r.status_code == 422 and "photo_pose: 1 value(s) for 2 photo_image" in r.json()["detail"], r.text
        depth1 = [_files(second, depth_key="photo_depth")[1]]
        r = c.post("/anchors", files=_files(ref) + imgs + depth1, data={**base, **two, "photo_pose": pose2})
        assert r.status_code == 422 and "photo_depth: 1 file(s) for 2 photo_image" in r.json()["detail"], r.text
        # the method takes its scale from each photo's depth: the further photos have none
        r = c.post("/anchors", files=_files(ref) + imgs, data={**base, **two, "photo_pose": pose2})
        assert r.status_code == 422 and r.json()["detail"].startswith("photo 1 ('frame_00022.jpg'): method"), r.text
        assert "depth" in r.json()["detail"]
        # a depth map of the wrong size for its photo, and an image that is not one
        wrong = [("photo_depth", ("d.png", ref.depth_path("sensor").read_bytes()[:200], "image/png"))] * 2
        r = c.post("/anchors", files=_files(ref) + imgs + wrong, data={**base, **two, "photo_pose": pose2})
        assert r.status_code == 422 and r.json()["detail"].startswith("photo 1 ('frame_00022.jpg'): depth"), r.text
        r = c.post(
            "/anchors",
            files=_files(ref) + [("photo_image", ("x.jpg", b"not a jpeg", "image/jpeg"))],
            data={**base, **_form(second.intrinsics, "photo_"), "photo_pose": pose2[0]},
        )
        assert r.status_code == 422 and r.json()["detail"].startswith("photo 1 ('x.jpg'): image"), r.text
        # adding a photo: same checks, the photo named by the index it would get
        a = c.post("/anchors", files=_files(ref), data=base).json()
        r = c.post(
            f"/anchors/{a['id']}/photos",
            files=_files(second),
            data={**_form(second.intrinsics), "pose": "0 0 0 0 0 0 0"},
        )
        assert r.status_code == 422 and "photo 1 ('frame_00022.jpg'): pose: the quaternion" in r.json()["detail"]
        r = c.post(
            f"/anchors/{a['id']}/photos",
            files=[_files(second)[0]],
            data={**_form(second.intrinsics), "pose": _pose_text(second.pose)},
        )
        assert r.status_code == 422 and "photo 1" in r.json()["detail"] and "depth" in r.json()["detail"], r.text
        assert c.get(f"/anchors/{a['id']}").json()["num_photos"] == 1  # nothing stored by the refused ones
        assert c.delete(f"/anchors/{a['id']}").status_code == 204


def _make_two_photo_anchor(client, ref, second, name: str = "two") -> dict:
    r = client.post(
        "/anchors",
        files=_files(ref) + _files(second, "photo_image", "photo_depth"),
        data={
            **_form(ref.intrinsics),
            **_form(second.intrinsics, "photo_"),
            "method": METHOD,
            "photo_pose": _pose_text(second.pose),
            "name": name,
        },
    )
    assert r.status_code == 201, r.text
    return r.json()


def _add(client, aid: str, frame, pose: Pose | None = None):
    return client.post(
        f"/anchors/{aid}/photos",
        files=_files(frame),
        data={**_form(frame.intrinsics), "pose": _pose_text(pose or frame.pose)},
    )


def _bytes_of(frame) -> int:
    return len(frame.image_path.read_bytes()) + len(frame.depth_path("sensor").read_bytes())


def test_delete_a_photo_then_localize_uses_the_photos_left(server, scene):
    """``DELETE /anchors/{id}/photos/{k}``: owner only, photo 0 (the anchor's frame) refused with a 409, the
    other indices kept; the next localize never answers from the deleted photo, and its bytes leave the quota."""
    ref, second, third, far = scene.reference, scene.frame(SECOND), scene.frame(THIRD), scene.frame(FAR_QUERY)
    with server.client("alice") as alice, server.client("bob") as bob, server.client() as anon:
        anchor = _make_two_photo_anchor(alice, ref, second)
        aid = anchor["id"]
        assert _add(alice, aid, third).json()["photos"][2]["index"] == 2
        used = alice.get("/api/me").json()["storage_used_bytes"]
        est = _localize(bob, aid, far)
        assert est["ok"] and est["photo"] == 1 and _errors(est, far.pose)[0] < 0.15, est  # prepared and cached
        assert alice.get(f"/anchors/{aid}/photos/1").content == second.image_path.read_bytes()
        assert bob.delete(f"/anchors/{aid}/photos/1").status_code == 403
        assert anon.delete(f"/anchors/{aid}/photos/1").status_code == 401
        r = alice.delete(f"/anchors/{aid}/photos/0")
        assert r.status_code == 409 and "anchor's frame" in r.json()["detail"], r.text
        r = alice.delete(f"/anchors/{aid}/photos/7")
        assert r.status_code == 404 and "has no photo 7 (its photos: 0, 1, 2)" in r.json()["detail"], r.text
        r = alice.delete(f"/anchors/{aid}/photos/1")
        assert r.status_code == 200, r.text
        assert [p["index"] for p in r.json()["photos"]] == [0, 2] and r.json()["num_photos"] == 2
        assert alice.get(f"/anchors/{aid}").json()["photos"][1]["index"] == 2
        assert alice.get(f"/anchors/{aid}/photos/1").status_code == 404
        assert alice.get("/api/me").json()["storage_used_bytes"] == used - _bytes_of(second)
        est = _localize(bob, aid, far)  # the photo that answered is gone: another one answers, or none
        assert est.get("photo", 0) in (0, 2), est
        assert alice.delete(f"/anchors/{aid}/photos/1").status_code == 404
        # the next photo takes the index after the highest one left
        assert [p["index"] for p in _add(alice, aid, second).json()["photos"]] == [0, 2, 3]
        est = _localize(bob, aid, far)
        assert est["ok"] and est["photo"] == 3 and _errors(est, far.pose)[0] < 0.15, est
        # the highest photo deleted: its index is not given again (it used to be: "photo 3" became another photo)
        assert [p["index"] for p in alice.delete(f"/anchors/{aid}/photos/3").json()["photos"]] == [0, 2]
        assert [p["index"] for p in _add(alice, aid, second).json()["photos"]] == [0, 2, 4]
        assert alice.delete(f"/anchors/{aid}/photos/4").status_code == 200
        assert alice.delete(f"/anchors/{aid}").status_code == 204
        assert alice.get("/api/me").json()["storage_used_bytes"] == used - _bytes_of(ref) - _bytes_of(
            second
        ) - _bytes_of(third)


def test_photo_indices_are_never_reused_in_a_database_from_before_the_retired_indices(make_app, scene):  # noqa: F811
    """A database made before ``anchor_retired_indices`` existed gains the table on start (migration 0001), and
    from then on the index of a deleted highest photo is never given again, even to an anchor created before."""
    ref, second, third = scene.reference, scene.frame(SECOND), scene.frame(THIRD)
    app = make_app()
    c, auth = app.client, app.auth("ann")
    c.headers.update(auth)
    aid = _make_two_photo_anchor(c, ref, second)["id"]
    engine = make_engine(app.settings.db_url)
    with engine.begin() as conn:  # what an older version of the service left (from before schema versions)
        conn.execute(text("DROP TABLE anchor_retired_indices"))
        conn.execute(text("DROP TABLE alembic_version"))
    engine.dispose()
    with TestClient(create_app(app.settings), raise_server_exceptions=False, headers=auth) as restarted:
        assert [p["index"] for p in _add(restarted, aid, third).json()["photos"]] == [0, 1, 2]
        assert [p["index"] for p in restarted.delete(f"/anchors/{aid}/photos/2").json()["photos"]] == [0, 1]
        assert [p["index"] for p in restarted.delete(f"/anchors/{aid}/photos/1").json()["photos"]] == [0]
        r = _add(restarted, aid, third)
        assert r.status_code == 201 and [p["index"] for p in r.json()["photos"]] == [0, 3], r.text
        assert r.json()["photos"][1]["pose"] == pytest.approx(
            [float(x) for x in _pose_text(third.pose).split()], abs=1e-6
        )
        assert restarted.get(f"/anchors/{aid}/photos/2").status_code == 404
        assert restarted.delete(f"/anchors/{aid}").status_code == 204
    with TestClient(create_app(app.settings), headers=auth) as again:  # deleting the anchor took its row along
        assert again.get(f"/anchors/{aid}").status_code == 404


def test_another_api_process_never_answers_from_a_deleted_photo(server, scene, realmini_dir):
    """Photo 1 replaced by a photo of another place through the server: an API process that had prepared the
    anchor (the same photo count as now) prepares it again instead of answering from the deleted photo."""
    ref, second, far = scene.reference, scene.frame(SECOND), scene.frame(FAR_QUERY)
    elsewhere = Dataset(realmini_dir).scene("val", "s00001").reference
    other = TestClient(
        create_app(Settings(db_url=server.db_url, data_root=server.data.root, gt_root=server.data.gt)),
        raise_server_exceptions=False,
    )
    other.headers["Authorization"] = f"Bearer {server.tokens['alice']}"
    aid = None
    try:
        with server.client("alice") as alice:
            aid = _make_two_photo_anchor(alice, ref, second, "replaced")["id"]
            est = _localize(other, aid, far)
            assert est["ok"] and est["photo"] == 1 and _errors(est, far.pose)[0] < 0.15, est
            assert alice.delete(f"/anchors/{aid}/photos/1").status_code == 200
            r = _add(alice, aid, elsewhere, Pose.from_qt([1, 0, 0, 0], [0.3, 0, 0]))
            assert r.status_code == 201 and r.json()["num_photos"] == 2, r.text
        est = _localize(other, aid, far)
        assert not (est["ok"] and _errors(est, far.pose)[0] < 0.15), est  # not the stale answer
    finally:
        other.close()
        if aid is not None:
            with server.client("alice") as alice:
                assert alice.delete(f"/anchors/{aid}").status_code == 204


def test_anchor_photos_count_against_the_storage_quota(make_app, scene):  # noqa: F811
    ref, second, third = scene.reference, scene.frame(SECOND), scene.frame(THIRD)
    app = make_app(storage_quota_bytes=_bytes_of(ref) + max(_bytes_of(second), _bytes_of(third)) + 100)
    c, auth = app.client, app.auth("ann")
    r = c.post(
        "/anchors",
        headers=auth,
        files=_files(ref) + _files(second, "photo_image", "photo_depth"),
        data={
            **_form(ref.intrinsics),
            **_form(second.intrinsics, "photo_"),
            "method": METHOD,
            "photo_pose": _pose_text(second.pose),
        },
    )
    assert r.status_code == 201, r.text
    aid = r.json()["id"]
    assert c.get("/api/me", headers=auth).json()["storage_used_bytes"] == _bytes_of(ref) + _bytes_of(second)
    r = c.post(
        f"/anchors/{aid}/photos",
        headers=auth,
        files=_files(third),
        data={**_form(third.intrinsics), "pose": _pose_text(third.pose)},
    )
    assert r.status_code == 413 and "storage quota" in r.json()["detail"] and "anchor photos" in r.json()["detail"]
    assert c.delete(f"/anchors/{aid}/photos/1", headers=auth).status_code == 200  # room again
    r = c.post(
        f"/anchors/{aid}/photos",
        headers=auth,
        files=_files(third),
        data={**_form(third.intrinsics), "pose": _pose_text(third.pose)},
    )
    assert r.status_code == 201, r.text
    assert c.get("/api/me", headers=auth).json()["storage_used_bytes"] == _bytes_of(ref) + _bytes_of(third)


def test_an_upload_that_came_while_the_anchor_was_prepared_counts(make_app, scene):  # noqa: F811
    """The quota is counted again, locked, in the transaction that stores a new anchor: another upload of the
    same account stored while the method prepared the photos (no lock held then) makes this one a 413."""
    ref, second = scene.reference, scene.frame(SECOND)
    app = make_app(storage_quota_bytes=_bytes_of(ref) + _bytes_of(second) + 100)
    c, auth = app.client, app.auth("ann")
    localizers = c.app.state.localizers
    prepare = localizers.check
    engine = make_engine(app.settings.db_url)
    make = session_factory(engine)

    def check_while_another_upload_lands(aid, *args, **kw):
        prepare(aid, *args, **kw)
        with make.begin() as db:  # the other upload: another anchor of ann's, as large as this one
            uid = db.scalar(select(User.id).where(User.name == "ann"))
            db.add(Anchor(user_id=uid, method=METHOD, intrinsics={}, image=b"x" * (_bytes_of(ref) + 50)))

    localizers.check = check_while_another_upload_lands
    try:
        r = c.post("/anchors", headers=auth, files=_files(ref), data={**_form(ref.intrinsics), "method": METHOD})
    finally:
        localizers.check = prepare
    assert r.status_code == 413 and "storage quota" in r.json()["detail"], r.text
    assert c.get("/api/me", headers=auth).json()["storage_used_bytes"] == _bytes_of(ref) + 50  # the other only
    with make() as db:
        assert db.scalar(select(func.count()).select_from(Anchor)) == 1
    engine.dispose()


@pytest.mark.parametrize("backend", BACKENDS)
def test_two_concurrent_uploads_cannot_both_pass_the_quota(backend, tmp_path):
    """``check_quota`` locks the account's writes (PostgreSQL: ``SELECT … FOR UPDATE`` on the user row; SQLite:
    ``BEGIN IMMEDIATE``) until the bytes are stored: a second upload waits, then counts the first and is
    refused. Without the lock both would read the same room on PostgreSQL and both pass."""
    url = db_url_for(backend, tmp_path)
    create_users(url, {"ann": None})
    engine = make_engine(url)
    make = session_factory(engine)
    settings = Settings(db_url=url, storage_quota_bytes=1500)
    first, second = make(), make()
    try:
        uid = first.scalar(select(User.id).where(User.name == "ann"))
        check_quota(first, settings, uid, 1000, "this photo")  # passes; holds the lock until its commit
        outcome: dict = {}

        def other_upload():
            try:
                check_quota(second, settings, uid, 1000, "this photo")
                outcome["passed"] = True
            except UploadError as e:
                outcome["error"] = e
            finally:
                second.rollback()

        t = threading.Thread(target=other_upload)
        t.start()
        t.join(0.5)
        assert t.is_alive() and not outcome, outcome  # waiting for the first upload's transaction
        first.add(Anchor(user_id=uid, method=METHOD, intrinsics={}, image=b"x" * 1000))
        first.commit()
        t.join(30)
        assert not t.is_alive() and "error" in outcome, outcome
        assert outcome["error"].status == 413 and "1000 are stored" in outcome["error"].message
    finally:
        first.close()
        second.close()
        engine.dispose()


def _camera_line(frame, pose: bool) -> str:
    K = frame.intrinsics
    return f"{frame.image_path.name} {K.fx} {K.fy} {K.cx} {K.cy}" + (f" {_pose_text(frame.pose)}" if pose else "")


def _page_files(*frames, depth: bool = True) -> list:
    """The create-anchor form's two multiple file inputs: photos, and depth maps matched by file name."""
    out = [("photos", (f.image_path.name, f.image_path.read_bytes(), "image/jpeg")) for f in frames]
    if depth:
        out += [
            ("depths", (f.depth_path("sensor").name, f.depth_path("sensor").read_bytes(), "image/png")) for f in frames
        ]
    return out


def test_the_relocalize_page_creates_an_anchor_and_adds_and_deletes_photos(server, scene):
    """The page's forms do what the API does, with its limits and messages; a form that fails comes back with
    the error and the values typed."""
    ref, second, third, far = scene.reference, scene.frame(SECOND), scene.frame(THIRD), scene.frame(FAR_QUERY)
    cameras = _camera_line(ref, False) + "\n" + _camera_line(second, True) + "\n"
    html = {"Accept": "text/html"}
    with server.client("alice", headers=html) as alice, server.client("bob", headers=html) as bob:
        form = {"name": "lobby", "method": METHOD, "cameras": cameras}
        for files, data, status, words in (
            (
                _page_files(ref, second, depth=False) + _page_files(ref)[1:],
                form,
                422,
                "photo 1 (&#39;frame_00022.jpg&#39;): method",
            ),  # photo 1 has no depth map
            (
                _page_files(ref, second),
                {**form, "cameras": _camera_line(ref, False) + "\n" + _camera_line(second, False)},
                422,
                "cameras line 2: expected",
            ),
            (
                _page_files(ref, second),
                {**form, "cameras": cameras.replace(_pose_text(second.pose), "2 0 0 0 0.1 0.2 0.3")},
                422,
                "photo 1 (&#39;frame_00022.jpg&#39;): pose: the quaternion",
            ),
            (_page_files(ref), form, 422, "cameras line 2: no chosen photo is named &#39;frame_00022.jpg&#39;"),
            (
                _page_files(ref, second) + [("depths", ("other.png", b"x", "image/png"))],
                form,
                422,
                "depths: &#39;other.png&#39; goes with no chosen photo",
            ),
        ):
            r = alice.post("/relocalize/anchors", files=files, data=data)
            assert r.status_code == status and words in r.text, r.text[-3000:]
            assert 'id="anchor-error" role="alert">' in r.text  # shown above the create form, not hidden
            assert 'value="lobby"' in r.text and data["cameras"].splitlines()[0] in r.text  # values kept
        r = alice.post("/relocalize/anchors", files=_page_files(ref, second), data=form)
        assert r.status_code == 303, r.text[-2000:]
        aid = r.headers["location"].rsplit("/", 1)[1]
        anchor = alice.get(f"/anchors/{aid}").json()
        assert anchor["name"] == "lobby" and anchor["num_photos"] == 2 and anchor["photos"][1]["has_depth"]
        assert np.allclose(anchor["photos"][1]["pose"], [float(x) for x in _pose_text(second.pose).split()], atol=1e-6)
        assert _localize(bob, aid, far)["photo"] == 1
        assert f'href="/relocalize/anchors/{aid}"' in alice.get("/relocalize").text  # listed as hers
        page = alice.get(f"/relocalize/anchors/{aid}").text
        assert 'id="delete-photo-1"' in page and 'id="delete-photo-0"' not in page and 'id="add-photo-form"' in page
        assert 'id="delete-photo-1"' not in bob.get(f"/relocalize/anchors/{aid}").text  # not bob's
        # add a photo: a bad pose keeps the values typed; then a good one
        add = {**_form(third.intrinsics), "pose": "1 0 0"}
        r = alice.post(f"/relocalize/anchors/{aid}/photos", files=_files(third), data=add)
        assert r.status_code == 422 and "photo 2 (&#39;frame_00005.jpg&#39;): pose: expected 7 numbers" in r.text
        assert f'value="{third.intrinsics.fx}"' in r.text and 'value="1 0 0"' in r.text
        r = alice.post(
            f"/relocalize/anchors/{aid}/photos", files=_files(third), data={**add, "pose": _pose_text(third.pose)}
        )
        assert r.status_code == 303 and alice.get(f"/anchors/{aid}").json()["num_photos"] == 3
        # delete: photo 0 refused on the page, bob refused, photo 1 deleted
        r = alice.post(f"/relocalize/anchors/{aid}/photos/0/delete")
        assert r.status_code == 409 and "anchor&#39;s frame" in r.text and 'id="photos"' in r.text
        assert bob.post(f"/relocalize/anchors/{aid}/photos/1/delete").status_code == 403
        assert alice.post(f"/relocalize/anchors/{aid}/photos/1/delete").status_code == 303
        assert [p["index"] for p in alice.get(f"/anchors/{aid}").json()["photos"]] == [0, 2]
        assert _localize(bob, aid, far).get("photo", 0) in (0, 2)
        assert alice.delete(f"/anchors/{aid}", headers={"Accept": "application/json"}).status_code == 204


@pytest.mark.browser
@pytest.mark.skipif(not Path(CHROMIUM).exists(), reason=f"{CHROMIUM} is absent (apt-get install chromium)")
def test_relocalize_page_uses_a_two_photo_anchor_at_phone_width(phone, sqlite_server, scene):  # noqa: F811
    ref, second, far = scene.reference, scene.frame(SECOND), scene.frame(FAR_QUERY)
    with sqlite_server.client("alice") as alice:
        aid = alice.post(
            "/anchors",
            files=_files(ref) + _files(second, "photo_image", "photo_depth"),
            data={
                **_form(ref.intrinsics),
                **_form(second.intrinsics, "photo_"),
                "method": METHOD,
                "photo_pose": _pose_text(second.pose),
                "name": "hall",
            },
        ).json()["id"]
    try:
        _sign_in(phone, sqlite_server, "bob")
        phone.goto("/relocalize")
        phone.select_option("#anchor", aid)
        phone.set_input_files("#anchor-query", str(far.image_path))
        phone.click("#anchor-button")
        phone.wait_for_selector("#figure")
        phone.wait_for_function("() => document.getElementById('figure').naturalWidth > 0")
        assert "answered by photo 1" in phone.inner_text("#anchor-result")
        assert "Pose found" in phone.inner_text("#result")  # intrinsics guessed: a pose, not checked against GT
        assert phone.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
        shot(phone, "phone-relocalize-anchor")
    finally:
        with sqlite_server.client("alice") as alice:
            assert alice.delete(f"/anchors/{aid}").status_code == 204


# ------------------------------------------------------------------- review: hostile indices, counts, names


def _web_session(app) -> tuple[TestClient, str]:
    """A browser-like client of ``app`` signed in as ann (session cookie), and its session's CSRF token."""
    web = TestClient(app.client.app, raise_server_exceptions=False, follow_redirects=False)
    login = web.get("/login").text.split('name="csrf_token" value="')[1].split('"')[0]
    assert web.post("/login", data={"token": app.tokens["ann"], "csrf_token": login}).status_code == 303
    return web, web.get("/relocalize").text.split('name="csrf_token" value="')[1].split('"')[0]


def test_a_photo_index_past_the_database_integer_is_a_422_not_a_500(make_app, scene):  # noqa: F811
    """``GET /anchors/{id}/photos/{k}`` with ``k`` beyond a 64-bit integer used to crash SQLite's driver (a 500);
    an index the database cannot hold is a 422 naming the largest, one it can but the anchor lacks a 404."""
    app = make_app()
    auth = app.auth("ann")
    r = app.client.post(
        "/anchors",
        headers=auth,
        files=_files(scene.reference),
        data={**_form(scene.reference.intrinsics), "method": METHOD},
    )
    assert r.status_code == 201, r.text
    aid = r.json()["id"]
    for k in (2**63, 10**20, 2**31, -1):
        r = app.client.get(f"/anchors/{aid}/photos/{k}", headers=app.auth("ben"))
        assert r.status_code == 422 and "k: Input should be" in r.json()["detail"], (k, r.text)
        assert app.client.delete(f"/anchors/{aid}/photos/{k}", headers=auth).status_code == 422
    k = 2**31 - 1
    r = app.client.get(f"/anchors/{aid}/photos/{k}", headers=app.auth("ben"))
    assert r.status_code == 404 and f"has no photo {k}" in r.json()["detail"], (k, r.text)
    assert app.client.delete(f"/anchors/{aid}/photos/{k}", headers=auth).status_code == 404
    assert (
        app.client.get(f"/anchors/{aid}/photos/0", headers=app.auth("ben")).content
        == scene.reference.image_path.read_bytes()
    )


def test_too_many_photos_are_refused_before_any_is_decoded(make_app):  # noqa: F811
    """The photo limit is checked before reading the photos (API and page): a small PNG can decode to tens of
    MB, and a 64 MB request holds a thousand of them. Unreadable photos show the count is checked first."""
    app = make_app(limits=Limits(max_anchor_photos=3))
    junk = b"not an image"
    n = 4
    files = [("image", ("p0.png", junk, "image/png"))] + [
        ("photo_image", (f"p{i}.png", junk, "image/png")) for i in range(1, n)
    ]
    cam = {"fx": "1", "fy": "1", "cx": "1", "cy": "1"}
    data = {**cam, **{f"photo_{k}": [v] * (n - 1) for k, v in cam.items()}, "photo_pose": ["1 0 0 0 0 0 0"] * (n - 1)}
    r = app.client.post("/anchors", headers=app.auth("ann"), files=files, data=data)
    assert r.status_code == 413 and "at most 3 photos; got 4" in r.json()["detail"], r.text
    web, csrf = _web_session(app)
    cameras = "p0.png 1 1 1 1\n" + "".join(f"p{i}.png 1 1 1 1 1 0 0 0 0 0 0\n" for i in range(1, n))
    r = web.post(
        "/relocalize/anchors",
        files=[("photos", (f"p{i}.png", junk, "image/png")) for i in range(n)],
        data={"cameras": cameras, "csrf_token": csrf},
    )
    assert r.status_code == 413 and "at most 3 photos; got 4" in r.text, r.text[-2000:]


def test_a_depth_map_whose_name_fits_two_photos_is_refused(make_app, scene):  # noqa: F811
    """The page matches depth maps by the name before the first dot: with photos ``frame.jpg`` and
    ``frame.png``, ``frame.sensor.png`` used to go silently to the last one chosen."""
    import cv2

    ref = scene.reference
    K = ref.intrinsics
    ok, png = cv2.imencode(".png", cv2.imread(str(ref.image_path)))
    assert ok
    app = make_app()
    web, csrf = _web_session(app)
    files = [
        ("photos", ("frame.jpg", ref.image_path.read_bytes(), "image/jpeg")),
        ("photos", ("frame.png", png.tobytes(), "image/png")),
        ("depths", ("frame.sensor.png", ref.depth_path("sensor").read_bytes(), "image/png")),
    ]
    cameras = f"frame.jpg {K.fx} {K.fy} {K.cx} {K.cy}\nframe.png {K.fx} {K.fy} {K.cx} {K.cy} 1 0 0 0 0.1 0 0\n"
    r = web.post("/relocalize/anchors", files=files, data={"cameras": cameras, "method": METHOD, "csrf_token": csrf})
    assert r.status_code == 422, r.text[-2000:]
    assert "depths: &#39;frame.sensor.png&#39; could go with any of &#39;frame.jpg&#39;, &#39;frame.png&#39;" in r.text


def test_a_photo_is_decoded_without_holding_the_database_write_lock(make_app, scene, monkeypatch):  # noqa: F811
    """Adding a photo decodes up to 16 MB; on SQLite every transaction is the database's write lock, so it must not
    be held meanwhile (every other writer would wait). Checked from a second connection during the decode."""
    import sqlite3

    import mapfree.service.anchors.domain as api

    ref, second = scene.reference, scene.frame(SECOND)
    app = make_app()
    c, auth = app.client, app.auth("ann")
    r = c.post("/anchors", headers=auth, files=_files(ref), data={**_form(ref.intrinsics), "method": METHOD})
    assert r.status_code == 201, r.text
    aid = r.json()["id"]
    db_file = app.settings.db_url.removeprefix("sqlite:///")
    seen, decode = [], api.photo_upload

    def probing_decode(*args, **kw):
        other = sqlite3.connect(db_file, timeout=0.05)
        try:
            other.execute("BEGIN IMMEDIATE")
            other.execute("ROLLBACK")
            seen.append("free")
        except sqlite3.OperationalError as e:  # "database is locked"
            seen.append(str(e))
        finally:
            other.close()
        return decode(*args, **kw)

    monkeypatch.setattr(api, "photo_upload", probing_decode)
    r = c.post(
        f"/anchors/{aid}/photos",
        headers=auth,
        files=_files(second),
        data={**_form(second.intrinsics), "pose": _pose_text(second.pose)},
    )
    assert r.status_code == 201, r.text
    assert seen == ["free"] and [p["index"] for p in r.json()["photos"]] == [0, 1]


def test_bytes_after_a_jpegs_end_are_not_stored_or_served(server, realmini_dir):
    """Phones append a motion photo's MP4 clip or a vendor trailer after the JPEG's end-of-image marker; those
    bytes used to be stored and served to every other user. Now the stored photo ends at the marker, baseline
    and progressive alike, its pixels unchanged."""
    import io

    import cv2
    from PIL import Image

    from mapfree.data import Dataset
    from mapfree.service.anchors.exif import clean_photo

    ref = Dataset(realmini_dir).scene("val", "s00000").reference
    trailer = b"\x00\x00\x00\x18ftypmp42" + b"MotionPhoto_Data SECRET-CLIP " * 50 + b"\xff\xd9tail"
    baseline = ref.image_path.read_bytes()
    progressive = io.BytesIO()
    Image.open(ref.image_path).save(progressive, format="JPEG", progressive=True, quality=90)
    for jpeg in (baseline, progressive.getvalue()):
        assert jpeg.endswith(b"\xff\xd9")
        cleaned = clean_photo(jpeg + trailer)
        assert cleaned == jpeg  # cut at the marker, nothing re-encoded
        decode = lambda b: cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_COLOR)  # noqa: E731
        assert np.array_equal(decode(cleaned), decode(jpeg))
    K = ref.intrinsics
    with server.client("alice") as c:
        r = c.post(
            "/anchors",
            files={
                "image": ("ref.jpg", baseline + trailer, "image/jpeg"),
                "depth": ("ref.png", ref.depth_path("sensor").read_bytes(), "image/png"),
            },
            data={"fx": str(K.fx), "fy": str(K.fy), "cx": str(K.cx), "cy": str(K.cy), "method": "sift_pnp_sensor"},
        )
        assert r.status_code == 201, r.text
        served = c.get(f"/anchors/{r.json()['id']}/photos/0").content
        assert served == baseline  # the photo byte for byte (it has no metadata), without the trailer
        assert c.delete(f"/anchors/{r.json()['id']}").status_code == 204
