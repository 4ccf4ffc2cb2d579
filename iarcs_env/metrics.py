"""The paper's physical-plausibility metrics and the set-level statistics, batched.

Definitions (the paper's, after PhyScene; where they leave a choice, it is said):

* **Ground objects**: all objects but ``ceiling_lamp`` and ``pendant_lamp``.
* **Collision**: two ground objects whose oriented 3D boxes overlap with a volume > 1e-6 m^3.
  ``Col_obj`` = colliding ground objects / ground objects (pooled over all scenes);
  ``Col_scene`` = scenes with at least one collision / scenes.
* **Out of bound**: an object (any object, lamps included) whose footprint, shrunk by 0.05 m on each
  side, has more than 1e-5 m^2 outside the floor polygon. ``R_out`` = such objects / all objects (pooled).
* **Walkable grid**: 0.05 m cells (configurable) over the floor's bounding box; a cell is free when its
  centre lies inside the floor polygon at least the agent radius (0.3 m) from the boundary (the floor
  eroded by a disk of that radius) and at least the agent radius from every ground object's footprint
  (outside the footprint inflated by a disk of that radius).
  ``R_walkable`` = cells of the largest 4-connected free component / free cells (0 when nothing is free),
  per scene, averaged over scenes. (PhyScene's public code returns component 1, not the largest; we
  take the largest.)
* ``R_reach`` = ground objects whose inflated footprint touches, within one cell (8-neighbourhood), the
  largest free component / ground objects (pooled). A scene with no free cell has no reachable object.
* ``R_off_floor`` (our addition): ground objects whose bottom is more than 0.05 m above or
  below the floor / ground objects (pooled). Every ground object of the real 3D-FRONT rooms stands on the
  floor, and nothing else asks for it: an RL adapter that may move objects vertically sinks beds into the
  floor to pass a height limit, or lifts furniture to avoid collisions.
* ``R_misaligned`` (our addition): ground objects whose axes are more than 10 degrees from every wall
  direction of the floor (:func:`~iarcs_env.geometry.wall_misalignment`) / ground objects (pooled). The
  procedural rooms have none and the real bedrooms almost none; a diffusion prior turns some furniture
  away from the walls, which no other metric sees.
* Set-level statistics against a reference set: ``KL_class`` = KL(reference || generated) of the class
  frequencies (per object, smoothed with 1e-6); ``count_distance`` = earth mover's (1-Wasserstein)
  distance between the object-count histograms, in objects; plus both mean counts; ``footprint_change``
  (our addition) = the geometric mean of the footprint areas over the generated objects, class by class,
  divided by the reference's, minus 1 (-0.14: footprints 14% smaller than the reference's objects of the same
  classes), and ``footprint_change_by_class``. An RL adapter can shrink furniture to avoid collisions
  and walls, which no other metric sees.

All counts come from :func:`evaluate_batch` (one :class:`~iarcs_env.scene.SceneBatch` at a time, fully
batched geometry from :mod:`iarcs_env.geometry`), which also keeps per-scene results (which objects
collide, which are out of bound, which are unreachable, the unreachable floor) so that renders can mark
them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np
import torch

from . import geometry as geo
from .walkable import FreeSpace, free_space
from .render import Overlays
from .rooms import get_room
from .scene import Layout, SceneBatch

#: The five headline metrics, fractions in [0, 1].
HEADLINE = ("Col_obj", "Col_scene", "R_out", "R_reach", "R_walkable")


@dataclass
class SceneResult:
    """Per-scene outcome. Object indices refer to the scene's objects in order (empty slots dropped)."""

    id: str
    n_objects: int
    n_ground: int
    colliding: list[int]
    out_of_bound: list[int]
    off_floor: list[int]
    unreachable_objects: list[int]
    walkable: float
    free_cells: int
    largest_cells: int
    penetration: float  # total pairwise overlap volume of ground objects (m^3)
    out_area: float  # total out-of-bound area of the shrunk footprints (m^2)
    unreachable: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # (grid, xs, zs), centred frame

    @property
    def has_issue(self) -> bool:
        return bool(self.colliding or self.out_of_bound or self.off_floor or self.unreachable_objects)

    def overlays(self) -> Overlays:
        """Overlays for :func:`iarcs_env.render.render_layout` of the scene's centred layout."""
        return Overlays(colliding=self.colliding, out_of_bound=self.out_of_bound, off_floor=self.off_floor,
                        unreachable=self.unreachable)


@dataclass
class BatchResult:
    """Per-slot arrays of one batch (``(B, N)`` booleans) and per-scene walkability."""

    mask: np.ndarray
    ground: np.ndarray
    colliding: np.ndarray
    out_of_bound: np.ndarray
    off_floor: np.ndarray
    misaligned: np.ndarray
    reachable: np.ndarray
    walkable: np.ndarray  # (B,)
    free_cells: np.ndarray
    largest_cells: np.ndarray
    overlap: np.ndarray  # (B, N, N) m^3
    out_area: np.ndarray  # (B, N) m^2
    space: FreeSpace
    scenes: list[SceneResult] = field(default_factory=list)


@geo.single_thread()
def evaluate_batch(batch: SceneBatch, cell: float = geo.WALK_CELL, agent_radius: float = geo.AGENT_RADIUS,
                   keep_masks: bool = False) -> BatchResult:
    """All per-object and per-scene metric results of one batch (see the module docstring)."""
    mask = batch.mask
    ground = batch.ground_mask
    overlap = geo.box_overlap_volumes(batch.translations, batch.half_sizes, batch.yaws, ground)
    colliding = (overlap > geo.COLLISION_VOLUME).any(-1) & ground
    out_area = geo.box_out_of_floor_area(batch.translations, batch.half_sizes, batch.yaws, batch.floors, mask,
                                         shrink=geo.OUT_OF_BOUND_SHRINK)
    out = (out_area > geo.OUT_OF_BOUND_AREA) & mask
    off_floor = geo.floor_gaps(batch.translations, batch.half_sizes, ground) > geo.FLOOR_CONTACT_TOL
    misaligned = geo.wall_misalignment(batch.yaws, batch.floors, ground) > geo.ALIGNMENT_TOL_DEG
    space = free_space(batch.floors, batch.translations, batch.half_sizes, batch.yaws, ground,
                           cell=cell, radius=agent_radius, reach=True)
    m, g = mask.cpu().numpy(), ground.cpu().numpy()
    res = BatchResult(m, g, colliding.cpu().numpy(), out.cpu().numpy(), off_floor.cpu().numpy(),
                      misaligned.cpu().numpy(), space.reach & g, space.walkable_ratio,
                      space.free_cells, space.largest_cells, overlap.cpu().numpy(), out_area.cpu().numpy(), space)
    for b in range(batch.batch_size):
        slots = np.nonzero(m[b])[0]  # slot -> object index (empty slots dropped)
        idx = {int(s): i for i, s in enumerate(slots)}
        unreachable = None
        if keep_masks:
            grid = space.scene_grid(b)
            unreachable = (grid["unreachable"], grid["xs"], grid["zs"])
        res.scenes.append(SceneResult(
            id=batch.ids[b] if batch.ids else f"scene_{b:05d}",
            n_objects=int(m[b].sum()), n_ground=int(g[b].sum()),
            colliding=[idx[int(s)] for s in np.nonzero(res.colliding[b])[0]],
            out_of_bound=[idx[int(s)] for s in np.nonzero(res.out_of_bound[b])[0]],
            off_floor=[idx[int(s)] for s in np.nonzero(res.off_floor[b])[0]],
            unreachable_objects=[idx[int(s)] for s in np.nonzero(g[b] & ~res.reachable[b])[0]],
            walkable=float(res.walkable[b]), free_cells=int(res.free_cells[b]),
            largest_cells=int(res.largest_cells[b]),
            penetration=float(np.triu(res.overlap[b], 1).sum()), out_area=float(res.out_area[b][m[b]].sum()),
            unreachable=unreachable,
        ))
    return res


# ------------------------------------------------------------------------------------------------------
# set-level statistics
# ------------------------------------------------------------------------------------------------------
def class_frequencies(layouts: Iterable[Layout], classes: Sequence[str]) -> np.ndarray:
    """Per-object class frequencies over ``classes`` (sums to 1, or all zeros for no objects)."""
    counts = np.zeros(len(classes))
    index = {c: i for i, c in enumerate(classes)}
    for lay in layouts:
        for lbl in lay.labels:
            counts[index[lbl]] += 1
    return counts / max(counts.sum(), 1)


def class_kl(reference: Sequence[Layout], generated: Sequence[Layout], eps: float = 1e-6) -> float:
    """KL(reference || generated) between per-object class frequencies (nats), smoothed with ``eps``."""
    classes = get_room(reference[0].room_type).classes
    p = class_frequencies(reference, classes) + eps
    q = class_frequencies(generated, classes) + eps
    p, q = p / p.sum(), q / q.sum()
    return float(np.sum(p * np.log(p / q)))


def footprint_change(reference: Sequence[Layout], generated: Sequence[Layout], min_objects: int = 5) -> dict:
    """``{"all": r, "by_class": {label: r_c}}``: r_c the geometric-mean footprint area of the generated objects
    of class c over the reference's, minus 1 (classes with ``min_objects`` objects in both), and r the same
    over all of them, the log-ratios weighted by the generated objects' class counts (``by_class`` lists the
    most frequent generated class first)."""
    def log_areas(layouts):
        out: dict[str, list[float]] = {}
        for lay in layouts:
            for label, h in zip(lay.labels, lay.half_sizes):
                out.setdefault(label, []).append(float(np.log(max(4 * h[0] * h[2], 1e-8))))
        return out

    ref, gen = log_areas(reference), log_areas(generated)
    frequent_first = sorted(gen, key=lambda c: -len(gen[c]))
    shifts = {c: (float(np.mean(gen[c]) - np.mean(ref[c])), len(gen[c])) for c in frequent_first
              if len(gen[c]) >= min_objects and len(ref.get(c, ())) >= min_objects}
    total = sum(n for _, n in shifts.values())
    overall = sum(d * n for d, n in shifts.values()) / total if total else 0.0
    return {"all": float(np.expm1(overall)), "by_class": {c: float(np.expm1(d)) for c, (d, _) in shifts.items()}}


def count_histogram(layouts: Sequence[Layout], max_count: int | None = None) -> np.ndarray:
    counts = np.array([len(lay) for lay in layouts], dtype=np.int64)
    n = max(int(counts.max(initial=0)), max_count or 0)
    return np.bincount(counts, minlength=n + 1).astype(np.float64)


def count_distance(reference: Sequence[Layout], generated: Sequence[Layout]) -> float:
    """Earth mover's (1-Wasserstein) distance between object-count distributions, in objects."""
    n = max(max(len(lay) for lay in reference), max(len(lay) for lay in generated))
    p = count_histogram(reference, n)
    q = count_histogram(generated, n)
    p, q = p / max(p.sum(), 1), q / max(q.sum(), 1)
    return float(np.abs(np.cumsum(p) - np.cumsum(q)).sum())


# ------------------------------------------------------------------------------------------------------
# the whole evaluation
# ------------------------------------------------------------------------------------------------------
def batch_float64(layouts: Sequence[Layout]) -> SceneBatch:
    """``SceneBatch.from_layouts`` with float64 geometry (the metrics' precision: float32 positions move
    cells whose centre is exactly at the agent radius from a footprint, common with round coordinates)."""
    batch = SceneBatch.from_layouts(layouts)
    n = batch.num_slots
    t = np.zeros((len(layouts), n, 3))
    h = np.zeros((len(layouts), n, 3))
    y = np.zeros((len(layouts), n))
    for i, lay in enumerate(layouts):
        c = lay.centred()
        k = len(c)
        t[i, :k], h[i, :k], y[i, :k] = c.translations, c.half_sizes, c.yaws
    batch.translations, batch.half_sizes, batch.yaws = torch.from_numpy(t), torch.from_numpy(h), torch.from_numpy(y)
    return batch


def _batches(layouts: Sequence[Layout], batch_size: int):
    for start in range(0, len(layouts), batch_size):
        yield batch_float64(layouts[start:start + batch_size])


def one_room_type(layouts: Sequence[Layout], verb: str = "evaluate") -> list[Layout]:
    """The layouts as a list, after checking there are some and that they share one room type."""
    layouts = list(layouts)
    if not layouts:
        raise ValueError(f"no scenes to {verb}")
    room_types = {get_room(lay.room_type).name for lay in layouts}
    if len(room_types) > 1:
        raise ValueError(f"scenes of several room types ({', '.join(sorted(room_types))}); {verb} one at a time")
    return layouts


def evaluate_layouts(layouts: Sequence[Layout], reference: Sequence[Layout] | None = None,
                     cell: float = geo.WALK_CELL, agent_radius: float = geo.AGENT_RADIUS, batch_size: int = 256,
                     keep_scenes: bool = False, keep_masks: bool = False, progress: bool = False,
                     features: str | None = None, distribution_kwargs: dict | None = None) -> dict:
    """Evaluate layouts with the metrics defined in this module's docstring.

    Returns a dict with ``Col_obj``, ``Col_scene``, ``R_out``, ``R_reach``, ``R_walkable`` and
    ``R_off_floor`` and ``R_misaligned`` (fractions in [0, 1]) plus counts (``n_scenes``, ``n_objects``,
    ``n_ground_objects``),
    ``mean_objects`` and ``mean_ground_objects`` (per scene; the latter without ceiling and pendant lamps), and
    the grid settings. With a ``reference`` set: ``KL_class``, ``count_distance``,
    ``reference_mean_objects``, ``footprint_change`` and ``footprint_change_by_class``; with ``features`` too
    (``"cnn"`` or ``"clip:PATH"``, see :mod:`iarcs_env.distribution`): ``FID``, ``KID``, ``SCA`` and
    ``feature_extractor``. With ``keep_scenes``, ``"scenes"`` holds the :class:`SceneResult` list
    (``keep_masks`` adds the unreachable masks, in each layout's centred frame).
    """
    layouts = one_room_type(layouts)
    totals = dict(objects=0, ground=0, colliding=0, scenes_colliding=0, out=0, off_floor=0, misaligned=0,
                  reachable=0)
    walkable, scenes = [], []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(layouts), desc="metrics", unit="scene")
    for batch in _batches(layouts, batch_size):
        r = evaluate_batch(batch, cell=cell, agent_radius=agent_radius, keep_masks=keep_masks)
        totals["objects"] += int(r.mask.sum())
        totals["ground"] += int(r.ground.sum())
        totals["colliding"] += int(r.colliding.sum())
        totals["scenes_colliding"] += int(r.colliding.any(1).sum())
        totals["out"] += int(r.out_of_bound.sum())
        totals["off_floor"] += int(r.off_floor.sum())
        totals["misaligned"] += int(r.misaligned.sum())
        totals["reachable"] += int(r.reachable.sum())
        walkable.append(r.walkable)
        if keep_scenes:
            scenes.extend(r.scenes)
        if bar is not None:
            bar.update(batch.batch_size)
    if bar is not None:
        bar.close()
    n = len(layouts)
    ground = max(totals["ground"], 1)
    out = {
        "Col_obj": totals["colliding"] / ground,
        "Col_scene": totals["scenes_colliding"] / n,
        "R_out": totals["out"] / max(totals["objects"], 1),
        "R_reach": totals["reachable"] / ground if totals["ground"] else 1.0,
        "R_walkable": float(np.concatenate(walkable).mean()),
        "R_off_floor": totals["off_floor"] / ground,
        "R_misaligned": totals["misaligned"] / ground,
        "n_scenes": n,
        "n_objects": totals["objects"],
        "n_ground_objects": totals["ground"],
        "mean_objects": totals["objects"] / n,
        "mean_ground_objects": totals["ground"] / n,
        "room_type": get_room(layouts[0].room_type).name,
        "cell": cell,
        "agent_radius": agent_radius,
    }
    if reference is not None:
        reference = list(reference)
        out["n_reference_scenes"] = len(reference)
        out["KL_class"] = class_kl(reference, layouts)
        out["count_distance"] = count_distance(reference, layouts)
        out["reference_mean_objects"] = sum(len(lay) for lay in reference) / max(len(reference), 1)
        change = footprint_change(reference, layouts)
        out["footprint_change"], out["footprint_change_by_class"] = change["all"], change["by_class"]
        if features:
            from .distribution import distribution_metrics

            out.update(distribution_metrics(layouts, reference, features=features, progress=progress,
                                            **(distribution_kwargs or {})))
    if keep_scenes:
        out["scenes"] = scenes
    return out
