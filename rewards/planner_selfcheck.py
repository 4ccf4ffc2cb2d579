"""The offline planner's self-check (:mod:`rewards.planner`): for every check of a plan, small hand-placed rooms
that satisfy it and rooms that violate it, built from the check's own reading (its objects, thresholds and
scope; no data needed). A program whose check, or whose reward, does not score the satisfying room above the
violating one is refused: it would reward something else, or the opposite, of what the plan says."""

from __future__ import annotations

import math

import numpy as np

from iarcs_env.floorplan import FloorPlan
from iarcs_env.relations import CLASS_GROUPS
from iarcs_env.rooms import get_room
from iarcs_env.scene import Layout

from .planner_checks import Check, Entity, Plan

#: Half sizes (x, y, z) of a subject and of a reference object in the example rooms (m).
SUBJECT, REFERENCE = (0.3, 0.4, 0.25), (0.8, 0.4, 0.6)
#: The least margin by which a check must score its satisfying room above its violating one.
MARGIN = 0.05


def _class(ent: Entity, classes: tuple[str, ...]) -> str | None:
    """A class of the room that the entity names (the first one, in the room's order)."""
    names = {c for n in ent.names for c in CLASS_GROUPS.get(n, (n,))}
    return next((c for c in classes if c in names), None)


def _ground(classes: tuple[str, ...]) -> list[str]:
    """The room's classes that stand on the floor (obstacles of the free-space checks)."""
    return [c for c in classes if c in CLASS_GROUPS["ground"]]


def _obj(label: str, x: float, z: float, half=SUBJECT, yaw: float = 0.0) -> tuple:
    return label, (x, half[1], z), half, yaw


def _layout(room: str, objects: list[tuple], w: float = 8.0, d: float = 6.0) -> Layout:
    floor = FloorPlan.from_vertices([(0, 0), (w, 0), (w, d), (0, d)])
    return Layout(room, floor, [o[0] for o in objects], np.array([o[1] for o in objects], float).reshape(-1, 3),
                  np.array([o[2] for o in objects], float).reshape(-1, 3), np.array([o[3] for o in objects], float))


def _value(check: Check, name: str, default: float = 0.0) -> float:
    return next((p.value for p in check.params if p.name.rstrip("_0123456789") == name), default)


def _relation(check: Check, s: str, r: str) -> tuple[list[tuple], list[tuple]] | None:
    """(objects where "s <relation> r" holds, objects where it does not) for a relation check."""
    ref = _obj(r, 4.0, 3.0, REFERENCE)
    hw, hd = REFERENCE[0], REFERENCE[2]
    kind = check.kind
    if kind in ("near", "far"):
        d = _value(check, "DISTANCE", _value(check, "NEAR_DISTANCE", _value(check, "FAR_DISTANCE", 0.5)))
        x = 4.0 + hw + SUBJECT[0]
        return [ref, _obj(s, x + d / 2, 3.0)], [ref, _obj(s, min(x + d + 1.0, 7.6), 3.0)]
    if kind in ("facing", "away"):
        toward, away = _obj(s, 4.0, 5.0, yaw=math.pi), _obj(s, 4.0, 5.0)
        return ([ref, toward], [ref, away]) if kind == "facing" else ([ref, away], [ref, toward])
    if kind in ("in_front", "behind"):
        depth = _value(check, "DEPTH", _value(check, "FRONT_DEPTH", 0.9))
        sign = 1 if kind == "in_front" else -1
        inside = _obj(s, 4.0, 3.0 + sign * (hd + min(depth, 1.2) / 2))
        return [ref, inside], [ref, _obj(s, 4.0, 3.0 - sign * (hd + 1.0))]
    if kind in ("side", "either_side"):
        bed = _obj(r, 4.0, 3.0, (0.9, 0.4, 1.0))
        left, right = _obj(s, 4.0 + 0.9 + 0.3, 2.5), _obj(s, 4.0 - 0.9 - 0.3, 2.5)
        far_l, far_r = _obj(s, 4.0 + 2.8, 2.5), _obj(s, 4.0 - 2.8, 2.5)
        if kind == "either_side":
            return [bed, left, right], [bed, far_l, far_r]
        wanted_left = check.key.split("_of_")[0].endswith("left")
        return ([bed, left], [bed, right]) if wanted_left else ([bed, right], [bed, left])
    if kind == "view":
        lo, hi = _value(check, "VIEW_MIN", 1.5), _value(check, "VIEW_MAX", 3.5)
        viewer = _obj(r, 4.0, 0.8)
        z = 0.8 + (lo + hi) / 2
        return [viewer, _obj(s, 4.0, z, yaw=math.pi)], [viewer, _obj(s, 4.0, z)]
    return None


def examples(check: Check, room: str) -> tuple[list[Layout], list[Layout]] | None:
    """(rooms satisfying the check, rooms violating it), or None when the check has none here (a class the room type
    lacks, a kind without examples)."""
    classes = get_room(room).classes
    labels = [_class(e, classes) for e in check.entities]
    if None in labels:
        return None
    kind, scope = check.kind, check.scope
    s = labels[0] if labels else None
    if kind == "between":
        x, a, b = labels
        ends = [_obj(a, 1.5, 3.0), _obj(b, 6.5, 3.0)]
        return [_layout(room, ends + [_obj(x, 4.0, 3.0)])], [_layout(room, ends + [_obj(x, 4.0, 5.5)])]
    if kind in ("near", "far", "facing", "away", "in_front", "behind", "side", "either_side", "view"):
        if kind == "view":
            s, r = labels[0], labels[1]
        else:
            r = labels[1]
        pair = _relation(check, s, r)
        good, bad = pair if kind != "far" and scope not in ("none", "without") else pair[::-1]
        return [_layout(room, good)], [_layout(room, bad)]
    if kind in ("exists", "count"):
        lo = 1.0 if kind == "exists" else check.params[0].value
        hi = check.params[1].value if kind == "count" and check.params[1].kind == "threshold" else None
        n_good = int(lo) if lo >= 1 or hi is not None else 1
        n_bad = int(lo) - 1 if lo >= 1 else int(hi) + 1
        if n_bad > 12:
            return None
        spots = [(0.5 + 1.0 * (k % 7), 0.5 + 1.2 * (k // 7)) for k in range(12)]
        return [_layout(room, [_obj(s, x, z) for x, z in spots[:n_good]])], \
            [_layout(room, [_obj(s, x, z) for x, z in spots[:n_bad]])]
    if kind == "height":
        limit = _value(check, "HEIGHT_LIMIT", 1.0)
        low, high = (0.3, max(limit - 0.2, 0.1) / 2, 0.25), (0.3, (limit + 0.6) / 2, 0.25)
        return [_layout(room, [_obj(s, 4.0, 3.0, low)])], [_layout(room, [_obj(s, 4.0, 3.0, high)])]
    if kind in ("wall", "aligned", "wall_far", "middle", "centred_wall"):
        size = max(8.0, 2 * _value(check, "WALL_AWAY", 0.0) + 3.0)
        c = size / 2
        walled, inside = _obj(s, c, SUBJECT[2]), _obj(s, c, c)
        pair = {"wall": (walled, inside), "aligned": (inside, _obj(s, c, c, yaw=math.radians(35))),
                "wall_far": (inside, walled), "middle": (inside, _obj(s, 1.0, 1.0)),
                "centred_wall": (walled, _obj(s, 1.5, SUBJECT[2]))}[kind]
        good, bad = pair if scope not in ("none", "without") else pair[::-1]
        return [_layout(room, [good], size, size)], [_layout(room, [bad], size, size)]
    if kind.startswith("free_") and kind != "free_area":
        depth = _value(check, "FREE_DEPTH", 0.8)
        other = next(c for c in _ground(classes) if c != s)
        hw, hd = SUBJECT[0], SUBJECT[2]
        spots = {"front": [(0, hd + depth / 2)], "back": [(0, -hd - depth / 2)],
                 "sides": [(hw + depth / 2, 0), (-hw - depth / 2, 0)]}
        spots["around"] = spots["front"] + spots["back"] + spots["sides"]
        small = (depth / 2, 0.4, depth / 2)
        blockers = [_obj(other, 4.0 + x, 3.0 + z, small) for x, z in spots[kind[5:]]]
        return [_layout(room, [_obj(s, 4.0, 3.0)])], [_layout(room, [_obj(s, 4.0, 3.0)] + blockers)]
    if kind == "free_area":
        size = _value(check, "FREE_SIZE", 1.5)
        big = size * 1.5 + 3.0
        if "MIDDLE_RADIUS" in {p.name for p in check.params}:
            block = _value(check, "MIDDLE_RADIUS", 1.0) + size / 2 + 0.1
            other = _ground(classes)[0]
            return ([_layout(room, [], big, big)],
                    [_layout(room, [_obj(other, big / 2, big / 2, (block, 0.4, block))], big, big)])
        return [_layout(room, [], big, big)], [_layout(room, [], size * 0.7, big)]
    if kind == "room_size":
        lo, hi = _value(check, "AREA_MIN", 0.0), _value(check, "AREA_MAX", 1e4)
        good = (lo + min(hi, lo + 10)) / 2 if lo > 0 else hi - 2
        bad = lo - 5 if lo > 6 else hi + 8
        good, bad = math.sqrt(good), math.sqrt(bad)
        return [_layout(room, [], good, good)], [_layout(room, [], bad, bad)]
    if kind == "turning":
        narrow = _value(check, "TURN_DIAMETER", 1.5) * 0.6
        near = [_obj(labels[0], 1.0, narrow / 2, (0.3, 0.4, 0.2))] if labels else []
        return [_layout(room, near, 6.0, 6.0)], [_layout(room, near, 6.0, narrow)]
    if kind == "clear_path":
        return _barrier(room, _value(check, "PATH_WIDTH", 0.9))
    return None


def _barrier(room: str, width: float) -> tuple[list[Layout], list[Layout]]:
    """Clear paths: an object behind a barrier across the room, the gap in it twice the width, or half."""
    ground = _ground(get_room(room).classes)
    rooms = []
    for gap in (2 * width, 0.5 * width):
        half = (6.0 - gap) / 4
        objs = [_obj(ground[0], half, 4.0, (half, 0.4, 0.2)), _obj(ground[0], 6.0 - half, 4.0, (half, 0.4, 0.2)),
                _obj(ground[1], 3.0, 5.3, (0.3, 0.4, 0.3))]
        rooms.append([_layout(room, objs, 6.0, 6.0)])
    return rooms[0], rooms[1]


def self_check(plan: Plan, run) -> list[str]:
    """What is wrong with a program of ``plan``: for each check with examples, its satisfying rooms must score above
    its violating rooms by MARGIN on the check, and above them on the reward. ``run(layouts) -> (reward (n,),
    {check key: (n,)})`` scores the program."""
    problems = []
    for check in plan.checks:
        rooms = examples(check, plan.room)
        if rooms is None:
            continue
        good, bad = rooms
        reward, parts = run(good + bad)
        mine = parts[check.key]
        g, b = len(good), len(bad)
        if not mine[:g].min() >= mine[g:].max() + MARGIN:
            problems.append(f"{check.key} scores rooms that satisfy it ({', '.join(f'{v:.2f}' for v in mine[:g])}) "
                            f"not above rooms that violate it ({', '.join(f'{v:.2f}' for v in mine[g:])})")
        elif not reward[:g].min() > reward[g:g + b].max():
            problems.append(f"the reward does not score the rooms that satisfy {check.key} above those that violate it")
    return problems
