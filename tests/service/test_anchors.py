"""The relocalization API over real HTTP with real photos (realmini-dev, metric sensor depth)."""

from __future__ import annotations

import numpy as np

from mapfree.data import Dataset
from mapfree.geometry import Pose

METHOD = "sift_pnp_sensor"


def _form(K) -> dict:
    return {"fx": str(K.fx), "fy": str(K.fy), "cx": str(K.cx), "cy": str(K.cy)}


def test_anchor_lifecycle_and_localize(server, realmini_dir):
    scene = Dataset(realmini_dir).scene("val", "s00000")
    ref, query = scene.reference, scene.frame("seq1/frame_00009.jpg")
    with server.client("alice") as alice:
        r = alice.post(
            "/anchors",
            files={
                "image": ("ref.jpg", ref.image_path.read_bytes(), "image/jpeg"),
                "depth": ("ref.png", ref.depth_path("sensor").read_bytes(), "image/png"),
            },
            data={**_form(ref.intrinsics), "method": METHOD, "name": "office"},
        )
        assert r.status_code == 201, r.text
        anchor = r.json()
        assert anchor["has_depth"] and anchor["method"] == METHOD
        assert alice.get(f"/anchors/{anchor['id']}").json()["name"] == "office"
    with server.client("bob") as bob:  # any signed-in user can localize against alice's anchor
        r = bob.post(
            f"/anchors/{anchor['id']}/localize",
            files={"image": ("q.jpg", query.image_path.read_bytes(), "image/jpeg")},
            data=_form(query.intrinsics),
        )
        assert r.status_code == 200, r.text
        est = r.json()
        assert est["ok"], est
        pose = Pose(np.array(est["R"]), np.array(est["t"]))
        gt = query.pose  # world = reference camera in val scenes
        assert np.linalg.norm(pose.center - gt.center) < 0.25
        assert np.degrees(np.arccos(np.clip((np.trace(pose.R.T @ gt.R) - 1) / 2, -1, 1))) < 5
        assert est["confidence"] > 0 and est["timings"]["total"] > 0 and est["num_matches"] >= est["inliers"]
        # a photo of something else: a clean "no estimate" (or a low-confidence one), never an error
        other = Dataset(realmini_dir).scene("val", "s00001").reference
        r = bob.post(
            f"/anchors/{anchor['id']}/localize",
            files={"image": ("o.jpg", other.image_path.read_bytes(), "image/jpeg")},
            data=_form(other.intrinsics),
        )
        assert r.status_code == 200 and isinstance(r.json()["ok"], bool)
        assert bob.delete(f"/anchors/{anchor['id']}").status_code == 403
        assert (
            bob.post(
                "/anchors/nope/localize",
                files={"image": ("q.jpg", query.image_path.read_bytes())},
                data=_form(query.intrinsics),
            ).status_code
            == 404
        )
    with server.client("alice") as alice:
        assert alice.delete(f"/anchors/{anchor['id']}").status_code == 204
        assert alice.get(f"/anchors/{anchor['id']}").status_code == 404


def test_anchor_default_method_is_the_registry_preset(server, realmini_dir):
    from mapfree.service.anchors.localizers import default_method

    ref = Dataset(realmini_dir).scene("val", "s00001").reference
    with server.client("carol") as c:
        r = c.post(
            "/anchors",
            files={
                "image": ("ref.jpg", ref.image_path.read_bytes(), "image/jpeg"),
                "depth": ("ref.png", ref.depth_path("sensor").read_bytes(), "image/png"),
            },
            data=_form(ref.intrinsics),
        )
        assert r.status_code == 201, r.text
        assert r.json()["method"] == default_method() and r.json()["has_depth"]
        assert c.delete(f"/anchors/{r.json()['id']}").status_code == 204
        # the default preset takes its scale from the anchor's depth: without one it could never localize
        r = c.post(
            "/anchors",
            files={"image": ("ref.jpg", ref.image_path.read_bytes(), "image/jpeg")},
            data=_form(ref.intrinsics),
        )
        assert r.status_code == 422 and "depth" in r.json()["detail"], r.text
        r = c.post(
            "/anchors",
            files={"image": ("ref.jpg", ref.image_path.read_bytes(), "image/jpeg")},
            data={**_form(ref.intrinsics), "method": "sift_emat_none"},
        )
        assert r.status_code == 201 and not r.json()["has_depth"], r.text
        assert c.delete(f"/anchors/{r.json()['id']}").status_code == 204


def test_needs_reference_depth_one_definition_two_questions():
    """Files-depth methods need the reference's map for their scale; ``scale_free_too`` adds the depth-free
    PnP/Procrustes methods, which cannot give any pose without one (they use an uploaded map when given)."""
    from mapfree import methods
    from mapfree.service.anchors.localizers import needs_reference_depth

    table = {  # name: (for the metric scale, for any pose at all)
        "sift_pnp_sensor": (True, True),
        "sift_emat_sensor": (True, True),
        "sift_pnp_none": (False, True),
        "sift_procrustes_none": (False, True),
        "sift_emat_none": (False, False),
        "xfeat_pnp_dpt-kitti": (False, False),
        "rpr-3d3d": (False, False),
    }
    for name, (scale, any_pose) in table.items():
        assert needs_reference_depth(name, scale_free_too=False) is scale, name
        assert needs_reference_depth(methods.get(name), scale_free_too=True) is any_pose, name


def test_scale_free_pnp_anchor_needs_depth_and_the_try_page_runs_it_without(server, realmini_dir):
    scene = Dataset(realmini_dir).scene("val", "s00000")
    ref, query = scene.reference, scene.frame("seq1/frame_00009.jpg")
    image = ("ref.jpg", ref.image_path.read_bytes(), "image/jpeg")
    with server.client("carol") as c:
        r = c.post("/anchors", files={"image": image}, data={**_form(ref.intrinsics), "method": "sift_pnp_none"})
        assert r.status_code == 422 and "depth" in r.json()["detail"], r.text  # it could never localize
        r = c.post(
            "/anchors",
            files={"image": image, "depth": ("d.png", ref.depth_path("sensor").read_bytes(), "image/png")},
            data={**_form(ref.intrinsics), "method": "sift_pnp_none"},
        )
        assert r.status_code == 201, r.text
        est = c.post(
            f"/anchors/{r.json()['id']}/localize",
            data=_form(query.intrinsics),
            files={"image": ("q.jpg", query.image_path.read_bytes(), "image/jpeg")},
        ).json()
        assert (
            est["ok"] and np.linalg.norm(Pose(np.array(est["R"]), np.array(est["t"])).center - query.pose.center) < 0.25
        ), est  # metric: the anchor's depth
        assert c.delete(f"/anchors/{r.json()['id']}").status_code == 204
        pair = {"reference": image, "query": ("q.jpg", query.image_path.read_bytes(), "image/jpeg")}
        form = {
            **{f"ref_{k}": v for k, v in _form(ref.intrinsics).items()},
            **{f"q_{k}": v for k, v in _form(query.intrinsics).items()},
        }
        r = c.post("/relocalize", files=pair, data={**form, "method": "sift_pnp_sensor"})
        assert r.status_code == 422 and "needs the reference depth" in r.text  # refused before anything runs
        r = c.post("/relocalize", files=pair, data={**form, "method": "sift_pnp_none"})
        assert r.status_code == 200 and 'id="no-estimate"' in r.text  # one-off pair: runs, shows why no pose


def test_phone_photos_without_intrinsics_take_their_exif_focal_or_the_default(make_app, realmini_dir):
    """Intrinsics fields are optional: an anchor photo and a query stored sideways by a phone (EXIF orientation 6
    and 35 mm-equivalent focal) get the calibrated focal of the upright photo from EXIF, the pose is the
    calibrated one's, and each response says where the intrinsics came from; a query without tags takes the
    default camera; three of the four fields is still a 422."""
    import io

    import cv2

    from cli_support import FOCAL_35MM, phone_jpeg, stored_grid
    from mapfree.data import read_image

    scene = Dataset(realmini_dir).scene("val", "s00000")
    ref, query = scene.reference, scene.frame("seq1/frame_00009.jpg")

    def phone(frame, tags, orientation=6) -> bytes:
        buf = io.BytesIO()
        phone_jpeg(buf, read_image(frame.image_path), orientation, tags)
        return buf.getvalue()

    ok, png = cv2.imencode(".png", stored_grid(cv2.imread(str(ref.depth_path("sensor")), cv2.IMREAD_UNCHANGED), 6))
    assert ok
    app = make_app()
    second = scene.frame("seq1/frame_00001.jpg")  # a further photo, without tags or fields: the default camera
    files = [
        ("image", ("ref.jpg", phone(ref, {FOCAL_35MM: 33}), "image/jpeg")),
        ("depth", ("d.png", png.tobytes())),
        ("photo_image", ("p1.jpg", phone(second, {}, 1))),
        ("photo_depth", ("p1.png", second.depth_path("sensor").read_bytes())),
    ]
    data = {"method": METHOD, "photo_pose": " ".join(map(str, np.concatenate(second.pose.qt())))}
    r = app.client.post("/anchors", headers=app.auth("ann"), files=files, data=data)
    assert r.status_code == 201, r.text
    anchor = r.json()
    photo = anchor["photos"][0]
    assert [p["intrinsics_source"] for p in anchor["photos"]] == ["exif", "default"]
    assert anchor["photos"][1]["intrinsics"]["fx"] == 0.8 * 540
    assert (photo["intrinsics"]["width"], photo["intrinsics"]["height"]) == (540, 360)
    assert (
        photo["intrinsics"]["fx"] == np.float64(33 / 36 * 540)
        and abs(photo["intrinsics"]["fx"] / ref.intrinsics.fx - 1) < 2e-3
    )
    url = f"/anchors/{anchor['id']}/localize"
    r = app.client.post(url, headers=app.auth("ann"), files={"image": ("q.jpg", phone(query, {FOCAL_35MM: 33}, 8))})
    est = r.json()
    assert r.status_code == 200 and est["ok"] and est["intrinsics_source"] == "exif", est
    pose = Pose(np.array(est["R"]), np.array(est["t"]))
    assert np.linalg.norm(pose.center - query.pose.center) < 0.25
    r = app.client.post(url, headers=app.auth("ann"), files={"image": ("q.jpg", phone(query, {}, 1))})
    assert r.status_code == 200 and r.json()["intrinsics_source"] == "default", r.text
    r = app.client.post(
        url, headers=app.auth("ann"), files={"image": ("q.jpg", phone(query, {}))}, data={"fx": 1, "fy": 1, "cx": 1}
    )
    assert r.status_code == 422 and "cy must be a number" in r.json()["detail"], r.text
    r = app.client.post(
        url, headers=app.auth("ann"), files={"image": ("q.jpg", phone(query, {}))}, data=_form(query.intrinsics)
    )
    assert r.json()["intrinsics_source"] == "given"
