"""What a newcomer's first hour ran into: each defect and friction item, reproduced on small synthetic or real data,
with the clear error (naming the file, the option, the flag) or the honest exit status it now gets."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mapfree.data import FormatError, read_image
from mapfree.relocalize import run_split

SYNTH_ARGS = ["--size", "240x320", "--no-mono", "--quiet"]


@pytest.fixture(scope="module")
def synth(synth_val) -> Path:
    """A small synthetic val split: two scenes of 10 queries, sensor depth (suffix ``sensor``); read-only."""
    return synth_val


# --------------------------------------------------------------------------- defect 1: 0-byte / corrupt image


@pytest.mark.parametrize("content", [b"", b"\xff\xd8\xff\xe0 truncated"])
def test_empty_or_corrupt_image_names_the_file(tmp_path, content):
    bad = tmp_path / "empty.jpg"
    bad.write_bytes(content)
    with pytest.raises(FormatError, match="empty.jpg"):
        read_image(bad)


def test_empty_image_in_a_dataset_fails_with_its_name(synth, tmp_path):
    import shutil

    root = tmp_path / "data"
    shutil.copytree(synth / "val" / "s00000", root / "val" / "s00000")
    (root / "val" / "s00000" / "seq1" / "frame_00005.jpg").write_bytes(b"")
    res = run_split(root, "val", "sift_pnp_sensor", tmp_path / "sub.zip", progress=False)
    failures = [json.loads(x) for x in res.failures.read_text().splitlines()]
    reason = next(f["reason"] for f in failures if f["frame"] == "seq1/frame_00005.jpg")
    assert "frame_00005.jpg" in reason and "empty" in reason and "buf.empty" not in reason


# --------------------------------------------------------------------------- defect 2: misspelt option in a YAML


def test_misspelt_yaml_option_names_the_file_and_suggests(synth, tmp_path):
    cfg = tmp_path / "typo.yaml"
    cfg.write_text("extends: sift_emat_sensor\nmatcher_opts: {max_featurs: 1000}\n")
    with pytest.raises(ValueError, match=r"typo\.yaml.*max_featurs.*did you mean 'max_features'"):
        run_split(synth, "val", str(cfg), tmp_path / "sub.zip", progress=False)
    assert not (tmp_path / "sub.journal.jsonl").exists()  # refused before any work
    cfg.write_text("extends: sift_emat_sensor\nsolver_opts: {ransac_treshold_px: 2}\n")
    with pytest.raises(ValueError, match=r"solver_opts\.ransac_treshold_px.*'ransac_threshold_px'"):
        run_split(synth, "val", str(cfg), tmp_path / "sub.zip", progress=False)


def test_shipped_method_configs_pass_the_option_check():
    from mapfree.methods import config_dirs, get

    files = [p for d in config_dirs() for p in d.glob("*.yaml")]
    assert files
    for p in files:
        get(str(p))


# --------------------------------------------------------------------------- defect 4: unknown scene names


def test_unknown_scene_names_are_refused_with_suggestions(synth, tmp_path):
    with pytest.raises(ValueError, match=r"no scene s0009 \(did you mean s0000"):
        run_split(synth, "val", "sift_pnp_sensor", tmp_path / "a.zip", scenes=["s00001", "s0009"], progress=False)
    assert not (tmp_path / "a.zip").exists()
    res = run_split(synth, "val", "sift_pnp_sensor", tmp_path / "b.zip", scenes=["s00001"], progress=False)
    assert res.scenes == 1


# --------------------------------------------------------------------------- defect 6: resume after the data changed


def test_resume_recomputes_a_scene_whose_data_changed(synth, tmp_path, capsys):
    import shutil

    from mapfree.data import Dataset, read_intrinsics, read_poses, write_intrinsics, write_poses
    from mapfree.relocalize import read_journal

    root = tmp_path / "data"
    shutil.copytree(synth, root)
    out = tmp_path / "sub.zip"
    first = run_split(root, "val", "sift_pnp_sensor", out, all_frames=True, progress=False)
    assert first.computed == 20 and first.stale_scenes == []
    # s00001 "regenerated" with 5 queries fewer: its journaled frames no longer describe it.
    scene = root / "val" / "s00001"
    poses, intr = read_poses(scene / "poses.txt"), read_intrinsics(scene / "intrinsics.txt")
    write_poses(scene / "poses.txt", poses.names[:6], [poses.pose(i) for i in range(6)])
    write_intrinsics(scene / "intrinsics.txt", {n: intr[n] for n in poses.names[:6]})
    again = run_split(root, "val", "sift_pnp_sensor", out, all_frames=True, resume=True, progress=False)
    assert again.stale_scenes == ["s00001"]
    assert again.skipped == 10 and again.computed == 5  # s00000 kept, s00001 recomputed on its new frames
    frames = {(r["scene"], r["frame"]) for r in read_journal(again.journal)[1]}
    now = {("s00001", f.name) for f in Dataset(root).scene("val", "s00001").queries}
    assert {f for f in frames if f[0] == "s00001"} == now and len(frames) == 15
    # Nothing changed since: a plain resume recomputes nothing.
    third = run_split(root, "val", "sift_pnp_sensor", out, all_frames=True, resume=True, progress=False)
    assert third.computed == 0 and third.skipped == 15 and third.stale_scenes == []
    # A re-rendered image (new bytes, new mtime) is a change too; the CLI says which scene it recomputes.
    import os

    from mapfree.cli import main

    img = root / "val" / "s00000" / "seq1" / "frame_00003.jpg"
    st = img.stat()
    os.utime(img, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert main(["run", str(root), "--method", "sift_pnp_sensor", "-o", str(out), "--all-frames", "--resume",
                 "--no-progress"]) == 0
    res = capsys.readouterr()
    assert "the data of s00000 changed" in res.err and "10 computed, 5 from the journal" in res.out


# --------------------------------------------------------------------------- defect 7: depth network not available


def test_unavailable_depth_network_is_refused_before_any_work(synth, tmp_path, monkeypatch):
    from mapfree.depth.hf import MissingModelError

    monkeypatch.setenv("MAPFREE_OFFLINE", "1")
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "empty-cache"))  # nothing cached
    import huggingface_hub.constants as hc

    monkeypatch.setattr(hc, "HF_HUB_CACHE", str(tmp_path / "empty-cache"))
    out = tmp_path / "sub.zip"
    with pytest.raises(MissingModelError, match="huggingface-cli download"):
        run_split(synth, "val", "sift_pnp_dav2-indoor", out, progress=False)
    assert not out.exists() and not (tmp_path / "sub.journal.jsonl").exists()


# --------------------------------------------------------------------------- scenes.png


def _visible_labels(axis, renderer):
    lo, hi = axis.get_view_interval()
    return [t for t in axis.get_ticklabels(minor=False) + axis.get_ticklabels(minor=True)
            if t.get_text() and lo <= t.get_position()[axis is axis.axes.yaxis] <= hi]


def test_scene_scatter_tick_labels_never_overlap_and_empty_scenes_are_named(realmini):
    """Per-scene medians over 2-3 decades once labelled 0.3 and 0.4 (300, 400) on top of each other; a scene
    without any estimate vanished from the figure without a word."""
    import copy

    import numpy as np

    from mapfree.benchmark import evaluate
    from mapfree.benchmark.plots import scene_scatter_figure
    from mapfree.geometry import Pose

    gt = {}
    for d in sorted((realmini / "val").iterdir())[:3]:
        from mapfree.data import read_poses

        t = read_poses(d / "poses.txt")
        gt[d.name] = [(n, Pose(t.pose(i).R, t.pose(i).t + 0.3), 1.0) for i, n in enumerate(t.names)
                      if n.startswith("seq1/")]
    base = evaluate(gt, realmini, "val")
    rng = np.random.default_rng(0)
    for trial in range(12):
        report = copy.copy(base)
        lo_r, lo_t = 10 ** rng.uniform(-1.5, 1), 10 ** rng.uniform(-2, 0)
        report.per_scene = {f"s{i:05d}": {"Average Median Rotation Error": lo_r * 10 ** rng.uniform(0, 2.6),
                                          "Average Median Translation Error": lo_t * 10 ** rng.uniform(0, 2.6),
                                          "Precision @ VCRE < 90px": 0.5} for i in range(16)}
        fig = scene_scatter_figure(report)
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        for axis in (fig.axes[0].xaxis, fig.axes[0].yaxis):
            labels = _visible_labels(axis, renderer)
            boxes = [t.get_window_extent(renderer) for t in labels]
            clash = [(a.get_text(), b.get_text()) for i, a in enumerate(labels) for j, b in enumerate(labels)
                     if i < j and boxes[i].overlaps(boxes[j])]
            assert len(labels) >= 2 and not clash, clash
    fig = scene_scatter_figure(base)  # realmini has 4 val scenes: the 4th got no estimate
    missing = sorted(set(base.per_scene) - set(gt))
    assert missing
    texts = [t.get_text() for t in fig.axes[0].texts] + [fig.axes[0].get_title()]
    assert any(all(s in t for s in missing) for t in texts), texts
    assert f"3 of {len(base.per_scene)} scenes" in fig.axes[0].get_title()


# --------------------------------------------------------------------------- print(Estimate)


def test_estimate_prints_in_one_short_line():
    import numpy as np

    from mapfree.estimate import Estimate
    from mapfree.geometry import Pose

    R = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    est = Estimate(Pose(R, np.array([0.1, -0.2, 1.5])), 12.5, 140, extras={"matches": np.zeros((4000, 4))})
    text = str(est)
    assert "\n" not in text and len(text) < 120, text
    assert "90.00 deg" in text and "1.500" in text and "inliers 140" in text
    failed = Estimate.failure("no depth for the query image")
    assert str(failed) == "Estimate(no estimate: no depth for the query image)"


# --------------------------------------------------------------------------- --references K beyond the mapping frames


def test_more_references_than_mapping_frames_is_refused_up_front(synth, tmp_path):
    from mapfree.relocalize.references import with_references

    out = tmp_path / "k10.zip"
    with pytest.raises(ValueError, match=r"--references 10 needs 10 posed seq0.*s00000 \(1\), s00001 \(1\)"):
        run_split(synth, "val", with_references("sift_pnp_sensor", 10), out, progress=False)
    with pytest.raises(ValueError, match=r"triangulation needs 2 posed seq0"):
        run_split(synth, "val", with_references("sift_emat_none", 2, "triangulation"), out, progress=False)
    assert not out.exists() and not (tmp_path / "k10.journal.jsonl").exists()


# --------------------------------------------------------------------------- mapfree run: exit codes, output, --viz


def test_run_exit_codes_summary_table_and_viz(synth, tmp_path, capsys):
    from mapfree.cli import main

    out, viz = tmp_path / "sub.zip", tmp_path / "viz"
    rc = main(["run", str(synth), "--method", "sift_pnp_sensor", "-o", str(out), "--no-progress", "--evaluate",
               "--viz", str(viz)])
    res = capsys.readouterr()
    assert rc == 0, res.err
    assert res.out.startswith(f"wrote {out}: ") and "AUC @ VCRE < 90px" in res.out  # evaluate's table, not JSON
    figs = sorted(p.relative_to(viz).as_posix() for p in viz.rglob("*.jpg"))
    assert figs == [f"{s}/seq1_frame_{i:05d}.jpg" for s in ("s00000", "s00001") for i in (0, 5)], figs
    import cv2

    img = cv2.imread(str(viz / "s00000" / "seq1_frame_00005.jpg"))
    assert img.shape[:2] == (2 * 320 + 6, 2 * 240)  # matches above the AR check, reference | query in each
    # --json: the summary and the scores as JSON.
    assert main(["run", str(synth), "--method", "sift_pnp_sensor", "-o", str(out), "--no-progress", "--resume",
                 "--evaluate", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["skipped"] == 4 and "AUC @ VCRE < 90px" in data["metrics"]


def test_run_exit_3_when_nothing_or_not_everything_is_estimated(synth, tmp_path, capsys):
    import shutil

    from mapfree.cli import main

    root = tmp_path / "data"
    shutil.copytree(synth, root)
    for p in (root / "val" / "s00001" / "seq1").glob("*.sensor.png"):
        p.unlink()  # s00001's queries lose their depth: Procrustes cannot solve them
    args = ["run", str(root), "--method", "sift_procrustes_sensor", "--no-progress"]
    assert main([*args, "-o", str(tmp_path / "a.zip")]) == 0  # s00000 estimated
    assert main([*args, "-o", str(tmp_path / "b.zip"), "--strict"]) == 3
    assert "2 frame(s) without an estimate" in capsys.readouterr().err
    assert main([*args, "-o", str(tmp_path / "c.zip"), "--scenes", "s00001"]) == 3
    err = capsys.readouterr().err
    assert "no frame got an estimate" in err and "c.failures.jsonl" in err
    assert (tmp_path / "c.zip").is_file()  # the (empty) submission is still written


def test_run_cli_errors_are_exit_1_with_one_line(synth, tmp_path, capsys):
    from mapfree.cli import main

    base = ["run", str(synth), "--method", "sift_pnp_sensor", "--no-progress", "-o", str(tmp_path / "x.zip")]
    assert main([*base, "--scenes", "s0009"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("mapfree run: error: the val split has no scene s0009") and "Traceback" not in err
    assert main([*base, "--references", "3"]) == 1
    assert "--references 3 needs 3 posed seq0" in capsys.readouterr().err
    (tmp_path / "afile").write_text("")
    assert main([*base, "--viz", str(tmp_path / "afile")]) == 1
    assert "not a folder" in capsys.readouterr().err
    assert main([*base]) == 0
    capsys.readouterr()
    assert main([*base]) == 1  # the journal holds results: the message names the flags, not Python
    err = capsys.readouterr().err
    assert "--resume" in err and "--overwrite" in err and "resume=True (" not in err


def test_every_method_in_the_run_help_exists():
    """`mapfree run --help` showed `--method configs/methods/best-offline.yaml`, a file that did not exist."""
    import re

    from mapfree.cli import build_parser
    from mapfree.methods import get

    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction").choices
    root = Path(__file__).resolve().parents[1]
    for name in ("run", "relocalize"):
        for method in re.findall(r"--method (\S+)", sub[name].format_help().split("examples:")[1]):
            get(str(root / method) if method.endswith(".yaml") else method)


# --------------------------------------------------------------------------- mapfree relocalize


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


def test_figure_of_a_method_without_matches_has_no_matches_panel(synth):
    """A regression method (RPR) has no correspondences: its --viz showed an empty "0 matches" panel."""
    from mapfree.data import Dataset
    from mapfree.estimate import Estimate
    from mapfree.viz import estimate_figure

    scene = Dataset(synth).scene("val", "s00000")
    ref, q = scene.reference, scene.queries[5]
    rel = q.pose @ ref.pose.inverse()
    args = (ref.image(), q.image(), ref.intrinsics, q.intrinsics)
    h, w = ref.image().shape[:2]
    regression = estimate_figure(*args, Estimate(rel, 1.0), rel, title="rpr")
    assert regression.shape[:2] == (h, 2 * w)  # the AR check alone
    from mapfree.matching.base import Matches

    import numpy as np

    k = np.array([[10.0, 10.0], [50.0, 60.0]])
    matched = estimate_figure(*args, Estimate(rel, 1.0, extras={"matches": Matches(k, k + 1, np.ones(2))}), rel)
    assert matched.shape[:2] == (2 * h + 6, 2 * w)


# --------------------------------------------------------------------------- mapfree evaluate


@pytest.fixture(scope="module")
def run_with_viz(synth, tmp_path_factory):
    """A run of the synthetic split with its figures (``run --viz``)."""
    from mapfree.cli import main

    d = tmp_path_factory.mktemp("runviz")
    assert main(["run", str(synth), "--method", "sift_pnp_sensor", "-o", str(d / "sub.zip"), "--no-progress",
                 "--viz", str(d / "viz")]) == 0
    return d


def _embedded_pictures(page: str) -> list[bytes]:
    """The plots (PNG) and the frames' figures (JPEG) embedded in a report page, in page order."""
    import base64
    import re

    return [base64.b64decode(b) for b in re.findall(r'src="data:image/(?:png|jpeg);base64,([^"]+)"', page)]


def test_evaluate_html_report_is_self_contained(synth, run_with_viz, tmp_path, capsys):
    import re

    from mapfree.cli import main

    sub, viz = run_with_viz / "sub.zip", run_with_viz / "viz"
    page_path = tmp_path / "out" / "report.html"
    assert main(["evaluate", str(sub), "--dataset", str(synth), "--html", str(page_path), "--viz", str(viz)]) == 0
    page = page_path.read_text()
    assert "AUC @ VCRE &lt; 90px" in page and "s00000" in page and "s00001" in page  # tables
    assert not re.search(r'(src|href)="(?!data:)', page)  # nothing fetched from elsewhere
    pics = _embedded_pictures(page)
    assert len(pics) == 3 + 4 and all(p.startswith(b"\x89PNG") for p in pics[:3])  # 3 plots, 4 scored frames
    assert all(p.startswith(b"\xff\xd8\xff") for p in pics[3:])  # the frames as JPEG
    # The worst frames' pictures are the run's own figures (matches + AR check), byte for byte (small enough).
    figs = {p.read_bytes() for p in viz.rglob("*.jpg")}
    assert set(pics[3:]) == figs
    # Without the run's figures, the AR check is drawn from the dataset's images.
    assert main(["evaluate", str(sub), "--dataset", str(synth), "--html", str(tmp_path / "r2.html")]) == 0
    pics2 = _embedded_pictures((tmp_path / "r2.html").read_text())
    assert len(pics2) == 7 and not set(pics2[3:]) & figs
    capsys.readouterr()


def test_evaluate_exit_codes_plots_file_and_track_mixup(synth, run_with_viz, tmp_path, capsys):
    from mapfree.benchmark import write_submission
    from mapfree.cli import main

    sub = run_with_viz / "sub.zip"
    base = ["evaluate", str(sub), "--dataset", str(synth)]
    (tmp_path / "afile").write_text("")
    assert main([*base, "--plots", str(tmp_path / "afile")]) == 1
    err = capsys.readouterr().err
    assert err.strip() == f"mapfree evaluate: error: --plots {tmp_path / 'afile'}: not a folder (it names a file)"
    assert main([*base, "--strict"]) == 0  # every scored frame estimated, no problem
    capsys.readouterr()
    write_submission(tmp_path / "empty.zip", {})
    assert main(["evaluate", str(tmp_path / "empty.zip"), "--dataset", str(synth)]) == 3
    assert "no scored frame has an estimate" in capsys.readouterr().err
    # A multi-frame submission scored on the single-frame track: said, not silent zeros.
    multi = tmp_path / "multi.zip"
    assert main(["run", str(synth), "--track", "multi", "--method", "sift_pnp_sensor", "-o", str(multi),
                 "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["evaluate", str(multi), "--dataset", str(synth)]) == 3
    assert "score it with --track multi" in capsys.readouterr().err
    assert main(["evaluate", str(multi), "--dataset", str(synth), "--track", "multi"]) == 0


# --------------------------------------------------------------------------- mapfree build


def test_build_on_an_empty_folder_is_an_error(tmp_path, capsys):
    from mapfree.cli import main

    (tmp_path / "scans").mkdir()
    assert main(["build", str(tmp_path / "scans"), "--out", str(tmp_path / "out"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("mapfree build: error:") and "no place folders" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv", [["synth", "ROOT", "--size", "big"],
                                  ["synth", "ROOT", "--split", "val", "--private-gt", "G"],
                                  ["build", "SCANS", "--out", "OUT", "--matcher", "nope"],
                                  ["build", "SCANS", "--out", "OUT", "--workers", "0"]])
def test_synth_and_build_flag_checks_say_error_like_every_command(argv, tmp_path, capsys):
    from mapfree.cli import main

    argv = [str(tmp_path / a) if a.isupper() else a for a in argv]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"mapfree {argv[0]}: error: ") and err.count("\n") == 1


# --------------------------------------------------------------------------- mapfree train


@pytest.mark.parametrize("argv", [["nosuch"], ["R6D_t_cpu_synth", "--set", "model.rotation=euler"],
                                  ["R6D_t_cpu_synth", "--resume", "nosuch.ckpt"]])
def test_train_argument_errors_come_before_lightning_is_imported(argv, tmp_path):
    """A typo in `mapfree train`'s command line once waited for Lightning (seconds) and its banner lines."""
    import os
    import subprocess
    import sys

    probe = ("import sys\nfrom mapfree.cli import main\ncode = main(sys.argv[1:])\n"
             "print('LOADED' if any(m in sys.modules for m in ('pytorch_lightning', 'lightning')) else 'CLEAN', code)")
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
    p = subprocess.run([sys.executable, "-c", probe, "train", *argv, "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, env=env, timeout=120)
    assert p.stdout.split() == ["CLEAN", "1"], (p.stdout, p.stderr)
    assert p.stderr.startswith("mapfree train: error:") and "Traceback" not in p.stderr


# --------------------------------------------------------------------------- depth-free PnP/Procrustes, best-offline


def test_depth_free_pnp_and_procrustes_are_not_listed_and_refused_for_a_split(synth, tmp_path):
    from mapfree.methods import list_methods

    names = list_methods()
    assert "sift_emat_none" in names and "sift_pnp_sensor" in names
    assert not [n for n in names if n.endswith(("_pnp_none", "_procrustes_none"))]
    for name in ("sift_pnp_none", "xfeat_procrustes_none"):
        with pytest.raises(ValueError, match=r"no depth source.*needs a depth map.*_emat_none"):
            run_split(synth, "val", name, tmp_path / "x.zip", progress=False)
    assert not (tmp_path / "x.journal.jsonl").exists()


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
    rc = main(["relocalize", str(scene.reference.image_path), str(bare), "--K-query", k,
               "--K-ref", k])
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


# --------------------------------------------------------------------------- docs/reports.md


@pytest.mark.slow
def test_the_reports_page_example_runs_as_printed(tmp_path):
    """The "Try it" block of docs/reports.md, run as a reader would, prints the statuses its comments say."""
    import os
    import re
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[1]
    block = re.findall(r"```bash\n(.*?)```", (repo / "docs" / "reports.md").read_text(), re.S)[-1]
    env = {**os.environ, "PYTHONPATH": str(repo / "src"), "PATH": f"{Path(sys.executable).parent}{os.pathsep}"
           f"{os.environ['PATH']}"}
    p = subprocess.run(["bash", "-c", block], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    lines = p.stdout.splitlines()
    assert [ln for ln in lines if ln in ("0", "3")] == ["0", "3"], p.stdout + p.stderr
    assert (tmp_path / "out" / "report.html").is_file() and (tmp_path / "out" / "none.zip").is_file()
    assert "Traceback" not in p.stderr


def test_demo_with_a_bad_method_is_one_line_exit_1(tmp_path, capsys):
    from mapfree.cli import main

    assert main(["demo", "--out", str(tmp_path), "--method", "sift_pnp_sensr", "--scenes", "1", "--queries", "5"]) == 1
    err = capsys.readouterr().err
    assert err.splitlines()[-1].startswith("mapfree demo: error:") and "sensr" in err and "Traceback" not in err


@pytest.mark.slow
def test_train_prints_no_lightning_banner(tmp_path):
    """`mapfree train` printed Lightning's accelerator banner, a tip and two warnings that ask nothing of the user
    before its own output; its real warnings (no validation ran here) stay."""
    import os
    import subprocess
    import sys

    from mapfree.cli import main

    for split in ("train", "val"):
        assert main(["synth", str(tmp_path / "data"), "--split", split, "--scenes", "1", "--queries", "10",
                     *SYNTH_ARGS]) == 0
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
    p = subprocess.run([sys.executable, "-m", "mapfree", "train", "R6D_t_cpu_synth", "--data", str(tmp_path / "data"),
                        "--out", str(tmp_path / "run"), "--max-steps", "1", "--set", "data.batch_size=2",
                        "--no-progress"], capture_output=True, text=True, env=env, timeout=600)
    assert p.returncode == 0, p.stderr
    for noise in ("GPU available", "TPU available", "Tip:", "LeafSpec", "in eval mode"):
        assert noise not in p.stderr, p.stderr
    assert (tmp_path / "run" / "checkpoints" / "last.ckpt").is_file()
