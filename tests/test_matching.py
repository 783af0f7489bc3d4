"""Matchers on real images (realmini-dev): matches agree with the ground-truth relative pose, keypoints are in
original pixels, blank images give nothing; loaders of downloadable weights work on random weights saved here."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

import mapfree.matching as M
from mapfree.data import Dataset
from mapfree.matching import Features, Matches, MissingWeightsError

torch.set_num_threads(1)  # 2 shared cores: extra threads only spin

OFFLINE = ["sift", "xfeat", "xfeat-star", "xfeat-lighterglue", "aliked-lightglue", "disk-lightglue"]
# test-time settings that keep each matcher to a second or two on 2 cores
FAST = {
    "aliked-lightglue": {"max_keypoints": 1024},
    "disk-lightglue": {"max_keypoints": 512, "max_size": 400},
    "xfeat-star": {"top_k": 4000},
}
# fraction of matches within 3 px of the ground-truth epipolar geometry (xfeat: mutual NN only, no filtering)
MIN_GOOD = {"xfeat": 0.6}


def sampson_px(m: Matches, K0: np.ndarray, K1: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Sampson distance (pixels) of each match to the epipolar geometry of X1 = R X0 + t."""
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(K1).T @ tx @ R @ np.linalg.inv(K0)
    x0 = np.c_[m.kpts0, np.ones(len(m))]
    x1 = np.c_[m.kpts1, np.ones(len(m))]
    Fx0, Ftx1 = x0 @ F.T, x1 @ F
    num = np.sum(x1 * Fx0, axis=1) ** 2
    den = Fx0[:, 0] ** 2 + Fx0[:, 1] ** 2 + Ftx1[:, 0] ** 2 + Ftx1[:, 1] ** 2
    return np.sqrt(num / den)


@pytest.fixture(scope="module")
def pair(realmini):
    scene = Dataset(realmini).scene("val", "s00000")
    ref, query = scene.reference, scene.queries[10]
    return ref, query, ref.image(), query.image()


_MATCHERS: dict[str, object] = {}


def matcher(name: str, **options):
    """Matchers are built once per test session (and option set)."""
    key = name + repr(sorted(options.items()))
    if key not in _MATCHERS:
        _MATCHERS[key] = M.create(name, device="cpu", **{**FAST.get(name, {}), **options})
    return _MATCHERS[key]


_FEATURES: dict[tuple[str, str], Features] = {}


def features(name: str, pair, which: int) -> Features:
    """Features of the pair's reference (0) or query (1), extracted once per session."""
    key = (name, which)
    if key not in _FEATURES:
        _FEATURES[key] = matcher(name).extract(pair[2 + which])
    return _FEATURES[key]


def check_geometry(m: Matches, ref, query, min_good: float) -> None:
    w0, h0 = ref.intrinsics.width, ref.intrinsics.height
    w1, h1 = query.intrinsics.width, query.intrinsics.height
    assert np.all(np.isfinite(m.kpts0)) and np.all(np.isfinite(m.kpts1)) and np.all(np.isfinite(m.scores))
    assert np.all((m.kpts0 >= -0.5) & (m.kpts0 <= [w0 - 0.5, h0 - 0.5]))
    assert np.all((m.kpts1 >= -0.5) & (m.kpts1 <= [w1 - 0.5, h1 - 0.5]))
    err = sampson_px(m, ref.intrinsics.K, query.intrinsics.K, query.pose.R, query.pose.t)
    assert np.mean(err < 3.0) >= min_good, f"only {np.mean(err < 3.0):.2f} of {len(m)} matches within 3 px"


@pytest.mark.parametrize("name", OFFLINE)
def test_offline_matcher_agrees_with_ground_truth(name, pair):
    ref, query, im0, im1 = pair
    mt = matcher(name)
    f0, f1 = features(name, pair, 0), features(name, pair, 1)
    assert isinstance(f0, Features) and f0.image_size == (im0.shape[1], im0.shape[0])
    m = mt.match(f0, f1)
    assert len(m) >= 100, f"{name}: only {len(m)} matches"
    check_geometry(m, ref, query, MIN_GOOD.get(name, 0.8))


@pytest.mark.parametrize("name", OFFLINE)
def test_blank_images_give_no_matches(name, pair):
    _, _, im0, _ = pair
    mt = matcher(name)
    blank = np.full_like(im0, 127)
    fb = mt.extract(blank)
    assert len(mt.match(fb, mt.extract(np.zeros_like(im0)))) == 0
    assert len(mt.match(features(name, pair, 0), fb)) == 0


def test_resized_extraction_still_reports_original_pixels(pair):
    """Extract at a smaller size: keypoints mapped back must still fit the ground truth in original pixels."""
    ref, query, im0, im1 = pair
    for mt in (M.create("sift", max_size=400), matcher("aliked-lightglue", max_size=320, max_keypoints=512)):
        m = mt.match(mt.extract(im0), mt.extract(im1))
        assert len(m) >= 50
        check_geometry(m, ref, query, 0.8)


def test_reference_features_are_reusable_and_match_many_equals_match(pair):
    mt = matcher("aliked-lightglue", max_keypoints=256)
    small0, small1 = (cv2.resize(im, (270, 180), interpolation=cv2.INTER_AREA) for im in pair[2:])
    f0, f1 = mt.extract(small0), mt.extract(small1)
    single = mt.match(f0, f1)
    assert len(single) > 0
    many = mt.match_many(f0, [f1, mt.extract(np.zeros_like(small1)), f1])
    assert [len(x) for x in many] == [len(single), 0, len(single)]
    np.testing.assert_allclose(many[2].kpts1, single.kpts1)
    batch = mt.extract_many([small1, small0, small1[:90]])
    np.testing.assert_allclose(batch[0].kpts, f1.kpts, atol=1e-3)
    np.testing.assert_allclose(batch[1].kpts, f0.kpts, atol=1e-3)
    assert batch[2].image_size == (270, 90)


def test_registry():
    assert set(OFFLINE) <= set(M.available())
    assert set(M.available()) <= set(M.names())
    with pytest.raises(KeyError, match="unknown matcher"):
        M.create("no-such-matcher")
    assert M.create("SIFT").name == "sift"


def test_invalid_image_is_a_clear_error():
    with pytest.raises(ValueError, match="RGB image"):
        M.create("sift").extract(np.zeros((10, 10, 4), np.uint8))


# ---------------------------------------------------------------------- downloadable weights


@pytest.fixture
def offline(monkeypatch, tmp_path):
    """No weights anywhere: empty weights dir and torch hub cache, downloads refused."""
    monkeypatch.setenv("MAPFREE_OFFLINE", "1")
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setenv(M.WEIGHTS_ENV, str(tmp_path / "empty"))
    return tmp_path


@pytest.mark.parametrize(
    "name, filename",
    [
        ("loftr", "loftr_outdoor.ckpt"),
        ("loftr-indoor", "loftr_indoor.ckpt"),
        ("superpoint-lightglue", "superpoint_v1.pth"),
    ],
)
def test_missing_weights_error_says_what_to_place_where(offline, name, filename):
    with pytest.raises(MissingWeightsError) as e:
        M.create(name)
    msg = str(e.value)
    assert filename in msg and M.WEIGHTS_ENV in msg and "http" in msg
    assert name not in M.available()


def test_missing_explicit_weights_path_is_named(offline):
    with pytest.raises(MissingWeightsError, match="nowhere"):
        M.create("loftr", weights=str(offline / "nowhere.ckpt"))


def test_loftr_loader_with_random_weights(tmp_path, pair):
    from kornia.feature import LoFTR

    torch.manual_seed(0)
    net = LoFTR(pretrained=None)
    torch.save({"state_dict": {"matcher." + k: v for k, v in net.state_dict().items()}}, tmp_path / "loftr_indoor.ckpt")
    mt = M.create("loftr-indoor", weights=str(tmp_path), max_size=160, device="cpu")
    for k, v in net.state_dict().items():
        assert torch.equal(mt.net.state_dict()[k], v), k
    _, _, im0, im1 = pair
    f0 = mt.extract(im0)
    assert len(f0) > 0 and f0.kpts.max() < im0.shape[1]  # the coarse grid, in original pixels
    m = mt.match(f0, mt.extract(im1))
    assert isinstance(m, Matches) and np.all(np.isfinite(m.kpts0))
    assert len(mt.match(f0, mt.extract(np.zeros_like(im1)))) == 0
    # a checkpoint of the wrong network is refused with its path
    torch.save({"state_dict": {"x": torch.zeros(1)}}, tmp_path / "bad.ckpt")
    with pytest.raises(ValueError, match="bad.ckpt"):
        M.create("loftr", weights=str(tmp_path / "bad.ckpt"), device="cpu")


def test_superpoint_lightglue_loader_with_random_weights(tmp_path, monkeypatch, pair):
    from kornia.feature import LightGlue

    from mapfree.matching.superpoint import SuperPoint

    torch.manual_seed(0)
    sp = SuperPoint()
    glue = LightGlue(None, **{k: v for k, v in LightGlue.features["superpoint"].items() if k != "weights"})
    torch.save(sp.state_dict(), tmp_path / "superpoint_v1.pth")
    # the released file uses the old layer names; the loader remaps them
    old = {k.replace("transformers.0.self_attn", "self_attn.0"): v for k, v in glue.state_dict().items()}
    torch.save(old, tmp_path / "superpoint_lightglue.pth")
    monkeypatch.setenv(M.WEIGHTS_ENV, str(tmp_path))
    assert "superpoint-lightglue" in M.available()
    mt = M.create("superpoint-lightglue", max_size=256, max_keypoints=256, device="cpu")
    for k, v in glue.state_dict().items():
        assert torch.equal(mt.glue.state_dict()[k], v), k
    _, _, im0, im1 = pair
    f0, f1 = mt.extract(im0), mt.extract(im1)
    assert 0 < len(f0) <= 256 and f0.data["descriptors"].shape == (len(f0), 256)
    assert np.all((f0.kpts >= 0) & (f0.kpts < [im0.shape[1], im0.shape[0]]))
    m = mt.match(f0, f1)
    assert isinstance(m, Matches) and np.all(np.isfinite(m.scores))


def test_sift_ratio_test_equals_opencv_brute_force(pair):
    """The BLAS nearest-neighbour search gives exactly OpenCV's knnMatch(k=2) + ratio test match set."""
    f0, f1 = features("sift", pair, 0), features("sift", pair, 1)
    d0, d1 = f0.data["descriptors"], f1.data["descriptors"]
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d0, d1, k=2)
    expected = {(a.queryIdx, a.trainIdx) for a, b in knn if a.distance < 0.8 * b.distance}
    m = matcher("sift").match(f0, f1)
    got_pts = {(tuple(a), tuple(b)) for a, b in zip(m.kpts0.tolist(), m.kpts1.tolist())}
    want_pts = {(tuple(f0.kpts[i]), tuple(f1.kpts[j])) for i, j in expected}
    assert len(expected) > 50 and got_pts == want_pts and len(m) == len(expected)


def _straightforward_two_nearest(d0: np.ndarray, d1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plain formula: clipped squared distances, then the nearest and second nearest of every row."""
    sq = np.maximum((d0 * d0).sum(1)[:, None] + (d1 * d1).sum(1)[None, :] - 2.0 * (d0 @ d1.T), 0.0)
    nearest = sq.argmin(axis=1)
    rows = np.arange(len(sq))
    first = sq[rows, nearest]
    sq[rows, nearest] = np.inf
    return nearest, np.sqrt(np.stack([first, sq.min(axis=1)], axis=1))


def test_sift_fast_distances_equal_the_straightforward_formula(pair):
    """Cached norms, 2 a.b as (2 a).b and unclipped distances give the plain formula's bits on real descriptors,
    also where rounding makes distances negative (a descriptor matched against copies of itself)."""
    from mapfree.matching.sift import squared_distances, two_nearest

    f0, f1 = features("sift", pair, 0), features("sift", pair, 1)
    d0, d1 = f0.data["descriptors"], f1.data["descriptors"]
    dup = np.vstack([d1[:300], d0[:200], d0[:200]])  # every d0[:200] row has two exact copies among these columns
    for a, b, fa, fb in ((d0, d1, f0, f1), (d1, d0, f1, f0), (d0, dup, f0, None)):
        want = _straightforward_two_nearest(a, b)
        nb = fb.data["sq_norms"] if fb is not None else None
        sq = squared_distances(a, b, fa.data["sq_norms"], nb, clip=False)
        got = two_nearest(sq)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
        assert np.array_equal(sq, squared_distances(a, b))  # negative rows were clipped in place: mutual sees these
    sq = squared_distances(d0, dup, clip=False)
    assert (sq < 0).any(), "the duplicate rows are meant to exercise the negative-distance branch"
