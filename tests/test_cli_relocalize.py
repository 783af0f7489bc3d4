"""``mapfree relocalize``: bad inputs in one line, no estimate as exit 3, the default method's fallback to PnP, the JSON
and the figure's headline."""

from __future__ import annotations

import json

from cli_support import one_line as _one_line
from cli_support import query_pair as _pair
from mapfree.cli import main
from mapfree.data import read_image


def test_relocalize_bad_inputs_are_one_line_and_no_estimate_is_exit_3(synth, tmp_path, capfd):
    from mapfree.cli import main

    scene = synth / "val" / "s00000"
    ref, q = str(scene / "seq0/frame_00000.jpg"), str(scene / "seq1/frame_00005.jpg")
    empty = tmp_path / "empty.jpg"
    empty.write_bytes(b"")
    K = "200,200,120,160"
    assert main(["relocalize", ref, str(empty), "--method", "sift_pnp_sensor", "--K-ref", K, "--K-query", K]) == 1
    err = capfd.readouterr().err
    assert f"{empty}: image file is empty" in err and "Traceback" not in err and "buf.empty" not in err
    assert main(["relocalize", ref, q, "--method", "sift_pnp_sensor", "--intrinsics", "nosuch.txt"]) == 1
    assert "intrinsics file nosuch.txt not found" in capfd.readouterr().err
    cfg = tmp_path / "typo.yaml"
    cfg.write_text("extends: sift_emat_sensor\nmatcher_opts: {max_featurs: 1000}\n")
    assert main(["relocalize", ref, q, "--method", str(cfg)]) == 1
    err = capfd.readouterr().err
    assert "typo.yaml" in err and "max_featurs" in err and "Traceback" not in err
    # A missing depth map: our one line, without OpenCV's "[ WARN ] can't open/read file" before it.
    assert main(["relocalize", ref, q, "--method", "sift_pnp_sensor", "--depth-ref", str(tmp_path / "no.png")]) == 1
    err = capfd.readouterr().err
    assert err.strip() == f"mapfree relocalize: error: {tmp_path / 'no.png'}: depth image not found", err
    # Ran, but no estimate (a featureless grey query): exit 3, the JSON says why.
    import cv2
    import numpy as np

    grey = tmp_path / "grey.png"
    cv2.imwrite(str(grey), np.full(read_image(ref).shape, 127, np.uint8))
    assert main(["relocalize", ref, str(grey), "--method", "sift_pnp_sensor", "--K-query", K]) == 3
    res = capfd.readouterr()
    assert json.loads(res.out)["ok"] is False and "no estimate" in res.err
    assert main(["relocalize", ref, q, "--method", "sift_pnp_sensor"]) == 0


def test_relocalize_default_method_falls_back_to_pnp_for_a_query_without_depth(synth, tmp_path, capsys):
    """The default best-offline (Procrustes: depth at both images) on a query without a depth map: the PnP twin,
    with the reference's metric depth, as the service answers a plain photo (was: no estimate)."""
    import shutil

    from mapfree.cli import main
    from mapfree.data import Dataset

    scene = Dataset(synth).scene("val", "s00000")
    q = scene.queries[5]
    bare = tmp_path / "photo.jpg"
    shutil.copy(q.image_path, bare)  # no photo.sensor.png beside it
    K = q.intrinsics
    k = f"{K.fx},{K.fy},{K.cx},{K.cy}"
    rc = main(["relocalize", str(scene.reference.image_path), str(bare), "--K-query", k, "--K-ref", k])
    res = capsys.readouterr()
    assert rc == 0, res.err
    out = json.loads(res.out)
    assert out["ok"] and out["method"] == "best-offline+pnp" and "runs with PnP" in res.err
    gt = q.pose @ scene.reference.pose.inverse()
    import numpy as np

    assert np.linalg.norm(np.array(out["center"]) - gt.center) < 0.1  # metric: the reference's depth
    # PnP without any depth source and no map given: refused with the reason.
    ref = str(scene.reference.image_path)
    assert main(["relocalize", ref, str(q.image_path), "--method", "sift_pnp_none"]) == 1
    assert "needs a depth map of the reference" in capsys.readouterr().err


def test_relocalize_refuses_an_unknown_depth_suffix(synth, capfd):
    """`--method sift_pnp_sensr` ran and answered exit 3 "no depth for the reference image"."""
    a, b = _pair(synth)
    assert main(["relocalize", a, b, "--method", "sift_pnp_sensr"]) == 1
    out, line = _one_line(capfd)
    assert not out and "reads depth maps *.sensr.png" in line and "depth suffixes there: sensor" in line, line


def test_the_figure_headline_gives_the_json_inliers(synth, tmp_path, capfd, monkeypatch):
    """The --viz headline said "387 matches, 303 consistent" beside "inliers": 296 in the JSON of the same call."""
    import mapfree.viz as viz

    drawn: list[str] = []
    real = viz._label
    monkeypatch.setattr(viz, "_label", lambda img, text, row=0: (drawn.append(text), real(img, text, row)))
    a, b = _pair(synth)
    assert main(["relocalize", a, b, "--method", "sift_pnp_sensor", "--viz", str(tmp_path / "f.jpg")]) == 0
    res = json.loads(capfd.readouterr().out)
    head = next(t for t in drawn if " matches, " in t)
    assert f"{res['inliers']} solver inliers" in head and "green: " in head, head
    assert (tmp_path / "f.jpg").read_bytes()[:3] == b"\xff\xd8\xff"  # the name's format


def test_same_viewpoint_is_in_the_relocalize_json(synth, capfd):
    a, _ = _pair(synth)
    assert main(["relocalize", a, a, "--method", "sift_pnp_sensor"]) == 0
    res = json.loads(capfd.readouterr().out)
    assert res["same_viewpoint"] is True and res["ok"]
