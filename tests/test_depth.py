"""Depth sources: sensor files on realmini-dev, the scale-free ``none``, and a transformers depth network
(a tiny randomly initialised Depth Anything saved here) loaded by path, batched and cached."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import mapfree.depth as D
from mapfree.data import Dataset, read_depth
from mapfree.depth.hf import MissingModelError

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def scene(realmini):
    return Dataset(realmini).scene("val", "s00000")


def test_files_source_reads_the_png(scene):
    src = D.create("files:sensor")
    assert src.metric and src.name == "files:sensor" and isinstance(src, D.DepthSource)
    for frame in (scene.reference, scene.queries[5]):
        d = src.depth(frame)
        ref = read_depth(frame.depth_path("sensor"))
        assert d.dtype == np.float32 and d.shape == (frame.intrinsics.height, frame.intrinsics.width)
        np.testing.assert_array_equal(d, ref)
        assert (d > 0).mean() > 0.5


def test_files_source_refuses_a_map_of_another_frame(scene, tmp_path):
    """A depth PNG whose aspect ratio is not the image's (another frame's map, rotated, cropped) or that is 8-bit
    (not millimetres) is a FormatError naming the file, not a silently stretched or 1000x too small scale.
    A map at another resolution of the same aspect ratio is still resized (ScanNet stores depth smaller)."""
    import cv2

    from mapfree.data import FormatError, Frame

    src_frame = scene.queries[5]
    mm = cv2.imread(str(src_frame.depth_path("sensor")), cv2.IMREAD_UNCHANGED)  # 540x360 uint16
    frame = Frame(src_frame.name, tmp_path / "q.jpg", src_frame.intrinsics)
    src = D.create("files:sensor")
    cv2.imwrite(str(frame.depth_path("sensor")), cv2.resize(mm, (100, 80), interpolation=cv2.INTER_NEAREST))
    with pytest.raises(FormatError, match=r"q\.sensor\.png.*100x80.*540x360"):
        src.depth(frame)
    cv2.imwrite(str(frame.depth_path("sensor")), np.ascontiguousarray(mm.T))  # portrait map for a landscape image
    with pytest.raises(FormatError, match="360x540"):
        src.depth(frame)
    cv2.imwrite(str(frame.depth_path("sensor")), (mm // 100).astype(np.uint8))
    with pytest.raises(FormatError, match=r"q\.sensor\.png.*8-bit"):
        src.depth(frame)
    cv2.imwrite(str(frame.depth_path("sensor")), cv2.resize(mm, (270, 180), interpolation=cv2.INTER_NEAREST))
    assert src.depth(frame).shape == (360, 540)


def test_files_source_missing_file_is_none(realmini, scene):
    no_depth = Dataset(realmini).scene("val", "s00003")  # ships without depth maps
    assert D.create("files:sensor").depth(no_depth.reference) is None
    assert D.create("files:dptkitti").depth(scene.reference) is None


def test_none_and_unknown_specs(scene):
    src = D.create("none")
    assert src.metric is False and src.depth(scene.reference) is None
    with pytest.raises(KeyError, match="unknown depth spec"):
        D.create("magic")
    with pytest.raises(ValueError):
        D.create("files:")
    assert D.HUB_MODELS["dav2-indoor"] == "depth-anything/Depth-Anything-V2-Metric-Indoor-Small-hf"


@pytest.fixture(scope="module")
def tiny_model_dir(tmp_path_factory):
    """A 0.5 MB metric Depth Anything (DINOv2 backbone, random weights) with its processor, saved like a hub repo."""
    from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config
    from transformers.models.dpt.image_processing_pil_dpt import DPTImageProcessorPil

    torch.manual_seed(0)
    backbone = Dinov2Config(
        image_size=56,
        patch_size=14,
        hidden_size=32,
        num_hidden_layers=4,
        num_attention_heads=2,
        intermediate_size=64,
        out_indices=[1, 2, 3, 4],
        reshape_hidden_states=False,
    )
    cfg = DepthAnythingConfig(
        backbone_config=backbone,
        patch_size=14,
        reassemble_hidden_size=32,
        neck_hidden_sizes=[8, 16, 16, 32],
        fusion_hidden_size=16,
        head_hidden_size=8,
        depth_estimation_type="metric",
        max_depth=20,
    )
    model = DepthAnythingForDepthEstimation(cfg)
    proc = DPTImageProcessorPil(
        size={"height": 56, "width": 56},
        keep_aspect_ratio=True,
        ensure_multiple_of=14,
        image_mean=[0.485, 0.456, 0.406],
        image_std=[0.229, 0.224, 0.225],
    )
    d = tmp_path_factory.mktemp("tiny-depth-anything")
    model.save_pretrained(d)
    proc.save_pretrained(d)
    return d


def test_transformers_model_from_local_dir_runs_and_caches(tiny_model_dir, scene, tmp_path):
    src = D.create(f"hf:{tiny_model_dir}", cache_dir=str(tmp_path / "cache"), device="cpu", batch_size=2)
    assert src.metric and isinstance(src, D.DepthSource)
    ref, q = scene.reference, scene.queries[5]
    d = src.depth(ref)
    assert d.shape == (ref.intrinsics.height, ref.intrinsics.width) and d.dtype == np.float32
    assert np.all(np.isfinite(d)) and np.all(d >= 0) and d.max() > 0
    assert src.predictions == 1
    # second time: from the disk cache, identical, no network run
    again = src.depth(ref)
    assert src.predictions == 1 and src.cache.hits == 1
    np.testing.assert_array_equal(again, d)
    # a fresh source (another process) reuses the cache too; a batch predicts only the missing frame
    other = D.create(f"hf:{tiny_model_dir}", cache_dir=str(tmp_path / "cache"), device="cpu")
    both = other.depth_many([ref, q])
    assert other.predictions == 1 and other.cache.hits == 1
    np.testing.assert_array_equal(both[0], d)
    assert both[1].shape == (q.intrinsics.height, q.intrinsics.width)


def test_batched_prediction_equals_single(tiny_model_dir, scene):
    src = D.create(f"hf:{tiny_model_dir}", device="cpu", batch_size=4)
    frames = [scene.reference, scene.queries[5]]
    batch = src.depth_many(frames)
    assert src.predictions == 2
    for f, b in zip(frames, batch):
        np.testing.assert_allclose(src.depth(f), b, rtol=1e-4, atol=1e-4)


def test_missing_model_names_the_id(monkeypatch, tmp_path, scene):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    src = D.create("dav2-outdoor", device="cpu")
    with pytest.raises(MissingModelError) as e:
        src.depth(scene.reference)
    msg = str(e.value)  # the one shape of every missing model: where it was looked for, how to get it
    assert "depth-anything/Depth-Anything-V2-Metric-Outdoor-Small-hf" in msg and "$MAPFREE_WEIGHTS_DIR" in msg
    assert "hf download depth-anything/Depth-Anything-V2-Metric-Outdoor-Small-hf --local-dir" in msg
    with pytest.raises(MissingModelError, match="does not exist"):
        D.create(f"hf:{tmp_path / 'nothing-here'}")
