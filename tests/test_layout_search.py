"""The greedy layout search (agents/layout_search.py) and its use as the physics gradient's regression target."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agents.layout_search import search_room, search_rooms, wheelchair_score
from iarcs_env.metrics import batch_float64, evaluate_layouts
from iarcs_env.tasks import task_results
from scene_factory import box, make_layout

SQUARE = [(0, 0), (4, 0), (4, 4), (0, 4)]


def boxed_in():
    """A double bed against the z = 0 wall with a nightstand between it and the x = 0 wall: a 0.5 m gap, where a
    wheelchair (0.9 m) does not reach the nightstand; a wardrobe on the far wall."""
    return make_layout([box("double_bed", 1.4, 1.0, 0.9, 1.0), box("nightstand", 0.25, 0.25, 0.25, 0.25),
                        box("wardrobe", 3.0, 3.7, 0.6, 0.3, yaw=np.pi)], floor=SQUARE)


def test_the_search_frees_a_boxed_in_nightstand_with_the_rooms_own_furniture_on_the_floor_and_clear():
    room = boxed_in()
    assert not task_results("wheelchair", [room])[0] and wheelchair_score(batch_float64([room]))[0] < 3
    (moved,) = search_room(batch_float64([room]), "wheelchair").to_layouts()
    assert task_results("wheelchair", [moved])[0]
    assert moved.labels == room.labels and np.allclose(moved.half_sizes, room.half_sizes)
    metrics = evaluate_layouts([moved])
    assert metrics["Col_obj"] == 0 and metrics["R_out"] == 0
    # what passes already stays where it is
    again = search_room(batch_float64([moved]), "wheelchair")
    np.testing.assert_allclose(again.to_layouts()[0].translations, moved.translations, atol=1e-9)


def test_search_rooms_keeps_the_batch_and_rejects_tasks_without_a_search():
    batch = batch_float64([boxed_in(), boxed_in()])
    out = search_rooms(batch, "wheelchair")
    assert len(out) == 2 and torch.equal(out.labels, batch.labels) and task_results("wheelchair", out).all()
    with pytest.raises(ValueError, match="no layout search for task 'tv_from_bed'; tasks with one: wheelchair"):
        search_room(batch[[0]], "tv_from_bed")


def test_searched_rooms_moves_only_positions_and_yaws_to_where_the_search_put_them():
    """PhysicsGradient.searched_rooms (ddpo.layout_search): the targets are the rollout's rooms with the searched
    positions and yaws in place; sizes and classes are the rooms' own."""
    from agents.physics_gradient import PhysicsGradient
    from iarcs_env.scene import SceneBatch
    from test_ddpo import make_model

    model = make_model(PhysicsGradient, best_of_floor_weight=1.0, layout_search="wheelchair")
    rollout = model.collect_rollouts()
    finals, _ = model.final_rooms(rollout)
    targets = model.searched_rooms(finals, rollout)
    torch.testing.assert_close(targets[..., 3:6], finals[..., 3:6])
    torch.testing.assert_close(targets[..., 8:], finals[..., 8:])
    floors = [model.venv.floors[int(i)] for i in rollout["floor_index"][:, 0]]
    expected = search_rooms(SceneBatch.decode(finals, model.venv.stats, floors), "wheelchair")
    got = SceneBatch.decode(targets, model.venv.stats, floors)
    held = expected.mask
    miss = (got.translations[held] - expected.translations[held].float()).abs().amax(-1)
    # exact but where the search left an object in R_out's 0.05 m margin through a wall: the model's features span
    # the floor's bounding box, so it is encoded touching the wall
    assert (miss < 1e-3).float().mean() > 0.95 and miss.max() < 0.1
    with pytest.raises(ValueError, match="layout_search 'wheelchair' needs best_of_floor_weight > 0"):
        make_model(PhysicsGradient, layout_search="wheelchair")
