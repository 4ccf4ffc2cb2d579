"""The placement engine of the procedural rooms (:mod:`iarcs_env.datasets.procedural`): object sizes, room shapes,
rectilinear floor plans, and a room that places axis-aligned boxes against walls, beside and in front of each
other, with the flaws (touching, overlapping, crossing a wall) that real 3D-FRONT rooms have."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import Polygon, box

from ..floorplan import FloorPlan
from ..scene import Layout

#: Smallest gap (m) between two objects, or an object and a wall, in a flawless placement.
EPS = 0.005

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
def tilted(p: float, tilt: float) -> float:
    """A probability ``p`` tilted like :func:`pick_count`'s second index (odds times ``tilt``)."""
    return p * tilt / (1 - p + p * tilt)


def pick(rng: np.random.Generator, table: dict[str, float]) -> str:
    keys = list(table)
    p = np.array([table[k] for k in keys], dtype=float)
    return keys[int(np.searchsorted(np.cumsum(p), rng.random() * p.sum(), side="right").clip(0, len(keys) - 1))]


def pick_count(rng: np.random.Generator, probs, tilt: float = 1.0) -> int:
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
    kind = pick(rng, shape_p.shapes)
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
        return aabb(self.x, self.z, self.w, self.d, self.yaw)

    @property
    def front(self) -> tuple[float, float]:
        return math.sin(self.yaw), math.cos(self.yaw)

    @property
    def right(self) -> tuple[float, float]:
        """World direction of the local +x axis: (cos yaw, -sin yaw)."""
        return math.cos(self.yaw), -math.sin(self.yaw)


def aabb(x, z, w, d, yaw):
    if abs(math.sin(yaw)) > 0.5:
        w, d = d, w
    return (x - w / 2, z - d / 2, x + w / 2, z + d / 2)


def _overlap(a, b, tol=EPS) -> bool:
    """True when boxes a and b are closer than ``tol`` on both axes (i.e. overlap or nearly touch)."""
    return a[0] < b[2] + tol and b[0] < a[2] + tol and a[1] < b[3] + tol and b[1] < a[3] + tol


def snap_yaw(nx, nz) -> float:
    """Yaw whose front (sin yaw, cos yaw) is the axis direction (nx, nz), wrapped to [-pi, pi)."""
    yaw = math.atan2(nx, nz)
    return -math.pi if yaw > math.pi - 1e-9 else yaw


class PlacementRoom:
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
        self.keep.append((aabb(cx, cz, o.w + extra, depth, o.yaw), owner))

    def front_clear(self, x, z, w, d, yaw, depth) -> bool:
        """The strip of ``depth`` m in front of a would-be object is floor and holds no object."""
        fx, fz = math.sin(yaw), math.cos(yaw)
        b = aabb(x + fx * (d / 2 + depth / 2), z + fz * (d / 2 + depth / 2), w, depth, yaw)
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
        return x, z, snap_yaw(wall.nx, wall.nz)

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
            b = aabb(x, z, ww, d, yaw)
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
        b = aabb(x, z, w, d, p.yaw)
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
        yaw = snap_yaw(-fx, -fz)
        b = aabb(x, z, w, d, yaw)
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
            b = aabb(x, z, ww, d, yaw)
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
            b = aabb(x, z, w, d, yaw)
            bm = (b[0] - margin, b[1] - margin, b[2] + margin, b[3] + margin)
            if self.ok(b, ignore) and (margin == 0 or (self.inside(bm) and self.free(bm, ignore, False))):
                return self.add(label, round(x, 3), round(z, 3), size, yaw)
        return None

    def lamp(self, label, x, z, size=None, variant=None):
        """Hang a lamp at (x, z): centre y = ceiling - half height (pendants may hang a little lower)."""
        size = size or SIZES[variant or label].sample(self.rng)
        w, d, h = size
        for _ in range(3):  # the lamp's footprint stays over the floor: shrink it, else skip it
            if self.inside(aabb(x, z, w, d, 0.0)):
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
            b = aabb(x, z, 0.9, 0.85, yaw)
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
