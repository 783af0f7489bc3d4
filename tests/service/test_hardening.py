"""Issue 11, security and reliability: each test here failed on the service before its fix."""

from __future__ import annotations

import io
import zipfile

import pytest

from .conftest import make_submission

BOM = b"\xef\xbb\xbf"


def _with_bom(data: bytes) -> bytes:
    """The same submission with a UTF-8 byte-order mark at the start of every pose file."""
    src, buf = zipfile.ZipFile(io.BytesIO(data)), io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for info in src.infolist():
            z.writestr(info.filename, BOM + src.read(info))
    return buf.getvalue()


def test_bom_is_accepted_by_evaluate_and_the_server(server, tmp_path):
    from mapfree.benchmark import evaluate

    plain = make_submission(server.data.root / "val", noise=0.05, seed=11)
    bom = _with_bom(plain)
    (tmp_path / "plain.zip").write_bytes(plain)
    (tmp_path / "bom.zip").write_bytes(bom)
    want = evaluate(tmp_path / "plain.zip", server.data.root, "val")
    got = evaluate(tmp_path / "bom.zip", server.data.root, "val")
    assert not any("unknown frame" in str(p) for p in got.problems), got.problems
    assert got.metrics == pytest.approx(want.metrics, nan_ok=True)
    with server.client("alice") as c:
        r = c.post("/api/submissions", files={"file": ("bom.zip", bom)}, data={"split": "val", "name": "bom"})
        assert r.status_code == 202, r.text
    d = server.wait_done(r.json()["id"], "alice")
    assert d["status"] == "done" and not any("unknown frame" in p for p in d["problems"]), d
    assert d["metrics"]["AUC @ VCRE < 90px"] == pytest.approx(want.metrics["AUC @ VCRE < 90px"])
