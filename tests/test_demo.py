"""``mapfree demo``: it says what a working install scores, and a bad method is one line."""

from __future__ import annotations


def test_the_demo_says_what_to_expect():
    """The demo's numbers are those of simulated monocular depth; a user could not tell a broken install."""
    import argparse

    from mapfree.cli.demo import DEFAULTS, EXPECTED, expectation

    args = argparse.Namespace(**DEFAULTS)
    good = {k: v for k, (v, _) in EXPECTED.items()}
    lines = expectation(args, good)
    assert "AUC @ VCRE < 90px is about 0.76" in lines[0] and lines[-1] == "This run matches: the install works."
    broken = {**good, "AUC @ VCRE < 90px": 0.31}
    assert expectation(args, broken)[-1].startswith("UNEXPECTED: AUC @ VCRE < 90px 0.310 (expected 0.761")
    other = argparse.Namespace(**{**DEFAULTS, "scenes": 1})
    assert "changed --scenes 1" in expectation(other, broken)[-1]


def test_demo_with_a_bad_method_is_one_line_exit_1(tmp_path, capsys):
    from mapfree.cli import main

    assert main(["demo", "--out", str(tmp_path), "--method", "sift_pnp_sensr", "--scenes", "1", "--queries", "5"]) == 1
    err = capsys.readouterr().err
    assert err.splitlines()[-1].startswith("mapfree demo: error:") and "sensr" in err and "Traceback" not in err
