"""What a test evaluation reveals of the private ground truth (the threat model: ``mapfree.service.leaderboard.disclosure``).

The attack replayed here: a one-scene test split of 12 scored frames; each submission estimates 7 of them (over half,
which used to publish the medians): a probe frame at the identity rotation with its camera centre 100 m along
one axis, three frames at the identity pose (surely smaller errors) and three 1e5 m away (surely larger). The
published median translation error was then the probe's private error, and three such submissions (x, y, z)
placed that frame's camera centre to millimetres."""

from __future__ import annotations

import numpy as np
import pytest

from .conftest import zip_of

PROBE_M = 100.0


def _one_scene_split(root, gt, scored: int = 12):
    """A test split of one scene whose ``scored`` frames (every 5th query) lie at random poses within a few metres
    (private GT) -> (the scored frames' names, their poses)."""
    from mapfree.data import write_poses
    from mapfree.geometry import Pose, quat_to_rotmat

    rng = np.random.default_rng(26)
    scene = root / "test" / "s00900"
    scene.mkdir(parents=True)
    names = ["seq0/frame_00000.jpg"] + [f"seq1/frame_{i:05d}.jpg" for i in range(5 * scored)]
    (scene / "intrinsics.txt").write_text("".join(f"{n} 590.5 591.0 269.5 359.5 540 720\n" for n in names))
    (scene / "poses.txt").write_text("".join(f"{n} 0 0 0 0 0 0 0\n" for n in names))
    poses = [Pose.identity()]
    for _ in names[1:]:
        q = rng.normal(size=4) * 0.1 + [1, 0, 0, 0]
        poses.append(Pose(quat_to_rotmat(q / np.linalg.norm(q)), rng.uniform(-3, 3, size=3)))
    (gt / "test" / "s00900").mkdir(parents=True)
    write_poses(gt / "test" / "s00900" / "poses.txt", names, poses)
    return names[1::5], poses[1::5]


def _probe_zip(names: list[str], axis: int) -> bytes:
    """The probe (frame 0) 100 m along ``axis``, frames 1-3 at the identity pose, 4-6 at 1e5 m on every axis."""
    centre = np.zeros(3)
    centre[axis] = PROBE_M
    lines = [f"{names[0]} 1 0 0 0 {' '.join(f'{-c:.6f}' for c in centre)} 9"]  # t = -R c with R = I
    lines += [f"{n} 1 0 0 0 0 0 0 9" for n in names[1:4]]
    lines += [f"{n} 1 0 0 0 -1e5 -1e5 -1e5 9" for n in names[4:7]]
    return zip_of({"pose_s00900.txt": ("\n".join(lines) + "\n").encode()})


def trilaterate(d: list[float]) -> np.ndarray | None:
    """The camera centre c (near the origin) with |c - 100 e_i| = d_i for i = x, y, z, or None when a distance
    is not published. c_i = (|c|² + 100² - d_i²) / 200: a quadratic in r = |c|²; the root near the reference."""
    if any(x is None for x in d):
        return None
    k = (PROBE_M**2 - np.square(d)) / (2 * PROBE_M)  # c_i = r / 200 + k_i
    a, b, c = 3 / (2 * PROBE_M) ** 2, 2 * k.sum() / (2 * PROBE_M) - 1, float(k @ k)
    disc = b * b - 4 * a * c
    if disc < 0:
        return None
    r = min((-b - np.sqrt(disc)) / (2 * a), (-b + np.sqrt(disc)) / (2 * a), key=abs)
    return r / (2 * PROBE_M) + k


def test_three_probe_submissions_recover_nothing_better_than_a_metre(tmp_path):
    """The trilateration of three probe submissions, from what the server publishes (``evaluation.score``, then
    ``to_json``'s ``shown_metrics``): the medians are not published, so nothing places the frame; a control on
    val, where the ground truth is public and the medians stay, shows the same attack working to millimetres."""
    from mapfree.service import Settings
    from mapfree.service.leaderboard.disclosure import MEDIAN_KEYS
    from mapfree.service.leaderboard.scoring import score
    from mapfree.service.leaderboard.submissions import shown_metrics

    root, gt = tmp_path / "data", tmp_path / "gt"
    names, poses = _one_scene_split(root, gt)
    truth = poses[0].center  # the probe frame's camera centre
    settings = Settings(data_root=root, gt_root=gt)
    published = []
    for axis in range(3):
        z = tmp_path / f"probe{axis}.zip"
        z.write_bytes(_probe_zip(names, axis))
        result, plots = score(settings, "test", z)
        assert plots is None and "per_scene" not in result
        shown = shown_metrics("test", result["metrics"])
        assert all(shown[k] is None for k in MEDIAN_KEYS), shown
        assert any("median errors are not published" in p for p in result["problems"])
        published.append(shown["Average Median Translation Error"])
        assert f"{np.linalg.norm(truth - PROBE_M * np.eye(3)[axis]):.3f}" not in str(result)
    found = trilaterate(published)
    assert found is None or np.linalg.norm(found - truth) > 1.0

    # a result stored before medians were withheld is shown without them too
    old = {"Average Median Translation Error": 98.122, "Precision @ VCRE < 90px": 0.41234}
    assert shown_metrics("test", old) == {"Average Median Translation Error": None, "Precision @ VCRE < 90px": 0.412}

    # control: the same three submissions against the same poses as val (public truth) do place the frame
    (root / "val").mkdir()
    (root / "test" / "s00900").rename(root / "val" / "s00900")
    (gt / "test" / "s00900" / "poses.txt").replace(root / "val" / "s00900" / "poses.txt")
    d = [
        score(settings, "val", tmp_path / f"probe{axis}.zip")[0]["metrics"]["Average Median Translation Error"]
        for axis in range(3)
    ]
    assert np.linalg.norm(trilaterate(d) - truth) < 0.01


@pytest.mark.parametrize("frames_sent", [1, 12])
def test_no_test_result_carries_a_median(tmp_path, frames_sent):
    """Neither a one-frame probe nor a submission of every frame publishes a median on test; the rest is
    rounded to leaderboard precision."""
    from mapfree.service import Settings
    from mapfree.service.leaderboard.disclosure import DECIMALS, DEFAULT_DECIMALS, MEDIAN_KEYS
    from mapfree.service.leaderboard.scoring import score

    root, gt = tmp_path / "data", tmp_path / "gt"
    names, poses = _one_scene_split(root, gt)
    rng = np.random.default_rng(frames_sent)
    lines = []
    for n, p in list(zip(names, poses))[:frames_sent]:
        t = p.t + rng.normal(scale=0.3, size=3)
        lines.append(
            f"{n} {' '.join(f'{x:.9f}' for x in p.qt()[0])} {' '.join(f'{x:.9f}' for x in t)} {rng.uniform(1, 9):.3f}"
        )
    z = tmp_path / "s.zip"
    z.write_bytes(zip_of({"pose_s00900.txt": ("\n".join(lines) + "\n").encode()}))
    m = score(Settings(data_root=root, gt_root=gt), "test", z)[0]["metrics"]
    assert all(m[k] is None for k in MEDIAN_KEYS), m
    assert m["Precision @ VCRE < 90px"] is not None and m["AUC @ VCRE < 90px"] is None
    for k, v in m.items():
        if isinstance(v, float):
            assert round(v, DECIMALS.get(k, DEFAULT_DECIMALS)) == v, (k, v)


def _ranked_zip(names: list[str], poses, passed: int) -> bytes:
    """Seven frames with confidences 7..1: frame i at its true pose when bit i of ``passed`` is set (it passes
    every threshold), else 1e5 m away (it fails every one); the rest of the split left out."""
    lines = []
    for i, (n, p) in enumerate(zip(names[:7], poses[:7])):
        t = p.t if passed >> i & 1 else np.full(3, -1e5)
        q = p.qt()[0]
        lines.append(f"{n} {' '.join(f'{x:.9f}' for x in q)} {' '.join(f'{x:.6f}' for x in t)} {7 - i}")
    return zip_of({"pose_s00900.txt": ("\n".join(lines) + "\n").encode()})


def test_seven_ranked_frames_reveal_only_how_many_passed(tmp_path):
    """The ranking attack: 7 chosen frames with confidences 7..1, every one of the 2^7 pass/fail patterns against
    the private ground truth. What a test evaluation publishes (stored, and shown) must be the same for every
    pattern with the same number of passing frames: the attacker learns that count (3 bits per threshold,
    ``log2(7 + 1)``, the stated bound), never which frames passed. A control on val (public truth, AUCs kept)
    tells the 128 patterns apart."""
    from mapfree.service import Settings
    from mapfree.service.leaderboard.scoring import score
    from mapfree.service.leaderboard.submissions import shown_metrics

    root, gt = tmp_path / "data", tmp_path / "gt"
    names, poses = _one_scene_split(root, gt)
    settings = Settings(data_root=root, gt_root=gt)
    z = tmp_path / "ranked.zip"

    def published(split: str, passed: int) -> tuple:
        z.write_bytes(_ranked_zip(names, poses, passed))
        result, plots = score(settings, split, z)
        shown = shown_metrics(split, result["metrics"])
        if split == "test":
            assert plots is None and shown == result["metrics"]
            assert any("AUCs are not published" in p for p in result["problems"])
        return tuple(sorted(shown.items()))

    by_count: dict[int, set] = {}
    for passed in range(2**7):
        by_count.setdefault(bin(passed).count("1"), set()).add(published("test", passed))
    assert all(len(seen) == 1 for seen in by_count.values()), {k: len(v) for k, v in by_count.items()}
    assert len(set().union(*by_count.values())) == 8  # the count itself is published (the precisions)
    shown = dict(next(iter(by_count[3])))
    assert shown["Precision @ VCRE < 90px"] == round(3 / 12, 3) and shown["AUC @ VCRE < 90px"] is None

    # a result stored before AUCs were withheld is shown without them too
    old = {"AUC @ VCRE < 90px": 0.41234, "AUC @ Pose Error < (50.0cm, 10deg)": 0.2, "Precision @ VCRE < 90px": 0.25}
    assert shown_metrics("test", old) == {
        "AUC @ VCRE < 90px": None,
        "AUC @ Pose Error < (50.0cm, 10deg)": None,
        "Precision @ VCRE < 90px": 0.25,
    }

    # control: the same submissions against the same poses as val (public truth) tell every pattern apart
    (root / "val").mkdir()
    (root / "test" / "s00900").rename(root / "val" / "s00900")
    (gt / "test" / "s00900" / "poses.txt").replace(root / "val" / "s00900" / "poses.txt")
    assert len({published("val", passed) for passed in range(2**7)}) == 2**7
