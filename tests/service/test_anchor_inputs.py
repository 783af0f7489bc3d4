"""What ``POST /anchors`` refuses, with a 422 or 413 naming the problem (never a 500): hostile images, depth maps and
intrinsics, a method that names a file, a method that cannot run here."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from sqlalchemy import select

from .conftest import png_of as _png

IMAGE_CASES = {
    "corrupt image": (lambda: b"\xff\xd8\xff\xe0" + b"\0" * 100, {}, 422, "image"),
    "not an image": (lambda: b"GIF89a not really", {}, 422, "image"),
    "truncated png": (lambda: _png(64, 64)[:60], {}, 422, "image"),
    "decompression bomb": (lambda: _png(5000, 5000, 1), {}, 413, "pixels"),
    "negative focal": (lambda: _png(48, 64), {"fx": -5}, 422, "focal"),
    "nan focal": (lambda: _png(48, 64), {"fx": "nan"}, 422, "finite"),
    "text focal": (lambda: _png(48, 64), {"fx": "abc"}, 422, "fx"),
    "missing intrinsics": (lambda: _png(48, 64), {"cy": None}, 422, "cy"),
}


@pytest.mark.parametrize("case", list(IMAGE_CASES))
def test_hostile_images(server, case):
    build, override, status, words = IMAGE_CASES[case]
    form = {"fx": 50, "fy": 50, "cx": 32, "cy": 24, **override}
    form = {k: str(v) for k, v in form.items() if v is not None}
    with server.client("alice") as c:
        r = c.post("/anchors", files={"image": ("a.png", build())}, data=form)
    assert r.status_code == status, (case, r.status_code, r.text)
    assert words.lower() in r.json()["detail"].lower(), r.json()


def test_depth_must_match_the_image(server):
    with server.client("alice") as c:
        r = c.post(
            "/anchors",
            files={"image": ("a.png", _png(48, 64)), "depth": ("d.png", _png(10, 10, 1, np.uint16))},
            data={"fx": 50, "fy": 50, "cx": 32, "cy": 24},
        )
        assert r.status_code == 422 and "must match" in r.json()["detail"]
        r = c.post(
            "/anchors",
            files={"image": ("a.png", _png(48, 64)), "depth": ("d.png", b"junk")},
            data={"fx": 50, "fy": 50, "cx": 32, "cy": 24},
        )
        assert r.status_code == 422 and "depth" in r.json()["detail"]
        r = c.post(
            "/anchors",
            files={"image": ("a.png", _png(48, 64))},
            data={"fx": 50, "fy": 50, "cx": 32, "cy": 24, "method": "no_such_method"},
        )
        assert r.status_code == 422 and "method" in r.json()["detail"]


def _jpg(h: int, w: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", np.full((h, w, 3), 7, np.uint8))
    assert ok
    return buf.tobytes()


DEPTH_CASES = {
    "jpeg depth": ({"depth": ("d.jpg", lambda: _jpg(48, 64))}, {}, "PNG"),
    "8-bit rgb png depth": ({"depth": ("d.png", lambda: _png(48, 64))}, {}, "16-bit"),
    "8-bit gray png depth": ({"depth": ("d.png", lambda: _png(48, 64, 1))}, {}, "16-bit"),
    "16-bit rgb png depth": ({"depth": ("d.png", lambda: _png(48, 64, 3, np.uint16))}, {}, "single-channel"),
    "huge focal": ({}, {"fx": "1e308"}, "focal"),
    "focal too long": ({}, {"fy": "6401"}, "focal"),
    "principal point outside": ({}, {"cx": "-1"}, "principal point"),
    "principal point far": ({}, {"cy": "90"}, "principal point"),
    "no depth for a depth method": ({"depth": None}, {"method": "sift_pnp_sensor"}, "depth"),
}


@pytest.mark.parametrize("case", list(DEPTH_CASES))
def test_depth_and_intrinsics_are_checked(server, case):
    files_over, form_over, words = DEPTH_CASES[case]
    files = {"image": ("a.png", _png(48, 64)), "depth": ("d.png", _png(48, 64, 1, np.uint16))}
    for k, v in files_over.items():
        if v is None:
            files.pop(k)
        else:
            files[k] = (v[0], v[1]())
    form = {"fx": "50", "fy": "50", "cx": "32", "cy": "24", "method": "sift_pnp_sensor", **form_over}
    with server.client("alice") as c:
        r = c.post("/anchors", files=files, data=form)
    assert r.status_code == 422, (case, r.text)
    assert words.lower() in r.json()["detail"].lower(), r.json()


def test_method_cannot_read_or_probe_server_files(server, tmp_path):
    secret = tmp_path / "secrets.yaml"
    secret.write_text("aws_secret_key: AKIA123\ndb_password: hunter2\n")
    form = {"fx": "50", "fy": "50", "cx": "32", "cy": "24"}
    answers = []
    with server.client("alice") as c:
        for method in (
            str(secret),
            str(tmp_path / "missing.yaml"),
            "/proc/self/environ",
            "/etc/hostname",
            "secrets.yaml",
            "../../etc/passwd",
            "sift_pnp_hf:/tmp",
            "best-offline@hf:/tmp",
        ):
            r = c.post("/anchors", files={"image": ("a.png", _png(48, 64))}, data={**form, "method": method})
            assert r.status_code == 422, (method, r.text)
            detail = r.json()["detail"]
            for leak in ("aws_secret_key", "db_password", "not found", "unknown key", "line ", "No such file"):
                assert leak not in detail, (method, detail)
            assert "best-offline" in detail and "allowed" in detail, detail
            answers.append(detail.replace(method[:64], "M"))
    assert len(set(answers)) == 1, answers  # an existing path and a missing one get the same answer


def test_anchor_whose_method_cannot_run_is_refused_at_creation(server):
    from mapfree import matching

    if "loftr" in matching.available():
        pytest.skip("LoFTR weights are installed here")
    with server.client("alice") as c:
        r = c.post(
            "/anchors",
            files={"image": ("a.png", _png(48, 64)), "depth": ("d.png", _png(48, 64, 1, np.uint16))},
            data={"fx": "50", "fy": "50", "cx": "32", "cy": "24", "method": "loftr_emat_sensor"},
        )
    assert r.status_code == 422, r.text
    assert "loftr_outdoor.ckpt" in r.json()["detail"] and "/root" not in r.json()["detail"], r.json()


def test_operator_methods_folder_and_old_anchors_whose_method_cannot_run(make_app, tmp_path):
    """Methods from ``--methods-dir`` are offered by name (a broken file is skipped, not fatal); an anchor stored
    before this check whose method cannot run here is a 422 at localize time, not a 500."""
    from mapfree import matching
    from mapfree.service.database.models import Anchor, User

    folder = tmp_path / "methods"
    folder.mkdir()
    (folder / "site-sift.yaml").write_text("extends: sift_pnp_sensor\ndescription: the operator's choice\n")
    (folder / "broken.yaml").write_text("aws_secret_key: x\n")
    app = make_app(methods_dir=folder)
    form = {"fx": "50", "fy": "50", "cx": "32", "cy": "24"}
    files = {"image": ("a.png", _png(48, 64)), "depth": ("d.png", _png(48, 64, 1, np.uint16))}
    r = app.client.post("/anchors", headers=app.auth("ann"), files=files, data={**form, "method": "site-sift"})
    assert r.status_code == 201 and r.json()["method"] == "site-sift", r.text
    r = app.client.post("/anchors", headers=app.auth("ann"), files=files, data={**form, "method": "broken"})
    assert r.status_code == 422 and "aws_secret_key" not in r.json()["detail"], r.text
    if "loftr" in matching.available():
        return
    with app.client.app.state.sessions.begin() as db:
        user = db.scalar(select(User).where(User.name == "ann"))
        old = Anchor(
            user_id=user.id,
            method="loftr_emat_sensor",
            image=_png(48, 64),
            intrinsics={**{k: float(v) for k, v in form.items()}, "width": 64, "height": 48},
        )
        db.add(old)
    r = app.client.post(
        f"/anchors/{old.id}/localize", headers=app.auth("ben"), files={"image": ("q.png", _png(48, 64))}, data=form
    )
    assert r.status_code == 422 and "loftr_outdoor.ckpt" in r.json()["detail"], r.text
