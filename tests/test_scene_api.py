"""The reward programs' scene API (rewards.scene_api): shapes, documented values, class selection, and
the generated prompt text."""

import math

import pytest
import torch

from iarcs_env.scene import SceneBatch
from rewards.scene_api import Scene, api_reference, public_members
from scene_factory import box, make_layout

ROOM = [(0, 0), (4, 0), (4, 3), (0, 3)]  # centred: x in [-2, 2], z in [-1.5, 1.5]


def scene(*objects, floor=ROOM):
    return Scene(SceneBatch.from_layouts([make_layout(list(objects), floor=floor)]))


def test_shapes_and_basic_properties():
    layouts = [make_layout([box("double_bed", 2, 1, 0.8, 1.0, hy=0.25), box("nightstand", 0.9, 0.3, 0.25, 0.2)]),
               make_layout([box("desk", 1, 1, 0.6, 0.3), box("ceiling_lamp", 2, 1.5, 0.3, 0.3, y0=2.4, hy=0.1),
                            box("chair", 1, 1.6, 0.25, 0.25)])]
    s = Scene(SceneBatch.from_layouts(layouts, num_slots=5))
    B, N = 2, 5
    assert (s.batch_size, s.num_slots, s.room) == (B, N, "bedroom") and "nightstand" in s.classes
    shapes = {"present": (B, N), "position": (B, N, 3), "size": (B, N, 3), "top_height": (B, N), "yaw": (B, N),
              "forward": (B, N, 2)}
    for name, shape in shapes.items():
        assert tuple(getattr(s, name).shape) == shape, name
    for name in ("distance", "gap", "facing_angle"):
        assert tuple(getattr(s, name)().shape) == (B, N, N), name
    assert tuple(s.local_offset().shape) == (B, N, N, 2)
    for name in ("wall_distance", "back_to_wall", "wall_angle"):
        assert tuple(getattr(s, name)().shape) == (B, N), name
    assert tuple(s.walkable().shape) == (B,) and tuple(s.reachable().shape) == (B, N)
    assert s.free_circle(0.5).dtype == torch.bool and tuple(s.free_circle(0.5).shape) == (B,)
    assert s.present.sum(1).tolist() == [2, 3]
    assert s.count("bed").tolist() == [1.0, 0.0]
    assert s.count("seat", "table").tolist() == [1.0, 2.0]  # a nightstand is a table
    assert s.count("support_surface").tolist() == [2.0, 1.0] and s.count("lamp").tolist() == [0.0, 1.0]
    assert s.count("ground").tolist() == [2.0, 2.0] and s.count().tolist() == [2.0, 3.0]
    assert s.top_height[0, :2].tolist() == pytest.approx([0.5, 0.8])
    assert s.size[0, 0].tolist() == pytest.approx([1.6, 0.5, 2.0])
    assert s.reachable()[1].tolist() == [True, False, True, False, False]  # the lamp is no ground object


def test_class_names():
    s = scene(box("double_bed", 2, 1, 0.8, 1.0))
    assert s.objects("dining_table").tolist() == [[False]]  # a living-room class: allowed, never present
    with pytest.raises(ValueError, match="unknown object class or group 'bedd'.*groups: bed, table"):
        s.objects("bedd")
    with pytest.raises(ValueError, match="support_surface"):
        s.count("tv")


def test_local_offset_and_facing_angle():
    # an object at the centre facing +z (left is +x), others to its left, front, right and behind
    s = scene(box("chair", 2, 1.5, 0.2, 0.2), box("stool", 3, 1.5, 0.1, 0.1), box("stool", 2, 2.5, 0.1, 0.1),
              box("stool", 1.5, 1.5, 0.1, 0.1), box("stool", 2, 0.5, 0.1, 0.1))
    off = s.local_offset()[0, 0, 1:]
    assert off.flatten().tolist() == pytest.approx([1, 0, 0, 1, -0.5, 0, 0, -1], abs=1e-6)
    assert s.facing_angle()[0, 0, 1:].tolist() == pytest.approx([math.pi / 2, 0, math.pi / 2, math.pi], abs=1e-6)
    assert s.distance()[0, 0, 1:].tolist() == pytest.approx([1, 1, 0.5, 1], abs=1e-6)
    # turned to face +x: its left is -z
    s = scene(box("chair", 2, 1.5, 0.2, 0.2, yaw=math.pi / 2), box("stool", 3, 1.5, 0.1, 0.1),
              box("stool", 2, 0.5, 0.1, 0.1))
    assert s.forward[0, 0].tolist() == pytest.approx([1, 0], abs=1e-6)
    assert s.local_offset()[0, 0, 1:].flatten().tolist() == pytest.approx([0, 1, 1, 0], abs=1e-6)
    assert s.facing_angle()[0, 0, 1:].tolist() == pytest.approx([0, math.pi / 2], abs=1e-6)


def test_gap():
    s = scene(box("cabinet", 1, 1, 0.5, 0.5), box("cabinet", 2, 1, 0.5, 0.5), box("cabinet", 3.5, 1, 0.5, 0.5),
              box("stool", 1.2, 1.2, 0.1, 0.1), box("shelf", 1, 2.7, 0.5, 0.2, yaw=math.pi / 4))
    gap = s.gap()[0]
    assert float(gap[0, 1]) == pytest.approx(0, abs=1e-6)  # touching
    assert float(gap[1, 2]) == pytest.approx(0.5, abs=1e-6) and float(gap[2, 1]) == pytest.approx(0.5, abs=1e-6)
    assert float(gap[0, 3]) == 0  # inside
    # the rotated shelf's lowest corner: z = 2.7 - (0.5 + 0.2) / sqrt(2); the cabinet's top edge is z = 1.5
    assert float(gap[0, 4]) == pytest.approx(2.7 - 0.7 / math.sqrt(2) - 1.5, abs=1e-5)
    assert torch.equal(gap, gap.T)


def test_walls():
    # centred room: x in [-2, 2], z in [-1.5, 1.5]
    s = scene(box("cabinet", 1, 1, 0.5, 0.3), box("double_bed", 2, 1.0, 0.8, 1.0),
              box("tv_stand", 2, 1.5, 0.6, 0.3, yaw=math.pi), box("wardrobe", 3.9, 1.5, 0.3, 0.5))
    assert s.wall_distance()[0].tolist() == pytest.approx([0.5, 0, 1.2, 0], abs=1e-6)  # the wardrobe pokes out
    back = s.back_to_wall()[0]
    assert float(back[1]) == pytest.approx(0, abs=1e-6)  # headboard against the wall z = 0
    assert float(back[2]) == pytest.approx(3 - 1.8, abs=1e-6)  # facing -z: its back faces the wall z = 3
    assert float(back[0]) == pytest.approx(0.7, abs=1e-6)
    assert s.wall_angle()[0].tolist() == pytest.approx([0, 0, 0, 0], abs=1e-6)  # the TV stand's half turn too
    turned = scene(box("wardrobe", 1, 1, 0.5, 0.3, yaw=math.radians(100)), box("desk", 2, 2, 0.5, 0.3, yaw=0.7))
    assert turned.wall_angle()[0].tolist() == pytest.approx([math.radians(10), 0.7], abs=1e-6)


def test_free_space_with_radius():
    # a row of cabinets across the 4 x 3 room leaves a 0.7 m gap; a stool sits behind it, in the far corner
    row = [box("cabinet", 0.55 + 1.1 * k, 1.8, 0.55, 0.3) for k in range(3)]  # x 0..3.3
    s = scene(*row, box("stool", 0.4, 2.7, 0.2, 0.2))
    assert s.reachable(0.3)[0].all() and not s.reachable(0.4)[0, 3] and s.reachable(0.4)[0, :3].all()
    assert float(s.walkable(0.3)[0]) == pytest.approx(1.0)
    assert 0 < float(s.walkable(0.4)[0]) < 1
    empty = scene(box("ceiling_lamp", 2, 1.5, 0.3, 0.3, y0=2.4, hy=0.1))  # lamps do not block the floor
    assert empty.free_circle(1.45).tolist() == [True] and empty.free_circle(1.55).tolist() == [False]


def test_free_circle_near():
    # a bed along the left wall of a 6 x 3 room (x 0..2, z 1..2); a 0.75 m disk fits right next to it
    bed = box("single_bed", 1.0, 1.5, 0.5, 1.0, yaw=math.pi / 2)
    s = scene(bed, floor=[(0, 0), (6, 0), (6, 3), (0, 3)])
    beds = s.objects("bed")
    assert s.free_circle(0.75).tolist() == [True]
    assert s.free_circle(0.75, near=beds, within=0.5).tolist() == [True]
    # a wardrobe across the room at x = 2.2..2.8: the nearest disk is beyond it, its edge 0.8 m from the bed
    s = scene(bed, box("wardrobe", 2.5, 1.5, 0.3, 1.5), floor=[(0, 0), (6, 0), (6, 3), (0, 3)])
    beds = s.objects("bed")
    assert s.free_circle(0.75).tolist() == [True]
    assert s.free_circle(0.75, near=beds, within=0.5).tolist() == [False]
    assert s.free_circle(0.75, near=beds, within=1.0).tolist() == [True]


def test_shaping_helpers():
    s = scene(box("chair", 1, 1, 0.2, 0.2), box("desk", 2, 1, 0.5, 0.3), box("stool", 3, 1, 0.2, 0.2))
    x = torch.tensor([0.5, 1.0, 1.2])
    assert s.below(x, 1.0).tolist() == pytest.approx([1, 1, math.exp(-2)])
    assert s.above(x, 1.0).tolist() == pytest.approx([math.exp(-5), 1, 1])
    assert s.within(x, 0.6, 1.1, scale=0.5).tolist() == pytest.approx([math.exp(-0.2), 1, math.exp(-0.2)])
    seats, desks, beds = s.objects("seat"), s.objects("desk"), s.objects("bed")
    assert s.pair_mask(seats, seats)[0].nonzero().tolist() == [[0, 2], [2, 0]]
    dist = s.distance()
    assert s.best_pair(-dist, desks, seats).tolist() == pytest.approx([-1.0])
    assert s.best_pair(dist, beds, seats).tolist() == [0.0]
    values = torch.tensor([[0.2, 0.9, 0.5]])
    assert s.all_of(values, seats).tolist() == pytest.approx([0.2]) and s.all_of(values, beds).tolist() == [1.0]
    assert s.any_of(values, seats).tolist() == pytest.approx([0.5]) and s.any_of(values, beds).tolist() == [0.0]
    assert s.mean_of(values, seats).tolist() == pytest.approx([0.35]) and s.mean_of(values, beds).tolist() == [0.0]


def test_results_are_copies():
    s = scene(box("chair", 1, 1, 0.2, 0.2), box("stool", 2, 1, 0.2, 0.2))
    s.distance().zero_()
    s.position.zero_()
    assert float(s.distance()[0, 0, 1]) == pytest.approx(1.0) and float(s.position[0, 0, 0]) != 0


def test_api_reference_documents_every_public_member():
    text = api_reference()
    assert public_members()[:5] == ["batch_size", "num_slots", "room", "classes", "present"]
    for name in public_members():
        assert f"scene.{name}" in text, name
    assert "scene.free_circle(radius, near=None, within=0.5, middle=None)" in text
    assert "def reward(scene):" in text and "support_surface (" in text and "forward = (sin(yaw), cos(yaw))" in text
    assert "dining_table" not in api_reference("bedroom").split("Classes:")[1]
    assert "``" not in text.replace("```", "")
