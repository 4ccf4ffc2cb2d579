"""Requests beyond the five paper tasks, each with its own hand-written checker, to judge the offline planner
(issue 43): does the program it writes rank the rooms that pass the checker above those that fail (AUC), or does
it refuse the request?

The checkers are written here from the request's words, over :class:`iarcs_env.scene.Layout` with NumPy and
shapely only (no scene API, no relations module, no planner code), with the planner's documented readings of the
words that have no number ("beside" = footprints within 0.5 m, "behind" = up to 0.9 m beyond the back and within
the width + 0.1 m, "in the middle" = centre within 1 m of the middle of the floor's bounding box, "against a wall"
= the boundary within 0.1 m straight behind the back edge's midpoint, "facing" = within 30 degrees, "facing away"
= the other object more than 120 degrees from the facing direction, "a small bedroom" = at most 12 m^2,
"spacious" = at least 16 m^2, "free space" = a 0.8 m strip 95 % free). "every X ..." needs at least one X; "no X
..." holds in a room without X.

Print the table (docs/results/planner_requests.md): ``python -m experiments.planner_requests``.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import shapely
from shapely.geometry import Point, Polygon

from iarcs_env.scene import Layout

BEDS = ("double_bed", "single_bed", "kids_bed")
CEILING = ("ceiling_lamp", "pendant_lamp")
SUPPORT = ("table", "desk", "nightstand", "coffee_table", "dressing_table", "cabinet", "children_cabinet", "shelf",
           "bookshelf", "tv_stand", "wardrobe") + BEDS


# --------------------------------------------------------------------------------------------------------
# Geometry over one layout (NumPy and shapely)
# --------------------------------------------------------------------------------------------------------
class Room:
    """One layout's objects as footprints, frames and the floor, for the checkers."""

    def __init__(self, layout: Layout):
        self.layout = layout
        self.labels = list(layout.labels)
        self.floor = Polygon(np.asarray(layout.floor.vertices, float))
        self.corners = layout.footprints()
        self.feet = [Polygon(c) for c in self.corners]
        self.xz = layout.translations[:, [0, 2]]
        self.half = layout.half_sizes
        self.yaw = layout.yaws
        xmin, zmin, xmax, zmax = self.floor.bounds
        self.middle = np.array([(xmin + xmax) / 2, (zmin + zmax) / 2])

    def of(self, *classes: str) -> list[int]:
        return [i for i, c in enumerate(self.labels) if c in classes]

    def ground(self) -> list[int]:
        return [i for i, c in enumerate(self.labels) if c not in CEILING]

    def forward(self, i: int) -> np.ndarray:
        return np.array([math.sin(self.yaw[i]), math.cos(self.yaw[i])])

    def left(self, i: int) -> np.ndarray:
        return np.array([math.cos(self.yaw[i]), -math.sin(self.yaw[i])])

    def local(self, i: int, j: int) -> tuple[float, float]:
        """j's centre in i's frame: (lateral, ahead)."""
        d = self.xz[j] - self.xz[i]
        return float(d @ self.left(i)), float(d @ self.forward(i))

    def gap(self, i: int, j: int) -> float:
        return self.feet[i].distance(self.feet[j])

    def angle(self, i: int, j: int) -> float:
        """Degrees between i's facing direction and the direction from i to j."""
        lat, ahead = self.local(i, j)
        return math.degrees(math.atan2(abs(lat), ahead))

    def back_point(self, i: int) -> np.ndarray:
        return self.xz[i] - self.forward(i) * self.half[i, 2]

    def against_wall(self, i: int) -> bool:
        """The wall straight behind: the 0.1 m segment from the back edge's midpoint backwards meets the boundary
        (or the midpoint is outside the floor)."""
        p = self.back_point(i)
        ray = shapely.LineString([p, p - 0.1 * self.forward(i)])
        return ray.intersects(self.floor.exterior) or not self.floor.contains(Point(p))

    def wall_gap(self, i: int) -> float:
        inside = self.floor.contains(self.feet[i])
        return self.floor.exterior.distance(self.feet[i]) if inside else 0.0

    def in_front(self, j: int, i: int, sign: float = 1.0, depth: float = 0.9) -> bool:
        """j's centre in front of i (behind with ``sign`` -1): within i's width + 0.1 m, up to ``depth`` m beyond."""
        lat, ahead = self.local(i, j)
        ahead *= sign
        return abs(lat) <= self.half[i, 0] + 0.1 and 0 < ahead <= self.half[i, 2] + depth

    def free(self) -> shapely.Geometry:
        """The floor outside every ground footprint."""
        feet = [self.feet[i] for i in self.ground()]
        return self.floor.difference(shapely.union_all(feet)) if feet else self.floor

    def strip_free(self, i: int, zone: str, depth: float = 0.8) -> bool:
        """The strip ``depth`` m deep beyond i's edges of ``zone`` is at least 95 % free floor."""
        hw, hd = self.half[i, 0], self.half[i, 2]
        rects = {"front": [(-hw, hw, hd, hd + depth)], "back": [(-hw, hw, -hd - depth, -hd)],
                 "sides": [(hw, hw + depth, -hd, hd), (-hw - depth, -hw, -hd, hd)]}
        rects["around"] = rects["front"] + rects["back"] + rects["sides"]
        others = [self.feet[k] for k in self.ground() if k != i]
        blocked = shapely.union_all(others) if others else Polygon()
        total = free = 0.0
        for x0, x1, z0, z1 in rects[zone]:
            local = np.array([(x0, z0), (x1, z0), (x1, z1), (x0, z1)])
            world = Polygon(self.xz[i] + local[:, :1] * self.left(i) + local[:, 1:] * self.forward(i))
            total += world.area
            free += world.intersection(self.floor).difference(blocked).area
        return free >= 0.95 * total

    def free_disk(self, radius: float, middle: bool = False) -> bool:
        room = self.free().buffer(-radius)
        if middle:
            room = room.intersection(Point(self.middle).buffer(1.0))
        return not room.is_empty

    def free_square(self, side: float) -> bool:
        """An axis-aligned square (in the floor's frame) fits on free floor."""
        return not self.free().buffer(-side / 2, join_style="mitre").is_empty


def every(items, test) -> bool:
    items = list(items)
    return bool(items) and all(test(i) for i in items)


def none(pairs, test) -> bool:
    return not any(test(*p) for p in pairs)


def pairs(a, b):
    return [(i, j) for i in a for j in b if i != j]


def between(r: Room, x: int, a: int, c: int) -> bool:
    """x's centre projects onto the segment a -> c and lies at most 1 m from the line."""
    ac, ax = r.xz[c] - r.xz[a], r.xz[x] - r.xz[a]
    length = float(np.linalg.norm(ac))
    if length < 1e-6:
        return False
    t = float(ax @ ac) / length
    off = abs(float(ax[0] * ac[1] - ax[1] * ac[0])) / length
    return 0 <= t <= length and off <= 1.0


def centred_on_wall(r: Room, i: int) -> bool:
    """Back against a wall, and the centre within 0.3 m (along that wall) of the middle of the wall segment."""
    p = Point(r.back_point(i))
    v = np.asarray(r.floor.exterior.coords)
    edges = [(v[k], v[k + 1]) for k in range(len(v) - 1)]
    a, b = min(edges, key=lambda e: shapely.LineString(e).distance(p))
    if shapely.LineString((a, b)).distance(p) > 0.1:
        return False
    along = (b - a) / np.linalg.norm(b - a)
    return abs(float((r.xz[i] - (a + b) / 2) @ along)) <= 0.3


# --------------------------------------------------------------------------------------------------------
# The requests
# --------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Request:
    """A request, the word family it exercises, its checker (one layout -> pass) and the checker in words."""

    text: str
    family: str
    check: Callable[[Room], bool]
    reading: str


def _r(text, family, reading, check) -> Request:
    return Request(text, family, check, reading)


REQUESTS: list[Request] = [
    # negation
    _r("A bedroom without a desk", "negation", "no desk", lambda r: not r.of("desk")),
    _r("A bedroom with no wardrobe", "negation", "no wardrobe", lambda r: not r.of("wardrobe")),
    _r("No chair within 1 m of the bed", "negation", "every chair-bed footprint gap > 1 m",
       lambda r: none(pairs(r.of("chair"), r.of(*BEDS)), lambda i, j: r.gap(i, j) <= 1.0)),
    _r("None of the nightstands within 0.3 m of the wardrobe", "negation", "every nightstand-wardrobe gap > 0.3 m",
       lambda r: none(pairs(r.of("nightstand"), r.of("wardrobe")), lambda i, j: r.gap(i, j) <= 0.3)),
    _r("The bed is not against a wall", "negation",
       "no bed against a wall (the boundary within 0.1 m straight behind its back)",
       lambda r: not any(r.against_wall(i) for i in r.of(*BEDS))),
    _r("The wardrobe should never face the bed", "negation", "no wardrobe within 30 deg of facing a bed",
       lambda r: none(pairs(r.of("wardrobe"), r.of(*BEDS)), lambda i, j: r.angle(i, j) <= 30)),
    _r("Do not put a chair in front of the wardrobe", "negation", "no chair centre in a wardrobe's front zone",
       lambda r: none(pairs(r.of("chair"), r.of("wardrobe")), lambda i, j: r.in_front(i, j))),
    _r("A bedroom where no two pieces of furniture stand closer than 0.1 m", "negation",
       "every pair of ground objects has a footprint gap >= 0.1 m",
       lambda r: none(pairs(r.ground(), r.ground()), lambda i, j: r.gap(i, j) < 0.1)),
    _r("A nightstand that is not next to the bed", "negation", "no nightstand within 0.5 m of a bed",
       lambda r: none(pairs(r.of("nightstand"), r.of(*BEDS)), lambda i, j: r.gap(i, j) <= 0.5)),
    # direction
    _r("The desk faces away from the bed", "direction", "a desk with a bed > 120 deg from its facing direction",
       lambda r: any(r.angle(i, j) > 120 for i, j in pairs(r.of("desk"), r.of(*BEDS)))),
    _r("The wardrobe with its back to the bed", "direction", "a wardrobe with a bed > 120 deg from its facing",
       lambda r: any(r.angle(i, j) > 120 for i, j in pairs(r.of("wardrobe"), r.of(*BEDS)))),
    _r("An armchair turned toward the bed", "direction", "an armchair facing a bed within 30 deg",
       lambda r: any(r.angle(i, j) <= 30 for i, j in pairs(r.of("armchair"), r.of(*BEDS)))),
    _r("The TV stand facing the bed", "direction", "a TV stand facing a bed within 30 deg",
       lambda r: any(r.angle(i, j) <= 30 for i, j in pairs(r.of("tv_stand"), r.of(*BEDS)))),
    _r("A chair behind the desk", "direction", "a chair centre up to 0.9 m beyond a desk's back, within its width",
       lambda r: any(r.in_front(i, j, sign=-1) for i, j in pairs(r.of("chair"), r.of("desk")))),
    _r("A nightstand beside the bed", "direction", "a nightstand within 0.5 m of a bed",
       lambda r: any(r.gap(i, j) <= 0.5 for i, j in pairs(r.of("nightstand"), r.of(*BEDS)))),
    _r("Nightstands on both sides of the bed", "direction",
       "a bed with a nightstand centre 0-0.5 m out from each side, along the head half",
       lambda r: any(all(any(_beside_head(r, b, n, s) for n in r.of("nightstand")) for s in (1, -1))
                     for b in r.of(*BEDS))),
    _r("A nightstand between the bed and the wardrobe", "direction",
       "a nightstand centre whose foot lies between a bed's and a wardrobe's centres, at most 1 m off that line",
       lambda r: any(between(r, x, a, c) for x in r.of("nightstand") for a in r.of(*BEDS) for c in r.of("wardrobe"))),
    _r("The bed in the middle of the room", "direction", "every bed centre within 1 m of the floor's middle",
       lambda r: every(r.of(*BEDS), lambda i: np.linalg.norm(r.xz[i] - r.middle) <= 1.0)),
    _r("The desk centered in the room", "direction", "every desk centre within 1 m of the floor's middle",
       lambda r: every(r.of("desk"), lambda i: np.linalg.norm(r.xz[i] - r.middle) <= 1.0)),
    _r("The double bed centred on a wall", "direction",
       "every double bed against a wall, centre within 0.3 m of that wall's middle",
       lambda r: every(r.of("double_bed"), lambda i: centred_on_wall(r, i))),
    _r("The wardrobe against a wall", "direction", "every wardrobe with its back against the boundary",
       lambda r: every(r.of("wardrobe"), r.against_wall)),
    _r("The desk at least 1 m away from the walls", "direction", "every desk footprint >= 1 m from the boundary",
       lambda r: every(r.of("desk"), lambda i: r.wall_gap(i) >= 1.0)),
    # quantifiers and their scope
    _r("Every chair within 1 m of a desk", "quantifier", "every chair (at least one) within 1 m of some desk",
       lambda r: every(r.of("chair"), lambda i: any(r.gap(i, j) <= 1.0 for j in r.of("desk")))),
    _r("A chair within 1 m of the desk", "quantifier", "some chair within 1 m of some desk",
       lambda r: any(r.gap(i, j) <= 1.0 for i, j in pairs(r.of("chair"), r.of("desk")))),
    _r("All nightstands within 0.5 m of a bed", "quantifier", "every nightstand (at least one) within 0.5 m of a bed",
       lambda r: every(r.of("nightstand"), lambda i: any(r.gap(i, j) <= 0.5 for j in r.of(*BEDS)))),
    _r("Each wardrobe against a wall", "quantifier", "every wardrobe (at least one) against the boundary",
       lambda r: every(r.of("wardrobe"), r.against_wall)),
    _r("Some cabinet against a wall", "quantifier", "a cabinet with its back against the boundary",
       lambda r: any(r.against_wall(i) for i in r.of("cabinet"))),
    _r("Any 2 pieces of furniture at least 0.05 m apart", "quantifier", "every pair of ground objects >= 0.05 m apart",
       lambda r: none(pairs(r.ground(), r.ground()), lambda i, j: r.gap(i, j) < 0.05)),
    _r("Every chair facing a desk", "quantifier", "every chair (at least one) facing some desk within 30 deg",
       lambda r: every(r.of("chair"), lambda i: any(r.angle(i, j) <= 30 for j in r.of("desk")))),
    _r("At least 2 nightstands", "quantifier", ">= 2 nightstands", lambda r: len(r.of("nightstand")) >= 2),
    _r("At most 5 pieces of furniture", "quantifier", "<= 5 ground objects", lambda r: len(r.ground()) <= 5),
    _r("No more than 1 wardrobe", "quantifier", "<= 1 wardrobe", lambda r: len(r.of("wardrobe")) <= 1),
    _r("Fewer than 7 objects", "quantifier", "<= 6 ground objects", lambda r: len(r.ground()) <= 6),
    _r("Exactly 2 nightstands", "quantifier", "2 nightstands", lambda r: len(r.of("nightstand")) == 2),
    _r("Only 1 bed", "quantifier", "1 bed", lambda r: len(r.of(*BEDS)) == 1),
    _r("There must be exactly one wardrobe and it must be against a wall", "quantifier",
       "1 wardrobe, with its back against the boundary",
       lambda r: len(r.of("wardrobe")) == 1 and r.against_wall(r.of("wardrobe")[0])),
    _r("All support surfaces at most 0.8 m high", "quantifier", "a support surface; every one's top <= 0.8 m",
       lambda r: every(r.of(*SUPPORT), lambda i: r.layout.translations[i, 1] + r.half[i, 1] <= 0.8)),
    _r("Every chair within 1 m of a desk and no chair within 1 m of the bed", "quantifier",
       "every chair within 1 m of a desk, none within 1 m of a bed",
       lambda r: every(r.of("chair"), lambda i: any(r.gap(i, j) <= 1.0 for j in r.of("desk")))
       and none(pairs(r.of("chair"), r.of(*BEDS)), lambda i, j: r.gap(i, j) <= 1.0)),
    # distances, free space, room size
    _r("The desk and the bed at least 1.5 m apart", "distance", "every desk-bed footprint gap >= 1.5 m",
       lambda r: none(pairs(r.of("desk"), r.of(*BEDS)), lambda i, j: r.gap(i, j) < 1.5)),
    _r("The chair and the desk at most 0.3 m apart", "distance", "a chair within 0.3 m of a desk",
       lambda r: any(r.gap(i, j) <= 0.3 for i, j in pairs(r.of("chair"), r.of("desk")))),
    _r("1 m of free space in front of the wardrobe", "free space",
       "every wardrobe (at least one): the 1 m strip in front 95 % free floor",
       lambda r: every(r.of("wardrobe"), lambda i: r.strip_free(i, "front", 1.0))),
    _r("Free space of 0.6 m on both sides of the bed", "free space",
       "every bed (at least one): the 0.6 m strips at both sides 95 % free floor",
       lambda r: every(r.of(*BEDS), lambda i: r.strip_free(i, "sides", 0.6))),
    _r("Keep the area around the desk clear", "free space",
       "every desk (at least one): the 0.8 m strips around it 95 % free floor",
       lambda r: every(r.of("desk"), lambda i: r.strip_free(i, "around", 0.8))),
    _r("A bedroom with a free 2 m square", "free space", "a 2 m axis-aligned square fits on free floor",
       lambda r: r.free_square(2.0)),
    _r("An open circle 1.5 m across in the middle of the room", "free space",
       "a free disk of 0.75 m radius with its centre within 1 m of the floor's middle",
       lambda r: r.free_disk(0.75, middle=True)),
    _r("An open area in the middle of the room", "free space",
       "a free disk 1.5 m across with its centre within 1 m of the floor's middle",
       lambda r: r.free_disk(0.75, middle=True)),
    _r("0.5 m of clearance beside the bed", "free space",
       "every bed (at least one): the 0.5 m strips at both sides 95 % free floor",
       lambda r: every(r.of(*BEDS), lambda i: r.strip_free(i, "sides", 0.5))),
    _r("The wardrobe turned away from the bed", "direction", "a wardrobe with a bed > 120 deg from its facing",
       lambda r: any(r.angle(i, j) > 120 for i, j in pairs(r.of("wardrobe"), r.of(*BEDS)))),
    _r("There is no wardrobe closer than 1 m to the bed", "negation", "every wardrobe-bed footprint gap >= 1 m",
       lambda r: none(pairs(r.of("wardrobe"), r.of(*BEDS)), lambda i, j: r.gap(i, j) < 1.0)),
    _r("Place the wardrobe far from the bed", "distance", "every wardrobe-bed footprint gap >= 1 m",
       lambda r: none(pairs(r.of("wardrobe"), r.of(*BEDS)), lambda i, j: r.gap(i, j) < 1.0)),
    _r("The nightstands beside the bed, not in front of it", "refusal",
       "a nightstand within 0.5 m of a bed, none in a bed's front zone",
       lambda r: any(r.gap(i, j) <= 0.5 for i, j in pairs(r.of("nightstand"), r.of(*BEDS)))
       and none(pairs(r.of("nightstand"), r.of(*BEDS)), lambda i, j: r.in_front(i, j))),
    _r("Keep at least 0.2 m between all furniture", "quantifier", "every pair of ground objects >= 0.2 m apart",
       lambda r: none(pairs(r.ground(), r.ground()), lambda i, j: r.gap(i, j) < 0.2)),
    _r("A small bedroom", "room size", "floor area <= 12 m^2", lambda r: r.floor.area <= 12.0),
    _r("A spacious bedroom", "room size", "floor area >= 16 m^2", lambda r: r.floor.area >= 16.0),
    _r("A bedroom of at least 14 square metres", "room size", "floor area >= 14 m^2",
       lambda r: r.floor.area >= 14.0),
    # more phrasings
    _r("A desk without a chair in front of it", "negation", "a desk with no chair centre in its front zone",
       lambda r: any(not any(r.in_front(i, d) for i in r.of("chair")) for d in r.of("desk"))),
    _r("The bed is never near the wardrobe", "negation", "every bed-wardrobe gap > 0.5 m",
       lambda r: none(pairs(r.of(*BEDS), r.of("wardrobe")), lambda i, j: r.gap(i, j) <= 0.5)),
    _r("The chairs are not facing the bed", "negation", "no chair facing a bed within 30 deg",
       lambda r: none(pairs(r.of("chair"), r.of(*BEDS)), lambda i, j: r.angle(i, j) <= 30)),
    _r("Never place the desk behind the bed", "negation", "no desk centre in a bed's back zone",
       lambda r: none(pairs(r.of("desk"), r.of(*BEDS)), lambda i, j: r.in_front(i, j, sign=-1))),
    _r("The bed not in the middle of the room", "negation", "no bed centre within 1 m of the floor's middle",
       lambda r: not any(np.linalg.norm(r.xz[i] - r.middle) <= 1.0 for i in r.of(*BEDS))),
    _r("Both nightstands against the wall", "direction", "every nightstand (at least one) against the boundary",
       lambda r: every(r.of("nightstand"), r.against_wall)),
    _r("Nightstands on either side of the double bed", "direction",
       "a double bed with a nightstand centre 0-0.5 m out from each side, along the head half",
       lambda r: any(all(any(_beside_head(r, b, n, s) for n in r.of("nightstand")) for s in (1, -1))
                     for b in r.of("double_bed"))),
    _r("Keep the bed away from the walls", "direction", "every bed footprint >= 0.5 m from the boundary",
       lambda r: every(r.of(*BEDS), lambda i: r.wall_gap(i) >= 0.5)),
    _r("Some chairs near the desk", "quantifier", "a chair within 0.5 m of a desk",
       lambda r: any(r.gap(i, j) <= 0.5 for i, j in pairs(r.of("chair"), r.of("desk")))),
    _r("Every shelf no higher than 1.5 m", "quantifier", "a shelf; every shelf's top <= 1.5 m",
       lambda r: every(r.of("shelf"), lambda i: r.layout.translations[i, 1] + r.half[i, 1] <= 1.5)),
    _r("A bedroom with at least 0.6 m of free space around every bed", "free space",
       "every bed (at least one): the 0.6 m strips around it 95 % free floor",
       lambda r: every(r.of(*BEDS), lambda i: r.strip_free(i, "around", 0.6))),
    # requests the planner must refuse (their meaning-changing words are not read)
    _r("At least 3 pieces of furniture against a wall", "refusal", ">= 3 ground objects against the boundary",
       lambda r: sum(r.against_wall(i) for i in r.ground()) >= 3),
    _r("A chair in front of every desk", "refusal", "every desk (at least one) with a chair in its front zone",
       lambda r: every(r.of("desk"), lambda d: any(r.in_front(i, d) for i in r.of("chair")))),
    _r("Only chairs near the desk", "refusal", "a desk; every ground object within 0.5 m of a desk is a chair",
       lambda r: bool(r.of("desk")) and all(r.labels[i] == "chair" for i in r.ground() for d in r.of("desk")
                                            if i != d and r.gap(i, d) <= 0.5)),
    _r("A bed with nothing in front of it", "refusal", "a bed with no ground object centre in its front zone",
       lambda r: any(not any(r.in_front(i, b) for i in r.ground() if i != b) for b in r.of(*BEDS))),
    _r("A nightstand on the left of every bed", "refusal", "every bed with a nightstand on its left",
       lambda r: every(r.of(*BEDS), lambda b: any(0 < r.local(b, n)[0] for n in r.of("nightstand")))),
    _r("The desk faces the bed and the wardrobe", "refusal", "a desk facing a bed and a wardrobe within 30 deg",
       lambda r: any(any(r.angle(d, b) <= 30 for b in r.of(*BEDS))
                     and any(r.angle(d, w) <= 30 for w in r.of("wardrobe")) for d in r.of("desk"))),
    _r("Not every chair faces the desk", "refusal", "some chair not facing any desk within 30 deg",
       lambda r: any(all(r.angle(i, j) > 30 for j in r.of("desk")) for i in r.of("chair"))),
]


def _beside_head(r: Room, bed: int, stand: int, side: int) -> bool:
    lat, ahead = r.local(bed, stand)
    hw, hd = r.half[bed, 0], r.half[bed, 2]
    return side * lat > hw and side * lat <= hw + 0.5 and -hd <= ahead <= 0


# --------------------------------------------------------------------------------------------------------
# Scoring
# --------------------------------------------------------------------------------------------------------
def auc(pos: np.ndarray, neg: np.ndarray) -> float:
    """Probability that a passing room's score beats a failing one's (ties count half)."""
    diff = pos[:, None] - neg[None, :]
    return float((diff > 0).mean() + 0.5 * (diff == 0).mean())


def scores(code: str, layouts: list[Layout]) -> np.ndarray:
    """A program's reward on layouts (in the reward sandbox, as every written program runs)."""
    from rewards.planner import program_values

    return program_values(code, layouts[0].room_type, layouts)


def evaluate(request: Request, rooms: dict[str, list[Layout]]) -> dict:
    """The planner's answer to a request: its program's AUC per room set (None when one kind is missing, with the
    pass rate), or the refusal's reason."""
    from rewards.planner import OfflinePlanner
    from rewards.proposal import meaning_lost

    row = {"request": request.text, "family": request.family, "reading": request.reading}
    try:
        proposal = OfflinePlanner().synthesize("bedroom", request.text)
    except ValueError as err:
        return {**row, "refused": str(err).split(" (")[0]}
    lost = meaning_lost(proposal.not_understood)
    if lost:
        return {**row, "refused": "did not understand " + ", ".join(repr(w) for w in lost)}
    for name, layouts in rooms.items():
        passed = np.array([bool(request.check(Room(layout))) for layout in layouts])
        values = scores(proposal.code, layouts)
        row[f"rate_{name}"] = float(passed.mean())
        row[f"auc_{name}"] = auc(values[passed], values[~passed]) if passed.any() and (~passed).any() else None
    return row


def shuffled(layouts: list[Layout], seed: int = 0) -> list[Layout]:
    """The rooms with about half their objects moved to a random spot of the floor and turned to a random quarter
    (plus up to 10 degrees): relations the generator rarely makes (a desk facing away from the bed, a bed in the
    middle) then occur, passing and failing."""
    from dataclasses import replace

    rng = np.random.default_rng(seed)
    out = []
    for layout in layouts:
        t, yaw = layout.translations.copy(), layout.yaws.copy()
        floor = Polygon(np.asarray(layout.floor.vertices, float))
        xmin, zmin, xmax, zmax = floor.bounds
        for i in np.flatnonzero(rng.random(len(t)) < 0.5):
            for _ in range(20):
                x, z = rng.uniform(xmin, xmax), rng.uniform(zmin, zmax)
                if floor.contains(Point(x, z)):
                    t[i, 0], t[i, 2] = x, z
                    break
            yaw[i] = rng.integers(4) * math.pi / 2 + rng.uniform(-0.17, 0.17)
        out.append(replace(layout, translations=t, yaws=yaw))
    return out


def room_sets(n: int = 500, seed: int = 7, real: str | None = None) -> dict[str, list[Layout]]:
    """The procedural bedrooms, the same shuffled, and the real ones (when ``real`` is given)."""
    from iarcs_env.datasets import load_layouts
    from iarcs_env.datasets.procedural import generate_layouts

    procedural = generate_layouts("bedroom", n, seed=seed)
    rooms = {"procedural": procedural, "shuffled": shuffled(procedural, seed)}
    if real:
        rooms["real"] = load_layouts(real, "bedroom")
    return rooms


def table(rows: list[dict]) -> str:
    """The rows as a Markdown table."""
    def cell(row, name):
        if f"auc_{name}" not in row:
            return "-"
        value = row[f"auc_{name}"]
        rate = row[f"rate_{name}"]
        return f"{value:.3f} (pass {rate:.0%})" if value is not None else f"n/a (pass {rate:.0%})"

    lines = ["| # | request | family | checker | AUC procedural | AUC shuffled | AUC real |",
             "|---|---|---|---|---|---|---|"]
    for k, row in enumerate(rows, 1):
        if "refused" in row:
            result = f"refused: {row['refused']} |  |  |"
        else:
            result = " | ".join(cell(row, name) for name in SETS) + " |"
        lines.append(f"| {k} | {row['request']} | {row['family']} | {row['reading']} | {result}")
    return "\n".join(lines)


#: The room sets, in the table's order.
SETS = ("procedural", "shuffled", "real")


def summary(rows: list[dict]) -> str:
    keys = [f"auc_{name}" for name in SETS]
    aucs = [row[k] for row in rows for k in keys if row.get(k) is not None]
    written = [row for row in rows if "refused" not in row]
    good = [row for row in written if all(row.get(k) is None or row[k] >= 0.9 for k in keys)]
    judged = [row for row in written if any(row.get(k) is not None for k in keys)]
    return (f"{len(rows)} requests: {len(written)} programs ({len(judged)} judged on some room set with passing and "
            f"failing rooms), {len(good)} of them with AUC >= 0.9 on every room set that has both kinds, "
            f"{len(rows) - len(written)} refused; lowest AUC {min(aucs):.3f}.")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rooms", type=int, default=500, help="procedural bedrooms (default 500)")
    parser.add_argument("--seed", type=int, default=7, help="seed of the procedural bedrooms (default 7)")
    parser.add_argument("--real", default="../shared/data/3dfront/bedroom_val.json",
                        help="real validation bedrooms (skipped when the file is absent)")
    args = parser.parse_args(argv)
    from pathlib import Path

    real = args.real if Path(args.real).exists() else None
    if real is None:
        print(f"{args.real} is absent: the real-room column is left out")
    rooms = room_sets(args.rooms, args.seed, real)
    rows = [evaluate(request, rooms) for request in REQUESTS]
    print(table(rows))
    print()
    print(summary(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
