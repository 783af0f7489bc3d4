"""Submission ZIPs: round trip, every malformed-line case, hostile archives."""

from __future__ import annotations

import io
import struct
import zipfile

import numpy as np

from mapfree.benchmark import SubmissionLimits, evaluate, read_submission, write_submission
from mapfree.data import REFERENCE_NAME, write_intrinsics, write_poses
from mapfree.geometry import Intrinsics, Pose, quat_to_rotmat

NAMES = [f"seq1/frame_{i:05d}.jpg" for i in range(10)]
EXPECTED = {"s00000": frozenset([REFERENCE_NAME, *NAMES]), "s00001": frozenset([REFERENCE_NAME, *NAMES])}
GOOD = "seq1/frame_00000.jpg 1 0 0 0 0.1 0.2 0.3 5\n"


def zip_bytes(files: dict[str, bytes | str]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in files.items():
            zf.writestr(name, data)
    return buf.getvalue()


def reasons(problems, scene=None, line=None) -> list[str]:
    return [p.reason for p in problems if (scene is None or p.scene == scene) and (line is None or p.line == line)]


def test_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    est = {
        s: [
            (n, Pose(quat_to_rotmat(rng.normal(size=4)), rng.normal(size=3)), float(rng.integers(0, 100)))
            for n in NAMES
        ]
        for s in ("s00000", "s00001")
    }
    est["s00001"].append(("seq1/frame_00009.jpg", None, 1.0))  # no estimate: left out
    skipped = write_submission(tmp_path / "sub.zip", est)
    assert skipped == []
    with zipfile.ZipFile(tmp_path / "sub.zip") as zf:
        assert sorted(zf.namelist()) == ["pose_s00000.txt", "pose_s00001.txt"]
    back, problems = read_submission(tmp_path / "sub.zip", EXPECTED)
    assert problems == []
    for s, items in est.items():
        got = back[s].to_list()
        assert len(got) == len(NAMES)
        for (n, p, c), (n2, p2, c2) in zip(items, got):
            assert n == n2 and c == c2
            np.testing.assert_allclose(p.R, p2.R, rtol=0, atol=1e-12)
            np.testing.assert_allclose(p.t, p2.t, rtol=0, atol=1e-12)


def test_writer_never_writes_non_finite_or_negative(tmp_path):
    est = {
        "s00000": [
            ("seq1/frame_00000.jpg", Pose(np.eye(3), [np.nan, 0, 0]), 1.0),
            ("seq1/frame_00001.jpg", Pose.identity(), float("inf")),
            ("seq1/frame_00002.jpg", Pose.identity(), -2.0),
            ("seq1/frame_00003.jpg", Pose.identity(), 2.0),
        ]
    }
    skipped = write_submission(tmp_path / "s.zip", est)
    assert len(skipped) == 3
    text = zipfile.ZipFile(tmp_path / "s.zip").read("pose_s00000.txt").decode()
    assert text.count("\n") == 1 and "nan" not in text and "inf" not in text and text.startswith("seq1/frame_00003.jpg")


def test_every_malformed_line_is_reported_and_the_rest_kept():
    body = (
        "# a comment line\n"  # 1 comment
        + GOOD  # 2 ok
        + "seq1/frame_00001.jpg 1 0 0 0 0 0 0\n"  # 3 wrong field count
        + "seq1/frame_00002.jpg 1 0 zero 0 0 0 0 1\n"  # 4 unparseable
        + "seq1/frame_00003.jpg 1 0 0 0 nan 0 0 1\n"  # 5 non-finite
        + "seq1/frame_00004.jpg 0 0 0 0 0 0 0 1\n"  # 6 zero quaternion
        + "seq1/frame_99999.jpg 1 0 0 0 0 0 0 1\n"  # 7 unknown frame
        + "seq1/frame_00000.jpg 1 0 0 0 9 9 9 1\n"  # 8 duplicate
        + "seq1/frame_00005.jpg 1 0 0 0 0 0 0 -3\n"  # 9 negative confidence
        + "seq1/frame_00006.jpg 1 0 0 0 0 0 0 inf\n"  # 10 non-finite confidence
        + "seq1/frame_0000x.jpg 1 0 0 0 0 0 0 1\n"  # 11 no frame number
        + "seq1/frame_00007.jpg   2  0  0  0  0  0  0  1\n"  # 12 ok (extra spaces)
    )
    data = zip_bytes({"pose_s00000.txt": body, "pose_s00042.txt": GOOD, "sub/pose_s00001.txt": GOOD})
    est, problems = read_submission(data, EXPECTED)
    assert est["s00000"].names == ["seq1/frame_00000.jpg", "seq1/frame_00007.jpg"]
    np.testing.assert_allclose(est["s00000"].t[0], [0.1, 0.2, 0.3])  # the first of the duplicates wins
    expect = {
        3: "expected 9 fields",
        4: "unparseable number in field qy",
        5: "non-finite",
        6: "zero quaternion",
        7: "unknown frame",
        8: "duplicate frame",
        9: "negative confidence",
        10: "non-finite",
        11: "5-digit number",
    }
    for line, text in expect.items():
        got = reasons(problems, "s00000", line)
        assert len(got) == 1 and text in got[0], (line, got)
    assert not reasons(problems, "s00000", 1) and not reasons(problems, "s00000", 2)
    assert "s00042" not in est and any("not part of the evaluated split" in r for r in reasons(problems, "s00042"))
    assert "s00001" not in est and any("inside a folder" in r for r in reasons(problems, "s00001"))
    assert not any(p.fatal for p in problems)


def test_official_mode_keys_by_number_last_duplicate_wins():
    body = GOOD + "seq1/frame_00000.jpg 1 0 0 0 7 7 7 1\nseq1/frame_00001.jpg 1 0 0 0 0 0 0 -1\n"
    est, problems = read_submission(zip_bytes({"pose_s00000.txt": body}), EXPECTED, compat="official")
    assert est["s00000"].names == ["seq1/frame_00000.jpg", "seq1/frame_00001.jpg"]
    np.testing.assert_allclose(est["s00000"].t[0], [7, 7, 7])
    assert est["s00000"].confidence[1] == -1  # kept: the scorer aborts only if this frame is scored


def test_non_utf8_and_crlf_and_comments():
    body = GOOD.replace("\n", "\r\n").encode() + b"seq1/frame_00001.jpg 1 0 0 0 0 0 0 1 \xff\xfe\r\n# x\r\n"
    est, problems = read_submission(zip_bytes({"pose_s00000.txt": body}), EXPECTED)
    assert est["s00000"].names == ["seq1/frame_00000.jpg"]
    assert any("UTF-8" in r for r in reasons(problems, "s00000", 2))
    est, problems = read_submission(zip_bytes({"pose_s00000.txt": body}), EXPECTED, compat="official")
    assert any(p.fatal for p in problems)


def test_clean_and_messy_files_parse_identically():
    rng = np.random.default_rng(1)
    lines = [f"{n} " + " ".join(repr(float(v)) for v in rng.normal(size=8)) for n in NAMES]
    lines = [ln.rsplit(" ", 1)[0] + " " + str(abs(float(ln.rsplit(" ", 1)[1]))) for ln in lines]
    clean = "\n".join(lines) + "\n"
    messy = "# header\r\n" + "\r\n".join("  " + ln.replace(" ", "\t") for ln in lines) + "\r\n"
    a, pa = read_submission(zip_bytes({"pose_s00000.txt": clean}), EXPECTED)
    b, pb = read_submission(zip_bytes({"pose_s00000.txt": messy}), EXPECTED)
    assert pa == [] and pb == []
    assert a["s00000"].names == b["s00000"].names
    np.testing.assert_array_equal(a["s00000"].q, b["s00000"].q)
    np.testing.assert_array_equal(a["s00000"].confidence, b["s00000"].confidence)


def test_unsafe_paths_and_junk_entries_are_ignored():
    data = zip_bytes(
        {
            "/etc/pose_s00000.txt": GOOD,
            "../pose_s00000.txt": GOOD,
            "__MACOSX/._pose_s00000.txt": "x",
            "README.md": "hello",
            "pose_s00001.txt": GOOD,
        }
    )
    est, problems = read_submission(data, EXPECTED)
    assert list(est) == ["s00001"]
    text = " ".join(str(p) for p in problems)
    assert text.count("absolute or '..'") == 2 and "README.md" in text and "__MACOSX" in text


def test_not_a_zip_empty_and_missing_file(tmp_path):
    for src in (b"definitely not a zip", b"", tmp_path / "nope.zip"):
        est, problems = read_submission(src, EXPECTED)
        assert est == {} and len(problems) == 1 and problems[0].fatal
    truncated = zip_bytes({"pose_s00000.txt": GOOD * 100})[:-30]
    est, problems = read_submission(truncated, EXPECTED)
    assert est == {} and problems[0].fatal


def test_thousands_of_entries():
    data = zip_bytes({f"junk/{i}.txt": "" for i in range(3000)} | {"pose_s00000.txt": GOOD})
    est, problems = read_submission(data, EXPECTED, limits=SubmissionLimits(max_entries=1000))
    assert est == {} and problems[0].fatal and "3001 entries" in problems[0].reason
    est, problems = read_submission(data, EXPECTED)  # under the default limit: read, junk reported
    assert list(est) == ["s00000"] and problems[-1].reason.endswith("more problems not listed")


def test_decompression_bomb_and_lying_directory():
    bomb = zip_bytes({"pose_s00000.txt": b"0" * (8 << 20), "pose_s00001.txt": GOOD})
    assert len(bomb) < 100_000
    limits = SubmissionLimits(max_file_bytes=1 << 20)
    est, problems = read_submission(bomb, EXPECTED, limits=limits)
    assert list(est) == ["s00001"] and "over the limit" in reasons(problems, "s00000")[0]
    # Patch the central directory to claim a tiny uncompressed size: reading is still capped and fails cleanly.
    raw = bytearray(bomb)
    at = raw.find(b"PK\x01\x02")
    struct.pack_into("<I", raw, at + 24, 100)
    est, problems = read_submission(bytes(raw), EXPECTED, limits=limits)
    assert list(est) == ["s00001"] and reasons(problems, "s00000")


def test_bad_scene_file_counts_as_missing_in_evaluation(tmp_path):
    K = Intrinsics(500.0, 500.0, 269.5, 359.5, 540, 720)
    d = tmp_path / "val" / "s00000"
    d.mkdir(parents=True)
    names = [REFERENCE_NAME, *NAMES]
    write_poses(d / "poses.txt", names, [Pose.identity()] * len(names))
    write_intrinsics(d / "intrinsics.txt", {n: K for n in names})
    r = evaluate(zip_bytes({"pose_s00000.txt": b"\x00" * 10}), tmp_path, "val")
    assert not r.estimated.any() and r.problems
    assert r.to_json()  # serialisable, no NaN


def test_a_file_read_in_pieces_gives_what_the_whole_file_gives(monkeypatch):
    import mapfree.benchmark.submission as sub

    rng = np.random.default_rng(4)
    lines = [
        f"{NAMES[i % 10]} " + " ".join(repr(float(v)) for v in rng.normal(size=7)) + f" {i % 7}" for i in range(40)
    ]
    lines[3] = "seq1/frame_00099.jpg 1 0 0 0 0 0 0 1"  # unknown frame
    lines[17] = "seq1/frame_00002.jpg 1 0 0 0 0 0 x 1"  # unparseable number
    lines[25] = "seq1/frame_00004.jpg 0 0 0 0 0 0 0 1"  # zero quaternion
    body = ("\ufeff" + "\r\n".join(lines[:20]) + "\r\n\n" + "\n".join(lines[20:])).encode()  # BOM, CRLF, blank line
    files = {"pose_s00000.txt": body, "pose_s00001.txt": "\n".join(lines[5:]) + "\n"}
    for compat in ("default", "official"):
        whole = read_submission(zip_bytes(files), EXPECTED, compat=compat)
        monkeypatch.setattr(sub, "CHUNK_BYTES", 97)  # pieces of a few lines, cut anywhere
        pieces = read_submission(zip_bytes(files), EXPECTED, compat=compat)
        monkeypatch.undo()
        assert pieces[1] == whole[1] and len(whole[1]) > 20  # same problems, same scene:line, same words
        assert any("duplicate" in p.reason and "line" in p.reason for p in whole[1])
        for scene in ("s00000", "s00001"):
            a, b = whole[0][scene], pieces[0][scene]
            assert a.names == b.names and (a.lines == b.lines).all()
            np.testing.assert_array_equal(np.c_[a.q, a.t, a.confidence], np.c_[b.q, b.t, b.confidence])


def test_a_large_file_is_parsed_in_memory_bounded_by_its_compressed_size():
    import tracemalloc

    # 8 MB of pose lines (frames repeat: the first of each is kept, the rest reported), 4-5x compressible.
    rng = np.random.default_rng(1)
    block = "".join(
        f"{NAMES[i % 10]} 1.0 0.0 0.0 0.0 {a:.4f} {b:.4f} {c:.4f} {abs(d) * 10:.1f}\n"
        for i, (a, b, c, d) in enumerate(rng.normal(size=(20000, 4)))
    ).encode()
    text = block * (8_000_000 // len(block) + 1)
    data = zip_bytes({"pose_s00000.txt": text})
    tracemalloc.start()
    try:
        est, problems = read_submission(data, EXPECTED)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert est["s00000"].names == NAMES and "more problems not listed" in problems[-1].reason
    # Reading it whole took over 5x the text (the text, then a Python object per number); in pieces the
    # peak stays under the compressed size however large the file.
    assert peak < len(data), (peak, len(data), len(text))
