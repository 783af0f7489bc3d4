"""Options of matchers, solvers and devices: one check, with the same words, for the command line, a method YAML and
Python, before anything is loaded."""

from __future__ import annotations

import pytest

from cli_support import one_line as _one_line
from cli_support import query_pair as _pair
from mapfree.cli import main
from mapfree.relocalize import run_split


def _cuda() -> bool:
    import torch

    return torch.cuda.is_available()


def test_misspelt_yaml_option_names_the_file_and_suggests(synth, tmp_path):
    cfg = tmp_path / "typo.yaml"
    cfg.write_text("extends: sift_emat_sensor\nmatcher_opts: {max_featurs: 1000}\n")
    with pytest.raises(ValueError, match=r"typo\.yaml.*max_featurs.*did you mean 'max_features'"):
        run_split(synth, "val", str(cfg), tmp_path / "sub.zip", progress=False)
    assert not (tmp_path / "sub.journal.jsonl").exists()  # refused before any work
    cfg.write_text("extends: sift_emat_sensor\nsolver_opts: {ransac_treshold_px: 2}\n")
    with pytest.raises(ValueError, match=r"solver_opts\.ransac_treshold_px.*'ransac_threshold_px'"):
        run_split(synth, "val", str(cfg), tmp_path / "sub.zip", progress=False)


def test_option_values_are_checked_in_one_place_for_cli_yaml_and_python(synth, tmp_path, capfd):
    """A bad value once reached OpenCV (a 26-line cv2.error) or silently disabled the ratio test; an unknown key
    read differently on the command line (a TypeError's text) and in a YAML file."""
    from mapfree.matching.sift import SIFTMatcher
    from mapfree.options import OptionError

    a, b = _pair(synth)
    for opt, expected in (
        ("max_features=abc", "option max_features='abc' for matcher 'sift': expected an integer"),
        ("max_features=-5", "option max_features=-5 for matcher 'sift': expected an integer >= 1"),
        ("ratio=5", "option ratio=5 for matcher 'sift': expected a number in (0, 1]"),
        ("bogus=1", "unknown option bogus for matcher 'sift': known: device, max_features"),
    ):
        assert main(["match", a, b, "--option", opt]) == 1
        _, line = _one_line(capfd)
        assert line.startswith("mapfree match: error: ") and expected in line, line
    # The same check, the same words, for a method YAML (run and relocalize) and for Python.
    for body, expected in (
        (
            "matcher_opts: {max_features: abc}",
            "option matcher_opts.max_features='abc' for matcher 'sift': expected an integer",
        ),
        ("matcher_opts: {bogus: 1}", "unknown option matcher_opts.bogus for matcher 'sift'"),
        (
            "solver_opts: {reprojection_threshold_px: -1}",
            "option solver_opts.reprojection_threshold_px=-1 for solver 'pnp': expected a number > 0",
        ),
    ):
        cfg = tmp_path / "m.yaml"
        cfg.write_text(f"extends: sift_pnp_sensor\n{body}\n")
        assert main(["run", str(synth), "--method", str(cfg), "-o", str(tmp_path / "s.zip"), "--no-progress"]) == 1
        _, line = _one_line(capfd)
        assert line.startswith(f"mapfree run: error: {cfg}: ") and expected in line, line
        assert main(["relocalize", a, b, "--method", str(cfg)]) == 1
        assert expected in _one_line(capfd)[1]
    assert not (tmp_path / "s.journal.jsonl").exists()  # refused before any work
    with pytest.raises(OptionError, match=r"option ratio=5 for matcher 'sift': expected a number in \(0, 1\]"):
        SIFTMatcher(ratio=5)
    with pytest.raises(OptionError, match="unknown option bogus for matcher 'sift'"):
        SIFTMatcher(bogus=1)


def test_devices_are_checked_before_anything_is_loaded(synth, tmp_path, capfd):
    """--device tpu and --device cuda on a machine without CUDA were 41-line torch tracebacks (55 from a YAML)."""
    a, b = _pair(synth)
    assert main(["match", a, b, "--matcher", "xfeat", "--device", "tpu"]) == 1
    assert _one_line(capfd)[1] == "mapfree match: error: --device tpu: expected cpu, cuda, cuda:N, mps or auto"
    if _cuda():
        assert main(["match", a, b, "--device", "cuda:99"]) == 1
        assert "CUDA device(s)" in _one_line(capfd)[1]
        return
    assert main(["match", a, b, "--matcher", "xfeat", "--device", "cuda"]) == 1
    assert _one_line(capfd)[1].startswith("mapfree match: error: --device cuda: CUDA is not available on this machine")
    cfg = tmp_path / "gpu.yaml"
    cfg.write_text("extends: xfeat_pnp_sensor\nmatcher_opts: {device: cuda}\n")
    assert main(["run", str(synth), "--method", str(cfg), "-o", str(tmp_path / "s.zip"), "--no-progress"]) == 1
    assert "option matcher_opts.device='cuda' for matcher 'xfeat': CUDA is not available" in _one_line(capfd)[1]


def test_literal_mode_fields_are_checked_as_strings_among_their_choices():
    """A mode typed ``Literal[...]`` (a solver's backend, confidence, depth sampling) reads as a string with
    choices: the same words as a ``str`` field with the same choices."""
    from mapfree.options import OptionError
    from mapfree.solvers.pnp import PnPOptions
    from mapfree.solvers.procrustes import ProcrustesOptions

    assert PnPOptions.build({"backend": "poselib", "confidence": "score"}).backend == "poselib"
    for values, expected in (
        ({"backend": 3}, "option backend=3: expected a string"),
        ({"backend": "x"}, "option backend='x': expected one of opencv, poselib"),
        ({"depth_sampling": None}, "option depth_sampling=None: expected a string, not null"),
        ({"confidence": "zz"}, "option confidence='zz': expected one of inliers, score"),
    ):
        with pytest.raises(OptionError) as e:
            PnPOptions.build(values)
        assert str(e.value) == expected
    with pytest.raises(OptionError, match="option icp_method=1: expected a string$"):
        ProcrustesOptions.build({"icp_method": 1})
