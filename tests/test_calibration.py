"""Calibrated probabilities: signals from the solvers, fitting, the file, run/evaluate with probabilities, the
cascade."""

from __future__ import annotations

import json
import math
import zipfile
from pathlib import Path

import numpy as np
import pytest

from mapfree.benchmark import evaluate
from mapfree.benchmark.reliability import reliability
from mapfree.calibration import (
    FORMAT_VERSION,
    Calibrated,
    Calibration,
    CalibrationError,
    centred_knots,
    features,
    fit,
)
from mapfree.cli import main
from mapfree.estimate import Estimate, Signals
from mapfree.geometry import Pose
from mapfree.methods import get
from mapfree.relocalize import build_localizer, read_journal
from mapfree.relocalize.cascade import Cascade
from mapfree.solvers import EssentialSolver, PnPSolver, ProcrustesSolver
from test_solvers import K_QRY, K_REF, synthetic_pair

# --------------------------------------------------------------------------- signals


@pytest.mark.parametrize("solver", [EssentialSolver(), PnPSolver(), ProcrustesSolver()], ids=lambda s: s.name)
def test_solvers_fill_typed_signals(solver):
    matches, D0, D1 = synthetic_pair(np.random.default_rng(0), outliers=0.3)
    est = solver.solve(matches, K_REF, K_QRY, D0, D1)
    assert est.ok, est.reason
    s = est.signals
    assert s.n_matches == len(matches)
    assert 0 < s.n_inliers < len(matches)  # the outliers are not inliers
    assert 0.5 < s.inlier_ratio <= 1.0
    assert s.score is not None and s.score > 0
    assert s.residual is not None and 0 <= s.residual < 1.0  # exact geometry: tiny residuals (px or m)
    assert 0 < s.depth_valid_fraction <= 1.0
    if solver.name != "pnp":  # both images' depths: two independent scales of the same points, here consistent
        assert s.scale_ratio == pytest.approx(1.0, abs=0.05)
    else:
        assert s.scale_ratio is None
    assert "signals" not in est.extras and est.to_dict()["signals"]["n_inliers"] == s.n_inliers


def test_scale_ratio_reveals_a_query_depth_at_the_wrong_scale():
    """Query depth twice too large: Ess.Mat still finds a scale, and its signals say the two depths disagree."""
    matches, D0, D1 = synthetic_pair(np.random.default_rng(1))
    good = EssentialSolver().solve(matches, K_REF, K_QRY, D0, D1)
    bad = EssentialSolver().solve(matches, K_REF, K_QRY, D0, 2.0 * D1)
    assert good.signals.scale_ratio == pytest.approx(1.0, abs=0.02)
    assert bad.signals.scale_ratio == pytest.approx(2.0, rel=0.05)


def test_signals_drop_non_finite_values_and_round_trip():
    s = Signals(n_matches=10, residual=float("nan"), scale_ratio=float("inf"), inlier_ratio=0.5)
    assert s.residual is None and s.scale_ratio is None
    assert Signals.from_dict({**s.to_dict(), "unknown": 3}) == s


# --------------------------------------------------------------------------- fitting and the file


def _synthetic_frames(n: int, seed: int = 0):
    """Frames whose chance of being right grows with the inlier ratio and falls with the scale disagreement."""
    rng = np.random.default_rng(seed)
    ratio = rng.uniform(0, 1, n)
    scale = np.exp(rng.normal(0, 0.3, n))
    p = 1 / (1 + np.exp(-(6 * ratio - 3 - 8 * np.abs(np.log(scale)))))
    right = rng.uniform(size=n) < p
    signals = [
        Signals(n_matches=500, n_inliers=int(500 * r), inlier_ratio=r, scale_ratio=s) for r, s in zip(ratio, scale)
    ]
    vcre = np.where(right, 20.0, 300.0)
    te = np.where(right, 0.1, 1.0)
    return signals, 500 * ratio, vcre, te, np.where(right, 2.0, 20.0), p


def test_fit_learns_a_calibrated_monotone_probability(tmp_path):
    signals, conf, vcre, te, re, p_true = _synthetic_frames(400)
    cal = fit("m", signals, conf, vcre, te, re, "synthetic")
    assert cal.frames == 400 and "inlier_ratio" in cal.signals and "scale_error" in cal.signals
    held = cal.figures["p_correct"]
    assert held["frames"] == 400 and held["ece"] < 0.07  # cross-validated, not in-sample
    # Better than the base rate's Brier score: the signals carry information.
    base = np.mean(vcre < 90)
    assert held["brier"] < base * (1 - base)
    # Monotone: more inliers (same scale agreement) never lowers the probability.
    ps = [cal.p_correct(Signals(500, int(500 * r), r, scale_ratio=1.0), 500 * r) for r in np.linspace(0, 1, 11)]
    assert all(b >= a - 1e-12 for a, b in zip(ps, ps[1:])) and ps[-1] > ps[0] + 0.5
    # A scale disagreement lowers it.
    assert cal.p_correct(Signals(500, 450, 0.9, scale_ratio=2.0), 450) < ps[-2]
    # The file: JSON without pickle, read back to the same predictions.
    path = tmp_path / "m.calib.json"
    cal.save(path)
    d = json.loads(path.read_text())
    assert d["version"] == FORMAT_VERSION and d["method"] == "m" and d["frames"] == 400
    assert set(d["models"]) == {"p_correct", "p_pose"} and d["models"]["p_correct"]["iso_x"]
    back = Calibration.load(path, "m")
    est = Estimate(Pose.identity(), 300.0, 300, signals=Signals(500, 300, 0.6, scale_ratio=1.1))
    assert back.probabilities(est) == pytest.approx(cal.probabilities(est))
    assert cal.apply(est).p_correct == pytest.approx(cal.probabilities(est)["p_correct"])
    assert cal.apply(Estimate.failure("none")).p_correct is None


def test_centred_isotonic_keeps_the_scores_order():
    """The isotonic map's flat blocks become one knot each at their centre: levels kept, ties between frames of
    different scores broken (the benchmark's AUC ranks by the probability), still monotone."""
    x, y = centred_knots(np.array([0.0, 1.0, 2.0, 3.0, 5.0, 6.0]), np.array([0.0, 0.0, 0.5, 0.5, 0.5, 1.0]))
    assert x.tolist() == [0.5, 3.5, 6.0] and y.tolist() == [0.0, 0.5, 1.0]
    signals, conf, vcre, te, re, _ = _synthetic_frames(400)
    cal = fit("m", signals, conf, vcre, te, re)
    ps = [cal.p_correct(Signals(500, int(500 * r), r, scale_ratio=1.0), 500 * r) for r in np.linspace(0.3, 0.7, 41)]
    assert all(b >= a for a, b in zip(ps, ps[1:])) and len(set(ps)) > 30  # a flat map would give a few levels


def test_probability_bins_against_truth():
    """The held-out probabilities are close to the true ones the frames were drawn with."""
    signals, conf, vcre, te, re, p_true = _synthetic_frames(800, seed=2)
    cal = fit("m", signals, conf, vcre, te, re)
    p = np.array([cal.p_correct(s, c) for s, c in zip(signals, conf)])
    assert np.mean(np.abs(p - p_true)) < 0.1


@pytest.mark.parametrize(
    "n, all_right, message",
    [(20, False, "at least 30"), (100, True, "one class only")],
)
def test_fit_refuses_too_little_data(n, all_right, message):
    signals, conf, vcre, te, re, _ = _synthetic_frames(n)
    if all_right:
        vcre = np.zeros(n)
    with pytest.raises(CalibrationError, match=message):
        fit("m", signals, conf, vcre, te, re)


@pytest.fixture(scope="module")
def calibration_file(tmp_path_factory) -> Path:
    signals, conf, vcre, te, re, _ = _synthetic_frames(200)
    path = tmp_path_factory.mktemp("cal") / "sift_emat_sensor.calib.json"
    fit("sift_emat_sensor", signals, conf, vcre, te, re).save(path)
    return path


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: {**d, "version": 0}, "format version 0"),
        (lambda d: {**d, "format": "x"}, "not a mapfree calibration"),
        (lambda d: {k: v for k, v in d.items() if k != "models"}, "corrupt: missing 'models'"),
        (lambda d: {**d, "signals": ["nope"]}, "corrupt: unknown signal"),
    ],
)
def test_bad_calibration_files_are_one_clear_error(calibration_file, tmp_path, change, message):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(change(json.loads(calibration_file.read_text()))))
    with pytest.raises(CalibrationError, match=message):
        Calibration.load(bad)
    (tmp_path / "torn.json").write_text(calibration_file.read_text()[:100])
    with pytest.raises(CalibrationError, match="not readable JSON"):
        Calibration.load(tmp_path / "torn.json")
    with pytest.raises(CalibrationError, match="fitted for method 'sift_emat_sensor', not 'other'"):
        Calibration.load(calibration_file, "other")


def test_features_mark_missing_signals():
    x = features(Signals(n_matches=9), 3.0)
    assert x[0] == pytest.approx(math.log1p(3.0)) and x[1] == pytest.approx(math.log1p(9))
    assert np.isnan(x[2:]).all()


def test_reliability_figures():
    p = np.array([0.95, 0.95, 0.85, 0.15, 0.15])
    y = np.array([True, True, False, False, True])
    r = reliability(p, y)
    assert r.brier == pytest.approx(np.mean((p - y) ** 2))
    # bins: [0.9,1]: p .95 right 1; [0.8,0.9): .85 vs 0; [0.1,0.2): .15 vs .5
    assert r.ece == pytest.approx((2 * 0.05 + 0.85 + 2 * 0.35) / 5)
    assert r.precision[0.9] == 1.0 and r.accepted[0.8] == 3 and r.precision[0.8] == pytest.approx(2 / 3)


# --------------------------------------------------------------------------- the commands on real computation


@pytest.fixture(scope="module")
def synth40(tmp_path_factory) -> Path:
    """Two synthetic val scenes of 20 queries at 240x320 (sensor depth): enough frames to fit on."""
    root = tmp_path_factory.mktemp("synth40")
    args = ["synth", str(root), "--scenes", "2", "--queries", "20", "--size", "240x320", "--no-mono", "--quiet"]
    assert main(args) == 0
    return root


@pytest.fixture(scope="module")
def calibrated(synth40, tmp_path_factory) -> dict[str, Path]:
    """Calibrations of two SIFT presets fitted by `mapfree calibrate` on every frame of synth40."""
    out = tmp_path_factory.mktemp("calibs")
    files = {}
    for name in ("sift_pnp_sensor", "sift_emat_sensor"):
        files[name] = out / f"{name}.calib.json"
        assert main(["calibrate", str(synth40), "--method", name, "-o", str(files[name]), "--no-progress"]) == 0
    return files


def test_calibrate_runs_every_frame_and_writes_held_out_figures(calibrated, synth40):
    d = json.loads(calibrated["sift_pnp_sensor"].read_text())
    header, recs = read_journal(calibrated["sift_pnp_sensor"].with_name("sift_pnp_sensor.calib.run.journal.jsonl"))
    assert header["all_frames"] and len(recs) == 40  # every query, not the scored fifth
    assert all("signals" in r for r in recs) and any(r["signals"].get("residual") for r in recs)
    assert d["method"] == "sift_pnp_sensor" and d["frames"] == sum(r["ok"] for r in recs)
    fig = d["figures"]["p_correct"]
    assert 0 <= fig["ece"] <= 1 and 0 <= fig["brier"] <= 1 and sum(fig["bins"]["count"]) == d["frames"]


def test_calibrate_reads_a_journal_instead_of_running(calibrated, synth40, tmp_path, capsys):
    journal = calibrated["sift_pnp_sensor"].with_name("sift_pnp_sensor.calib.run.journal.jsonl")
    out = tmp_path / "again.json"
    args = ["calibrate", str(synth40), "--method", "sift_pnp_sensor", "--journal", str(journal), "-o", str(out)]
    assert main(args) == 0
    assert json.loads(out.read_text())["models"] == json.loads(calibrated["sift_pnp_sensor"].read_text())["models"]
    assert "held-out ECE" in capsys.readouterr().out
    # the journal of one method is not another's calibration
    args[3] = "sift_emat_sensor"
    assert main(args) == 1
    assert "is a run of method 'sift_pnp_sensor', not 'sift_emat_sensor'" in capsys.readouterr().err


def test_calibrate_refuses_bad_splits(synth, tmp_path, capsys):
    # 20 frames: too few to fit
    args = ["calibrate", str(synth), "--method", "sift_pnp_sensor", "-o", str(tmp_path / "a.json"), "--no-progress"]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "a calibration needs at least 30" in err
    # a split without ground truth
    test_root = tmp_path / "t"
    assert main(["synth", str(test_root), "--split", "test", "--scenes", "1", "--queries", "3", "--quiet"]) == 0
    assert main(["calibrate", str(test_root), "--split", "test", "--method", "sift_pnp_sensor", "-o", "x.json"]) == 1
    assert "has no ground-truth poses" in capsys.readouterr().err


def test_run_with_calibration_submits_probabilities_and_evaluate_judges_them(calibrated, synth40, tmp_path, capsys):
    out = tmp_path / "sub.zip"
    cal = calibrated["sift_pnp_sensor"]
    args = ["run", str(synth40), "--method", "sift_pnp_sensor", "-o", str(out), "--no-progress"]
    assert main([*args, "--calibration", str(cal), "--confidence", "calibrated", "--all-frames"]) == 0
    _, recs = read_journal(out.with_name("sub.journal.jsonl"))
    calibration = Calibration.load(cal)
    for r in recs:
        if r["ok"]:
            assert r["p_correct"] == pytest.approx(calibration.p_correct(r["signals"], r["confidence"]))
    with zipfile.ZipFile(out) as z:
        conf = [float(line.split()[-1]) for n in z.namelist() for line in z.read(n).decode().splitlines()]
    assert conf and all(0 <= c <= 1 for c in conf)
    report = evaluate(out, synth40, "val")
    figures = report.to_dict()["calibration"]
    assert figures["probabilities"] and figures["frames"] == int(report.estimated.sum())
    html = tmp_path / "r.html"
    assert main(["evaluate", str(out), "--dataset", str(synth40), "--html", str(html)]) == 0
    assert "ECE" in capsys.readouterr().out and "reliability diagram" in html.read_text()
    # A run without --confidence calibrated: inlier counts, which are not probabilities, and the report says so.
    plain = tmp_path / "plain.zip"
    assert main(["run", str(synth40), "--method", "sift_pnp_sensor", "-o", str(plain), "--no-progress"]) == 0
    assert not evaluate(plain, synth40, "val").to_dict()["calibration"]["probabilities"]
    # --confidence calibrated without any calibration: one clear line
    assert main([*args, "--overwrite", "--confidence", "calibrated"]) == 1
    assert "has no calibration" in capsys.readouterr().err
    # a calibration of another method
    assert main([*args, "--overwrite", "--calibration", str(calibrated["sift_emat_sensor"])]) == 1
    assert "fitted for method 'sift_emat_sensor', not 'sift_pnp_sensor'" in capsys.readouterr().err


def test_api_gives_p_correct(calibrated, synth40):
    from mapfree.data import Dataset

    scene = Dataset(synth40).scene("val", "s00000")
    loc = build_localizer("sift_pnp_sensor", calibration=calibrated["sift_pnp_sensor"])
    assert isinstance(loc, Calibrated)
    est = loc.relocalize(scene.reference, scene.queries[0])
    assert est.ok and 0 <= est.p_correct <= 1 and "p_pose" in est.extras


# --------------------------------------------------------------------------- cascade


def test_cascade_names_and_yaml(tmp_path):
    m = get("sift_emat_sensor+best-offline@mono")
    assert m.kind == "cascade" and m.options == {"stages": ["sift_emat_sensor", "best-offline@mono"], "accept": 0.8}
    y = tmp_path / "c.yaml"
    y.write_text("kind: cascade\nstages: [sift_pnp_sensor, sift_emat_sensor]\naccept: 0.9\n")
    assert get(str(y)).options["accept"] == 0.9 and get(str(y)).name == "c"
    for text, message in [
        ("kind: cascade\nstages: sift_pnp_sensor\n", "needs stages: a list"),
        ("kind: cascade\nstages: [sift_pnp_sensor]\naccept: 2\n", "accept must be a probability"),
        ("kind: cascade\nstages: [nope_nope]\n", "stage 'nope_nope'"),
        ("kind: cascade\nstages: [sift_pnp_sensor]\nsolver: pnp\n", "unknown key"),
    ]:
        y.write_text(text)
        with pytest.raises(ValueError, match=message):
            get(str(y))


def test_cascade_runs_later_stages_only_where_needed(calibrated, synth40, tmp_path):
    files = [str(calibrated[n]) for n in ("sift_pnp_sensor", "sift_emat_sensor")]
    out = tmp_path / "cascade.zip"
    method = "sift_pnp_sensor+sift_emat_sensor"
    base = ["run", str(synth40), "--method", method, "--all-frames", "--no-progress"]
    assert main([*base, "-o", str(out), "--calibration", files[0], "--calibration", files[1]]) == 0
    _, recs = read_journal(out.with_name("cascade.journal.jsonl"))
    ok = [r for r in recs if r["ok"]]
    assert ok and all(r["stage"] in ("sift_pnp_sensor", "sift_emat_sensor") for r in ok)
    for r in ok:
        ran = [k for k in r["timings"] if k.startswith("stage:")]
        # the second stage ran exactly where the first was unsure (or had no estimate)
        if r["stage"] == "sift_pnp_sensor" and r["p_correct"] >= 0.8:
            assert ran == ["stage:sift_pnp_sensor"]
        if r["stage"] == "sift_emat_sensor":
            assert len(ran) == 2
        assert r["confidence"] == pytest.approx(r["p_correct"])
    # an estimate wherever a stage alone has one
    single = tmp_path / "pnp.zip"
    assert main(["run", str(synth40), "--method", "sift_pnp_sensor", "--all-frames", "-o", str(single)]) == 0
    _, alone = read_journal(single.with_name("pnp.journal.jsonl"))
    assert len(ok) >= sum(r["ok"] for r in alone)
    # a stage without a calibration (no preset ships one for sift_emat_sensor)
    assert main([*base, "-o", str(tmp_path / "c2.zip"), "--calibration", files[0]]) == 1


def test_cascade_localizer_in_python(calibrated, synth40):
    from mapfree.data import Dataset

    scene = Dataset(synth40).scene("val", "s00000")
    cals = [Calibration.load(calibrated[n]) for n in ("sift_pnp_sensor", "sift_emat_sensor")]
    stages = [get(n).build() for n in ("sift_pnp_sensor", "sift_emat_sensor")]
    never = Cascade(["sift_pnp_sensor", "sift_emat_sensor"], stages, cals, accept=1.01)  # above any p: always both
    first = Cascade(["sift_pnp_sensor", "sift_emat_sensor"], stages, cals, accept=1e-9)  # the first that answers
    anchor = never.prepare(scene.reference)
    for q in scene.queries[:4]:
        both, one = never.localize(q, anchor), first.localize(q, anchor)
        if both.ok:
            assert len([k for k in both.timings if k.startswith("stage:")]) == 2
            alone = [cal.apply(s.localize(q, a)) for s, cal, a in zip(stages, cals, anchor)]
            assert both.p_correct == pytest.approx(max(e.p_correct or 0 for e in alone if e.ok))
        if one.ok and one.stage == "sift_pnp_sensor":
            assert list(k for k in one.timings if k.startswith("stage:")) == ["stage:sift_pnp_sensor"]


def test_service_publishes_calibration_figures_for_val_only(calibrated, synth40, tmp_path):
    from mapfree.service.leaderboard.scoring import redact

    out = tmp_path / "p.zip"
    cal = str(calibrated["sift_pnp_sensor"])
    args = ["run", str(synth40), "--method", "sift_pnp_sensor", "-o", str(out), "--no-progress"]
    assert main([*args, "--calibration", cal, "--confidence", "calibrated"]) == 0
    report = evaluate(out, synth40, "val").to_dict()
    val = redact(report, [], "val")
    assert val["calibration"]["probabilities"] and "ece" in val["calibration"] and val["calibration"]["bins"]
    test = redact(report, [], "test")
    assert "calibration" not in test and "ece" not in json.dumps(test).lower()


def test_the_cascade_string_form_passes_the_relocalization_service_name_check():
    from mapfree.service.anchors.localizers import check_method

    assert check_method("best-offline+sift_procrustes_sensor") == "best-offline+sift_procrustes_sensor"
    with pytest.raises(ValueError, match="stage 'nope'"):
        get("best-offline+nope")
