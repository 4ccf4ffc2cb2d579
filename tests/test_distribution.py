"""FID, KID and SCA on top-down renders (iarcs_env.distribution)."""

import dataclasses

import numpy as np
import pytest

from iarcs_env import distribution as D
from iarcs_env.metrics import evaluate_layouts
from scene_factory import random_layouts


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("IARCS_CACHE_DIR", str(tmp_path))


def test_fid_and_kid_on_features():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(400, 16))
    b = rng.normal(size=(400, 16))
    assert D.fid(a, a) == pytest.approx(0.0, abs=1e-6)
    assert D.fid(a, b) < 1.0
    assert D.fid(a, b + 1.0) == pytest.approx(16.0, rel=0.15)  # squared mean shift of 1 in 16 dimensions
    assert abs(D.kid(a, b)) < 0.02 and D.kid(a, b + 1.0) > 0.5


def test_renders_have_a_fixed_scale_per_room_type():
    layouts = random_layouts(3, seed=0)
    img = D.render_set(layouts, size=32)
    assert img.shape == (3, 32, 32, 3) and img.dtype == np.uint8
    assert D.RENDER_EXTENT["bedroom"] == 3.1


def test_fid_of_a_set_with_itself_is_zero_and_grows_with_a_shift():
    real = random_layouts(64, seed=0, max_objects=6, spread=0.6)
    shifted = [dataclasses.replace(l, translations=l.translations + np.array([0.8, 0.0, 0.6])) for l in real]
    extractor = D.render_cnn_extractor(real, size=64, epochs=3)
    assert extractor.name.startswith("render-cnn:") and "64 reference renders" in extractor.name
    f_real = extractor(D.render_set(real))
    f_shift = extractor(D.render_set(shifted))
    a, b = D.standardise(f_real, f_real)
    assert D.fid(a, b) == pytest.approx(0.0, abs=1e-6)
    a, b = D.standardise(f_shift, f_real)
    assert D.fid(a, b) > 1.0
    # the trained network is cached by a hash of the reference renders
    again = D.render_cnn_extractor(real, size=64, epochs=3)
    assert again.name == extractor.name
    np.testing.assert_allclose(again(D.render_set(real[:4])), f_real[:4], rtol=1e-4, atol=1e-4)


def test_sca_is_near_half_for_one_distribution_and_high_for_different_ones():
    a = D.render_set(random_layouts(100, seed=1, max_objects=6, spread=0.6))
    b = D.render_set(random_layouts(100, seed=2, max_objects=6, spread=0.6))
    sparse = D.render_set([dataclasses.replace(l, labels=l.labels[:1], translations=l.translations[:1],
                                               half_sizes=l.half_sizes[:1] * 0.3, yaws=l.yaws[:1], extras=[{}])
                           for l in random_layouts(100, seed=3, max_objects=6, spread=0.6)])
    same = D.sca(a, b, epochs=8)
    different = D.sca(sparse, b, epochs=8)
    assert 0.3 <= same <= 0.7
    assert different >= 0.8


def test_distribution_metrics_through_evaluate_layouts_name_the_extractor():
    gen = random_layouts(40, seed=5, max_objects=5, spread=0.6)
    real = random_layouts(40, seed=6, max_objects=5, spread=0.6)
    out = evaluate_layouts(gen, reference=real, features="cnn",
                           distribution_kwargs={"cnn_epochs": 2, "sca_epochs": 2, "size": 32})
    assert {"FID", "KID", "SCA", "feature_extractor"} <= set(out)
    assert out["feature_extractor"].startswith("render-cnn:") and 0 <= out["SCA"] <= 1 and out["FID"] >= 0


def test_clip_needs_a_local_checkpoint(tmp_path):
    with pytest.raises(FileNotFoundError, match="no CLIP checkpoint"):
        D.get_extractor(f"clip:{tmp_path / 'missing'}", [])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="could not load a CLIP model"):
        D.clip_extractor(tmp_path / "empty")
    with pytest.raises(ValueError, match="unknown feature extractor"):
        D.get_extractor("inception", [])
