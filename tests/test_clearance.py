"""Free space with a gradient (iarcs_env/clearance.py): the same answers as the walkable grid, and a gradient that
opens a narrow walkway."""

from __future__ import annotations

import pytest
import torch

from iarcs_env import relations as rel
from iarcs_env.clearance import disk_clearance, reach_clearance
from iarcs_env.datasets.procedural import generate_layouts
from iarcs_env.scene import SceneBatch
from scene_factory import box, make_layout, random_layouts

SQUARE = [(0, 0), (4, 0), (4, 4), (0, 4)]


def test_clearances_say_what_the_walkable_grid_says():
    """On procedural bedrooms and random rooms (rotated, L-shaped, crossing boxes): an object's path clearance is at
    least the agent radius exactly where R_reach's grid reaches it, and the disk clearance next to a bed at least
    the disk's radius exactly where the wheelchair checker's turning circle fits; both answers occur."""
    layouts = [lay.centred() for lay in generate_layouts("bedroom", 24, seed=3) + random_layouts(24, seed=4)]
    batch = SceneBatch.from_layouts(layouts)
    t, h, y, ground = batch.translations.double(), batch.half_sizes.double(), batch.yaws.double(), batch.ground_mask
    bed = rel.class_mask(batch.labels, rel.BEDS, batch.spec.classes) & ground
    for radius in (0.3, 0.45):
        grid = rel.reachable(rel.free_grid(batch.floors, t, h, y, ground, radius=radius), ground)
        clear = reach_clearance(batch.floors, t, h, y, ground, radius)
        assert torch.equal((clear >= radius)[ground], grid[ground])
        assert 0 < int(grid[ground].sum()) < int(ground.sum())
        assert (clear[~ground] == -radius).all()
    for radius, near in ((0.75, bed), (0.75, None), (1.2, None)):
        fits = rel.free_disk(rel.free_grid(batch.floors, t, h, y, ground, radius=radius, reach=False), t, h, y, near,
                             0.5)
        clear = disk_clearance(batch.floors, t, h, y, ground, near=near, reach=radius + 0.5)
        assert torch.equal(clear >= radius, fits)
        assert 0 < int(fits.sum()) < len(layouts)


def test_a_narrow_walkway_has_its_clearance_and_its_gradient_widens_it():
    """A 4 m square room split by a cabinet that leaves a 0.51 m gap at the wall: the nightstand behind it is reached
    through the gap only, so its path clearance is that of the gap's best cell centre, it is
    reachable by a 0.2 m agent and not by R_reach's 0.3 m one, and the gradient moves the cabinet away from the gap
    and shortens it; the disk clearance of the empty room is the distance from the middle cell to the walls."""
    layout = make_layout([box("cabinet", 1.75, 1.2, 1.74, 0.3),  # x 0.01..3.49: the gap is x 3.49..4 at z 0.9..1.5
                          box("nightstand", 0.3, 0.3, 0.25, 0.25),
                          box("wardrobe", 2.0, 3.5, 1.0, 0.3)], floor=SQUARE)
    batch = SceneBatch.from_layouts([layout])
    t, h, y = (batch.translations.double().requires_grad_(True), batch.half_sizes.double().requires_grad_(True),
               batch.yaws.double())
    ground = batch.ground_mask
    clear = reach_clearance(batch.floors, t, h, y, ground, 0.3)
    assert clear[0, 1].item() == pytest.approx(0.235, abs=1e-6)  # the cell centres at x 3.725 (and 3.775: 0.225)
    assert clear[0, 0].item() >= 0.3 and clear[0, 2].item() >= 0.3  # the cabinet and wardrobe face the large side
    for radius, reached in ((0.2, True), (0.3, False)):
        grid = rel.reachable(rel.free_grid(batch.floors, t, h, y, ground, radius=radius), ground)
        assert bool(grid[0, 1]) is reached
    clear[0, 1].backward()
    assert t.grad[0, 0, 0].item() < -0.3  # the cabinet moving away from the gap (-x) widens it
    assert h.grad[0, 0, 0].item() < -0.3  # and so does a shorter cabinet
    assert t.grad[0, 1].abs().max().item() < 1e-6 and t.grad[0, 2].abs().max().item() < 1e-6  # nothing else narrows it
    empty = SceneBatch.from_layouts([make_layout([box("nightstand", 0.3, 0.3, 0.25, 0.25)], floor=SQUARE)])
    middle = disk_clearance(empty.floors, empty.translations.double(), empty.half_sizes.double(),
                            empty.yaws.double(), empty.ground_mask)
    assert middle.item() == pytest.approx(1.975, abs=1e-6)  # a cell centre 0.025 m from the room's middle


def test_kept_bottleneck_points_give_the_reach_clearance_and_follow_the_furniture():
    """The narrow walkway above: the clearance at the bottleneck points found once is the reach clearance; with the
    cabinet moved 0.05 m away from the gap, the kept point's clearance is its new distance to the nearest of cabinet
    and wall (0.275 m: the wall), without searching the grid again; other slots get -radius."""
    from iarcs_env.clearance import clearance_of_points, reach_points

    layout = make_layout([box("cabinet", 1.75, 1.2, 1.74, 0.3), box("nightstand", 0.3, 0.3, 0.25, 0.25),
                          box("wardrobe", 2.0, 3.5, 1.0, 0.3), box("ceiling_lamp", 2.0, 2.0, 0.2, 0.2, y0=2.4)],
                         floor=SQUARE)
    batch = SceneBatch.from_layouts([layout])
    t, h, y, ground = batch.translations.double(), batch.half_sizes.double(), batch.yaws.double(), batch.ground_mask
    points = reach_points(batch.floors, t, h, y, ground, 0.3)
    assert torch.isnan(points[0, 3]).all() and torch.isfinite(points[0, :3]).all()
    kept = clearance_of_points(batch.floors, points, t, h, y, ground, 0.3)
    assert torch.allclose(kept, reach_clearance(batch.floors, t, h, y, ground, 0.3))
    moved = t.clone()
    moved[0, 0, 0] -= 0.05
    assert clearance_of_points(batch.floors, points, moved, h, y, ground, 0.3)[0, 1].item() == pytest.approx(0.275)


def test_a_chair_is_drawn_out_only_where_no_passage_narrows_below_the_agent():
    """A 4 m square dining room, a table at its middle (x 1.4..2.6, z 1.6..2.4) with three chairs 0.1 m under it, drawn
    out to a 0.12 m gap: the south chair keeps 1.08 m to the wall behind it (allowed); the north one goes from 0.65 m
    to 0.43 m of a cabinet (refused for R_reach's 0.6 m agent, allowed for a 0.4 m one); the east one is already
    0.5 m from its cabinet and would be 0.28 m (refused for both)."""
    from iarcs_env.clearance import room_to_pull
    from iarcs_env.relations import class_mask

    layout = make_layout([box("dining_table", 2.0, 2.0, 0.6, 0.4),
                          box("dining_chair", 2.0, 1.5, 0.2, 0.2),    # south: z 1.3..1.7
                          box("dining_chair", 2.0, 2.5, 0.2, 0.2),    # north: z 2.3..2.7
                          box("dining_chair", 2.7, 2.0, 0.2, 0.2),    # east: x 2.5..2.9
                          box("cabinet", 3.7, 2.0, 0.3, 0.5),         # x 3.4..4.0
                          box("cabinet", 2.0, 3.55, 0.5, 0.2)],       # z 3.35..3.75
                         floor=SQUARE, room="diningroom")
    batch = SceneBatch.from_layouts([layout])
    spec = batch.spec
    ground = batch.ground_mask
    movers = class_mask(batch.labels, spec.classes, ["seat"]) & ground
    anchors = class_mask(batch.labels, spec.classes, ["table"]) & ground
    room = room_to_pull(batch.floors, batch.translations, batch.half_sizes, batch.yaws, movers, anchors, ground,
                        gap=0.12, radius=0.3)[0]
    assert room[1, 0] and not room[2, 0] and not room[3, 0]
    assert room[0].all() and room[4].all()  # a table or a cabinet is never drawn
    assert room[1, 2] and room[2, 1]  # two chairs are no pair
    wider = room_to_pull(batch.floors, batch.translations, batch.half_sizes, batch.yaws, movers, anchors, ground,
                         gap=0.12, radius=0.2)[0]
    assert wider[2, 0] and not wider[3, 0]  # a 0.4 m agent still passes the north chair, not the east one
    none = room_to_pull(batch.floors, batch.translations, batch.half_sizes, batch.yaws, movers & False, anchors, ground,
                        gap=0.12, radius=0.3)
    assert none.shape == (1, 6, 6) and none.all()  # no chair, nothing to refuse
