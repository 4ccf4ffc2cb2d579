import numpy as np
import pytest
import torch

from iarcs_env import DatasetStats, SceneBatch, floor_features, get_room
from iarcs_env.scene import box_corners_xz
from conftest import L_SHAPE, make_layout

BED = ("double_bed", (2.0, 0.4, 1.0), (0.9, 0.4, 1.05), np.pi / 2)
NIGHTSTAND = ("nightstand", (0.3, 0.25, 2.4), (0.25, 0.25, 0.2), -np.pi / 2)
LAMP = ("pendant_lamp", (2.0, 2.3, 1.5), (0.3, 0.2, 0.3), 0.0)


def _stats():
    return DatasetStats("bedroom", [-3.0, 0.0, -3.0, 3.0, 3.0, 3.0], [0.05, 0.05, 0.05, 2.0, 1.5, 1.5])


def test_room_specs():
    bed = get_room("bedroom")
    assert len(bed.classes) == 21 and bed.num_classes == 22 and bed.max_objects == 12
    assert bed.feature_dim == 30 and bed.vocabulary[-1] == "empty"
    for name in ("living_room", "LivingRoom", "livingroom", "dining-room"):
        spec = get_room(name)
        assert len(spec.classes) == 24 and spec.max_objects == 21
    with pytest.raises(ValueError, match="choose one of"):
        get_room("kitchen")


def test_encode_decode_round_trip_keeps_every_object():
    layouts = [make_layout([BED, NIGHTSTAND, LAMP]), make_layout([NIGHTSTAND], floor=L_SHAPE)]
    batch = SceneBatch.from_layouts(layouts, num_slots=12)
    stats = _stats()
    x = batch.encode(stats)
    assert x.shape == (2, 12, 30)
    # one-hot mapped to {-1, +1}; unused slots are class empty with zero geometry
    assert set(torch.unique(x[..., 8:]).tolist()) == {-1.0, 1.0}
    assert (x[0, 3:, 8 + 21] == 1).all() and (x[0, 3:, :8] == 0).all()
    # [cos, sin] of yaw
    torch.testing.assert_close(x[0, 0, 6:8], torch.tensor([0.0, 1.0]), atol=1e-6, rtol=0)
    back = SceneBatch.decode(x, stats, batch.floors)
    assert torch.equal(back.labels, batch.labels)
    m = batch.mask
    torch.testing.assert_close(back.translations[m], batch.translations[m], atol=1e-5, rtol=0)
    torch.testing.assert_close(back.half_sizes[m], batch.half_sizes[m], atol=1e-5, rtol=0)
    torch.testing.assert_close(back.yaws[m], batch.yaws[m], atol=1e-5, rtol=0)
    # decoded layouts carry the same objects (centred on the floor's bounding box)
    out = back.to_layouts()
    assert out[0].labels == ["double_bed", "nightstand", "pendant_lamp"] and out[1].labels == ["nightstand"]
    np.testing.assert_allclose(out[0].translations[0], [0.0, 0.4, -0.5], atol=1e-5)


def test_translations_are_relative_to_floor_bbox_centre():
    lay = make_layout([BED], floor=((10, 20), (14, 20), (14, 23), (10, 23)))
    lay.translations[0] = [12.5, 0.4, 21.0]
    batch = SceneBatch.from_layouts([lay])
    torch.testing.assert_close(batch.translations[0, 0], torch.tensor([0.5, 0.4, -0.5]))
    assert np.allclose(batch.floors[0].centre, 0)


def test_encoding_clips_to_bounds_and_decoding_keeps_sizes_positive():
    stats = _stats()
    lay = make_layout([("wardrobe", (2.0, 1.0, 1.5), (5.0, 1.0, 0.3), 0.0)], floor=((-8, -8), (8, -8), (8, 8), (-8, 8)))
    x = SceneBatch.from_layouts([lay]).encode(stats)
    assert x[..., :6].abs().max() <= 1
    x[0, 0, 3:6] = -5  # far below the size bounds
    back = SceneBatch.decode(x, stats, [lay.floor])
    assert (back.half_sizes[0, 0] > 0).all()


def test_too_many_objects_for_the_slots_is_a_clear_error():
    with pytest.raises(ValueError, match="raise num_slots"):
        SceneBatch.from_layouts([make_layout([NIGHTSTAND] * 3)], num_slots=2)


def test_floor_features_scale_points_and_keep_normals():
    stats = _stats()
    lay = make_layout([], floor=((-3, -3), (3, -3), (3, 3), (-3, 3)))
    f = floor_features([lay.floor], stats)
    assert f.shape == (1, 256, 4)
    assert f[0, :, :2].abs().max().item() == pytest.approx(1.0)
    torch.testing.assert_close(f[0, :, 2:].norm(dim=-1), torch.ones(256))


def test_box_corners_follow_the_rotation_convention():
    # R_y(yaw): local (lx, lz) -> (x + c*lx + s*lz, z - s*lx + c*lz); local +z (front) -> (sin, cos)
    c = box_corners_xz(np.zeros(2), np.array([1.0, 0.5]), np.array(np.pi / 2))
    np.testing.assert_allclose(c, [[-0.5, 1], [-0.5, -1], [0.5, -1], [0.5, 1]], atol=1e-12)
    t = box_corners_xz(torch.zeros(2), torch.tensor([1.0, 0.5]), torch.tensor(np.pi / 2))
    np.testing.assert_allclose(t.numpy(), c, atol=1e-6)


def test_stats_from_layouts_and_dataset_stats_file(tmp_path):
    layouts = [make_layout([BED, NIGHTSTAND]), make_layout([NIGHTSTAND])]
    stats = DatasetStats.from_layouts(layouts)
    assert stats.object_count_histogram[:3] == [0, 1, 1]
    assert stats.class_frequencies["nightstand"] == pytest.approx(2 / 3)
    assert stats.count_furniture["double_bed"] == 1
    stats.save(tmp_path / "dataset_stats.txt")
    raw = (tmp_path / "dataset_stats.txt").read_text()
    assert '"class_labels"' in raw and '"start"' in raw and '"end"' in raw
    back = DatasetStats.load(tmp_path / "dataset_stats.txt")
    assert back == stats
    np.testing.assert_allclose(back.count_distribution(2), [0, 0.5, 0.5])


def test_scene_batch_indexing():
    layouts = [make_layout([NIGHTSTAND], id=f"s{i}") for i in range(4)]
    batch = SceneBatch.from_layouts(layouts)
    assert batch[1:3].ids == ["s1", "s2"] and batch[[3, 0]].ids == ["s3", "s0"]
    picked = batch[np.array([True, False, False, True])]
    assert picked.ids == ["s0", "s3"] and picked.labels.shape == (2, 1) and len(picked.floors) == 2
