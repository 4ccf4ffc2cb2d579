"""The pretraining data of procedural rooms: generated in parallel processes as serially, cached in one file that
gives exactly the tensors and statistics of the uncached path, keyed so that another dataset misses it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import iarcs_env.datasets.procedural as procedural
from agents import pretrain_data
from agents.pretrain import PretrainConfig, train
from agents.pretrain_data import (SceneTensors, cache_key, cache_path, rotated_translation_bounds, stats_for_training,
                                  training_data)
from iarcs_env import FloorPlan, Layout
from iarcs_env.datasets.procedural import generate_layouts, map_room_chunks
from iarcs_env.stats import DatasetStats


@pytest.fixture(autouse=True)
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv(pretrain_data.CACHE_ENV, str(tmp_path / "cache"))
    return tmp_path / "cache"


def config(tmp_path, **kw) -> PretrainConfig:
    base = dict(preset="tiny", num_scenes=60, val_scenes=5, steps=2, batch_size=8, warmup_steps=1, log_every=1,
                checkpoint_every=2, eval_every=2, out=str(tmp_path / "run"), tensorboard=False, device="cpu")
    base.update(kw)
    return PretrainConfig(**base)


def same_rooms(a, b) -> bool:
    return len(a) == len(b) and all(
        x.id == y.id and x.labels == y.labels and np.array_equal(x.translations, y.translations)
        and np.array_equal(x.half_sizes, y.half_sizes) and np.array_equal(x.yaws, y.yaws)
        and np.array_equal(x.floor.vertices, y.floor.vertices) and x.ceiling_height == y.ceiling_height
        for x, y in zip(a, b))


def bitwise_equal(a: SceneTensors | None, b: SceneTensors | None) -> bool:
    """Every tensor the same, bit for bit (-0.0 is not 0.0)."""
    if a is None or b is None:
        return a is b
    if (a.draw_weights is None) != (b.draw_weights is None):
        return False
    for name in SceneTensors.room_fields() + (["draw_weights"] if a.draw_weights is not None else []):
        x, y = getattr(a, name), getattr(b, name)
        if x.dtype != y.dtype or x.shape != y.shape:
            return False
        if x.is_floating_point():
            x, y = x.view(torch.int32), y.view(torch.int32)
        if not torch.equal(x, y):
            return False
    return True


def test_parallel_generation_gives_the_serial_rooms():
    serial = generate_layouts("bedroom", 37, seed=4)
    assert same_rooms(generate_layouts("bedroom", 37, seed=4, processes=2), serial)
    chunks = list(map_room_chunks("bedroom", 37, seed=4, processes=2, chunk_size=5))
    assert [len(c) for c in chunks] == [5] * 7 + [2]
    assert same_rooms([lay for c in chunks for lay in c], serial)
    assert same_rooms(generate_layouts("livingroom", 9, seed=1, flaw_rate=0.5, processes=3),
                      generate_layouts("livingroom", 9, seed=1, flaw_rate=0.5))
    assert generate_layouts("bedroom", 0, processes=2) == []
    with pytest.raises(ValueError, match="num_scenes"):
        generate_layouts("bedroom", -1, processes=2)


def reference_stats(layouts, room, rotation_augment):
    """stats_for_training as it was: every room rotated by 90, 180 and 270 degrees as layouts."""
    stats = DatasetStats.from_layouts(layouts, room)
    if rotation_augment:
        rotated = [lay.centred().rotated(k * math.pi / 2) for lay in layouts for k in (1, 2, 3)]
        stats.bounds_translations = DatasetStats.from_layouts(list(layouts) + rotated, room).bounds_translations
    return stats


def test_rotated_bounds_per_room_give_the_statistics_of_the_rotated_rooms():
    rooms = generate_layouts("bedroom", 40, seed=7) + generate_layouts("livingroom", 10, seed=7)
    for lay in rooms[::7]:  # off-centre floors
        object.__setattr__(lay, "floor", lay.floor.translated([1.3, -0.7]))
        lay.translations[:, [0, 2]] += [1.3, -0.7]
    empty = Layout("bedroom", FloorPlan.from_vertices([(0, 0), (3, 0), (3, 2), (0, 2)]), [], [], [], [])
    for layouts in (rooms[:40], rooms[:40] + [empty], [empty]):
        for rot in (False, True):
            assert stats_for_training(layouts, "bedroom", rot) == reference_stats(layouts, "bedroom", rot)
    assert np.isinf(rotated_translation_bounds([empty])).all()


def test_the_cache_gives_exactly_the_uncached_data(tmp_path, monkeypatch):
    monkeypatch.setattr(pretrain_data, "ROOMS_PER_PROCESS", 20)  # 60 rooms in 2 processes (a pool, as 10,000 are)
    cfg = config(tmp_path)
    rooms = generate_layouts("bedroom", 60, seed=0)
    reference = training_data(cfg, rooms, log=lambda m: None)  # hand-given rooms: computed, never cached
    assert not cache_path(cache_key(cfg)).exists()
    logs = []
    built = training_data(cfg, log=logs.append, progress=False)
    assert logs[0] == "generating 60 procedural bedrooms in 2 processes" and logs[-1].startswith("cached at ")
    path = cache_path(cache_key(cfg))
    assert path.exists() and path.parent == tmp_path / "cache" / "pretrain_data"
    assert not list(path.parent.glob("*.tmp"))
    logs.clear()
    read = training_data(cfg, log=logs.append)
    assert logs == [f"read 55 training and 5 validation rooms from cache {path}"]
    for data in (built, read):
        assert bitwise_equal(data[0], reference[0]) and bitwise_equal(data[1], reference[1])
        assert data[2] == reference[2] and data[2].to_json() == reference[2].to_json()
    # the floor normals of the axis-aligned walls are stored as float16 (exact), the points as float32
    saved = torch.load(path, weights_only=True)
    assert saved["train"]["floor_normals_half"].dtype == torch.float16
    # without rotation augmentation, and without validation rooms
    for kw in (dict(rotation_augment=False), dict(val_scenes=0)):
        cfg2 = config(tmp_path, **kw)
        ref = training_data(cfg2, rooms, log=lambda m: None)
        for _ in range(2):
            got = training_data(cfg2, log=lambda m: None, progress=False)
            assert bitwise_equal(got[0], ref[0]) and bitwise_equal(got[1], ref[1]) and got[2] == ref[2]


def test_training_from_the_cache_is_training_on_the_rooms(tmp_path):
    cfg = config(tmp_path / "cached")
    quiet = dict(progress=False, log=lambda m: None)
    cached = [train(cfg, resume=False, **quiet) for _ in range(2)]  # the second run reads the cache
    given = train(config(tmp_path / "given"), generate_layouts("bedroom", 60, seed=0), **quiet)
    assert cached[0].losses == cached[1].losses == given.losses
    assert cached[0].val_losses == given.val_losses


def test_another_dataset_misses_the_cache(tmp_path, monkeypatch):
    cfg = config(tmp_path)
    training_data(cfg, log=lambda m: None, progress=False)
    first = cache_path(cache_key(cfg))
    changes = [dict(num_scenes=61), dict(data_seed=1), dict(val_scenes=6), dict(rotation_augment=False),
               dict(room="livingroom")]
    paths = {first}
    for kw in changes:
        logs = []
        training_data(config(tmp_path, **kw), log=logs.append, progress=False)
        assert logs[0].startswith("generating"), kw
        paths.add(cache_path(cache_key(config(tmp_path, **kw))))
    monkeypatch.setattr(procedural, "GENERATOR_VERSION", procedural.GENERATOR_VERSION + 1)
    logs = []
    training_data(cfg, log=logs.append, progress=False)
    assert logs[0].startswith("generating") and cache_path(cache_key(cfg)) not in paths
    assert len(paths) == len(changes) + 1 and all(p.exists() for p in paths)


@pytest.mark.parametrize("damage", ["garbage", "truncated", "foreign", "other key", "missing tensor"])
def test_a_corrupt_or_foreign_cache_file_is_built_again(tmp_path, damage):
    cfg = config(tmp_path)
    reference = training_data(cfg, log=lambda m: None, progress=False)
    path = cache_path(cache_key(cfg))
    if damage == "garbage":
        path.write_bytes(b"not a torch file")
    elif damage == "truncated":
        path.write_bytes(path.read_bytes()[:1000])
    elif damage == "foreign":
        torch.save({"model": torch.zeros(3)}, path)
    elif damage == "other key":
        other = config(tmp_path, data_seed=5)
        training_data(other, log=lambda m: None, progress=False)
        cache_path(cache_key(other)).replace(path)
    else:
        saved = torch.load(path, weights_only=True)
        del saved["train"]["yaws"]
        torch.save(saved, path)
    logs = []
    got = training_data(cfg, log=logs.append, progress=False)
    assert logs[0].startswith(f"ignored the data cache {path}") and logs[0].endswith("building it again")
    if damage == "other key":
        assert "data_seed=5" in logs[0]
    assert logs[1].startswith("generating") and logs[-1].startswith("cached at ")
    assert bitwise_equal(got[0], reference[0]) and bitwise_equal(got[1], reference[1]) and got[2] == reference[2]
    logs.clear()
    training_data(cfg, log=logs.append)
    assert logs[0].startswith("read ")


def test_file_datasets_and_given_rooms_are_not_cached(tmp_path, cache_dir):
    from iarcs_env.datasets import save_layouts

    data = save_layouts(generate_layouts("bedroom", 30, seed=2), tmp_path / "rooms.json")
    cfg = config(tmp_path, dataset=str(data))
    train_set, val, stats = training_data(cfg, log=lambda m: None)
    assert len(train_set) == 27 and len(val) == 3 and stats is not None
    assert training_data(cfg, log=lambda m: None, with_stats=False)[2] is None
    assert not cache_dir.exists()


def test_the_cache_keeps_the_canonical_slot_order_apart(tmp_path):
    if "canonical_order" not in PretrainConfig.__dataclass_fields__:
        pytest.skip("no canonical slot order in this iARCS")
    cfg = config(tmp_path, canonical_order=True, permutation_augment=False)
    assert cache_path(cache_key(cfg)) != cache_path(cache_key(config(tmp_path)))
    reference = training_data(cfg, generate_layouts("bedroom", 60, seed=0), log=lambda m: None)
    for _ in range(2):  # built, then read
        got = training_data(cfg, log=lambda m: None, progress=False)
        assert bitwise_equal(got[0], reference[0]) and bitwise_equal(got[1], reference[1]) and got[2] == reference[2]
    assert not bitwise_equal(got[0], training_data(config(tmp_path), log=lambda m: None)[0])
