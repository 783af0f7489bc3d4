"""What one API process keeps for relocalization, and how it is shared: the pool of built methods (bounded in
bytes, shared by equal configurations), the prepared-anchor cache and the heavy threads (a fair share per
account). In-process, with real SIFT relocalizers on realmini-dev photos."""

from __future__ import annotations

import pytest

from mapfree.data import Dataset


@pytest.fixture(scope="module")
def pair(realmini_dir):
    scene = Dataset(realmini_dir).scene("val", "s00000")
    ref, query = scene.reference, scene.frame("seq1/frame_00009.jpg")
    return ref.image(), ref.intrinsics, ref.depth("sensor"), query.image(), query.intrinsics, query.depth("sensor")


def test_a_depth_suffix_no_request_can_carry_is_refused_before_anything_is_built():
    from mapfree.service.reloc import check_method
    from mapfree.service.uploads import UploadError

    for name in ("disk-lightglue_pnp_d1", "aliked-lightglue_pnp_zz1", "sift_pnp_d10"):
        with pytest.raises(UploadError) as e:
            check_method(name)
        assert e.value.status == 422 and "uploaded with the photo" in e.value.message
    assert check_method("sift_pnp_mono") == "sift_pnp_mono"
    assert check_method("sift_emat_none") == "sift_emat_none"


def test_method_names_share_a_pool_bounded_in_bytes(pair):
    """Three names of one configuration build one relocalizer; three configurations over a budget of one keep
    one (the most recent), and every answer is the same as before the others came."""
    from mapfree.service.reloc import Localizers

    ref_img, ref_K, ref_d, q_img, q_K, q_d = pair
    locs = Localizers(per_method=1, pool_bytes=1 << 30)
    poses = [locs.localize(f"a{i}", name, ref_img, ref_K, ref_d, q_img, q_K).pose
             for i, name in enumerate(("sift_pnp_sensor", "sift_pnp_mono", "sift_pnp_dptkitti"))]
    assert locs.pool.built == 1 and locs.pool.configs() == 1
    assert all(p is not None for p in poses)

    small = Localizers(per_method=1, pool_bytes=1)  # room for less than one: the most recent is kept
    for name in ("sift_pnp_sensor", "sift_emat_sensor", "sift_procrustes_sensor", "sift_pnp_sensor"):
        est = small.localize("b", name, ref_img, ref_K, ref_d, q_img, q_K, q_d)  # query depth: each solver runs
        assert est.pose is not None, (name, est.reason)
        assert small.pool.configs() == 1
    assert small.pool.built == 4  # sift_pnp_sensor was dropped and built again
