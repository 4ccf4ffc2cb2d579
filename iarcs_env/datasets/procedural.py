"""The embedded procedural generator: "synthetic 3D-FRONT" rooms that need no download.

:func:`generate_layouts` builds bedrooms, living rooms (3D-FRONT's living-dining rooms) and dining rooms
from hand-written rules and parameters:

* **Floor plans** are rectilinear: rectangles, L shapes (one corner cut away), U shapes (a notch in the
  middle of a wall) and rooms with two or three cut corners. Areas are log-normal (bedroom median
  13 m^2, living room 28 m^2, dining room 16 m^2) and aspect ratios follow typical apartment rooms.
* **Sizes** come from furniture standards with variation (:data:`SIZES`): a double bed with its frame
  and headboard is 1.65-2.25 m wide and 2.05-2.35 m long, a nightstand 0.4-0.6 x 0.35-0.5 m and
  0.45-0.65 m high, a wardrobe 0.55-0.65 m deep, 0.9-2.4 m wide and 2.0-2.4 m high, and so on.
* **Placement rules** (:class:`_Room` does the geometry): the bed's head is against a wall with
  nightstands beside the head; wardrobes, cabinets and shelves stand against walls facing the room; a TV
  stand faces the bed or the sofa; desks and dressing tables stand against a wall with a chair or stool
  in front; dining tables stand free with chairs around them (in a cramped room, against a wall with
  chairs on the open sides); coffee tables stand in front of sofas with
  armchairs at their sides; ceiling and pendant lamps hang from the ceiling over the bed, the dining
  table, the coffee table or the room's centre. Each room also keeps a door's swing free.
* **Flaws** of the kinds real 3D-FRONT has (:data:`FLAWS`): nightstands and side tables overlapping the
  bed, nightstands, desks and tables poking through the wall, chairs pushed under desks and dining
  tables, coffee tables inside an L-shaped sofa's box. ``flaw_rate`` scales every flaw probability:
  0 gives rooms with no overlap between ground objects and every footprint inside the floor; 1 gives
  rates like the real validation data (bedrooms: Col_obj ~41%, Col_scene ~56%, R_out ~7%).

Living rooms draw a furnishing level (:data:`RICH_SIGMA`) that grows with floor area and tilts the
counts of optional pieces, which widens the object-count histogram the way real rooms vary.
Class mixes and object counts are hand-calibrated against the real data's summary figures
(``benchmarks/bench_realism.py`` checks them); no data is copied. Conventions are those of
:mod:`iarcs_env.scene`: y up, the floor is the x-z plane (centred at the origin), yaw about +y with
``R_y = [[c, 0, s], [0, 1, 0], [-s, 0, c]]``, an object's front (local +z) points along
``(sin yaw, cos yaw)``, floor objects have centre y = half height and lamps hang from the ceiling.
All objects are axis-aligned (yaw a multiple of pi/2), as 99.8% of real 3D-FRONT objects are.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np
import shapely
from shapely.geometry import Polygon, box

from ..floorplan import FloorPlan
from ..rooms import get_room
from ..scene import Layout

#: Version of the generated rooms. Bump it whenever :func:`generate_room` gives other rooms for the same
#: (room type, index, seed, flaw rate): caches of generated data (the pretraining data of
#: :func:`agents.pretrain_data.training_data`) are keyed by it, and a bump makes them be built again.
GENERATOR_VERSION = 1

#: Smallest gap (m) between two objects, or an object and a wall, in a flawless placement.
EPS = 0.005

#: Living rooms' furnishing level ``exp(N(0, RICH_SIGMA)) * (area / 28 m^2) ** RICH_AREA`` tilts the counts
#: of optional pieces (cabinets, side tables, armchairs, stools, a second table, dining chairs).
RICH_SIGMA, RICH_AREA, RICH_MAX = 0.55, 0.5, 1.8


# --------------------------------------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Size:
    """Full extents of one kind of furniture, in metres: ``w`` along its local x (side to side),
    ``d`` along local z (back to front), ``h`` its height; each a (low, high) range sampled with a
    triangular-ish (mean of two uniforms) law. ``square`` items have d = w (round or square tables)."""

    w: tuple[float, float]
    d: tuple[float, float]
    h: tuple[float, float]
    square: bool = False

    def sample(self, rng: np.random.Generator) -> tuple[float, float, float]:
        u = rng.random(6)
        w = self.w[0] + (self.w[1] - self.w[0]) * (u[0] + u[1]) / 2
        d = w if self.square else self.d[0] + (self.d[1] - self.d[0]) * (u[2] + u[3]) / 2
        h = self.h[0] + (self.h[1] - self.h[0]) * (u[4] + u[5]) / 2
        return round(w, 2), round(d, 2), round(h, 2)


#: Furniture sizes (full width, depth, height ranges in m). Keys are class names, or ``class:variant``.
SIZES: dict[str, Size] = {
    # beds: overall size with frame and headboard (mattress 1.5-1.8 x 2.0 m for a double)
    "double_bed": Size((1.65, 2.25), (2.05, 2.35), (0.8, 1.3)),
    "single_bed": Size((1.0, 1.3), (2.0, 2.25), (0.6, 1.0)),
    "kids_bed": Size((1.0, 1.5), (1.9, 2.2), (0.7, 1.6)),
    "nightstand": Size((0.4, 0.6), (0.35, 0.5), (0.45, 0.65)),
    "wardrobe": Size((0.9, 2.4), (0.55, 0.65), (2.0, 2.4)),
    "tv_stand": Size((1.4, 2.6), (0.35, 0.5), (0.4, 0.65)),
    "desk": Size((1.0, 1.6), (0.5, 0.75), (0.72, 0.78)),
    "chair": Size((0.45, 0.6), (0.5, 0.62), (0.8, 1.0)),
    "dressing_table": Size((0.8, 1.4), (0.4, 0.55), (0.75, 1.6)),
    "dressing_chair": Size((0.42, 0.52), (0.42, 0.52), (0.75, 0.9)),
    "stool": Size((0.35, 0.5), (0.35, 0.5), (0.4, 0.5)),
    "stool:bench": Size((1.1, 1.6), (0.38, 0.5), (0.4, 0.5)),
    "stool:bar": Size((0.35, 0.45), (0.35, 0.45), (0.65, 0.8)),
    "table": Size((0.4, 0.6), (0.4, 0.6), (0.45, 0.6)),
    "cabinet": Size((0.6, 1.8), (0.35, 0.55), (0.6, 1.0)),
    "cabinet:tall": Size((0.6, 1.4), (0.35, 0.55), (1.6, 2.2)),
    "children_cabinet": Size((0.6, 1.2), (0.35, 0.45), (0.6, 1.2)),
    "bookshelf": Size((0.8, 2.0), (0.28, 0.4), (1.8, 2.4)),
    "shelf": Size((0.4, 1.0), (0.25, 0.45), (0.4, 2.0)),
    "sofa": Size((1.5, 2.4), (0.8, 1.0), (0.75, 0.9)),
    "armchair": Size((0.7, 0.95), (0.75, 0.95), (0.75, 0.95)),
    "coffee_table": Size((0.9, 1.5), (0.55, 1.0), (0.3, 0.48)),
    "coffee_table:round": Size((0.7, 1.0), (0.7, 1.0), (0.3, 0.45), square=True),
    "multi_seat_sofa": Size((1.9, 2.8), (0.85, 1.05), (0.75, 0.95)),
    "l_shaped_sofa": Size((2.3, 3.6), (1.45, 2.0), (0.75, 0.9)),
    "loveseat_sofa": Size((1.3, 1.7), (0.8, 0.95), (0.75, 0.9)),
    "chaise_longue_sofa": Size((0.7, 1.0), (1.5, 1.9), (0.75, 0.9)),
    "lazy_sofa": Size((0.7, 1.0), (0.7, 1.0), (0.6, 0.8)),
    "lounge_chair": Size((0.55, 0.85), (0.6, 0.85), (0.72, 0.95)),
    "chinese_chair": Size((0.55, 0.7), (0.55, 0.7), (0.85, 1.0)),
    "corner_side_table": Size((0.4, 0.65), (0.4, 0.6), (0.4, 0.6)),
    "round_end_table": Size((0.4, 0.65), (0.4, 0.65), (0.4, 0.6), square=True),
    "console_table": Size((0.8, 1.3), (0.3, 0.45), (0.75, 0.85)),
    "dining_table": Size((1.2, 2.2), (0.75, 1.0), (0.72, 0.78)),
    "dining_table:square": Size((0.75, 1.0), (0.75, 1.0), (0.72, 0.78), square=True),
    "dining_chair": Size((0.43, 0.58), (0.48, 0.62), (0.8, 1.0)),
    "wine_cabinet": Size((0.6, 1.2), (0.4, 0.6), (1.8, 2.1)),
    "ceiling_lamp": Size((0.4, 0.8), (0.4, 0.8), (0.08, 0.25), square=True),
    "pendant_lamp": Size((0.3, 1.0), (0.3, 1.0), (0.5, 1.1), square=True),
    "pendant_lamp:linear": Size((0.8, 1.4), (0.15, 0.3), (0.5, 0.9)),
}


@dataclass(frozen=True)
class RoomShape:
    """Floor-plan parameters of a room type: log-normal area (``area_median`` m^2, ``area_sigma``,
    clipped to ``area_range``), aspect ratio ``1 + aspect_excess * exp(N(0, 0.6))`` of the bounding box,
    and the probabilities of each shape (``rect``, ``L``: one cut corner, ``two``: two cut corners,
    ``U``: a notch in a wall, ``three``: three cut corners)."""

    area_median: float
    area_sigma: float
    area_range: tuple[float, float]
    aspect_excess: float
    shapes: dict[str, float]


ROOM_SHAPES: dict[str, RoomShape] = {
    "bedroom": RoomShape(13.0, 0.28, (7.0, 32.0), 0.3,
                         {"rect": 0.6, "L": 0.26, "two": 0.08, "U": 0.04, "three": 0.02}),
    "livingroom": RoomShape(28.0, 0.45, (9.0, 90.0), 0.5,
                            {"rect": 0.3, "L": 0.25, "two": 0.2, "U": 0.1, "three": 0.15}),
    "diningroom": RoomShape(16.0, 0.3, (8.0, 40.0), 0.3,
                            {"rect": 0.6, "L": 0.25, "two": 0.1, "U": 0.05, "three": 0.0}),
}

#: Base probabilities of the deliberate flaws at ``flaw_rate = 1`` (each is multiplied by flaw_rate).
FLAWS: dict[str, float] = {
    "nightstand_into_bed": 0.65,    # a nightstand (or side table) overlaps the bed's side by 2-15 cm
    "into_wall": 0.2,               # nightstand / side table pushed 7-16 cm into the wall behind it
    "desk_into_wall": 0.12,         # desk, dressing table pushed into the wall
    "wall_object_into_wall": 0.03,  # wardrobe, cabinet, TV stand, bed ... pushed into the wall
    "chair_tucked": 0.6,            # desk / dressing-table chair pushed under the desk
    "dining_chair_tucked": 0.65,    # dining chair pushed under the table
    "bench_into_bed": 0.5,          # a bench at the foot of the bed touching the bed
    "sofa_overlap": 0.35,           # coffee table in an L sofa's box, side table touching a sofa arm
    "dining_chair_jostle": 0.05,    # two neighbouring dining chairs touching
    "slide_into_neighbour": 0.25,   # a wall object slid along the wall into its neighbour by 2-10 cm
    "living_into_wall": 0.11,       # living room: TV stand, shelf, console table, stool ... into the wall
}


# --------------------------------------------------------------------------------------------------------
# Floor plans
# --------------------------------------------------------------------------------------------------------
def _tilted(p: float, tilt: float) -> float:
    """A probability ``p`` tilted like :func:`_pick_count`'s second index (odds times ``tilt``)."""
    return p * tilt / (1 - p + p * tilt)


def _pick(rng: np.random.Generator, table: dict[str, float]) -> str:
    keys = list(table)
    p = np.array([table[k] for k in keys], dtype=float)
    return keys[int(np.searchsorted(np.cumsum(p), rng.random() * p.sum(), side="right").clip(0, len(keys) - 1))]


def _pick_count(rng: np.random.Generator, probs, tilt: float = 1.0) -> int:
    """Index drawn from a list of (unnormalised) probabilities; ``tilt`` > 1 favours larger indices
    (``p_k * tilt**k``), < 1 smaller ones."""
    if tilt != 1.0:
        probs = [p * tilt ** k for k, p in enumerate(probs)]
    c = np.cumsum(probs)
    return int(min(np.searchsorted(c, rng.random() * c[-1], side="right"), len(probs) - 1))


def sample_floor(rng: np.random.Generator, room_type: str) -> tuple[float, float, list[tuple]]:
    """A rectilinear floor: bounding box ``W x D`` centred at the origin minus notch rectangles.

    Returns ``(W, D, notches)`` with notches as ``(x0, z0, x1, z1)`` rectangles touching the boundary.
    """
    shape_p = ROOM_SHAPES[room_type]
    kind = _pick(rng, shape_p.shapes)
    lo, hi = shape_p.area_range
    area = float(np.clip(shape_p.area_median * math.exp(rng.normal(0, shape_p.area_sigma)), lo, hi))
    aspect = min(1 + shape_p.aspect_excess * math.exp(rng.normal(0, 0.6)), 3.0)
    # notches as fractions of the bounding box: (corner or side, fraction along x, fraction along z)
    corners = [(-1, -1), (1, -1), (1, 1), (-1, 1)]
    n_corner = {"rect": 0, "L": 1, "two": 2, "U": 0, "three": 3}[kind]
    picked = [corners[i] for i in rng.permutation(4)[:n_corner]]
    fracs = []
    for sx, sz in picked:
        fracs.append(("corner", sx, sz, rng.uniform(0.18, 0.45), rng.uniform(0.18, 0.45)))
    if kind == "U":
        side = int(rng.integers(4))
        fracs.append(("side", side, 0, rng.uniform(0.25, 0.45), rng.uniform(0.15, 0.35)))
    if n_corner >= 2:  # keep two corner notches on one side from meeting
        for i, f in enumerate(fracs):
            fracs[i] = (f[0], f[1], f[2], min(f[3], 0.4), min(f[4], 0.4))
    fill = 1.0 - sum(f[3] * f[4] for f in fracs)
    bbox_area = area / fill
    W = math.sqrt(bbox_area * aspect)
    D = bbox_area / W
    if rng.random() < 0.5:
        W, D = D, W
    W, D = round(W, 2), round(D, 2)
    notches = []
    for f in fracs:
        a, b = round(f[3] * W, 2), round(f[4] * D, 2)
        if f[0] == "corner":
            sx, sz = f[1], f[2]
            x0, x1 = (W / 2 - a, W / 2) if sx > 0 else (-W / 2, -W / 2 + a)
            z0, z1 = (D / 2 - b, D / 2) if sz > 0 else (-D / 2, -D / 2 + b)
        else:
            side = f[1]
            along, across = (W, D) if side in (0, 2) else (D, W)
            a, b = round(f[3] * along, 2), round(f[4] * across, 2)
            c = rng.uniform(-(along / 2 - a / 2 - 0.5), along / 2 - a / 2 - 0.5) if along > a + 1.0 else 0.0
            c = round(c, 2)
            if side == 0:
                x0, x1, z0, z1 = c - a / 2, c + a / 2, -D / 2, -D / 2 + b
            elif side == 2:
                x0, x1, z0, z1 = c - a / 2, c + a / 2, D / 2 - b, D / 2
            elif side == 1:
                x0, x1, z0, z1 = W / 2 - b, W / 2, c - a / 2, c + a / 2
            else:
                x0, x1, z0, z1 = -W / 2, -W / 2 + b, c - a / 2, c + a / 2
        notches.append((round(x0, 3), round(z0, 3), round(x1, 3), round(z1, 3)))
    return W, D, notches


def floor_polygon(W: float, D: float, notches: list[tuple]) -> Polygon:
    """The floor polygon: the box ``[-W/2, W/2] x [-D/2, D/2]`` minus the notches, counter-clockwise."""
    poly = box(-W / 2, -D / 2, W / 2, D / 2)
    if notches:
        poly = poly.difference(shapely.union_all([box(*n) for n in notches]))
    poly = shapely.simplify(poly, 1e-9)
    return shapely.orient_polygons(poly) if hasattr(shapely, "orient_polygons") else shapely.geometry.polygon.orient(poly)


# --------------------------------------------------------------------------------------------------------
# The placement engine (axis-aligned boxes on a rectilinear floor)
# --------------------------------------------------------------------------------------------------------
@dataclass
class _Wall:
    """One floor edge: start point, unit tangent, unit inward normal, length."""

    ax: float
    az: float
    ux: float
    uz: float
    nx: float
    nz: float
    length: float


@dataclass
class _Obj:
    label: str
    x: float
    z: float
    y: float
    w: float  # full width (local x)
    d: float  # full depth (local z)
    h: float
    yaw: float
    ground: bool = True
    emit: bool = True  # False for a placeholder that keeps floor space but is not written out

    @property
    def box(self) -> tuple[float, float, float, float]:
        return _aabb(self.x, self.z, self.w, self.d, self.yaw)

    @property
    def front(self) -> tuple[float, float]:
        return math.sin(self.yaw), math.cos(self.yaw)

    @property
    def right(self) -> tuple[float, float]:
        """World direction of the local +x axis: (cos yaw, -sin yaw)."""
        return math.cos(self.yaw), -math.sin(self.yaw)


def _aabb(x, z, w, d, yaw):
    if abs(math.sin(yaw)) > 0.5:
        w, d = d, w
    return (x - w / 2, z - d / 2, x + w / 2, z + d / 2)


def _overlap(a, b, tol=EPS) -> bool:
    """True when boxes a and b are closer than ``tol`` on both axes (i.e. overlap or nearly touch)."""
    return a[0] < b[2] + tol and b[0] < a[2] + tol and a[1] < b[3] + tol and b[1] < a[3] + tol


def _snap_yaw(nx, nz) -> float:
    """Yaw whose front (sin yaw, cos yaw) is the axis direction (nx, nz), wrapped to [-pi, pi)."""
    yaw = math.atan2(nx, nz)
    return -math.pi if yaw > math.pi - 1e-9 else yaw


class _Room:
    """A room being furnished: the floor (bounding box minus notches), its walls, the objects placed so
    far and keep-out zones (clearances in front of furniture and the door swing)."""

    def __init__(self, rng, room_type, W, D, notches, ceiling, flaw_rate):
        self.rng, self.room_type, self.W, self.D = rng, room_type, W, D
        self.notches = notches
        self.ceiling = ceiling
        self.flaw_rate = flaw_rate
        self.rich = 1.0  # how generously the room is furnished (tilts optional counts; see _livingroom)
        self.poly = floor_polygon(W, D, notches)
        v = np.asarray(self.poly.exterior.coords)[:-1]
        self.vertices = v
        self.walls: list[_Wall] = []
        for i in range(len(v)):
            a, b = v[i], v[(i + 1) % len(v)]
            e = b - a
            L = float(np.hypot(*e))
            if L < 1e-6:
                continue
            u = e / L
            # counter-clockwise polygon: the interior is on the left of each edge, (-uz, ux)
            self.walls.append(_Wall(float(a[0]), float(a[1]), float(u[0]), float(u[1]),
                                    float(-u[1]), float(u[0]), L))
        self.objs: list[_Obj] = []
        self.keep: list[tuple[tuple, int]] = []  # (box, owner index or -1)

    # --- tests ------------------------------------------------------------------------------------------
    def flaw(self, name: str) -> bool:
        """Draw whether the named flaw happens (probability FLAWS[name] * flaw_rate)."""
        return self.flaw_rate > 0 and self.rng.random() < FLAWS[name] * self.flaw_rate

    def inside(self, b) -> bool:
        W, D = self.W / 2 - EPS, self.D / 2 - EPS
        if b[0] < -W or b[1] < -D or b[2] > W or b[3] > D:
            return False
        return not any(_overlap(b, n) for n in self.notches)

    def free(self, b, ignore=(), keepout=True) -> bool:
        for i, o in enumerate(self.objs):
            if o.ground and i not in ignore and _overlap(b, o.box):
                return False
        if keepout:
            for kb, owner in self.keep:
                if owner not in ignore and _overlap(b, kb, 0.0):
                    return False
        return True

    def ok(self, b, ignore=(), keepout=True) -> bool:
        return self.inside(b) and self.free(b, ignore, keepout)

    def clear_of_objects(self, b, ignore=()) -> bool:
        return all(not (o.ground and i not in ignore and _overlap(b, o.box, 0.0)) for i, o in enumerate(self.objs))

    # --- adding ---------------------------------------------------------------------------------------
    def add(self, label, x, z, size, yaw, y=None, ground=True) -> int:
        w, d, h = size
        h = min(h, self.ceiling - 0.05)
        self.objs.append(_Obj(label, x, z, h / 2 if y is None else y, w, d, h, yaw, ground))
        return len(self.objs) - 1

    def add_keepout(self, owner, depth, extra=0.0):
        """Reserve a strip of ``depth`` m in front of object ``owner`` (as wide as it plus ``extra``)."""
        o = self.objs[owner]
        fx, fz = o.front
        cx, cz = o.x + fx * (o.d / 2 + depth / 2), o.z + fz * (o.d / 2 + depth / 2)
        self.keep.append((_aabb(cx, cz, o.w + extra, depth, o.yaw), owner))

    def front_clear(self, x, z, w, d, yaw, depth) -> bool:
        """The strip of ``depth`` m in front of a would-be object is floor and holds no object."""
        fx, fz = math.sin(yaw), math.cos(yaw)
        b = _aabb(x + fx * (d / 2 + depth / 2), z + fz * (d / 2 + depth / 2), w, depth, yaw)
        return self.clear_of_objects(b) and self.inside(b)

    def inside_center(self, x, z) -> bool:
        return abs(x) < self.W / 2 and abs(z) < self.D / 2 and not any(
            n[0] < x < n[2] and n[1] < z < n[3] for n in self.notches)

    def shift(self, i, dx, dz):
        self.objs[i].x += dx
        self.objs[i].z += dz

    def move_back(self, i, dist):
        """Move object i backwards (into the wall behind it) by ``dist``."""
        fx, fz = self.objs[i].front
        self.shift(i, -fx * dist, -fz * dist)

    # --- placement ------------------------------------------------------------------------------------
    def wall_pose(self, wall: _Wall, t: float, d: float, gap: float):
        x = wall.ax + wall.ux * t + wall.nx * (gap + d / 2)
        z = wall.az + wall.uz * t + wall.nz * (gap + d / 2)
        return x, z, _snap_yaw(wall.nx, wall.nz)

    def wall_gap(self) -> float:
        return EPS + 0.025 * self.rng.random()

    def on_wall(self, label, size, *, where="any", clear=0.0, keep=None, zone=None, tries=16,
                walls=None, shrink=True, min_w=None, slide=True) -> int | None:
        """Place an object with its back against a wall, facing into the room. ``where`` is ``any``,
        ``centre`` (near the wall's middle) or ``corner``; ``clear`` m in front must hold no object;
        ``keep`` reserves that much depth in front afterwards; ``zone`` (x0, z0, x1, z1) must hold the
        object's centre. A too-wide object is narrowed (down to ``min_w``) when ``shrink``."""
        rng = self.rng
        w, d, h = size
        cand = list(range(len(self.walls))) if walls is None else list(walls)
        if zone is not None:
            cand = [i for i in cand if self._wall_in_zone(self.walls[i], zone)]
        if not cand:
            return None
        lens = np.array([self.walls[i].length for i in cand])
        min_w = min_w if min_w is not None else w * 0.6
        for attempt in range(tries):
            ww = w
            fits = lens >= ww + 2 * EPS
            if not fits.any():
                if not shrink or lens.max() - 0.05 < min_w:
                    return None
                ww = round(max(min_w, lens.max() - 0.1), 2)
                fits = lens >= ww + 2 * EPS
            p = np.cumsum(np.where(fits, lens, 0.0))
            wall = self.walls[cand[int(np.searchsorted(p, rng.random() * p[-1], side="right").clip(0, len(cand) - 1))]]
            if shrink and attempt >= tries // 2 and ww > min_w:  # later tries: narrower
                ww = round(max(min_w, ww * rng.uniform(0.6, 0.95)), 2)
            L = wall.length
            if where == "centre":
                t = L / 2 + rng.normal(0, 0.06 * L)
            elif where == "corner":
                t = ww / 2 + EPS + 0.02 * rng.random()
                if rng.random() < 0.5:
                    t = L - t
            else:
                t = rng.uniform(ww / 2, max(ww / 2, L - ww / 2))
            t = min(max(t, ww / 2 + EPS), L - ww / 2 - EPS)
            x, z, yaw = self.wall_pose(wall, t, d, self.wall_gap())
            b = _aabb(x, z, ww, d, yaw)
            if zone is not None and not (zone[0] <= x <= zone[2] and zone[1] <= z <= zone[3]):
                continue
            if not self.ok(b):
                continue
            if clear > 0 and not self.front_clear(x, z, ww, d, yaw, clear):
                continue
            i = self.add(label, x, z, (ww, d, h), yaw)
            if keep:
                self.add_keepout(i, keep)
            if slide and self.flaw("slide_into_neighbour"):
                self.slide_into_neighbour(i, wall)
            return i
        return None

    def slide_into_neighbour(self, i, wall: _Wall, reach: float = 0.8):
        """Slide object i along ``wall`` until it overlaps the nearest ground object by 2-10 cm (a
        flaw); leave it where it was when nothing is within ``reach`` or the floor ends first."""
        o = self.objs[i]
        x0, z0 = o.x, o.z
        s = 1.0 if self.rng.random() < 0.5 else -1.0
        for k in range(1, int(reach / 0.02) + 1):
            o.x, o.z = x0 + s * wall.ux * 0.02 * k, z0 + s * wall.uz * 0.02 * k
            b = o.box
            if not self.inside(b):
                break
            if not self.free(b, ignore={i}, keepout=False):
                extra = self.rng.uniform(0.02, 0.1)
                o.x, o.z = o.x + s * wall.ux * extra, o.z + s * wall.uz * extra
                return
        o.x, o.z = x0, z0

    def _wall_in_zone(self, wall, zone) -> bool:
        mx, mz = wall.ax + wall.ux * wall.length / 2, wall.az + wall.uz * wall.length / 2
        ex, ez = wall.ax + wall.ux * wall.length, wall.az + wall.uz * wall.length
        inz = lambda x, z: zone[0] - 1e-6 <= x <= zone[2] + 1e-6 and zone[1] - 1e-6 <= z <= zone[3] + 1e-6  # noqa: E731
        return inz(mx, mz) or inz(wall.ax, wall.az) or inz(ex, ez)

    def beside(self, parent: int, label, size, side: int, gap: float, ignore=None) -> int | None:
        """Place an object beside ``parent`` (``side`` +1: its local +x, -1: local -x), backs aligned,
        facing the same way (nightstands beside a bed's head, side tables beside a sofa)."""
        p = self.objs[parent]
        w, d, h = size
        rx, rz = p.right
        fx, fz = p.front
        off = side * (p.w / 2 + gap + w / 2)
        back = -(p.d / 2 - d / 2)
        x, z = p.x + rx * off + fx * back, p.z + rz * off + fz * back
        b = _aabb(x, z, w, d, p.yaw)
        ign = {parent} if ignore is None else ignore
        if not self.ok(b, ignore=ign):
            return None
        return self.add(label, x, z, size, p.yaw)

    def facing(self, parent: int, label, size, gap: float, offset: float = 0.0, ignore=None) -> int | None:
        """Place an object in front of ``parent`` facing it (a chair at a desk), ``offset`` along the
        parent's local x."""
        p = self.objs[parent]
        w, d, h = size
        fx, fz = p.front
        rx, rz = p.right
        dist = p.d / 2 + gap + d / 2
        x, z = p.x + fx * dist + rx * offset, p.z + fz * dist + rz * offset
        yaw = _snap_yaw(-fx, -fz)
        b = _aabb(x, z, w, d, yaw)
        ign = {parent} if ignore is None else ignore
        if not self.ok(b, ignore=ign):
            return None
        return self.add(label, x, z, size, yaw)

    def raycast(self, x, z, dx, dz) -> tuple[float, _Wall] | None:
        """First wall hit from (x, z) along the axis direction (dx, dz), facing back at the ray."""
        best = None
        for wall in self.walls:
            if abs(wall.nx + dx) > 1e-6 or abs(wall.nz + dz) > 1e-6:
                continue
            if abs(dx) > 0.5:  # wall runs along z at x = ax
                lo, hi = sorted((wall.az, wall.az + wall.uz * wall.length))
                if not lo <= z <= hi:
                    continue
                dist = (wall.ax - x) * dx
            else:
                lo, hi = sorted((wall.ax, wall.ax + wall.ux * wall.length))
                if not lo <= x <= hi:
                    continue
                dist = (wall.az - z) * dz
            if dist > 0 and (best is None or dist < best[0]):
                best = (dist, wall)
        return best

    def across(self, parent: int, label, size, min_dist=0.6, keep=None) -> int | None:
        """Place an object against the wall in front of ``parent``, facing it (a TV stand facing a bed
        or sofa)."""
        p = self.objs[parent]
        fx, fz = p.front
        hit = self.raycast(p.x, p.z, round(fx), round(fz))
        if hit is None:
            return None
        dist, wall = hit
        w, d, h = size
        if dist - p.d / 2 - d < min_dist:
            return None
        t0 = (p.x - wall.ax) * wall.ux + (p.z - wall.az) * wall.uz
        for k in range(6):
            ww = w if k < 3 else round(w * 0.75, 2)
            t = t0 + (self.rng.normal(0, 0.1) if k else 0.0)
            t = min(max(t, ww / 2 + EPS), wall.length - ww / 2 - EPS)
            x, z, yaw = self.wall_pose(wall, t, d, self.wall_gap())
            b = _aabb(x, z, ww, d, yaw)
            if self.ok(b, ignore={parent}):
                i = self.add(label, x, z, (ww, d, h), yaw)
                if keep:
                    self.add_keepout(i, keep)
                return i
        return None

    def free_standing(self, label, size, yaw, centre, jitter, tries=12, margin=0.0, ignore=()) -> int | None:
        """Place an object at ``centre`` (+- ``jitter``) with ``margin`` m of free floor around it."""
        w, d, h = size
        for k in range(tries):
            j = jitter if k else 0.0
            x = centre[0] + self.rng.uniform(-j, j)
            z = centre[1] + self.rng.uniform(-j, j)
            b = _aabb(x, z, w, d, yaw)
            bm = (b[0] - margin, b[1] - margin, b[2] + margin, b[3] + margin)
            if self.ok(b, ignore) and (margin == 0 or (self.inside(bm) and self.free(bm, ignore, False))):
                return self.add(label, round(x, 3), round(z, 3), size, yaw)
        return None

    def lamp(self, label, x, z, size=None, variant=None):
        """Hang a lamp at (x, z): centre y = ceiling - half height (pendants may hang a little lower)."""
        size = size or SIZES[variant or label].sample(self.rng)
        w, d, h = size
        for _ in range(3):  # the lamp's footprint stays over the floor: shrink it, else skip it
            if self.inside(_aabb(x, z, w, d, 0.0)):
                break
            w, d = round(max(0.2, w * 0.6), 2), round(max(0.15, d * 0.6), 2)
        else:
            return None
        if label == "pendant_lamp":
            h = min(h, self.ceiling - 1.6)
            y = self.ceiling - h / 2 - 0.04 * self.rng.random()
        else:
            y = self.ceiling - h / 2
        return self.add(label, x, z, (w, d, h), 0.0, y=round(y, 3), ground=False)

    def door(self, tries: int = 8):
        """Keep a 0.9 m door swing free somewhere along a wall (where no object stands yet)."""
        walls = [w for w in self.walls if w.length > 1.2]
        for _ in range(tries if walls else 0):
            wall = walls[int(self.rng.integers(len(walls)))]
            if self.rng.random() < 0.7:  # most doors open near a corner
                t = 0.5 + 0.3 * self.rng.random()
                t = t if self.rng.random() < 0.5 else wall.length - t
            else:
                t = self.rng.uniform(0.55, wall.length - 0.55)
            x, z, yaw = self.wall_pose(wall, t, 0.85, 0.0)
            b = _aabb(x, z, 0.9, 0.85, yaw)
            if self.clear_of_objects(b):
                self.keep.append((b, -1))
                return

    def zone_split(self, frac):
        """Split the bounding box along its long axis: (zone A with ``frac`` of the length, zone B)."""
        W, D = self.W / 2, self.D / 2
        flip = self.rng.random() < 0.5
        if self.W >= self.D:
            cut = -W + frac * self.W if not flip else W - frac * self.W
            a, b = (-W, -D, cut, D), (cut, -D, W, D)
            return (a, b) if not flip else (b, a)
        cut = -D + frac * self.D if not flip else D - frac * self.D
        a, b = (-W, -D, W, cut), (-W, cut, W, D)
        return (a, b) if not flip else (b, a)

    # --- output ---------------------------------------------------------------------------------------
    def layout(self, room_type, sid, max_objects) -> Layout:
        objs = [o for o in self.objs if o.emit][:max_objects]  # lamps come last: dropped first
        n = len(objs)
        t = np.array([[o.x, o.y, o.z] for o in objs]).reshape(n, 3)
        hs = np.array([[o.w / 2, o.h / 2, o.d / 2] for o in objs]).reshape(n, 3)
        yaws = np.array([o.yaw for o in objs])
        return Layout(room_type, FloorPlan.from_vertices(self.vertices), [o.label for o in objs],
                      np.round(t, 4), np.round(hs, 4), yaws, id=sid, ceiling_height=self.ceiling)


# --------------------------------------------------------------------------------------------------------
# Room programs
# --------------------------------------------------------------------------------------------------------
def _sz(rng, key):
    return SIZES[key].sample(rng)


def _seat_at(room: _Room, parent: int, label, size, flaw: str, under: tuple[float, float] = (0.1, 0.3),
             offset: float = 0.0):
    """A chair or stool in front of ``parent`` facing it; with the ``flaw``, pushed partly under it."""
    rng = room.rng
    if room.flaw(flaw):
        i = room.facing(parent, label, size, gap=-rng.uniform(*under), offset=offset, ignore={parent})
        if i is not None:
            return i
    return room.facing(parent, label, size, gap=EPS + rng.uniform(0.02, 0.2), offset=offset)


def _wall_flaw(room: _Room, i, name="wall_object_into_wall", depth=(0.07, 0.16)):
    if i is not None and room.flaw(name):
        room.move_back(i, room.rng.uniform(*depth))


def _bed_group(room: _Room, label, size, wanted) -> tuple[int | None, list]:
    """Place a bed with its head against a wall, leaving room beside its head for the ``wanted``
    nightstands ``(label, side, size, gap)``: the whole group is placed as one box, then the bed takes its
    share. Nightstands that do not fit are dropped one by one; the bed shrinks as a last resort.
    Returns the bed's index (None when it does not fit) and the nightstands that fit."""
    rng = room.rng
    wanted = list(wanted)
    for attempt in range(6):
        extra = {s: sz[0] + gap for _, s, sz, gap in wanted}  # a flawed (overlapping) one takes less
        gw = size[0] + sum(extra.values())
        where = "centre" if attempt < 2 and rng.random() < 0.75 else "any" if attempt < 4 else "corner"
        g = room.on_wall(label, (gw, size[1], size[2]), where=where, clear=0.5, tries=10, shrink=False,
                         slide=False)
        if g is not None:
            o = room.objs[g]
            rx, rz = o.right
            shift = (extra.get(-1, 0.0) - extra.get(1, 0.0)) / 2  # towards the side without a nightstand
            o.x, o.z, o.w = o.x + rx * shift, o.z + rz * shift, size[0]
            room.add_keepout(g, 0.55)
            return g, wanted
        if wanted and attempt % 2 == 1:
            wanted.pop()
        elif attempt >= 4:
            size = (max(1.2, size[0] - 0.2), max(1.9, size[1] - 0.1), size[2])
    return None, []


def _bedroom(room: _Room):
    rng = room.rng
    # -- the bed and its nightstands
    u = rng.random()
    bed_label = "double_bed" if u < 0.87 else "single_bed" if u < 0.895 else "kids_bed" if u < 0.92 else None
    phantom = bed_label is None  # a room without a bed (study, guest room): its wall is still furnished
    size = _sz(rng, bed_label or "double_bed")
    n_ns = _pick_count(rng, [0.17, 0.17, 0.65, 0.01]) if not phantom else _pick_count(rng, [0.45, 0.2, 0.35])
    side_table = rng.random() < 0.06  # a small side table instead of a nightstand
    if side_table:
        n_ns = max(n_ns - 1, 0)
    sides = [1, -1] if rng.random() < 0.5 else [-1, 1]
    wanted = [("nightstand", s) for s in sides[:min(n_ns, 2)]]
    if side_table and len(wanted) < 2:
        wanted.append(("table", sides[len(wanted)]))
    # (label, side, size, gap): a flawed nightstand overlaps the bed's side (a negative gap)
    wanted = [(label, side, _sz(rng, label),
               -rng.uniform(0.02, 0.15) if room.flaw("nightstand_into_bed") else EPS + rng.uniform(0.0, 0.06))
              for label, side in wanted]
    bed, wanted = _bed_group(room, bed_label or "double_bed", size, wanted)
    if bed is not None:
        for label, side, ns_size, gap in wanted:
            ns = room.beside(bed, label, ns_size, side, gap)
            if ns is not None and room.flaw("into_wall"):
                room.move_back(ns, rng.uniform(0.07, 0.16))
    room.door()
    if bed is not None:
        if n_ns > 2 and len(wanted):
            room.on_wall("nightstand", _sz(rng, "nightstand"))
        if rng.random() < 0.035:  # a bench at the foot of the bed
            b = room.objs[bed]
            size = _sz(rng, "stool:bench")
            size = (min(size[0], b.w - 0.1), size[1], size[2])
            gap = EPS + rng.uniform(0.02, 0.1)
            i = room.facing(bed, "stool", size, gap, ignore={bed})
            if i is not None:
                room.objs[i].yaw = b.yaw
                if room.flaw("bench_into_bed"):  # pushed against the foot board
                    fx, fz = b.front
                    push = gap + rng.uniform(0.03, 0.15)
                    room.shift(i, -fx * push, -fz * push)
        _wall_flaw(room, bed, depth=(0.07, 0.12))
    bed_obj = room.objs[bed] if bed is not None else None
    # -- TV stand facing the bed
    if rng.random() < 0.26:
        tv = room.across(bed, "tv_stand", _sz(rng, "tv_stand"), keep=0.3) if bed is not None else None
        if tv is None:
            tv = room.on_wall("tv_stand", _sz(rng, "tv_stand"), clear=0.5, min_w=1.0)
        _wall_flaw(room, tv)
    if phantom and bed is not None:  # a placeholder: keeps its floor space free, not written out
        room.objs[bed].emit = False
    # -- wardrobe(s)
    for _ in range(_pick_count(rng, [0.3, 0.68, 0.02])):
        i = room.on_wall("wardrobe", _sz(rng, "wardrobe"), where="corner" if rng.random() < 0.5 else "any",
                         clear=0.5, keep=0.5, min_w=0.8, tries=24)
        _wall_flaw(room, i)
    # -- desk and chair, dressing table and stool
    if rng.random() < 0.2:
        desk = room.on_wall("desk", _sz(rng, "desk"), clear=0.6, min_w=0.9, tries=24)
        if desk is not None:
            if rng.random() < 0.8:
                _seat_at(room, desk, "chair", _sz(rng, "chair"), "chair_tucked")
            _wall_flaw(room, desk, "desk_into_wall")
    if rng.random() < 0.1:
        dt = room.on_wall("dressing_table", _sz(rng, "dressing_table"), clear=0.5, min_w=0.7, tries=24)
        if dt is not None:
            v = rng.random()
            seat = "stool" if v < 0.45 else "chair" if v < 0.7 else "dressing_chair" if v < 0.75 else None
            if seat:
                _seat_at(room, dt, seat, _sz(rng, seat), "chair_tucked", under=(0.05, 0.2))
            _wall_flaw(room, dt, "desk_into_wall")
    # -- storage against walls
    for label, p, key in (("cabinet", 0.16, None), ("bookshelf", 0.07, "bookshelf"), ("shelf", 0.035, "shelf"),
                          ("children_cabinet", 0.008, "children_cabinet")):
        if rng.random() < p:
            key = key or ("cabinet:tall" if rng.random() < 0.3 else "cabinet")
            i = room.on_wall(label, _sz(rng, key), clear=0.4, min_w=0.4)
            _wall_flaw(room, i)
    # -- seats and small tables
    if rng.random() < 0.13:  # an extra chair (reading corner, by the window)
        room.on_wall("chair", _sz(rng, "chair"), where="corner")
    if rng.random() < 0.02:
        room.on_wall("armchair", _sz(rng, "armchair"), where="corner")
    if rng.random() < 0.06:
        s = room.on_wall("sofa", _sz(rng, "sofa"), clear=0.5, min_w=1.1)
        if s is not None and rng.random() < 0.25:
            room.facing(s, "coffee_table", _sz(rng, "coffee_table"), gap=0.35)
    if rng.random() < 0.025:
        room.on_wall("stool", _sz(rng, "stool"))
    if rng.random() < 0.06:
        for _ in range(1 + (rng.random() < 0.3)):
            i = room.on_wall("table", _sz(rng, "table"), where="corner")
            _wall_flaw(room, i, "into_wall")
    # -- lamps
    cx, cz = (bed_obj.x, bed_obj.z) if bed_obj is not None else (0.0, 0.0)
    if bed_obj is not None:
        fx, fz = bed_obj.front
        cx, cz = cx + fx * 0.2, cz + fz * 0.2
    if not room.inside_center(cx, cz):
        cx, cz = room.poly.centroid.x, room.poly.centroid.y
    v = rng.random()
    if v < 0.5:
        room.lamp("pendant_lamp", round(cx, 3), round(cz, 3))
    elif v < 0.6:
        ox, oz = room.poly.centroid.x, room.poly.centroid.y
        room.lamp("pendant_lamp", round(ox, 3), round(oz, 3))
    if rng.random() < 0.1 and bed_obj is not None:  # bedside pendants
        for o in [o for o in room.objs if o.label == "nightstand"]:
            room.lamp("pendant_lamp", o.x, o.z, size=(0.25, 0.25, round(rng.uniform(0.5, 0.9), 2)))
    if rng.random() < 0.15:
        ox, oz = room.poly.centroid.x, room.poly.centroid.y
        room.lamp("ceiling_lamp", round(ox, 3), round(oz, 3))


def _dining_group(room: _Room, zone, n_chairs_probs, square_p=0.15, chair_label="dining_chair",
                  tilt: float = 1.0) -> int | None:
    """A dining table standing free in ``zone`` (its long side along the zone's long axis) with chairs
    around it; where no free spot is found, a smaller table pushed against a wall with chairs on its
    three open sides. Returns the table's index."""
    rng = room.rng
    n = _pick_count(rng, n_chairs_probs, tilt)
    # seats per side (long sides a, b) and at the ends
    plans = {0: (0, 0, 0), 1: (1, 0, 0), 2: (1, 1, 0), 3: (2, 1, 0), 4: (2, 2, 0), 5: (2, 2, 1),
             6: (3, 3, 0), 7: (3, 3, 1), 8: (3, 3, 2), 9: (4, 4, 1), 10: (4, 4, 2)}
    square = n <= 4 and rng.random() < square_p
    zx, zz = zone[2] - zone[0], zone[3] - zone[1]
    yaw = 0.0 if zx >= zz else math.pi / 2
    part = room.poly.intersection(box(*zone))
    c = part.centroid if not part.is_empty else room.poly.centroid
    centre = (round(c.x, 3), round(c.y, 3))
    for attempt in range(6):
        per_a, per_b, ends = plans[min(n, 10)]
        if square:
            size = _sz(rng, "dining_table:square")
            per_a, per_b, ends = (1, 1, 0) if n <= 2 else (1, 1, 2) if n == 4 else (1, 1, 1)
        else:
            size = _sz(rng, "dining_table")
            need = max(per_a, per_b) * 0.62 + 0.1
            size = (round(max(size[0], need), 2), size[1], size[2])
        chair = _sz(rng, chair_label)
        margin = chair[1] + 0.1 if n else 0.4
        jitter = 0.5 if attempt == 0 else max(0.5, min(zx, zz) / 2 - 0.5)
        t = room.free_standing("dining_table", size, yaw, centre, jitter=jitter, margin=margin, tries=16)
        if t is not None:
            break
        if attempt >= 3:  # fewer chairs (a smaller table) before pushing it against a wall
            n = max(min(n, 4), n - 2)
            square = square or n <= 2
    if t is None:  # a small room: the table against a wall, chairs along its front and at its ends
        n = min(n, 5)
        square = n <= 3 and rng.random() < 0.5
        size = _sz(rng, "dining_table:square" if square else "dining_table")
        for z in (zone, None):
            t = room.on_wall("dining_table", size, clear=chair[1] + 0.15, zone=z, min_w=0.7, slide=False)
            if t is not None:
                break
        if t is None:
            return None
        per_a = min(n, 1 if square else 3 if room.objs[t].w > 1.6 else 2)
        per_b, ends = 0, min(n - per_a, 2)
    tab = room.objs[t]
    seats = []
    for side, k in ((1, per_a), (-1, per_b)):
        for j in range(k):
            u = (j + 0.5) / k - 0.5
            seats.append((u * (tab.w - 0.1) if k > 1 else rng.normal(0, 0.03), side, "long"))
    for j in range(ends):
        seats.append(((1, -1)[j], 0, "end"))
    if n < len(seats):  # an odd count: drop random seats
        keep = rng.permutation(len(seats))[:n]
        seats = [seats[i] for i in sorted(keep)]
    placed = []
    for u, side, kind in seats:
        tucked = room.flaw("dining_chair_tucked")
        gap = -rng.uniform(0.05, 0.25) if tucked else EPS + rng.uniform(0.02, 0.09)
        rx, rz = tab.right
        fx, fz = tab.front
        if kind == "long":
            dist = tab.d / 2 + gap + chair[1] / 2
            x, z = tab.x + rx * u + fx * dist * side, tab.z + rz * u + fz * dist * side
            cyaw = _snap_yaw(-fx * side, -fz * side)
        else:
            dist = tab.w / 2 + gap + chair[1] / 2
            x, z = tab.x + rx * dist * u, tab.z + rz * dist * u
            cyaw = _snap_yaw(-rx * u, -rz * u)
        b = _aabb(x, z, chair[0], chair[1], cyaw)
        ignore = {t} | set(placed) if tucked else {t}
        if tucked:  # tucked under the table: only the table may be touched
            if not (room.inside(b) and room.free(b, ignore=ignore)):
                continue
        elif not room.ok(b, ignore={t}):
            continue
        placed.append(room.add(chair_label, round(x, 3), round(z, 3), chair, cyaw))
    if len(placed) >= 2 and room.flaw("dining_chair_jostle"):
        i = placed[int(rng.integers(len(placed)))]
        o = room.objs[i]
        rx, rz = o.right
        room.shift(i, rx * rng.uniform(0.05, 0.12), rz * rng.uniform(0.05, 0.12))
    return t


def _living_group(room: _Room, zone, dining_zone):
    """Sofa, coffee table, TV stand, side tables and armchairs in ``zone``."""
    rng = room.rng
    sofa_label = _pick(rng, {"multi_seat_sofa": 0.6, "l_shaped_sofa": 0.22, "loveseat_sofa": 0.05,
                             "chaise_longue_sofa": 0.01, "lazy_sofa": 0.002, None: 0.12})
    sofa = None
    if sofa_label is not None:
        size = _sz(rng, sofa_label)
        if dining_zone is not None and rng.random() < 0.3:
            # a sofa standing free with its back to the dining zone, facing the living end wall
            zc = ((zone[0] + zone[2]) / 2, (zone[1] + zone[3]) / 2)
            dc = ((dining_zone[0] + dining_zone[2]) / 2, (dining_zone[1] + dining_zone[3]) / 2)
            dx, dz = zc[0] - dc[0], zc[1] - dc[1]
            ax = (1.0 if dx > 0 else -1.0, 0.0) if abs(dx) > abs(dz) else (0.0, 1.0 if dz > 0 else -1.0)
            yaw = _snap_yaw(*ax)
            # the back edge a little inside the living zone
            edge = zone[0] if ax[0] > 0 else zone[2] if ax[0] < 0 else zone[1] if ax[1] > 0 else zone[3]
            off = edge + (ax[0] + ax[1]) * (0.3 + size[1] / 2)
            c = (off, zc[1]) if ax[0] else (zc[0], off)
            sofa = room.free_standing(sofa_label, size, yaw, c, jitter=0.15, tries=6)
            if sofa is not None and not room.front_clear(room.objs[sofa].x, room.objs[sofa].z, size[0], size[1], yaw, 1.6):
                room.objs.pop(sofa)
                sofa = None
            elif sofa is not None:
                room.add_keepout(sofa, 0.9)
        if sofa is None:
            sofa = room.on_wall(sofa_label, size, where="centre" if rng.random() < 0.6 else "any",
                                clear=1.4, keep=0.9, zone=zone, min_w=1.2)
    if sofa is not None:
        s = room.objs[sofa]
        # coffee table in front
        if rng.random() < 0.75:
            key = "coffee_table:round" if rng.random() < 0.2 else "coffee_table"
            ct_size = _sz(rng, key)
            ct_size = (min(ct_size[0], s.w - 0.2), ct_size[1], ct_size[2])
            gap = EPS + rng.uniform(0.3, 0.5)
            ct = room.facing(sofa, "coffee_table", ct_size, gap, ignore={sofa})
            if ct is not None:
                if rng.random() < 0.06:
                    room.facing(sofa, "coffee_table", _sz(rng, "coffee_table:round"), gap + ct_size[1] + 0.15,
                                ignore={sofa, ct})
                if s.label == "l_shaped_sofa" and room.flaw("sofa_overlap"):
                    room.move_back(ct, -(gap + rng.uniform(0.1, 0.5)))  # ct faces the sofa: move toward it
                # armchairs / lounge chairs at the coffee table's sides, facing it
                n_arm = _pick_count(rng, [0.72, 0.2, 0.07, 0.01], room.rich)
                n_lounge = _pick_count(rng, [0.85, 0.1, 0.05])
                seats = ["armchair"] * n_arm + ["lounge_chair"] * n_lounge
                sides = [1, -1] if rng.random() < 0.5 else [-1, 1]
                c = room.objs[ct]
                for k, label in enumerate(seats[:2]):
                    size = _sz(rng, label)
                    side = sides[k]
                    rx, rz = c.right
                    dist = c.w / 2 + 0.35 + size[1] / 2
                    x, z = c.x + rx * dist * side, c.z + rz * dist * side
                    yaw = _snap_yaw(-rx * side, -rz * side)
                    b = _aabb(x, z, size[0], size[1], yaw)
                    if room.ok(b, ignore={sofa}):
                        room.add(label, round(x, 3), round(z, 3), size, yaw)
                for label in seats[2:]:
                    room.on_wall(label, _sz(rng, label), where="corner")
        # TV stand facing the sofa
        if rng.random() < 0.86:
            tv = room.across(sofa, "tv_stand", _sz(rng, "tv_stand"), min_dist=1.2)
            _wall_flaw(room, tv, "living_into_wall")
        # side tables beside the sofa's arms
        n_side = _pick_count(rng, [0.3, 0.25, 0.45], room.rich)
        sides = [1, -1] if rng.random() < 0.5 else [-1, 1]
        for side in sides[:n_side]:
            label = "corner_side_table" if rng.random() < 0.75 else "round_end_table"
            gap = EPS + rng.uniform(0.0, 0.08)
            i = room.beside(sofa, label, _sz(rng, "corner_side_table" if label == "corner_side_table" else label),
                            side, gap)
            if i is not None and room.flaw("sofa_overlap"):
                rx, rz = s.right
                ov = gap + rng.uniform(0.03, 0.15)
                room.shift(i, -side * rx * ov, -side * rz * ov)
    else:
        if rng.random() < 0.6:
            room.on_wall("tv_stand", _sz(rng, "tv_stand"), clear=1.0, zone=zone)
        for _ in range(_pick_count(rng, [0.5, 0.3, 0.2])):
            room.on_wall("armchair" if rng.random() < 0.6 else "lounge_chair", _sz(rng, "armchair"), where="corner")
    return sofa


def _livingroom(room: _Room):
    """3D-FRONT "living rooms" are mostly living-dining rooms: a living zone and a dining zone."""
    rng = room.rng
    room.door()
    area = room.poly.area
    # how generously this room is furnished: bigger rooms hold more, and some owners simply own more
    room.rich = float(np.clip(math.exp(rng.normal(0, RICH_SIGMA)) * (area / 28) ** RICH_AREA, 0.4, RICH_MAX))
    has_dining = rng.random() < (0.85 if area > 18 else 0.76)
    if not has_dining:  # the whole room is a living room: more seats, side tables and storage
        room.rich = min(room.rich * 1.6, 2.5)
    rich = room.rich
    if has_dining:
        living, dining = room.zone_split(rng.uniform(0.5, 0.62))
    else:
        living, dining = (-room.W / 2, -room.D / 2, room.W / 2, room.D / 2), None
    table = None
    if dining is not None:
        table = _dining_group(room, dining, [0.02, 0.03, 0.05, 0.02, 0.48, 0.11, 0.2, 0.03, 0.04, 0.0, 0.01],
                              tilt=math.sqrt(rich),
                              chair_label="dining_chair" if rng.random() < 0.95 else
                              ("lounge_chair" if rng.random() < 0.9 else "chinese_chair"))
    sofa = _living_group(room, living, dining)
    if dining is not None:
        # a second table: a small table against a wall with a seat or two, or bar stools
        for p in (0.15, 0.05):
            if rng.random() < _tilted(p, rich):
                t2 = room.on_wall("dining_table", _sz(rng, "dining_table:square" if rng.random() < 0.5 else "dining_table"),
                                  clear=0.6, min_w=0.7)
                if t2 is not None:
                    for k in range(_pick_count(rng, [0.5, 0.3, 0.2])):
                        o = room.objs[t2]
                        off = 0.0 if k == 0 else (o.w / 4) * (1 if k == 1 else -1)
                        _seat_at(room, t2, "dining_chair" if rng.random() < 0.75 else "stool",
                                 _sz(rng, "dining_chair"), "dining_chair_tucked", under=(0.05, 0.2), offset=off)
    # storage and other pieces against walls
    for _ in range(_pick_count(rng, [0.5, 0.3, 0.13, 0.05, 0.02], rich)):
        i = room.on_wall("cabinet", _sz(rng, "cabinet:tall" if rng.random() < 0.3 else "cabinet"), clear=0.5,
                         min_w=0.5)
        _wall_flaw(room, i)
    for label, counts, key in (("bookshelf", [0.83, 0.14, 0.03], "bookshelf"),
                               ("console_table", [0.92, 0.06, 0.02], "console_table"),
                               ("desk", [0.965, 0.035], "desk"), ("shelf", [0.97, 0.03], "shelf"),
                               ("wardrobe", [0.975, 0.025], "wardrobe"), ("wine_cabinet", [0.99, 0.01], "wine_cabinet")):
        for _ in range(_pick_count(rng, counts)):
            i = room.on_wall(label, _sz(rng, key), clear=0.5, min_w=0.4)
            _wall_flaw(room, i, "living_into_wall")
            if label == "desk" and i is not None and rng.random() < 0.5:
                _seat_at(room, i, "dining_chair" if rng.random() < 0.5 else "lounge_chair", _sz(rng, "chair"),
                         "chair_tucked")
    # extra seats and small tables
    for _ in range(_pick_count(rng, [0.8, 0.1, 0.06, 0.02, 0.02], rich)):
        size = _sz(rng, "stool:bar" if rng.random() < 0.4 else "stool")
        _wall_flaw(room, room.on_wall("stool", size), "living_into_wall", depth=(0.06, 0.12))
    if rng.random() < 0.08:
        room.on_wall("round_end_table", _sz(rng, "round_end_table"), where="corner")
    if rng.random() < 0.08:
        for _ in range(1 + (rng.random() < 0.5)):
            room.on_wall("lounge_chair", _sz(rng, "lounge_chair"), where="corner")
    if rng.random() < 0.06:
        room.on_wall("armchair", _sz(rng, "armchair"), where="corner")
    if rng.random() < 0.01:
        room.on_wall("chinese_chair", _sz(rng, "chinese_chair"))
    # lamps: over the dining table (one or two), over the coffee table or the living zone
    if table is not None:
        _lamps_over_table(room, table, (0.6, 0.7, 0.85))
    if rng.random() < 0.7:
        ct = [o for o in room.objs if o.label == "coffee_table"]
        if ct:
            x, z = ct[0].x, ct[0].z
        else:
            x, z = (living[0] + living[2]) / 2, (living[1] + living[3]) / 2
        if room.inside_center(x, z):
            room.lamp("pendant_lamp", round(x, 3), round(z, 3))
    if rng.random() < 0.1:
        x, z = room.poly.centroid.x, room.poly.centroid.y
        room.lamp("ceiling_lamp", round(x, 3), round(z, 3))
    if rng.random() < 0.12:  # an entrance or corridor lamp
        room.lamp("pendant_lamp", round(rng.uniform(-room.W / 3, room.W / 3), 3), round(rng.uniform(-room.D / 3, room.D / 3), 3))


def _lamps_over_table(room: _Room, table: int, thresholds: tuple[float, float, float]) -> None:
    """Pendant lamps over a dining table: one (below thresholds[0]), two along a long table (below [1]),
    one linear lamp aligned with the table (below [2]), else none."""
    rng = room.rng
    t = room.objs[table]
    v = rng.random()
    if v < thresholds[0]:
        room.lamp("pendant_lamp", t.x, t.z)
    elif v < thresholds[1] and t.w > 1.3:
        rx, rz = t.right
        for s in (-1, 1):
            room.lamp("pendant_lamp", round(t.x + s * rx * t.w / 4, 3), round(t.z + s * rz * t.w / 4, 3))
    elif v < thresholds[2]:
        i = room.lamp("pendant_lamp", t.x, t.z, size=_sz(rng, "pendant_lamp:linear"))
        room.objs[i].yaw = t.yaw


def _diningroom(room: _Room):
    """Dining rooms: one dining table with 4-8 chairs dominates; sideboards, a wine cabinet, pendants."""
    rng = room.rng
    full = (-room.W / 2, -room.D / 2, room.W / 2, room.D / 2)
    table = _dining_group(room, full, [0.0, 0.01, 0.06, 0.02, 0.4, 0.08, 0.3, 0.05, 0.07, 0.0, 0.01])
    room.door()
    if table is not None and room.poly.area > 24 and rng.random() < 0.2:  # a second, small table
        t2 = room.on_wall("dining_table", _sz(rng, "dining_table:square"), clear=0.6)
        if t2 is not None:
            _seat_at(room, t2, "dining_chair", _sz(rng, "dining_chair"), "dining_chair_tucked")
    for _ in range(_pick_count(rng, [0.35, 0.45, 0.17, 0.03])):
        i = room.on_wall("cabinet", _sz(rng, "cabinet:tall" if rng.random() < 0.3 else "cabinet"), clear=0.6, min_w=0.5)
        _wall_flaw(room, i)
    for label, p in (("wine_cabinet", 0.3), ("console_table", 0.15), ("bookshelf", 0.08), ("shelf", 0.08)):
        if rng.random() < p:
            i = room.on_wall(label, _sz(rng, label), clear=0.6, min_w=0.4)
            _wall_flaw(room, i)
    if rng.random() < 0.05:
        room.on_wall("armchair", _sz(rng, "armchair"), where="corner")
    if rng.random() < 0.05:
        room.on_wall("corner_side_table", _sz(rng, "corner_side_table"), where="corner")
    if rng.random() < 0.06:
        for _ in range(1 + int(rng.integers(2))):
            room.on_wall("stool", _sz(rng, "stool:bar"))
    if table is not None:
        _lamps_over_table(room, table, (0.55, 0.75, 0.9))
    if rng.random() < 0.25:
        room.lamp("ceiling_lamp", round(room.poly.centroid.x, 3), round(room.poly.centroid.y, 3))


_PROGRAMS = {"bedroom": _bedroom, "livingroom": _livingroom, "diningroom": _diningroom}
_ROOM_CODE = {"bedroom": 1, "livingroom": 2, "diningroom": 3}


def generate_room(room_type: str, index: int, seed: int = 0, flaw_rate: float = 1.0) -> Layout:
    """Scene number ``index`` of the stream for (``room_type``, ``seed``): each scene has its own random
    generator, so the first k scenes of a longer run are the same as a run of k scenes."""
    spec = get_room(room_type)
    rng = np.random.default_rng([int(seed), _ROOM_CODE[spec.name], int(index)])
    W, D, notches = sample_floor(rng, spec.name)
    ceiling = 2.6 if rng.random() < 0.85 else round(float(rng.uniform(2.7, 3.0)), 2)
    room = _Room(rng, spec.name, W, D, notches, ceiling, float(flaw_rate))
    _PROGRAMS[spec.name](room)
    return room.layout(spec.name, f"procedural-{spec.name}-{index:05d}", spec.max_objects)


def generate_layouts(room_type: str, num_scenes: int, seed: int = 0, flaw_rate: float = 1.0,
                     progress: bool = False, processes: int | None = 1) -> list[Layout]:
    """Generate ``num_scenes`` synthetic 3D-FRONT rooms of ``room_type`` (bedroom, livingroom, diningroom).

    Deterministic for a ``seed``. ``flaw_rate`` scales the probability of the deliberate flaws real
    3D-FRONT has (0: no overlapping ground objects and every footprint inside the floor; 1: rates like
    the real data). Floors are centred at the origin; ids are ``procedural-<room>-<index:05d>``.
    ``progress=True`` shows a tqdm bar. ``processes``: worker processes generating chunks of rooms in
    parallel (None or 0: one per available core); the rooms are the same whatever the number.
    """
    if processes == 1:
        _check_arguments(num_scenes, flaw_rate)
        spec = get_room(room_type)
        it = range(int(num_scenes))
        if progress:
            from tqdm import tqdm

            it = tqdm(it, desc=f"procedural {spec.name}", unit="room")
        return [generate_room(spec.name, i, seed, flaw_rate) for i in it]
    return [lay for chunk in map_room_chunks(room_type, num_scenes, seed=seed, flaw_rate=flaw_rate,
                                             processes=processes, progress=progress) for lay in chunk]


def available_cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def map_room_chunks(room_type: str, num_scenes: int, fn: Callable[[list[Layout]], object] | None = None,
                    seed: int = 0, flaw_rate: float = 1.0, processes: int | None = None, chunk_size: int = 0,
                    progress: bool = False) -> Iterator:
    """``fn(rooms)`` (default: the rooms themselves) for consecutive chunks of the rooms
    :func:`generate_layouts` makes, in order, each chunk generated and handed to ``fn`` in one of
    ``processes`` worker processes (None or 0: one per available core; 1: in this process). ``fn`` must be
    picklable (a module-level function or a ``functools.partial`` of one) and so must what it returns.
    Each room has its own random generator (:func:`generate_room`), so chunks give the serial rooms.
    ``progress``: a tqdm bar counting rooms."""
    _check_arguments(num_scenes, flaw_rate)
    spec = get_room(room_type)
    num_scenes = int(num_scenes)
    processes = min(int(processes or available_cores()), max(1, num_scenes))
    if chunk_size <= 0:  # a few chunks per process (a balanced load and a moving bar), at most 500 rooms each
        chunk_size = max(1, min(500, -(-num_scenes // (4 * processes))))
    starts = range(0, num_scenes, chunk_size)
    tasks = [(spec.name, start, min(start + chunk_size, num_scenes), seed, float(flaw_rate), fn) for start in starts]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=num_scenes, desc=f"procedural {spec.name}", unit="room", dynamic_ncols=True)
    try:
        if processes == 1:
            results = map(_chunk, tasks)
            for task, result in zip(tasks, results):
                if bar is not None:
                    bar.update(task[2] - task[1])
                yield result
            return
        import multiprocessing

        methods = multiprocessing.get_all_start_methods()
        # fork starts a worker in milliseconds (spawn re-imports torch: seconds); the workers use numpy only
        context = multiprocessing.get_context("fork" if "fork" in methods else None)
        with context.Pool(processes, initializer=_worker_init) as pool:
            for task, result in zip(tasks, pool.imap(_chunk, tasks)):
                if bar is not None:
                    bar.update(task[2] - task[1])
                yield result
    finally:
        if bar is not None:
            bar.close()


def _worker_init() -> None:
    try:  # a worker computes on one thread: the processes share the cores
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover - torch is a dependency
        pass


def _chunk(task):
    room_type, start, stop, seed, flaw_rate, fn = task
    rooms = [generate_room(room_type, i, seed, flaw_rate) for i in range(start, stop)]
    return rooms if fn is None else fn(rooms)


def _check_arguments(num_scenes: int, flaw_rate: float) -> None:
    if num_scenes < 0:
        raise ValueError(f"num_scenes must be >= 0, got {num_scenes}")
    if not 0.0 <= float(flaw_rate) <= 1.0:
        raise ValueError(f"flaw_rate must be within [0, 1], got {flaw_rate}")


__all__ = ["FLAWS", "GENERATOR_VERSION", "ROOM_SHAPES", "SIZES", "RoomShape", "Size", "available_cores",
           "floor_polygon", "generate_layouts", "generate_room", "map_room_chunks", "sample_floor"]
