"""A greedy layout search: a room's own furniture rearranged, object by object, to satisfy a task whose check is made
of free-space tests that the reward's gradient cannot climb (wheelchair: a path opens only once it is 0.9 m wide).

Largest footprint first, ``sweeps`` times over the room, every placement of an object on a ``grid`` m grid of the
floor's bounds in its four wall-aligned turns that stays on the floor (R_out's test) and collides with no other ground
object (Col_obj's test) is scored by the task's :data:`SCORES` function, and the best is kept when it beats the room
as it stands. Classes, sizes and heights are kept. ``wheelchair_search.py`` measures what it reaches,
``search_sft.py`` whether an adapter learns its rooms.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from iarcs_env import geometry as geo
from iarcs_env.scene import SceneBatch
from iarcs_env.tasks import wheelchair_parts

CHUNK = 256
"""Placements scored at once."""


def wheelchair_score(batch: SceneBatch, margin: float = 0.0) -> np.ndarray:
    """(B,) 2 for a turning disk by a bed plus the share of ground objects a wheelchair reaches: 3 = passes; with
    ``margin`` (m), for a wheelchair and a turning disk that much wider than the checker's."""
    reached, circle = wheelchair_parts(batch, margin)
    ground = batch.ground_mask
    share = (reached & ground).sum(1).double() / ground.sum(1).clamp_min(1)
    return (2 * circle.double() + share).numpy()


SCORES = {"wheelchair": (wheelchair_score, 3.0)}
"""Task -> (score of a batch of rooms and a margin, the score at which a room passes)."""


def placements(room: SceneBatch, i: int, grid: float, radius: float | None = None) -> SceneBatch:
    """Copies of the one-room batch ``room`` with object ``i`` at every grid point of the floor's bounds in each of
    its four wall-aligned turns, kept where it is on the floor and clear of the other ground objects; with
    ``radius`` (m), only at the grid points within that distance of where it stands, in its own turn."""
    if radius is None:
        lo, hi = room.floors[0].vertices.min(0), room.floors[0].vertices.max(0)
        turns = float(room.yaws[0, i]) + np.arange(4) * math.pi / 2
    else:
        centre = room.translations[0, i, [0, 2]].numpy()
        lo, hi, turns = centre - radius, centre + radius, np.array([float(room.yaws[0, i])])
    xs, zs = np.arange(lo[0], hi[0] + 1e-9, grid), np.arange(lo[1], hi[1] + 1e-9, grid)
    x, z, yaw = (a.ravel() for a in np.meshgrid(xs, zs, turns, indexing="ij"))
    if radius is not None:
        near = np.hypot(x - centre[0], z - centre[1]) <= radius + 1e-9
        x, z, yaw = x[near], z[near], yaw[near]
    x, z, yaw = (torch.from_numpy(a) for a in (x, z, yaw))
    k = len(x)
    trans, yaws = room.translations.repeat(k, 1, 1), room.yaws.repeat(k, 1)
    trans[:, i, 0], trans[:, i, 2], yaws[:, i] = x.to(trans), z.to(trans), yaw.to(yaws)
    half, labels = room.half_sizes.repeat(k, 1, 1), room.labels.repeat(k, 1)
    batch = SceneBatch(room.spec, labels, trans, half, yaws, room.floors * k)
    overlap = geo.box_overlap_volumes(trans, half, yaws, batch.ground_mask)[:, i]
    outside = geo.box_out_of_floor_area(trans, half, yaws, batch.floors, batch.mask, geo.OUT_OF_BOUND_SHRINK)[:, i]
    keep = ~(overlap > geo.COLLISION_VOLUME).any(-1) & (outside <= geo.OUT_OF_BOUND_AREA)
    return batch[keep.numpy()]


def search_room(room: SceneBatch, task: str, grid: float = 0.25, sweeps: int = 2, margin: float = 0.0,
                radius: float | None = None) -> SceneBatch:
    """The one-room batch ``room`` (float64 geometry) rearranged greedily for ``task`` (module doc), scored with
    ``margin``: rooms that pass with room to spare, so that they still pass placed a little off; with ``radius``,
    each object moved by at most that much a sweep, its turn kept (:func:`placements`)."""
    if task not in SCORES:
        raise ValueError(f"no layout search for task {task!r}; tasks with one: {', '.join(SCORES)}")
    score, passing = SCORES[task]
    best = score(room, margin)[0]
    ground = room.ground_mask[0].numpy()
    area = (room.half_sizes[0, :, 0] * room.half_sizes[0, :, 2]).numpy()
    for _ in range(sweeps):
        for i in (i for i in np.argsort(-area) if ground[i]):
            if best >= passing:
                return room
            options = placements(room, i, grid, radius)
            if not len(options):
                continue
            got = np.concatenate([score(options[s:s + CHUNK], margin) for s in range(0, len(options), CHUNK)])
            k = int(np.argmax(got))
            if got[k] > best + 1e-9:
                best, room = got[k], options[[k]]
    return room


def search_rooms(batch: SceneBatch, task: str, grid: float = 0.25, sweeps: int = 2, margin: float = 0.0
                 ) -> SceneBatch:
    """Every room of ``batch`` rearranged by :func:`search_room` (geometry in float64)."""
    double = SceneBatch(batch.spec, batch.labels, batch.translations.double(), batch.half_sizes.double(),
                        batch.yaws.double(), batch.floors, batch.ids)
    rooms = [search_room(double[[b]], task, grid, sweeps, margin) for b in range(len(batch))]
    return SceneBatch(batch.spec, batch.labels, torch.cat([r.translations for r in rooms]),
                      double.half_sizes, torch.cat([r.yaws for r in rooms]), batch.floors, batch.ids)
