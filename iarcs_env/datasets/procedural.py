"""The embedded procedural generator: "synthetic 3D-FRONT" rooms that need no download.

:func:`generate_layouts` builds bedrooms, living rooms (3D-FRONT's living-dining rooms) and dining rooms
from hand-written rules and parameters:

* **Floor plans** are rectilinear: rectangles, L shapes (one corner cut away), U shapes (a notch in the
  middle of a wall) and rooms with two or three cut corners. Areas are log-normal (bedroom median
  13 m^2, living room 28 m^2, dining room 16 m^2) and aspect ratios follow typical apartment rooms.
* **Sizes** come from furniture standards with variation (:data:`iarcs_env.datasets.room_builder.SIZES`): a double bed with its frame
  and headboard is 1.65-2.25 m wide and 2.05-2.35 m long, a nightstand 0.4-0.6 x 0.35-0.5 m and
  0.45-0.65 m high, a wardrobe 0.55-0.65 m deep, 0.9-2.4 m wide and 2.0-2.4 m high, and so on.
* **Placement rules** (:class:`iarcs_env.datasets.room_builder.PlacementRoom` does the geometry): the bed's head is against a wall with
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
from typing import Callable, Iterator

import numpy as np
from shapely.geometry import box

from ..rooms import get_room
from ..scene import Layout
from .room_builder import EPS, SIZES, PlacementRoom, aabb, pick, pick_count, sample_floor, snap_yaw, tilted

#: Version of the generated rooms. Bump it whenever :func:`generate_room` gives other rooms for the same
#: (room type, index, seed, flaw rate): caches of generated data (the pretraining data of
#: :func:`agents.pretrain_data.training_data`) are keyed by it, and a bump makes them be built again.
GENERATOR_VERSION = 1

#: Living rooms' furnishing level ``exp(N(0, RICH_SIGMA)) * (area / 28 m^2) ** RICH_AREA`` tilts the counts
#: of optional pieces (cabinets, side tables, armchairs, stools, a second table, dining chairs).
RICH_SIGMA, RICH_AREA, RICH_MAX = 0.55, 0.5, 1.8


# --------------------------------------------------------------------------------------------------------
# Room programs
# --------------------------------------------------------------------------------------------------------
def _sz(rng, key):
    return SIZES[key].sample(rng)


def _seat_at(room: PlacementRoom, parent: int, label, size, flaw: str, under: tuple[float, float] = (0.1, 0.3),
             offset: float = 0.0):
    """A chair or stool in front of ``parent`` facing it; with the ``flaw``, pushed partly under it."""
    rng = room.rng
    if room.flaw(flaw):
        i = room.facing(parent, label, size, gap=-rng.uniform(*under), offset=offset, ignore={parent})
        if i is not None:
            return i
    return room.facing(parent, label, size, gap=EPS + rng.uniform(0.02, 0.2), offset=offset)


def _wall_flaw(room: PlacementRoom, i, name="wall_object_into_wall", depth=(0.07, 0.16)):
    if i is not None and room.flaw(name):
        room.move_back(i, room.rng.uniform(*depth))


def _bed_group(room: PlacementRoom, label, size, wanted) -> tuple[int | None, list]:
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


def _bedroom(room: PlacementRoom):
    rng = room.rng
    # -- the bed and its nightstands
    u = rng.random()
    bed_label = "double_bed" if u < 0.87 else "single_bed" if u < 0.895 else "kids_bed" if u < 0.92 else None
    phantom = bed_label is None  # a room without a bed (study, guest room): its wall is still furnished
    size = _sz(rng, bed_label or "double_bed")
    n_ns = pick_count(rng, [0.17, 0.17, 0.65, 0.01]) if not phantom else pick_count(rng, [0.45, 0.2, 0.35])
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
    for _ in range(pick_count(rng, [0.3, 0.68, 0.02])):
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


def _dining_group(room: PlacementRoom, zone, n_chairs_probs, square_p=0.15, chair_label="dining_chair",
                  tilt: float = 1.0) -> int | None:
    """A dining table standing free in ``zone`` (its long side along the zone's long axis) with chairs
    around it; where no free spot is found, a smaller table pushed against a wall with chairs on its
    three open sides. Returns the table's index."""
    rng = room.rng
    n = pick_count(rng, n_chairs_probs, tilt)
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
            cyaw = snap_yaw(-fx * side, -fz * side)
        else:
            dist = tab.w / 2 + gap + chair[1] / 2
            x, z = tab.x + rx * dist * u, tab.z + rz * dist * u
            cyaw = snap_yaw(-rx * u, -rz * u)
        b = aabb(x, z, chair[0], chair[1], cyaw)
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


def _living_group(room: PlacementRoom, zone, dining_zone):
    """Sofa, coffee table, TV stand, side tables and armchairs in ``zone``."""
    rng = room.rng
    sofa_label = pick(rng, {"multi_seat_sofa": 0.6, "l_shaped_sofa": 0.22, "loveseat_sofa": 0.05,
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
            yaw = snap_yaw(*ax)
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
                n_arm = pick_count(rng, [0.72, 0.2, 0.07, 0.01], room.rich)
                n_lounge = pick_count(rng, [0.85, 0.1, 0.05])
                seats = ["armchair"] * n_arm + ["lounge_chair"] * n_lounge
                sides = [1, -1] if rng.random() < 0.5 else [-1, 1]
                c = room.objs[ct]
                for k, label in enumerate(seats[:2]):
                    size = _sz(rng, label)
                    side = sides[k]
                    rx, rz = c.right
                    dist = c.w / 2 + 0.35 + size[1] / 2
                    x, z = c.x + rx * dist * side, c.z + rz * dist * side
                    yaw = snap_yaw(-rx * side, -rz * side)
                    b = aabb(x, z, size[0], size[1], yaw)
                    if room.ok(b, ignore={sofa}):
                        room.add(label, round(x, 3), round(z, 3), size, yaw)
                for label in seats[2:]:
                    room.on_wall(label, _sz(rng, label), where="corner")
        # TV stand facing the sofa
        if rng.random() < 0.86:
            tv = room.across(sofa, "tv_stand", _sz(rng, "tv_stand"), min_dist=1.2)
            _wall_flaw(room, tv, "living_into_wall")
        # side tables beside the sofa's arms
        n_side = pick_count(rng, [0.3, 0.25, 0.45], room.rich)
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
        for _ in range(pick_count(rng, [0.5, 0.3, 0.2])):
            room.on_wall("armchair" if rng.random() < 0.6 else "lounge_chair", _sz(rng, "armchair"), where="corner")
    return sofa


def _livingroom(room: PlacementRoom):
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
            if rng.random() < tilted(p, rich):
                t2 = room.on_wall("dining_table", _sz(rng, "dining_table:square" if rng.random() < 0.5 else "dining_table"),
                                  clear=0.6, min_w=0.7)
                if t2 is not None:
                    for k in range(pick_count(rng, [0.5, 0.3, 0.2])):
                        o = room.objs[t2]
                        off = 0.0 if k == 0 else (o.w / 4) * (1 if k == 1 else -1)
                        _seat_at(room, t2, "dining_chair" if rng.random() < 0.75 else "stool",
                                 _sz(rng, "dining_chair"), "dining_chair_tucked", under=(0.05, 0.2), offset=off)
    # storage and other pieces against walls
    for _ in range(pick_count(rng, [0.5, 0.3, 0.13, 0.05, 0.02], rich)):
        i = room.on_wall("cabinet", _sz(rng, "cabinet:tall" if rng.random() < 0.3 else "cabinet"), clear=0.5,
                         min_w=0.5)
        _wall_flaw(room, i)
    for label, counts, key in (("bookshelf", [0.83, 0.14, 0.03], "bookshelf"),
                               ("console_table", [0.92, 0.06, 0.02], "console_table"),
                               ("desk", [0.965, 0.035], "desk"), ("shelf", [0.97, 0.03], "shelf"),
                               ("wardrobe", [0.975, 0.025], "wardrobe"), ("wine_cabinet", [0.99, 0.01], "wine_cabinet")):
        for _ in range(pick_count(rng, counts)):
            i = room.on_wall(label, _sz(rng, key), clear=0.5, min_w=0.4)
            _wall_flaw(room, i, "living_into_wall")
            if label == "desk" and i is not None and rng.random() < 0.5:
                _seat_at(room, i, "dining_chair" if rng.random() < 0.5 else "lounge_chair", _sz(rng, "chair"),
                         "chair_tucked")
    # extra seats and small tables
    for _ in range(pick_count(rng, [0.8, 0.1, 0.06, 0.02, 0.02], rich)):
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


def _lamps_over_table(room: PlacementRoom, table: int, thresholds: tuple[float, float, float]) -> None:
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


def _diningroom(room: PlacementRoom):
    """Dining rooms: one dining table with 4-8 chairs dominates; sideboards, a wine cabinet, pendants."""
    rng = room.rng
    full = (-room.W / 2, -room.D / 2, room.W / 2, room.D / 2)
    table = _dining_group(room, full, [0.0, 0.01, 0.06, 0.02, 0.4, 0.08, 0.3, 0.05, 0.07, 0.0, 0.01])
    room.door()
    if table is not None and room.poly.area > 24 and rng.random() < 0.2:  # a second, small table
        t2 = room.on_wall("dining_table", _sz(rng, "dining_table:square"), clear=0.6)
        if t2 is not None:
            _seat_at(room, t2, "dining_chair", _sz(rng, "dining_chair"), "dining_chair_tucked")
    for _ in range(pick_count(rng, [0.35, 0.45, 0.17, 0.03])):
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
    room = PlacementRoom(rng, spec.name, W, D, notches, ceiling, float(flaw_rate))
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


__all__ = ["GENERATOR_VERSION", "available_cores", "generate_layouts", "generate_room", "map_room_chunks"]
