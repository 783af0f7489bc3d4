"""Hostile input over real HTTP: every case gets the right 4xx with a message naming the problem, never a 500
(the server fixture also fails if its log shows an unhandled error or a token)."""

from __future__ import annotations

import numpy as np
import pytest

from .conftest import make_submission
from .conftest import png_of as _png
from .conftest import zip_of as _zip


def _scene(server) -> str:
    return sorted(p.name for p in (server.data.root / "val").iterdir())[0]


def _bomb() -> bytes:
    return _zip({"pose_s00460.txt": b"\0" * (20 << 20)})  # 20 MB of zeros in ~20 kB


def _lying_header() -> bytes:
    """An entry whose header claims 10 bytes but which inflates to much more."""
    data = bytearray(_zip({"pose_s00460.txt": b"seq1/frame_00000.jpg 1 0 0 0 0 0 0 1\n" * 200000}))
    big = (200000 * 37).to_bytes(4, "little")
    small = (10).to_bytes(4, "little")
    return bytes(data.replace(big, small))


ZIP_CASES = {
    "not a zip": (lambda s: b"this is not a zip archive", 400, "not a valid ZIP"),
    "empty file": (lambda s: b"", 400, "empty"),
    "truncated zip": (lambda s: make_submission(s.data.root / "val")[:-30], 400, "ZIP"),
    "path traversal": (lambda s: _zip({f"../pose_{_scene(s)}.txt": b"x"}), 422, "path traversal"),
    "absolute path": (lambda s: _zip({f"/etc/pose_{_scene(s)}.txt": b"x"}), 422, "path traversal"),
    "folder entry": (lambda s: _zip({f"sub/pose_{_scene(s)}.txt": b"x"}), 422, "not allowed"),
    "wrong entry name": (lambda s: _zip({"poses.txt": b"x"}), 422, "pose_s00460.txt"),
    "unknown scene": (lambda s: _zip({"pose_s99999.txt": b"seq1/frame_00000.jpg 1 0 0 0 0 0 0 1\n"}), 422,
                      "not in the val split"),
    "zip bomb": (lambda s: _bomb(), 413, "zip bomb"),
    "lying header": (lambda s: _lying_header(), 422, "corrupt"),
    "too many entries": (lambda s: _zip({f"pose_s{i:05d}.txt": b"" for i in range(2001)}), 413, "entries"),
    "binary content": (lambda s: _zip({f"pose_{_scene(s)}.txt": bytes(range(256)) * 10}), 422, "UTF-8"),
    # parsing pose lines is the workers' job (uploads get cheap checks only): stored, then failed with the reason
    "no valid line": (lambda s: _zip({f"pose_{_scene(s)}.txt": b"garbage line\nmore garbage\n"}), 202,
                      "no valid pose line"),
    "empty zip": (lambda s: _zip({}), 422, "no pose_sNNNNN.txt"),
    "too large": (lambda s: np.random.default_rng(0).bytes(3 << 20), 413, "limit"),
}


@pytest.mark.parametrize("case", list(ZIP_CASES))
def test_hostile_submissions(server, case):
    build, status, words = ZIP_CASES[case]
    with server.client("alice") as c:
        r = c.post("/api/submissions", files={"file": ("s.zip", build(server), "application/zip")},
                   data={"split": "val", "name": case})
    assert r.status_code == status, (case, r.status_code, r.text)
    if status == 202:
        d = server.wait_done(r.json()["id"], "alice")
        assert d["status"] == "failed" and words.lower() in d["error"].lower(), d
    else:
        assert words.lower() in r.json()["detail"].lower(), r.json()


def test_malformed_forms(server):
    data = make_submission(server.data.root / "val")
    with server.client("alice") as c:
        r = c.post("/api/submissions", data={"split": "val"})
        assert r.status_code == 422 and "file" in r.json()["detail"]
        r = c.post("/api/submissions", files={"file": ("s.zip", data)}, data={"split": "train"})
        assert r.status_code == 422 and "split" in r.json()["detail"]
        r = c.post("/api/submissions", files={"file": ("s.zip", data)}, data={"split": "val", "name": "x" * 500})
        assert r.status_code == 422 and "name" in r.json()["detail"]
        r = c.post("/api/submissions", content=b"{not json", headers={"content-type": "application/json"})
        assert r.status_code == 422
        assert c.get("/api/submissions/" + "a" * 5000).status_code in (404, 414)
        assert c.patch("/api/submissions/x", json={"public": "maybe"}).status_code == 422


IMAGE_CASES = {
    "corrupt image": (lambda: b"\xff\xd8\xff\xe0" + b"\0" * 100, {}, 422, "image"),
    "not an image": (lambda: b"GIF89a not really", {}, 422, "image"),
    "truncated png": (lambda: _png(64, 64)[:60], {}, 422, "image"),
    "decompression bomb": (lambda: _png(5000, 5000, 1), {}, 413, "pixels"),
    "negative focal": (lambda: _png(48, 64), {"fx": -5}, 422, "focal"),
    "nan focal": (lambda: _png(48, 64), {"fx": "nan"}, 422, "finite"),
    "text focal": (lambda: _png(48, 64), {"fx": "abc"}, 422, "fx"),
    "missing intrinsics": (lambda: _png(48, 64), {"cy": None}, 422, "cy"),
}


@pytest.mark.parametrize("case", list(IMAGE_CASES))
def test_hostile_images(server, case):
    build, override, status, words = IMAGE_CASES[case]
    form = {"fx": 50, "fy": 50, "cx": 32, "cy": 24, **override}
    form = {k: str(v) for k, v in form.items() if v is not None}
    with server.client("alice") as c:
        r = c.post("/anchors", files={"image": ("a.png", build())}, data=form)
    assert r.status_code == status, (case, r.status_code, r.text)
    assert words.lower() in r.json()["detail"].lower(), r.json()


def test_depth_must_match_the_image(server):
    with server.client("alice") as c:
        r = c.post("/anchors", files={"image": ("a.png", _png(48, 64)), "depth": ("d.png", _png(10, 10, 1, np.uint16))},
                   data={"fx": 50, "fy": 50, "cx": 32, "cy": 24})
        assert r.status_code == 422 and "must match" in r.json()["detail"]
        r = c.post("/anchors", files={"image": ("a.png", _png(48, 64)), "depth": ("d.png", b"junk")},
                   data={"fx": 50, "fy": 50, "cx": 32, "cy": 24})
        assert r.status_code == 422 and "depth" in r.json()["detail"]
        r = c.post("/anchors", files={"image": ("a.png", _png(48, 64))},
                   data={"fx": 50, "fy": 50, "cx": 32, "cy": 24, "method": "no_such_method"})
        assert r.status_code == 422 and "method" in r.json()["detail"]


def test_oversized_request_is_refused_before_reading(server):
    """A body announced larger than the server's request limit is answered 413 without being read."""
    import socket
    from urllib.parse import urlparse

    u = urlparse(server.url)
    with socket.create_connection((u.hostname, u.port), timeout=30) as s:
        s.sendall(b"POST /api/submissions HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer " +
                  server.tokens["alice"].encode() + b"\r\nContent-Type: multipart/form-data; boundary=b\r\n"
                  b"Content-Length: 10000000000\r\n\r\n")
        head = s.recv(4096).decode(errors="replace")
    assert head.startswith("HTTP/1.1 413"), head
