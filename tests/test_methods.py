"""The method registry: preset names, YAML configs, depth swaps, and that every name builds valid options."""

from __future__ import annotations

from pathlib import Path

import pytest

from mapfree import depth, matching, methods, solvers
from mapfree.relocalize import run_split


def test_every_listed_method_parses_into_valid_components():
    names = methods.list_methods()
    assert "sift_emat_dptkitti" in names and "aliked-lightglue_procrustes_sensor" in names
    known_matchers = set(matching.names())
    for name in names:
        m = methods.get(name)
        if m.kind != "matching":
            continue
        assert m.matcher in known_matchers, name
        # The options must be ones the solver really has (raises TypeError otherwise).
        solvers.options_for(m.solver, **m.solver_opts)
        assert (
            m.depth == "none"
            or m.depth.startswith(("files:", "hf:"))
            or m.depth in depth.HUB_MODELS
            or m.depth in depth.PAIR_MODELS
        ), name


@pytest.mark.parametrize("matcher", methods.MATCHERS)
def test_paper_rows(matcher):
    emat = methods.get(f"{matcher}_emat_dptkitti")
    assert (emat.matcher, emat.solver, emat.depth) == (matcher, "essential", "files:dptkitti")
    assert emat.solver_opts["ransac_threshold_px"] == (3.0 if matcher == "sift" else 2.0)
    assert methods.get(f"{matcher}_pnp_sensor").solver == "pnp"
    assert methods.get(f"{matcher}_procrustes_mono").depth == "files:mono"
    assert methods.get(f"{matcher}_emat_none").depth == "none"
    assert methods.get(f"{matcher}_pnp_dav2-indoor").depth == "dav2-indoor"  # a depth network's short name


def test_unknown_names_say_what_exists():
    for bad in ("sift_emat", "surf_emat_sensor", "sift_ransac_sensor", "nonsense"):
        with pytest.raises(KeyError, match="unknown method"):
            methods.get(bad)


def test_depth_swap_keeps_everything_else():
    base = methods.get("xfeat_emat_sensor")
    swapped = methods.get("xfeat_emat_sensor@dptnyu")
    assert swapped.depth == "files:dptnyu" and swapped.solver_opts == base.solver_opts
    assert methods.get("xfeat_emat_sensor@none").depth == "none"


def test_yaml_config_loading(tmp_path: Path):
    cfg = tmp_path / "mine.yaml"
    cfg.write_text(
        "extends: sift_emat_sensor\nsolver_opts:\n  confidence: score\nmatcher_opts:\n  ratio: 0.9\n"
        "description: test config\n"
    )
    m = methods.get(str(cfg))
    assert m.name == "mine" and m.matcher == "sift" and m.depth == "files:sensor"
    assert m.solver_opts == {"ransac_threshold_px": 3.0, "confidence": "score"}
    assert m.matcher_opts == {"ratio": 0.9}
    solvers.options_for(m.solver, **m.solver_opts)

    plain = tmp_path / "plain.yml"
    plain.write_text("matcher: xfeat\nsolver: pnp\ndepth: sensor\n")
    p = methods.load_yaml(plain)
    assert (p.name, p.matcher, p.solver, p.depth) == ("plain", "xfeat", "pnp", "files:sensor")

    bad = tmp_path / "bad.yaml"
    bad.write_text("matcher: sift\nsolverr: pnp\n")
    with pytest.raises(ValueError, match="bad.yaml.*solverr"):
        methods.get(str(bad))
    broken = tmp_path / "broken.yaml"
    broken.write_text("matcher: sift\nsolver: [pnp\n")
    with pytest.raises(ValueError, match=r"broken.yaml:\d+"):
        methods.get(str(broken))
    with pytest.raises(FileNotFoundError):
        methods.get(str(tmp_path / "missing.yaml"))


def test_shipped_configs_and_best_preset_load():
    for d in methods.config_dirs():
        for path in d.glob("*.yaml"):
            m = methods.load_yaml(path)
            if m.kind == "matching":
                assert m.matcher in matching.names()
                solvers.options_for(m.solver, **m.solver_opts)
    best = methods.get(methods.BEST_OFFLINE)
    assert best.matcher in methods.OFFLINE_MATCHERS and best.depth.startswith("files:")


def test_register_and_kind_hook():
    m = methods.Method(name="test-registered-sift", matcher="sift", depth="files:sensor")
    methods.register(m, overwrite=True)
    assert methods.get("test-registered-sift") is m
    with pytest.raises(ValueError):
        methods.register(m)
    assert type(m.build()).__name__ == "Relocalizer"
    with pytest.raises(KeyError, match="unknown method kind"):
        methods.factory("no-such-kind")


def test_unknown_method_suggests_close_names():
    """A typo gets the nearest real names, not only the grammar of names."""
    for typo, meant in (
        ("best-ofline", "best-offline"),
        ("siftt_emat_sensor", "sift_emat_sensor"),
        ("xfeat-pnp-sensor", "xfeat_pnp_sensor"),
        ("rpr-3d3", "rpr-3d3d"),
    ):
        with pytest.raises(KeyError, match=f"did you mean .*'{meant}'"):
            methods.get(typo)


def test_every_registered_matcher_declares_its_options():
    """A method YAML is checked against its matcher's options: a matcher missing from that table made every config
    naming it fail with a bare KeyError."""
    from mapfree import matching

    for name in matching.names():
        assert matching.option_names(name), name


def test_shipped_method_configs_pass_the_option_check():
    from mapfree.methods import config_dirs, get

    files = [p for d in config_dirs() for p in d.glob("*.yaml")]
    assert files
    for p in files:
        get(str(p))


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


def test_depth_free_pnp_and_procrustes_are_not_listed_and_refused_for_a_split(synth, tmp_path):
    from mapfree.methods import list_methods

    names = list_methods()
    assert "sift_emat_none" in names and "sift_pnp_sensor" in names
    assert not [n for n in names if n.endswith(("_pnp_none", "_procrustes_none"))]
    for name in ("sift_pnp_none", "xfeat_procrustes_none"):
        with pytest.raises(ValueError, match=r"no depth source.*needs a depth map.*_emat_none"):
            run_split(synth, "val", name, tmp_path / "x.zip", progress=False)
    assert not (tmp_path / "x.journal.jsonl").exists()


def test_every_method_yaml_key_has_its_type_checked_in_one_place():
    """A key without an entry would be a KeyError in the check; a new ``Method`` field needs its type here."""
    from dataclasses import fields

    from mapfree.methods import YAML_KEY_TYPES, Method

    assert set(YAML_KEY_TYPES) == {f.name for f in fields(Method)} | {"extends"}


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty.yaml: an empty method config: give 'extends: NAME'"),
        ("description: mine\n", "empty.yaml: it names no method (only description)"),
        (
            "extends: sift_pnp_sensor\n\nmatcher: 5\n",
            "empty.yaml:3: matcher: expected a matcher name (e.g. sift), got 5",
        ),
        ("matcher: sift\nsolver: ' '\n", "empty.yaml:2: solver: expected a solver name"),
        ("extends: sift_pnp_sensor\nmatcher_opts: 3\n", "empty.yaml:2: matcher_opts: expected a mapping"),
    ],
)
def test_a_method_yaml_of_wrong_types_or_none_is_refused_with_file_line_and_key(tmp_path, text, message):
    from mapfree.methods import load_yaml

    path = tmp_path / "empty.yaml"
    path.write_text(text)
    with pytest.raises(ValueError) as e:
        load_yaml(path)
    assert str(e.value).startswith(f"{tmp_path}/{message}"), str(e.value)
