"""Per-anchor calibration in the relocalization API, on real photos (realmini-dev, sensor depth): an anchor uses
its method's shipped calibration, or the ``.calib.json`` files its owner uploads (checked as ``mapfree run
--calibration`` checks them), and an ``accept`` threshold; its answers' ``p_correct`` is the one the Python API
gives for the same pair with the same file.

The files in ``data/`` were fitted by ``mapfree calibrate realmini-dev --method M -o M.calib.json`` (no preset
ships one for ``sift_pnp_sensor``; the shipped ``sift_procrustes_sensor`` one was fitted on more frames).
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from mapfree import methods
from mapfree.calibration import Calibration, shipped
from mapfree.data import Dataset
from mapfree.relocalize import build_localizer
from mapfree.relocalize.cascade import STAGE_CALIBRATIONS

DATA = Path(__file__).parent / "data"
SIFT = "sift_pnp_sensor"
SIFT_CAL = DATA / f"{SIFT}.calib.json"


def _form(K) -> dict:
    return {"fx": str(K.fx), "fy": str(K.fy), "cx": str(K.cx), "cy": str(K.cy)}


def _photo(frame, depth: bool) -> list:
    files = [("image", ("photo.jpg", frame.image_path.read_bytes(), "image/jpeg"))]
    if depth:
        files.append(("depth", ("photo.png", frame.depth_path("sensor").read_bytes(), "image/png")))
    return files


def _cal_part(name: str, content: bytes) -> tuple:
    return ("calibration", (name, content, "application/json"))


@pytest.fixture(scope="module")
def ref_scene(realmini_dir):
    return Dataset(realmini_dir).scene("val", "s00000")


@pytest.fixture(scope="module")
def scene(ref_scene):
    return ref_scene.reference, ref_scene.frame("seq1/frame_00000.jpg")  # SIFT + PnP: right, p 0.67


def test_uploaded_calibration_gives_the_python_apis_p_correct(make_app, scene):
    ref, query = scene
    app = make_app()
    ann = app.auth("ann")
    r = app.client.post(
        "/anchors", headers=ann, files=_photo(ref, True), data={**_form(ref.intrinsics), "method": SIFT}
    )
    assert r.status_code == 201, r.text
    anchor = r.json()
    assert anchor["calibrations"] == [{"method": SIFT, "source": "none", "name": None, "frames": None, "ece": None}]
    assert anchor["accept"] is None
    url = f"/anchors/{anchor['id']}"
    localize = {"files": _photo(query, False), "data": _form(query.intrinsics)}
    est = app.client.post(url + "/localize", headers=ann, **localize).json()
    assert est["ok"] and not {"p_correct", "calibration", "accepted"} & set(est), est  # none shipped for SIFT + PnP

    r = app.client.put(
        url + "/calibration",
        headers=ann,
        files=[_cal_part("mine.calib.json", SIFT_CAL.read_bytes())],
        data={"accept": "0.5"},
    )
    assert r.status_code == 200, r.text
    cal = Calibration.load(SIFT_CAL, SIFT)
    assert r.json()["calibrations"] == [
        {
            "method": SIFT,
            "source": "uploaded",
            "name": "mine.calib.json",
            "frames": cal.frames,
            "ece": pytest.approx(cal.figures["p_correct"]["ece"]),
        }
    ]
    assert r.json()["accept"] == 0.5
    ben = app.auth("ben")  # anyone signed in localizes with the anchor's calibration
    est = app.client.post(url + "/localize", headers=ben, **localize).json()
    api = build_localizer(SIFT, calibration=SIFT_CAL).relocalize(ref, query)
    assert est["ok"] and api.ok and est["calibration"] == "uploaded"
    assert est["signals"] == pytest.approx(api.signals.to_dict()) and est["confidence"] == pytest.approx(api.confidence)
    assert est["p_correct"] == pytest.approx(api.p_correct, abs=1e-9)
    assert est["p_correct"] == pytest.approx(cal.p_correct(est["signals"], est["confidence"]), abs=1e-12)
    assert 0.5 < est["p_correct"] < 1 and est["accepted"] is True

    # the threshold is the anchor's: above this answer's probability it is refused
    high = min(1.0, est["p_correct"] + 1e-3)
    r = app.client.put(
        url + "/calibration",
        headers=ann,
        files=[_cal_part("mine.calib.json", SIFT_CAL.read_bytes())],
        data={"accept": str(high)},
    )
    assert r.status_code == 200 and r.json()["accept"] == high
    again = app.client.post(url + "/localize", headers=ann, **localize).json()
    assert again["p_correct"] == pytest.approx(est["p_correct"]) and again["accepted"] is False

    # it survives a restart: another app process on the same database
    with TestClient(__import__("mapfree.service", fromlist=["create_app"]).create_app(app.settings)) as other:
        got = other.get(url, headers=ann).json()
        assert got["calibrations"][0]["source"] == "uploaded" and got["accept"] == high
        assert other.post(url + "/localize", headers=ann, **localize).json()["p_correct"] == pytest.approx(
            est["p_correct"]
        )

    # no file: the method's shipped calibration again (none for this method), no threshold
    r = app.client.put(url + "/calibration", headers=ann, data={"csrf_token": ""})
    assert r.status_code == 200 and r.json()["calibrations"][0]["source"] == "none" and r.json()["accept"] is None
    assert "p_correct" not in app.client.post(url + "/localize", headers=ann, **localize).json()


def test_bad_calibration_uploads_are_one_clear_4xx(make_app, scene, realmini_dir):
    ref, _ = scene
    app = make_app()
    ann = app.auth("ann")
    r = app.client.post(
        "/anchors", headers=ann, files=_photo(ref, True), data={**_form(ref.intrinsics), "method": SIFT}
    )
    url = f"/anchors/{r.json()['id']}/calibration"
    good = json.loads(SIFT_CAL.read_text())
    cases = [
        (shipped("best-offline-pnp").read_bytes(), "fitted for method 'best-offline-pnp', not 'sift_pnp_sensor'"),
        (json.dumps({**good, "version": 0}).encode(), "has format version 0, this mapfree reads version 1"),
        (SIFT_CAL.read_bytes()[:200], "is not readable JSON"),
        (json.dumps({**good, "models": {}}).encode(), "is corrupt: missing 'p_correct'"),
        (b"\xff\xfe\x00garbage", "is not readable JSON"),
    ]
    for content, message in cases:
        r = app.client.put(url, headers=ann, files=[_cal_part("x.calib.json", content)])
        assert r.status_code == 422, r.text
        assert r.json()["detail"].startswith("calibration: calibration x.calib.json") and message in r.json()["detail"]
    two = [_cal_part("a.json", SIFT_CAL.read_bytes()), _cal_part("b.json", SIFT_CAL.read_bytes())]
    r = app.client.put(url, headers=ann, files=two)
    assert r.status_code == 422 and "two files for method 'sift_pnp_sensor'" in r.json()["detail"]
    for bad in ("1.5", "-0.1", "nan"):
        r = app.client.put(url, headers=ann, data={"accept": bad})
        assert r.status_code == 422, (bad, r.text)
    r = app.client.put(url, headers=app.auth("ben"), files=[_cal_part("x.json", SIFT_CAL.read_bytes())])
    assert r.status_code == 403 and "owner" in r.json()["detail"]
    assert app.client.put("/anchors/nope/calibration", headers=ann).status_code == 404
    # refused at creation too, before any photo is prepared; nothing stored
    r = app.client.post(
        "/anchors",
        headers=ann,
        files=[*_photo(ref, True), _cal_part("x.calib.json", shipped("best-offline-pnp").read_bytes())],
        data={**_form(ref.intrinsics), "method": SIFT},
    )
    assert r.status_code == 422 and "fitted for method 'best-offline-pnp'" in r.json()["detail"]
    assert r.json()["detail"].count("\n") == 0


def test_shipped_calibration_by_default_and_per_stage_in_a_cascade(make_app, scene, ref_scene):
    """The default is the method's shipped calibration; a cascade anchor takes an uploaded file for one stage and
    keeps the shipped one of the other, and its answer's p_correct is the answering stage's."""
    ref, query = scene
    app = make_app()
    ann = app.auth("ann")
    r = app.client.post(
        "/anchors", headers=ann, files=_photo(ref, True), data={**_form(ref.intrinsics), "method": "best-offline-pnp"}
    )
    assert r.status_code == 201, r.text
    entry = r.json()["calibrations"]
    cal = Calibration.load(shipped("best-offline-pnp"), "best-offline-pnp")
    assert entry == [
        {
            "method": "best-offline-pnp",
            "source": "shipped",
            "name": "best-offline-pnp.calib.json",
            "frames": cal.frames,
            "ece": pytest.approx(cal.figures["p_correct"]["ece"]),
        }
    ]
    est = app.client.post(
        f"/anchors/{r.json()['id']}/localize", headers=ann, files=_photo(query, False), data=_form(query.intrinsics)
    ).json()
    api = build_localizer("best-offline-pnp", calibration=shipped("best-offline-pnp")).relocalize(ref, query)
    assert est["ok"] and est["calibration"] == "shipped" and "accepted" not in est
    assert est["p_correct"] == pytest.approx(api.p_correct, abs=1e-9)
    assert est["p_correct"] == pytest.approx(cal.p_correct(est["signals"], est["confidence"]), abs=1e-12)

    # a cascade: an uploaded file for its first stage (fitted on realmini-dev), the shipped one for its second; on
    # this frame the uploaded file says 0.86 where the shipped one says 0.25, so the first stage answers alone
    proc, hard = "sift_procrustes_sensor", ref_scene.frame("seq1/frame_00002.jpg")
    mine = DATA / f"{proc}.calib.json"
    files = [*_photo(ref, True), _cal_part("proc.calib.json", mine.read_bytes())]
    form = {**_form(ref.intrinsics), "method": f"{proc}+best-offline-pnp", "accept": "0.9"}
    r = app.client.post("/anchors", headers=ann, files=files, data=form)
    assert r.status_code == 201, r.text
    assert [(c["method"], c["source"]) for c in r.json()["calibrations"]] == [
        (proc, "uploaded"),
        ("best-offline-pnp", "shipped"),
    ]
    est = app.client.post(
        f"/anchors/{r.json()['id']}/localize", headers=ann, files=_photo(hard, True), data=_form(hard.intrinsics)
    ).json()
    assert est["ok"] and est["stage"] == proc and est["calibration"] == "uploaded", est
    assert [k for k in est["timings"] if k.startswith("stage:")] == [f"stage:{proc}"]
    cascade = methods.get(form["method"])
    files_option = {STAGE_CALIBRATIONS: {proc: str(mine)}}
    expected = build_localizer(replace(cascade, options={**cascade.options, **files_option})).relocalize(ref, hard)
    assert expected.stage == proc and est["p_correct"] == pytest.approx(expected.p_correct, abs=1e-9)
    alone = {f: build_localizer(proc, calibration=f).relocalize(ref, hard).p_correct for f in (mine, shipped(proc))}
    assert est["p_correct"] == pytest.approx(alone[mine], abs=1e-9)
    assert alone[shipped(proc)] < 0.8 <= alone[mine] < 0.9 and est["accepted"] is False
