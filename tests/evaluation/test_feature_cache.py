"""The evaluation's feature cache keeps a query's descriptors about displaced centres."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sgvloc.core.config import RetrievalConfig
from sgvloc.core.encoders import EncoderSpec, make_encoder
from sgvloc.core.sequence import KittiSequence
from sgvloc.tools.evaluation.cache import FeatureCache


def test_variants_are_cached_with_their_centres(tmp_path: Path, balm_mini_dir: Path) -> None:
    """Stored with the centres asked for; asked again, read back the same; other centres,
    or a file stored before the encoder described them, are computed again; without
    centres the plain features come back."""
    path = KittiSequence(balm_mini_dir).paths[3]
    centres = RetrievalConfig().centres()
    cache = FeatureCache(tmp_path, make_encoder(EncoderSpec()))
    first = cache.get(path, centres)
    assert first.global_variants.shape == (8, len(first.global_descriptor))
    again = cache.get(path, centres)
    assert (cache.hits, cache.misses) == (1, 1)
    np.testing.assert_array_equal(again.global_variants, first.global_variants)
    assert cache.get(path).global_variants is None and cache.hits == 2
    other = cache.get(path, centres[:4])
    assert other.global_variants.shape[0] == 4 and cache.misses == 2
    # a file written when the encoder gave no variants for these centres
    f = cache.path_for(path)
    with np.load(f) as z:
        stored = {k: z[k] for k in z.files}
    stored.update(centres=centres, global_variants=np.zeros((0, stored["global_descriptor"].size)))
    np.savez(f, **stored)
    again = cache.get(path, centres)
    assert cache.misses == 3
    np.testing.assert_array_equal(again.global_variants, first.global_variants)
    # encoders without displaced descriptors: stored empty, read back as none
    for spec in ({"kind": "handcrafted"}, {"learned": {"global_descriptor": "network"}}):
        plain = FeatureCache(tmp_path, make_encoder(EncoderSpec.model_validate(spec)))
        assert plain.get(path, centres).global_variants is None
        assert plain.get(path, centres).global_variants is None and plain.hits == 1


def test_fpfh_keypoints_are_taken_from_the_handcrafted_files(
    tmp_path: Path, balm_mini_dir: Path, monkeypatch
) -> None:
    """The learned encoder with FPFH keypoints reuses the handcrafted encoder's cached
    cloud and FPFH of a scan (the self-test runs both): the features are those it computes
    alone, and FPFH is not computed again."""
    import sgvloc.core.encoders.learned as learned

    path = KittiSequence(balm_mini_dir).paths[3]
    centres = RetrievalConfig().centres()
    spec = EncoderSpec.model_validate({"learned": {"local_features": "fpfh"}})
    alone = FeatureCache(tmp_path / "alone", make_encoder(spec)).get(path, centres)
    FeatureCache(tmp_path / "shared", make_encoder(EncoderSpec(kind="handcrafted"))).get(path)

    def no_fpfh(*args, **kwargs):
        raise AssertionError("FPFH computed again")

    monkeypatch.setattr(learned, "keypoint_features", no_fpfh)
    cache = FeatureCache(tmp_path / "shared", make_encoder(spec))
    shared = cache.get(path, centres)
    for name in ("global_descriptor", "keypoints", "local_features", "global_variants"):
        np.testing.assert_array_equal(getattr(shared, name), getattr(alone, name))
    np.testing.assert_array_equal(
        cache.cloud(path), FeatureCache(tmp_path / "alone", make_encoder(spec)).cloud(path)
    )
    # without the handcrafted file it computes FPFH itself
    with pytest.raises(AssertionError, match="FPFH computed again"):
        FeatureCache(tmp_path / "other", make_encoder(spec)).get(path)
