"""The one registry of ``mapfree.matching``: the docs' tables, ``available()`` and ``mapfree match --help`` all follow
it, and the batched matchers' single forms are their batched forms."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from mapfree import matching
from mapfree.matching.base import BatchedMatcher, Matcher

DOCS = Path(__file__).resolve().parents[1] / "docs"


def test_api_reference_table_is_the_registry():
    text = (DOCS / "api" / "matching.md").read_text()
    assert matching.table() in text
    names = re.findall(r"`([a-z0-9-]+)`", matching.table())
    assert [n for n in names if n in matching.names()] == matching.names()


def test_methods_page_lists_every_registered_matcher_and_no_other():
    text = (DOCS / "methods.md").read_text()
    section = text.split("## Matchers\n", 1)[1].strip().split("\n\n", 1)[0]  # the table after the heading
    first_cells = [row.split("|")[1] for row in section.splitlines()[2:]]
    listed = {n for cell in first_cells for n in re.findall(r"`([a-z0-9-]+)`", cell)}
    assert listed == set(matching.names())


def test_available_reads_the_registry(monkeypatch):
    here = matching.available()
    assert here[0] == "sift" and set(here) <= set(matching.names())
    assert here == [n for n in matching.names() if n in here]  # registry order
    monkeypatch.setitem(
        matching._REGISTRY, "sift-again", matching.Entry("SIFT (OpenCV)", "sift.SIFTMatcher", "sift.SIFTOptions", "-")
    )
    assert "sift-again" in matching.available() and "`sift-again`" in matching.table()


def test_match_help_lists_the_registry(capsys):
    from mapfree.cli import main

    with pytest.raises(SystemExit):
        main(["match", "--help"])
    help_text = "".join(capsys.readouterr().out.split())  # argparse wraps lines, also after a hyphen
    assert all(f"{n}," in help_text or f"{n};" in help_text for n in matching.names())


def test_entries_name_real_classes_and_options():
    from mapfree.options import Options

    for name in matching.names():
        entry = matching._REGISTRY[name]
        assert issubclass(matching._load(entry.cls), Matcher), name
        assert issubclass(matching.options_class(name), Options), name


@pytest.mark.parametrize("name", ["xfeat", "xfeat-lighterglue"])
def test_batched_single_forms_are_the_batched_forms(name, realmini):
    from mapfree.data import Dataset

    if name not in matching.available():
        pytest.skip(f"{name} is not available here")
    m = matching.create(name, device="cpu")
    assert isinstance(m, BatchedMatcher)
    scene = Dataset(realmini).scene("val", "s00000")
    img0, img1 = scene.reference.image(), scene.frame("seq1/frame_00009.jpg").image()
    f0, f1 = m.extract(img0), m.extract(img1)
    # one network pass for both: the same keypoints up to float rounding (and the order of tied scores)
    assert [len(g) for g in m.extract_many([img0, img1])] == [len(f0), len(f1)]
    one, (many,) = m.match(f0, f1), m.match_many(f0, [f1])
    assert len(one) > 50
    np.testing.assert_array_equal(one.kpts0, many.kpts0)
    np.testing.assert_array_equal(one.kpts1, many.kpts1)
