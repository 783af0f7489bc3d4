"""``mapfree match`` on a real realmini-dev pair: the same .npz keys for every matcher (SIFT, XFeat, a tiny
SuperGlue saved here), keypoints in original pixels, a one-line summary, the drawing, and clear errors."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch

import mapfree.matching as M
from mapfree.cli import main
from mapfree.matching.export import NPZ_KEYS, load_npz

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def images(realmini):
    scene = realmini / "val" / "s00000"
    return scene / "seq0" / "frame_00000.jpg", scene / "seq1" / "frame_00010.jpg"


@pytest.fixture(scope="module")
def superglue_dir(tmp_path_factory):
    from test_hub_matchers import tiny_superglue

    d = tmp_path_factory.mktemp("sg") / "superglue_outdoor"
    tiny_superglue(0).save_pretrained(d)
    return d


def run_match(capsys, *argv: str) -> tuple[int, str, str]:
    rc = main(["match", *map(str, argv)])
    out = capsys.readouterr()
    return rc, out.out, out.err


@pytest.mark.parametrize(
    "matcher, extra",
    [
        ("sift", ()),
        ("xfeat", ("--option", "top_k=1000", "--device", "cpu")),
        ("superglue", ("--option", "match_threshold=0", "--device", "cpu")),
    ],
)
def test_every_matcher_writes_the_same_keys(matcher, extra, images, superglue_dir, tmp_path, capsys):
    if matcher == "superglue":
        extra = (*extra, "--option", f"weights={superglue_dir}")
    out = tmp_path / "m.npz"
    rc, stdout, err = run_match(capsys, *images, "--matcher", matcher, "-o", out, *extra)
    assert rc == 0, err
    d = load_npz(out)
    assert list(d) == list(NPZ_KEYS)
    n = len(d["kpts0"])
    assert n > 0 and d["kpts0"].shape == d["kpts1"].shape == (n, 2) and d["scores"].shape == (n,)
    assert d["kpts0"].dtype == d["kpts1"].dtype == d["scores"].dtype == np.float32
    assert str(d["matcher"]) == matcher and str(d["image0"]) == str(images[0]) and str(d["image1"]) == str(images[1])
    w, h = d["size0"]
    assert (w, h) == (540, 360) and tuple(d["size1"]) == (540, 360)
    for k in (d["kpts0"], d["kpts1"]):
        assert np.all((k >= -0.5) & (k <= [w - 0.5, h - 0.5]))
    assert np.all(np.isfinite(d["scores"])) and float(d["seconds"]) > 0
    line = stdout.strip()
    assert "\n" not in line and line.startswith(f"{matcher}: {n} matches") and str(out) in line


def test_sift_file_holds_what_the_matcher_finds(images, tmp_path, capsys):
    from mapfree.data import read_image

    out, viz = tmp_path / "sub" / "sift.npz", tmp_path / "sift.png"
    rc, _, err = run_match(capsys, *images, "-o", out, "--viz", viz)  # sift is the default
    assert rc == 0, err
    mt = M.create("sift")
    im0, im1 = (read_image(p) for p in images)
    m = mt.match(mt.extract(im0), mt.extract(im1))
    d = load_npz(out)
    np.testing.assert_allclose(d["kpts0"], m.kpts0, atol=1e-4)
    np.testing.assert_allclose(d["kpts1"], m.kpts1, atol=1e-4)
    np.testing.assert_allclose(d["scores"], m.scores, rtol=1e-6)
    drawing = cv2.imread(str(viz))
    assert drawing.shape == (360, 1080, 3)  # the two images side by side


def test_errors_are_one_line_naming_the_problem(images, tmp_path, capsys, monkeypatch):
    rc, _, err = run_match(capsys, *images, "--matcher", "superglu")
    assert rc == 1 and "did you mean 'superglue'" in err
    bad = tmp_path / "broken.jpg"
    bad.write_bytes(b"not a jpeg")
    rc, _, err = run_match(capsys, images[0], bad)
    assert rc == 1 and str(bad) in err and "decode" in err
    rc, _, err = run_match(capsys, images[0], tmp_path / "missing.png")
    assert rc == 1 and "missing.png" in err
    rc, _, err = run_match(capsys, *images, "--option", "nonsense=1")
    assert rc == 1 and "nonsense" in err and "sift" in err
    rc, _, err = run_match(capsys, *images, "--option", "novalue")
    assert rc == 1 and "KEY=VALUE" in err
    monkeypatch.setenv("MAPFREE_OFFLINE", "1")
    monkeypatch.setenv(M.WEIGHTS_ENV, str(tmp_path / "empty"))
    import huggingface_hub.constants as hf

    monkeypatch.setattr(hf, "HF_HUB_CACHE", str(tmp_path / "hf"))
    rc, _, err = run_match(capsys, *images, "--matcher", "efficientloftr")
    assert rc == 1 and "zju-community/efficientloftr" in err and M.WEIGHTS_ENV in err
    assert len(err.strip().splitlines()) == 1


def test_list_methods_has_the_new_presets(capsys):
    assert main(["run", "--list-methods"]) == 0
    rows = dict(line.split(None, 1) for line in capsys.readouterr().out.splitlines())
    for n in (
        "superglue_emat_dptkitti",
        "superglue_pnp_dptkitti",
        "superglue-indoor_emat_dptnyu",
        "superglue_pnp_sensor",
        "efficientloftr_emat_dptkitti",
        "efficientloftr_pnp_sensor",
    ):
        assert n in rows
    assert "magic-leap-community/superglue_outdoor" in rows["superglue_emat_dptkitti"]
    assert (
        "superglue_indoor" in rows["superglue-indoor_emat_dptnyu"]
        and "dptnyu.png" in rows["superglue-indoor_emat_dptnyu"]
    )
    assert "zju-community/efficientloftr" in rows["efficientloftr_pnp_sensor"]
    assert rows["sift_emat_none"].startswith("nothing")


def test_the_command_module_imports_nothing_heavy():
    code = (
        "import sys, mapfree.cli.match; "
        "print(sorted(m for m in ('torch', 'cv2', 'mapfree.matching', 'transformers') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_viz_checks_the_matches_with_each_photos_intrinsics(images, realmini, tmp_path, capsys):
    """--viz colours the matches by an essential-matrix check, which needs intrinsics: given with --K-ref/--K-query,
    else the photo's EXIF focal length (phone-style copies stored sideways: drawn upright, about the same matches
    pass), else the default camera; a principal point far outside the image is refused before any matching."""
    import re

    from cli_support import FOCAL_35MM, phone_jpeg
    from mapfree.data import read_image, read_intrinsics

    K = read_intrinsics(realmini / "val" / "s00000" / "intrinsics.txt")["seq0/frame_00000.jpg"]
    flag = f"{K.fx},{K.fy},{K.cx},{K.cy}"
    viz = tmp_path / "m.png"
    rc, out, err = run_match(capsys, *images, "--viz", viz, "--K-ref", flag, "--K-query", flag)
    assert rc == 0, err
    given = int(re.search(r"\((\d+) pass the check, intrinsics given/given\)$", out.strip())[1])
    n = int(re.match(r"sift: (\d+) matches", out)[1])
    assert 0.5 * n < given <= n
    drawing = cv2.cvtColor(cv2.imread(str(viz)), cv2.COLOR_BGR2RGB).reshape(-1, 3).astype(int)
    green = (drawing[:, 1] > 150) & (drawing[:, 0] < 100) & (drawing[:, 2] < 100)
    assert drawing.shape[0] == 360 * 1080 and green.sum() > 1000
    phones = [tmp_path / "a.jpg", tmp_path / "b.jpg"]
    for src, dst, o in zip(images, phones, (6, 8)):
        phone_jpeg(dst, read_image(src), o, {FOCAL_35MM: 33})
    rc, out, err = run_match(capsys, *phones, "--viz", viz)
    exif = int(re.search(r"\((\d+) pass the check, intrinsics exif/exif\)$", out.strip())[1])
    assert rc == 0 and abs(exif - given) <= 0.1 * given, (out, given)
    assert cv2.imread(str(viz)).shape == (360, 1080, 3)  # upright, as every reader of ours returns it
    rc, out, err = run_match(capsys, *images, "--viz", viz, "--K-query", "500,500,270,-1000")
    assert rc == 1 and not out
    assert err.strip() == (
        "mapfree match: error: --K-query: principal point cy = -1000 is far outside the 540x360 image "
        "(allowed -180 to 540; the image centre is 179.5)"
    )
