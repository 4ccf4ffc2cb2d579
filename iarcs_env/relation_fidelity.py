"""Relation fidelity: how often a set of rooms has the object relations its room type is about, next to a
reference set (``iarcs evaluate --scenes S --reference DATA`` reports it; definitions in ``docs/design.md``,
section "Relations").

Each relation has a **co-occurrence** (the room has the objects the relation needs, e.g. a bed and at least
two nightstands) and a condition that **holds** or not (the two nightstands flank the bed's head). For a set
of rooms :func:`relation_rates` gives, per relation, the rooms with the co-occurrence (count and rate), the
rate at which the relation holds given the co-occurrence, and the rate over all rooms. A relation only holds
in a room with its co-occurrence, so ``rate = co_occurrence_rate * rate_given_co_occurrence``. Against a
reference set, ``recall`` = rate over all rooms of the scenes / that of the reference.

Relations per room type (thresholds are the module constants below; "chairs" are :data:`CHAIRS`):

* bedroom
    * ``two_nightstands``: co-occurrence a bed and at least two nightstands; holds as the
      :func:`~iarcs_env.tasks.check_two_nightstands` task checker (a nightstand left and one right of one
      bed's head half, each centre 0 to 0.5 m out from the bed's side).
    * ``tv_from_bed``: a TV stand and a bed; holds as :func:`~iarcs_env.tasks.check_tv_from_bed` (centres 2-4 m
      apart, each within 30 degrees of facing the other).
    * ``study_zone``: a desk and a chair, stool or dressing chair (the checker's seats, :data:`STUDY_SEATS`);
      holds as :func:`~iarcs_env.tasks.check_study_zone`.
    * ``wardrobe_back_to_wall``: a wardrobe; holds when every wardrobe's back is against a wall: the midpoint of
      its back edge is at most :data:`WALL_TOLERANCE` (0.2 m) from the floor boundary straight behind it, in
      front of it or through it (as :func:`~iarcs_env.relations.back_to_wall`, see :attr:`_Scenes.back`).
* livingroom
    * ``coffee_table_front_of_sofa``: a sofa and a coffee table; holds when a coffee table's centre, in a sofa's
      frame, is ahead of the sofa's centre, laterally within the sofa's width, and the two footprints are at
      most :data:`COFFEE_TABLE_GAP` (1.0 m) apart.
    * ``tv_stand_facing_sofa``: a TV stand and a sofa; holds when a TV stand and a sofa have centres
      :data:`TV_SOFA_DISTANCE` (1.5 to 5.0 m) apart and each is within :data:`TV_SOFA_ANGLE` (30 degrees) of
      facing the other (as ``tv_from_bed``).
    * ``chairs_at_dining_table``: a dining table and at least two chairs; holds when at least two chairs are at
      one dining table: footprints at most :data:`CHAIR_GAP` (0.6 m) from the table's and facing it (the
      chair's forward ray from its centre meets the table's footprint).
* diningroom
    * ``chairs_at_dining_table``: as in living rooms.
    * ``four_chairs_at_dining_table``: a dining table and at least four chairs; holds when four or more chairs
      are at one dining table.

Geometry is batched with torch in float64 (:mod:`iarcs_env.relations`); layouts are evaluated in batches of
``batch_size`` rooms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Callable, Sequence

import numpy as np
import torch

from . import relations as rel
from . import tasks
from .rooms import get_room
from .scene import Layout, SceneBatch

#: Float slack on every threshold (m or rad), as the task checkers'.
EPS = tasks.EPS
#: wardrobe_back_to_wall: the back edge's midpoint at most this far (m) from the wall behind it, either side.
WALL_TOLERANCE = 0.2
#: coffee_table_front_of_sofa: largest gap (m) between the coffee table's and the sofa's footprints.
COFFEE_TABLE_GAP = 1.0
#: tv_stand_facing_sofa: centre distance range (m) and the largest angle (rad) off facing, both ways.
TV_SOFA_DISTANCE = (1.5, 5.0)
TV_SOFA_ANGLE = math.radians(30)
#: chairs_at_dining_table: largest gap (m) between a chair's footprint and the table's.
CHAIR_GAP = 0.6
#: Single seats that count as chairs at a dining table (sofas do not).
CHAIRS = ("chair", "dining_chair", "chinese_chair", "lounge_chair", "armchair", "stool", "dressing_chair")
#: The seats of the study_zone task checker (:func:`iarcs_env.tasks.check_study_zone`).
STUDY_SEATS = ("chair", "stool", "dressing_chair")


class _Scenes:
    """A batch's float64 geometry and pairwise relations, computed once on demand and shared by the
    relations of a room type."""

    def __init__(self, batch: SceneBatch):
        self.batch = batch
        self.t = batch.translations.double()
        self.h = batch.half_sizes.double()
        self.y = batch.yaws.double()
        self.eye = torch.eye(batch.num_slots, dtype=torch.bool, device=self.t.device)

    def mask(self, *names: str) -> torch.Tensor:
        return rel.class_mask(self.batch.labels, self.batch.spec.classes, names)

    def pairs(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """``(B, N, N)``: ``[b, i, j]`` = i in ``a``, j in ``b``, i != j."""
        return a[:, :, None] & b[:, None, :] & ~self.eye

    @cached_property
    def offset(self) -> torch.Tensor:  # [b, i, j]: centre of j in i's frame (lateral, forward)
        return rel.local_offset(self.t[..., 0:3:2], self.y)

    @cached_property
    def angle(self) -> torch.Tensor:  # [b, i, j]: from i's forward to i -> j
        return torch.atan2(self.offset[..., 0].abs(), self.offset[..., 1])

    @cached_property
    def distance(self) -> torch.Tensor:
        return rel.centre_distance(self.t[..., 0:3:2])

    def gap(self, pairs: torch.Tensor) -> torch.Tensor:
        """``(B, N, N)`` footprint gap (:func:`~iarcs_env.relations.footprint_gap`) of the ``pairs`` (B, N, N), inf
        elsewhere: computed for those pairs only (each as a two-object scene), which keeps large rooms fast."""
        b, i, j = pairs.nonzero(as_tuple=True)
        out = torch.full(pairs.shape, math.inf, dtype=self.t.dtype, device=self.t.device)
        if len(b):
            ij = torch.stack([i, j], 1)
            bb = b[:, None]
            out[b, i, j] = rel.footprint_gap(self.t[bb, ij], self.h[bb, ij], self.y[bb, ij])[:, 0, 1]
        return out

    @cached_property
    def back(self) -> torch.Tensor:
        """``(B, N)`` signed distance from the midpoint of each object's back edge to the nearest crossing of the
        floor boundary on the object's front-back axis: positive when the wall is behind the back edge, negative
        when the wall runs through the object (its back pokes through); inf when the axis meets no wall.

        Like :func:`~iarcs_env.relations.back_to_wall` where the midpoint lies strictly inside or outside the
        floor, but with no inside test, so a back edge exactly on a wall gives 0 (``back_to_wall`` reads such a
        midpoint as outside the floor and returns minus the distance to the opposite wall)."""
        edges = rel.floor_edges(self.batch.floors, device=self.t.device, dtype=torch.float64)
        f = rel.forward_xz(self.y)
        p = self.t[..., 0:3:2] - f * self.h[..., 2:3]  # back edge midpoints (B, N, 2)
        a, e = edges[:, None, :, :2], edges[:, None, :, 2:] - edges[:, None, :, :2]  # (B, 1, E, 2)
        r = a - p[:, :, None]
        back = -f[:, :, None]
        den = back[..., 0] * e[..., 1] - back[..., 1] * e[..., 0]
        ok = den.abs() > 1e-12
        den = torch.where(ok, den, torch.ones_like(den))
        along = (r[..., 0] * e[..., 1] - r[..., 1] * e[..., 0]) / den  # along -forward from the midpoint
        u = (r[..., 0] * back[..., 1] - r[..., 1] * back[..., 0]) / den  # along the edge
        ok = ok & (u >= -1e-12) & (u <= 1 + 1e-12)
        along = torch.where(ok, along, torch.full_like(along, math.inf))
        nearest = along.abs().argmin(-1, keepdim=True)
        return along.gather(-1, nearest)[..., 0]

    def looks_at(self, pairs: torch.Tensor) -> torch.Tensor:
        """``(B, N, N)`` bool: ``[b, i, j]`` = the forward ray from j's centre meets i's footprint (slab test in
        i's frame; a centre inside the footprint counts), for the ``pairs`` (B, N, N) only (False elsewhere)."""
        b, i, j = pairs.nonzero(as_tuple=True)
        out = torch.zeros_like(pairs)
        if not len(b):
            return out
        p = self.offset[b, i, j]  # j's centre in i's frame (lateral, forward), (P, 2)
        turn = self.y[b, j] - self.y[b, i]  # j's yaw relative to i's
        d = torch.stack([torch.sin(turn), torch.cos(turn)], -1)  # j's forward in i's frame
        half = torch.stack([self.h[b, i, 0], self.h[b, i, 2]], -1) + EPS
        flat = d.abs() < 1e-9
        safe = torch.where(flat, torch.ones_like(d), d)
        t1, t2 = (-half - p) / safe, (half - p) / safe
        inf = torch.full_like(t1, math.inf)
        inside = p.abs() <= half
        lo = torch.where(flat, torch.where(inside, -inf, inf), torch.minimum(t1, t2))
        hi = torch.where(flat, torch.where(inside, inf, -inf), torch.maximum(t1, t2))
        out[b, i, j] = hi.amin(-1) >= lo.amax(-1).clamp_min(0)
        return out


def _from_checker(check: Callable[[SceneBatch], np.ndarray]):
    def holds(s: _Scenes) -> torch.Tensor:
        return torch.as_tensor(check(s.batch), device=s.t.device)
    return holds


def _two_nightstands_co(s: _Scenes) -> torch.Tensor:
    return s.mask("bed").any(1) & (s.mask("nightstand").sum(1) >= 2)


def _tv_bed_co(s: _Scenes) -> torch.Tensor:
    return s.mask("bed").any(1) & s.mask("tv_stand").any(1)


def _study_co(s: _Scenes) -> torch.Tensor:
    return s.mask("desk").any(1) & s.mask(*STUDY_SEATS).any(1)


def _wardrobe_co(s: _Scenes) -> torch.Tensor:
    return s.mask("wardrobe").any(1)


def _wardrobe_holds(s: _Scenes) -> torch.Tensor:
    wardrobe = s.mask("wardrobe")
    at_wall = s.back.abs() <= WALL_TOLERANCE + EPS
    return wardrobe.any(1) & (at_wall | ~wardrobe).all(1)


def _coffee_co(s: _Scenes) -> torch.Tensor:
    return s.mask("sofa").any(1) & s.mask("coffee_table").any(1)


def _coffee_holds(s: _Scenes) -> torch.Tensor:
    lateral, forward = s.offset[..., 0], s.offset[..., 1]  # coffee table j in sofa i's frame
    pairs = s.pairs(s.mask("sofa"), s.mask("coffee_table"))
    ok = ((forward > 0) & (lateral.abs() <= s.h[..., 0][:, :, None] + EPS) & (s.gap(pairs) <= COFFEE_TABLE_GAP + EPS)
          & pairs)
    return ok.flatten(1).any(1)


def _tv_sofa_co(s: _Scenes) -> torch.Tensor:
    return s.mask("sofa").any(1) & s.mask("tv_stand").any(1)


def _tv_sofa_holds(s: _Scenes) -> torch.Tensor:
    lo, hi = TV_SOFA_DISTANCE
    limit = TV_SOFA_ANGLE + EPS
    ok = ((s.distance >= lo - EPS) & (s.distance <= hi + EPS) & (s.angle <= limit)
          & (s.angle.transpose(1, 2) <= limit) & s.pairs(s.mask("sofa"), s.mask("tv_stand")))
    return ok.flatten(1).any(1)


def chairs_at_tables(s: _Scenes) -> torch.Tensor:
    """``(B,)`` the most chairs at one dining table (footprint gap <= :data:`CHAIR_GAP`, facing it)."""
    pairs = s.pairs(s.mask("dining_table"), s.mask(*CHAIRS))
    at = (s.gap(pairs) <= CHAIR_GAP + EPS) & s.looks_at(pairs)
    return at.sum(2).amax(1) if at.shape[1] else torch.zeros(at.shape[0], dtype=torch.long)


def _chairs_co(k: int):
    def co(s: _Scenes) -> torch.Tensor:
        return s.mask("dining_table").any(1) & (s.mask(*CHAIRS).sum(1) >= k)
    return co


def _chairs_holds(k: int):
    def holds(s: _Scenes) -> torch.Tensor:
        return chairs_at_tables(s) >= k
    return holds


@dataclass(frozen=True)
class Relation:
    """A relation of a room type: ``co_occurrence`` and ``holds`` in words (the report's definitions), and the
    batched tests ``co(scenes)`` and ``test(scenes)``, each ``(B,)`` bool."""

    name: str
    co_occurrence: str
    holds: str
    co: Callable[[_Scenes], torch.Tensor]
    test: Callable[[_Scenes], torch.Tensor]


_CHAIRS_AT_TABLE = Relation(
    "chairs_at_dining_table", "a dining table and at least 2 chairs",
    f"at least 2 chairs at one dining table (footprints <= {CHAIR_GAP} m apart, the chair's forward ray meets "
    "the table)", _chairs_co(2), _chairs_holds(2))

#: Room type -> its relations, in report order.
RELATIONS: dict[str, tuple[Relation, ...]] = {
    "bedroom": (
        Relation("two_nightstands", "a bed and at least 2 nightstands",
                 "the two_nightstands task checker: a nightstand left and one right of a bed's head half",
                 _two_nightstands_co, _from_checker(tasks.check_two_nightstands)),
        Relation("tv_from_bed", "a TV stand and a bed",
                 "the tv_from_bed task checker: centres 2-4 m apart, each within 30 degrees of facing the other",
                 _tv_bed_co, _from_checker(tasks.check_tv_from_bed)),
        Relation("study_zone", "a desk and a chair, stool or dressing chair",
                 "the study_zone task checker: a seat in front of a desk, within its width + 0.1 m, <= 0.9 m out",
                 _study_co, _from_checker(tasks.check_study_zone)),
        Relation("wardrobe_back_to_wall", "a wardrobe",
                 f"every wardrobe's back edge midpoint within {WALL_TOLERANCE} m of the wall behind it",
                 _wardrobe_co, _wardrobe_holds),
    ),
    "livingroom": (
        Relation("coffee_table_front_of_sofa", "a sofa and a coffee table",
                 f"a coffee table ahead of a sofa's centre, within its width, footprints <= {COFFEE_TABLE_GAP} m "
                 "apart", _coffee_co, _coffee_holds),
        Relation("tv_stand_facing_sofa", "a TV stand and a sofa",
                 f"a TV stand and a sofa {TV_SOFA_DISTANCE[0]}-{TV_SOFA_DISTANCE[1]} m apart (centres), each "
                 f"within {math.degrees(TV_SOFA_ANGLE):.0f} degrees of facing the other", _tv_sofa_co, _tv_sofa_holds),
        _CHAIRS_AT_TABLE,
    ),
    "diningroom": (
        _CHAIRS_AT_TABLE,
        Relation("four_chairs_at_dining_table", "a dining table and at least 4 chairs",
                 "at least 4 chairs at one dining table (as chairs_at_dining_table)", _chairs_co(4), _chairs_holds(4)),
    ),
}


def room_relations(room: str) -> tuple[Relation, ...]:
    """The relations of a room type (``bedroom``, ``livingroom``, ``diningroom`` or an alias)."""
    name = get_room(room).name
    if name not in RELATIONS:
        raise ValueError(f"no relations are defined for {name} rooms; they are for {', '.join(RELATIONS)}")
    return RELATIONS[name]


def _room_of(scenes: SceneBatch | Sequence[Layout], room: str | None) -> tuple[str, SceneBatch | list[Layout]]:
    if isinstance(scenes, SceneBatch):
        found = scenes.spec.name
    else:
        scenes = list(scenes)
        if not scenes:
            raise ValueError("no scenes to measure relations on")
        kinds = sorted({get_room(lay.room_type).name for lay in scenes})
        if len(kinds) > 1:
            raise ValueError(f"scenes of several room types ({', '.join(kinds)}); measure relations one room type "
                             "at a time")
        found = kinds[0]
    if room is not None and get_room(room).name != found:
        raise ValueError(f"the scenes are {found} rooms, not {get_room(room).name} rooms")
    return found, scenes


def relation_flags(scenes: SceneBatch | Sequence[Layout], room: str | None = None, batch_size: int = 128
                   ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per relation of the scenes' room type, per-scene ``(co_occurs, holds)`` bool arrays ``(B,)``; ``holds``
    is False wherever ``co_occurs`` is. ``room`` (optional) must match the scenes' room type."""
    from .metrics import batch_float64

    room, scenes = _room_of(scenes, room)
    relations = room_relations(room)
    if isinstance(scenes, SceneBatch):
        batches = [scenes]
    else:
        batches = [batch_float64(scenes[i:i + batch_size]) for i in range(0, len(scenes), batch_size)]
    parts: dict[str, list] = {r.name: [] for r in relations}
    for batch in batches:
        s = _Scenes(batch)
        for r in relations:
            co = r.co(s).bool()
            parts[r.name].append((co.cpu().numpy(), (r.test(s).bool() & co).cpu().numpy()))
    return {name: (np.concatenate([c for c, _ in p]), np.concatenate([h for _, h in p])) for name, p in parts.items()}


def rates_of(co: np.ndarray, holds: np.ndarray) -> dict:
    """The figures of one relation from per-scene flags."""
    n, k, m = len(co), int(co.sum()), int(holds.sum())
    return {"rooms": n, "co_occurrence": k, "co_occurrence_rate": k / n if n else None, "holds": m,
            "rate_given_co_occurrence": m / k if k else None, "rate": m / n if n else None}


def relation_rates(scenes: SceneBatch | Sequence[Layout], room: str | None = None, batch_size: int = 128
                   ) -> dict[str, dict]:
    """Per relation of the scenes' room type (:data:`RELATIONS`, in order): ``rooms``, ``co_occurrence`` (rooms
    with the co-occurrence) and ``co_occurrence_rate``, ``holds`` (rooms where the relation holds),
    ``rate_given_co_occurrence`` (None without a co-occurrence) and ``rate`` (over all rooms)."""
    return {name: rates_of(co, holds) for name, (co, holds) in relation_flags(scenes, room, batch_size).items()}


def recall(scenes_rate: float | None, reference_rate: float | None) -> float | None:
    """Relation recall: the scenes' rate over all rooms / the reference's (None when the reference's is 0)."""
    if scenes_rate is None or not reference_rate:
        return None
    return scenes_rate / reference_rate


def compare_relations(scenes: dict[str, dict], reference: dict[str, dict] | None = None) -> dict[str, dict]:
    """Side by side: per relation ``{"scenes": rates, "reference": rates, "recall": ...}`` (of
    :func:`relation_rates` results); without a reference only ``"scenes"``."""
    out = {}
    for name, mine in scenes.items():
        out[name] = {"scenes": mine}
        if reference is not None:
            theirs = reference[name]
            out[name].update(reference=theirs, recall=recall(mine["rate"], theirs["rate"]))
    return out


def relation_table(relations: dict[str, dict]) -> str:
    """Markdown table of :func:`compare_relations`: percentages, scenes and reference side by side."""
    with_ref = any("reference" in v for v in relations.values())

    def pct(v):
        return "–" if v is None else f"{100 * v:.1f}"

    if with_ref:
        head = ("| Relation | co-occurrence % (scenes) | co-occurrence % (ref.) | holds given co-occ. % (scenes) "
                "| holds given co-occ. % (ref.) | rate % (scenes) | rate % (ref.) | recall |")
        rule = "|---|" + "---|" * 7
    else:
        head = "| Relation | co-occurrence % | holds given co-occurrence % | rate % |"
        rule = "|---|---|---|---|"
    rows = [head, rule]
    for name, v in relations.items():
        s = v["scenes"]
        if with_ref:
            r = v["reference"]
            rec = "–" if v.get("recall") is None else f"{v['recall']:.2f}"
            rows.append(f"| {name} | {pct(s['co_occurrence_rate'])} | {pct(r['co_occurrence_rate'])} "
                        f"| {pct(s['rate_given_co_occurrence'])} | {pct(r['rate_given_co_occurrence'])} "
                        f"| {pct(s['rate'])} | {pct(r['rate'])} | {rec} |")
        else:
            rows.append(f"| {name} | {pct(s['co_occurrence_rate'])} | {pct(s['rate_given_co_occurrence'])} "
                        f"| {pct(s['rate'])} |")
    return "\n".join(rows)


def main(argv: Sequence[str] | None = None) -> None:
    """Print the relation rates of procedural rooms:
    ``python -m iarcs_env.relation_fidelity [--num-scenes 500] [--seed 777] [--room ROOM ...]``."""
    import argparse

    from .datasets.procedural import generate_layouts

    p = argparse.ArgumentParser(description=main.__doc__.split(":")[0])
    p.add_argument("--num-scenes", type=int, default=500)
    p.add_argument("--seed", type=int, default=777)
    p.add_argument("--room", action="append", help="room type (repeatable; default: all)")
    args = p.parse_args(argv)
    for room in args.room or list(RELATIONS):
        rates = relation_rates(generate_layouts(room, args.num_scenes, seed=args.seed))
        print(f"\n{room}: {args.num_scenes} procedural rooms, seed {args.seed}\n")
        print(relation_table(compare_relations(rates)))


if __name__ == "__main__":
    main()
