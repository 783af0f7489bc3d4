"""SuperPoint + SuperGlue and EfficientLoFTR through transformers, on tiny randomly initialised models saved here
and a real realmini-dev pair: our split into extract/match gives the transformers forward's matches, our grey
input is the transformers image processors' tensor, keypoints come back in original pixels, the weight-free
EfficientLoFTR matching steps pair and refine the right cells, presets run end to end, and missing weights
offline are one clear error."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

import mapfree.matching as M
from mapfree import methods
from mapfree.data import Dataset
from mapfree.matching import Matches, MissingWeightsError
from mapfree.matching.efficientloftr import mutual_pairs, refine
from mapfree.matching.hub import grey_pixels

torch.set_num_threads(1)  # 2 shared cores: extra threads only spin

CPU = torch.device("cpu")


def tiny_superglue(seed: int):
    from transformers import SuperGlueConfig, SuperGlueForKeypointMatching

    torch.manual_seed(seed)
    sp = {"encoder_hidden_sizes": [8, 8, 16, 16], "decoder_hidden_size": 32, "descriptor_decoder_dim": 32}
    cfg = SuperGlueConfig(
        keypoint_detector_config=sp,
        hidden_size=32,
        keypoint_encoder_sizes=[8, 16],
        gnn_layers_types=["self", "cross"],
        num_attention_heads=2,
    )
    return SuperGlueForKeypointMatching(cfg).eval()


def tiny_efficientloftr(seed: int):
    from transformers import EfficientLoFTRConfig, EfficientLoFTRForKeypointMatching

    torch.manual_seed(seed)
    # 8 heads: the rotary embedding needs hidden_size / heads = hidden_size / 8
    cfg = EfficientLoFTRConfig(
        stage_num_blocks=[1, 1, 1, 1],
        out_features=[16, 16, 32, 32],
        hidden_size=32,
        num_attention_layers=1,
        num_attention_heads=8,
        fine_matching_slice_dim=4,
        initializer_range=0.5,
    )
    return EfficientLoFTRForKeypointMatching(cfg).eval()


@pytest.fixture(scope="module")
def weights_dir(tmp_path_factory):
    """A $MAPFREE_WEIGHTS_DIR holding tiny superglue_outdoor, superglue_indoor and efficientloftr folders."""
    d = tmp_path_factory.mktemp("hub-weights")
    tiny_superglue(0).save_pretrained(d / "superglue_outdoor")
    tiny_superglue(1).save_pretrained(d / "superglue_indoor")
    tiny_efficientloftr(0).save_pretrained(d / "efficientloftr")
    return d


@pytest.fixture(scope="module")
def pair(realmini):
    scene = Dataset(realmini).scene("val", "s00000")
    ref, query = scene.reference, scene.queries[10]
    return ref, query, ref.image(), query.image()


def in_bounds(m: Matches, im0: np.ndarray, im1: np.ndarray) -> bool:
    (h0, w0), (h1, w1) = im0.shape[:2], im1.shape[:2]
    return bool(
        np.all((m.kpts0 >= -0.5) & (m.kpts0 <= [w0 - 0.5, h0 - 0.5]))
        and np.all((m.kpts1 >= -0.5) & (m.kpts1 <= [w1 - 0.5, h1 - 0.5]))
    )


# ---------------------------------------------------------------------- preprocessing


@pytest.mark.parametrize("processor", ["SuperGlueImageProcessorPil", "EfficientLoFTRImageProcessorPil"])
@pytest.mark.parametrize("max_size, multiple", [(None, 1), (256, 1), (256, 32)])
def test_grey_input_is_the_image_processors_tensor(processor, max_size, multiple, pair):
    import transformers

    _, _, im0, im1 = pair
    x, scale = grey_pixels(im0, max_size, multiple, CPU)
    h, w = x.shape[-2:]
    assert (w, h) == (round(im0.shape[1] * scale[0]), round(im0.shape[0] * scale[1]))
    proc = getattr(transformers, processor)(size={"height": h, "width": w})
    ref = proc([im0, im1], return_tensors="pt")["pixel_values"][0, 0]  # (3, H, W): grey in every channel
    assert ref.shape == (3, h, w)
    torch.testing.assert_close(x[0, 0], ref[0], rtol=0, atol=1e-6)


# ---------------------------------------------------------------------- SuperGlue


def test_superglue_extract_and_match_equal_the_transformers_forward(weights_dir, pair):
    from transformers import SuperGlueImageProcessorPil

    _, _, im0, im1 = pair
    mt = M.create("superglue", weights=str(weights_dir / "superglue_outdoor"), match_threshold=0.0, device="cpu")
    assert mt.name == "superglue"
    cfg = mt.net.config  # the paper's settings on the loaded model
    sp = cfg.keypoint_detector_config
    assert (sp.max_keypoints, sp.keypoint_threshold, sp.nms_radius, cfg.sinkhorn_iterations) == (1024, 0.005, 4, 20)
    f0, f1 = mt.extract(im0), mt.extract(im1)
    assert 0 < len(f0) <= 1024 and f0.data["descriptors"].shape == (len(f0), 32)
    m = mt.match(f0, f1)
    assert len(m) > 0 and in_bounds(m, im0, im1)
    assert np.all((m.scores > 0) & (m.scores <= 1))
    m2 = mt.match(mt.extract(im0), mt.extract(im1))  # deterministic
    np.testing.assert_array_equal(m.kpts0, m2.kpts0)
    np.testing.assert_array_equal(m.kpts1, m2.kpts1)

    # The whole transformers forward on the processor's input finds the same matches.
    h, w = im0.shape[:2]
    pix = SuperGlueImageProcessorPil(size={"height": h, "width": w})([im0, im1], return_tensors="pt")["pixel_values"]
    with torch.inference_mode():
        out = mt.net(pix)
    kp = out.keypoints[0].numpy() * [w, h]
    m0, s0 = out.matches[0, 0].numpy(), out.matching_scores[0, 0].numpy()
    ok = m0 > -1
    np.testing.assert_allclose(m.kpts0, kp[0][ok], atol=1e-3)
    np.testing.assert_allclose(m.kpts1, kp[1][m0[ok]], atol=1e-3)
    np.testing.assert_allclose(m.scores, s0[ok], rtol=1e-4)


def test_superglue_resized_input_reports_original_pixels(weights_dir, pair):
    _, _, im0, im1 = pair
    big = M.create("superglue", weights=str(weights_dir / "superglue_outdoor"), device="cpu")
    small = M.create("superglue", weights=str(weights_dir / "superglue_outdoor"), max_size=270, device="cpu")
    f = small.extract(im0)
    assert f.data["resized"] == (270, 180) and len(f) > 0
    assert np.all((f.kpts >= 0) & (f.kpts <= [im0.shape[1] - 0.5, im0.shape[0] - 0.5]))
    # a keypoint at resized pixel (x, y) is at ((x + 0.5) * 2 - 0.5, ...) in the original
    np.testing.assert_allclose(f.kpts, (f.data["keypoints"].numpy() + 0.5) * 2 - 0.5)
    assert big.extract(im0).data["resized"] == (im0.shape[1], im0.shape[0])  # 540x360: matched as it is
    assert len(small.match(f, small.extract(np.zeros_like(im1)))) == 0  # a blank image: nothing


def test_indoor_weights_from_the_weights_dir(weights_dir, monkeypatch, pair):
    monkeypatch.setenv(M.WEIGHTS_ENV, str(weights_dir))
    assert {"superglue", "superglue-indoor", "efficientloftr"} <= set(M.available())
    mt = M.create("superglue-indoor", device="cpu")
    assert mt.name == "superglue-indoor"
    indoor = tiny_superglue(1).state_dict()
    for k, v in mt.net.state_dict().items():
        assert torch.equal(v, indoor[k]), k


def test_a_folder_of_another_model_is_refused_with_its_path(weights_dir):
    with pytest.raises(ValueError, match="efficientloftr"):
        M.create("superglue", weights=str(weights_dir / "efficientloftr"), device="cpu")


# ---------------------------------------------------------------------- EfficientLoFTR


def test_mutual_pairs_keep_each_cell_with_its_partner():
    # image 0 cell i matches image 1 cell perm[i]; the order is not raster order in image 1
    perm = [2, 0, 3, 1]
    conf = torch.zeros(4, 4)
    for i, j in enumerate(perm):
        conf[i, j] = 0.5 + 0.1 * i
    conf[0, 1] = 0.3  # a weaker, non-mutual candidate
    i, j, s = mutual_pairs(conf, (1, 4), (1, 4), 0.2, 0)
    assert list(zip(i.tolist(), j.tolist())) == list(enumerate(perm))
    torch.testing.assert_close(s, torch.tensor([0.5, 0.6, 0.7, 0.8]))
    # threshold and border: the 1-cell border of a 3x3 grid leaves the centre cell only
    eye = torch.eye(9)
    i, j, _ = mutual_pairs(eye, (3, 3), (3, 3), 0.5, 1)
    assert i.tolist() == [4] and j.tolist() == [4]
    assert len(mutual_pairs(eye * 0.1, (3, 3), (3, 3), 0.2, 0)[0]) == 0


def test_refine_moves_both_points_to_the_best_pixel_pair():
    w, c, sl = 8, 12, 4
    fine0 = torch.zeros(1, w * w, c)
    fine1 = torch.zeros(1, (w + 2) ** 2, c)
    left, (r_row, r_col) = 9, (2, 5)  # image 0: window pixel (1, 1); image 1: (2, 5) of the inner 8x8
    fine0[0, left, 0] = 10.0
    fine1[0, (r_row + 1) * (w + 2) + (r_col + 1), 0] = 10.0
    kp = torch.tensor([[80.0, 40.0]])
    k0, k1 = refine(fine0, fine1, kp, kp, sl, 10.0)
    torch.testing.assert_close(k0, kp + torch.tensor([[1 - 3.5, 1 - 3.5]]))
    torch.testing.assert_close(k1, kp + torch.tensor([[5 - 3.5, 2 - 3.5]]))  # stage 2 flat: no shift
    # stage 2: image 1's right-hand neighbour in the 3x3 block scores high -> a shift towards +x
    fine0[0, left, -1] = 5.0
    fine1[0, r_row * (w + 2) + r_col + 1, -1] = 20.0  # block (row r-1+1, col r-1+2) = the centre row's right
    _, k1b = refine(fine0, fine1, kp, kp, sl, 10.0)
    dx, dy = (k1b - k1)[0].tolist()
    assert dx > 0.5 and abs(dy) < 1e-6


def test_efficientloftr_on_a_real_pair(weights_dir, pair):
    _, _, im0, im1 = pair
    mt = M.create("efficientloftr", weights=str(weights_dir / "efficientloftr"), match_threshold=0.0, device="cpu")
    f0, f1 = mt.extract(im0), mt.extract(im1)
    assert f0.data["pixels"].shape[-2:] == (352, 544)  # sides multiples of 32
    m = mt.match(f0, f1)
    assert len(m) > 0 and in_bounds(m, im0, im1) and np.all((m.scores > 0) & (m.scores <= 1))
    m2 = mt.match(mt.extract(im0), mt.extract(im1))
    np.testing.assert_array_equal(m.kpts0, m2.kpts0)
    np.testing.assert_array_equal(m.kpts1, m2.kpts1)
    # a query of another size is brought to the reference's input size; points stay in its own pixels
    small = im1[::2, ::2].copy()
    ms = mt.match(f0, mt.extract(small))
    assert in_bounds(ms, im0, small)
    assert len(mt.match(f0, mt.extract(np.zeros_like(im1)))) == 0


def test_efficientloftr_coarse_matches_are_the_models(weights_dir, pair):
    """The coarse pairs we take are the transformers forward's own coarse matches (its row for image 0)."""
    _, _, im0, im1 = pair
    mt = M.create("efficientloftr", weights=str(weights_dir / "efficientloftr"), match_threshold=0.0, device="cpu")
    x0, x1 = mt.extract(im0).data["pixels"], mt.extract(im1).data["pixels"]
    net, cfg = mt.net, mt.net.config
    with torch.inference_mode():
        out = net(torch.stack([x0, x1], 1))
        coarse = net.efficientloftr(torch.stack([x0, x1], 1)).feature_maps[0]
    hc, wc = coarse.shape[-2:]
    flat = coarse[0].flatten(2).transpose(1, 2) / coarse.shape[2] ** 0.5
    sim = flat[0] @ flat[1].t() / cfg.coarse_matching_temperature
    i, j, _ = mutual_pairs(sim.softmax(0) * sim.softmax(1), (hc, wc), (hc, wc), 0.0, cfg.coarse_matching_border_removal)
    theirs = out.matches[0, 1]  # for each image-0 cell, its image-1 cell or -1
    mine = torch.full_like(theirs, -1)
    mine[i] = j
    assert len(i) > 0 and torch.equal(mine, torch.where(out.matching_scores[0, 1] > 0, theirs, -1))


# ---------------------------------------------------------------------- presets and missing weights


@pytest.mark.parametrize("name", ["superglue_pnp_sensor", "efficientloftr_emat_sensor"])
def test_preset_runs_end_to_end(name, weights_dir, monkeypatch, pair):
    from mapfree.estimate import Estimate
    from mapfree.relocalize import Relocalizer

    monkeypatch.setenv(M.WEIGHTS_ENV, str(weights_dir))
    ref, query, _, _ = pair
    method = methods.get(name)
    assert method.depth == "files:sensor"
    loc = Relocalizer.from_method(replace(method, matcher_opts={"device": "cpu", "match_threshold": 0.0}))
    est = loc.relocalize(ref, query)
    assert isinstance(est, Estimate)
    assert est.ok or est.reason  # random weights: a pose or a clean "no estimate" with its reason
    if est.ok:
        assert np.all(np.isfinite(est.pose.R)) and np.all(np.isfinite(est.pose.t))


def test_relocalize_command_with_a_superglue_preset(weights_dir, tmp_path, realmini, capsys):
    from mapfree.cli import main

    cfg = tmp_path / "sg.yaml"
    cfg.write_text(
        f"extends: superglue_emat_sensor\nmatcher_opts:\n  weights: {weights_dir / 'superglue_outdoor'}\n"
        "  device: cpu\n"
    )
    scene = realmini / "val" / "s00000"
    rc = main(
        [
            "relocalize",
            str(scene / "seq0" / "frame_00000.jpg"),
            str(scene / "seq1" / "frame_00010.jpg"),
            "--method",
            str(cfg),
        ]
    )
    out = json.loads(capsys.readouterr().out)
    assert out["method"] == "sg" and rc == (0 if out["ok"] else 3)  # 3: ran, no estimate
    assert out["ok"] or out["reason"]  # random weights at the paper's 0.2 threshold: usually no matches


@pytest.fixture
def offline(monkeypatch, tmp_path):
    """No weights anywhere: empty weights dir and Hugging Face cache, downloads refused."""
    import huggingface_hub.constants as hf

    monkeypatch.setenv("MAPFREE_OFFLINE", "1")
    monkeypatch.setenv(M.WEIGHTS_ENV, str(tmp_path / "empty"))
    monkeypatch.setattr(hf, "HF_HUB_CACHE", str(tmp_path / "hf"))
    return tmp_path


@pytest.mark.parametrize(
    "name, repo",
    [
        ("superglue", "magic-leap-community/superglue_outdoor"),
        ("superglue-indoor", "magic-leap-community/superglue_indoor"),
        ("efficientloftr", "zju-community/efficientloftr"),
    ],
)
def test_missing_weights_offline_name_the_model_and_where_to_put_it(offline, name, repo):
    with pytest.raises(MissingWeightsError) as e:
        M.create(name, device="cpu")
    msg = str(e.value)
    assert repo in msg and f"https://huggingface.co/{repo}" in msg
    assert f"{M.WEIGHTS_ENV}/{repo.split('/')[1]}" in msg and "MAPFREE_OFFLINE" in msg
    assert name not in M.available()


def test_missing_explicit_folder_is_named(offline):
    with pytest.raises(MissingWeightsError, match="nowhere"):
        M.create("efficientloftr", weights=str(offline / "nowhere"))


def test_a_folder_with_weights_of_the_wrong_shape_is_refused(weights_dir, tmp_path):
    import shutil

    bad = tmp_path / "superglue_outdoor"
    shutil.copytree(weights_dir / "superglue_outdoor", bad)
    cfg = json.loads((bad / "config.json").read_text())
    cfg["keypoint_encoder_sizes"] = [8, 24]  # the saved encoder has 16 channels in its second layer
    (bad / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match="superglue_outdoor.*wrong shape"):
        M.create("superglue", weights=str(bad), device="cpu")


@pytest.mark.parametrize("name, folder", [("superglue", "superglue_outdoor"), ("efficientloftr", "efficientloftr")])
def test_batched_path_equals_one_pair_at_a_time(name, folder, weights_dir, realmini):
    from mapfree.relocalize import Relocalizer
    from mapfree.relocalize.batched import BatchOptions

    scene = Dataset(realmini).scene("val", "s00000")
    loc = Relocalizer(
        name,
        "files:sensor",
        "pnp",
        matcher_opts={"device": "cpu", "match_threshold": 0.0, "weights": str(weights_dir / folder)},
    )
    anchor = loc.prepare(scene.reference)
    queries = scene.queries[3:5]
    one = [loc.localize(q, anchor) for q in queries]
    many = list(
        loc.localize_batched(
            queries, anchor=anchor, options=BatchOptions(batch_size=2, decode_workers=1, solve_workers=1)
        )
    )
    for a, b in zip(one, many, strict=True):
        assert a.ok == b.ok and a.reason == b.reason and a.inliers == b.inliers
        if a.ok:
            np.testing.assert_allclose(a.pose.t, b.pose.t, atol=1e-9)
