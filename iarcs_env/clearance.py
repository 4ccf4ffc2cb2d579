"""Free space with a gradient: how wide the path to each object is, and how large a disk fits, as numbers (m)
that move with the furniture.

The walkable grid (:mod:`iarcs_env.walkable`) says yes or no: a cell is free for an agent of radius r when its
centre is at least r from every ground footprint and from the walls; an object is reachable when its footprint,
inflated by r, touches (8-neighbourhood) the largest 4-connected free region. Both are the same thresholds on one
field, the **clearance** c(p) of a point p: its signed distance to the nearest ground footprint (negative inside
one, by the depth) or wall (negative outside the floor). A cell is free when c >= r, so:

* the **reach clearance** of an object is the largest bottleneck, min c along the path, over the 4-connected grid
  paths from the room's largest free region to a cell next to the object's inflated footprint (the cells the
  checker looks at): the object is reachable exactly when it is at least r (R_reach, the wheelchair's paths);
* the **disk clearance** is the largest c over the cells where the disk may stand (near an object, near the
  middle): the disk fits exactly when it is at least r (the wheelchair's turning circle).

Each is the clearance of one cell, the path's bottleneck or the disk's centre, found on the grid without a
gradient (the widest path by repeated max-min propagation from a cell of the largest region). Its value there is
exact; its gradient is that of a soft minimum over every footprint and wall (temperature ``SOFT_MIN``), so the
bottleneck pushes on every object that narrows it, not only the nearest one (which on a grid may be a wall).
Grid cells as :func:`iarcs_env.walkable.free_space`: centres at ``corner + (index + 0.5) * cell`` of the floor's
bounding box.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage

from .floorplan import FloorPlan
from .geometry import WALK_CELL
from .relations import _point_segment_distance, floor_edges, inside_floor

SOFT_MIN = 0.05
"""m: temperature of the soft minimum whose gradient the clearance of a cell carries."""


def footprint_distances(points: torch.Tensor, translations, half_sizes, yaws) -> torch.Tensor:
    """``(B, P, N)`` signed distance (m) from points ``(B, P, 2)`` (x, z) to every footprint: negative inside, by
    the distance to its nearest edge."""
    t, h, y = (g.to(points)[:, None] for g in (translations, half_sizes, yaws))
    dx, dz = points[..., 0:1] - t[..., 0], points[..., 1:2] - t[..., 2]
    cos, sin = torch.cos(y), torch.sin(y)
    lx = (dx * cos - dz * sin).abs() - h[..., 0]  # along the object's left, (cos, -sin)
    lz = (dx * sin + dz * cos).abs() - h[..., 2]  # along its front, (sin, cos)
    outside = torch.sqrt(lx.clamp_min(0).square() + lz.clamp_min(0).square() + 1e-18)
    return torch.where((lx > 0) | (lz > 0), outside, torch.maximum(lx, lz))


def wall_distances(points: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """``(B, P)`` signed distance (m) from points ``(B, P, 2)`` to their floor's boundary: negative outside."""
    d = _point_segment_distance(points[:, :, None], edges[:, None, :, :2], edges[:, None, :, 2:]).amin(-1)
    return torch.where(inside_floor(points, edges), d, -d)


def point_clearance(points, edges, translations, half_sizes, yaws, obstacles) -> torch.Tensor:
    """``(B, P)`` clearance (m) of points ``(B, P, 2)``: min of :func:`footprint_distances` over the ``obstacles``
    ``(B, N)`` and :func:`wall_distances`, the exact value with the gradient of a soft minimum (module doc)."""
    d = footprint_distances(points, translations, half_sizes, yaws).masked_fill(~obstacles[:, None], float("inf"))
    every = torch.cat([d, wall_distances(points, edges)[..., None]], -1)
    smooth = -SOFT_MIN * torch.logsumexp(-every / SOFT_MIN, -1)
    return every.amin(-1).detach() + smooth - smooth.detach()


EDGE_POINTS = ((1, 1), (1, -1), (-1, 1), (-1, -1), (1, 0), (-1, 0), (0, 1), (0, -1))
"""A footprint's corners and edge midpoints, in units of its half-extents: where its distance to a wall is taken."""


def room_to_pull(floors: Sequence[FloorPlan], translations, half_sizes, yaws, movers: torch.Tensor,
                 anchors: torch.Tensor, ground: torch.Tensor, gap: float, radius: float) -> torch.Tensor:
    """``(B, N, N)`` bool, no gradient: for a ``movers`` slot i and an ``anchors`` slot j (a chair and its table),
    whether drawing i out to ``gap`` (m) from j narrows no passage below an agent's width (2 ``radius``): i's bounds
    placed ``gap`` beyond j's along the axis that parts the pair soonest, on i's side of j, are, from each other
    ground object's bounds and from each wall (to its corners and edge midpoints), at least 2 ``radius`` or no nearer
    than i stands now. Other pairs: True. A chair pulled out towards a wall or a cabinet closes the walkway behind it and
    can split the room in two (issue 39's dining rooms)."""
    from .scene import footprint_reach

    with torch.no_grad():
        room = torch.ones(movers.shape + movers.shape[-1:], dtype=torch.bool, device=movers.device)
        b, i, j = (movers[:, :, None] & anchors[:, None]).nonzero(as_tuple=True)  # only these pairs are asked
        if not len(b):
            return room
        t = translations.detach()
        c = t[..., 0:3:2]  # (B, N, 2) x, z
        ext = footprint_reach(half_sizes.detach()[..., 0:3:2], torch.cos(yaws.detach()), torch.sin(yaws.detach()))
        d = c[b, i] - c[b, j]  # (P, 2): i's centre from j's, a pair each
        axis = (ext[b, i] + ext[b, j] - d.abs()).argmin(-1, keepdim=True)  # the axis parting them soonest
        side = torch.where(d.gather(-1, axis) >= 0, 1.0, -1.0).to(t)
        target = c[b, j].gather(-1, axis) + side * (ext[b, j].gather(-1, axis) + gap + ext[b, i].gather(-1, axis))
        moved = c[b, i].scatter(-1, axis, target)  # (P, 2): i's centre once drawn from j

        k = torch.arange(movers.shape[1], device=movers.device)
        others = ground[b] & (k != i[:, None]) & (k != j[:, None])  # (P, N): k neither i nor j
        corners = torch.tensor(EDGE_POINTS).to(t)
        edges = floor_edges(floors).to(t)[b]  # (P, E, 4)

        def distances(centre: torch.Tensor) -> torch.Tensor:  # (P, N + E): i's bounds at ``centre`` to the rest
            apart = (centre[:, None] - c[b]).abs() - ext[b, i][:, None] - ext[b]
            to_objects = apart.clamp_min(0).norm(dim=-1).masked_fill(~others, float("inf"))
            points = centre[:, None] + corners * ext[b, i][:, None]  # (P, 8, 2)
            to_walls = _point_segment_distance(points[:, :, None], edges[:, None, :, :2],
                                               edges[:, None, :, 2:]).amin(-2)  # (P, E)
            return torch.cat([to_objects, to_walls], -1)

        before, after = distances(c[b, i]), distances(moved)
        room[b, i, j] = ((after >= 2 * radius) | (after >= before - 1e-3)).all(-1)  # no passage narrowed
        return room


class ClearanceGrid:
    """The clearance of every grid cell of a batch (no gradient), padded to one ``(B, H, W)`` grid: ``centres``
    ``(B, H, W, 2)``, ``inside`` (the scene's own cells), ``value`` (-inf on padding), ``to_objects``
    ``(B, N, H, W)`` (signed distance to each footprint), ``edges`` (:func:`floor_edges`)."""

    def __init__(self, floors: Sequence[FloorPlan], translations, half_sizes, yaws, obstacles,
                 cell: float = WALK_CELL):
        self.geometry = (translations, half_sizes, yaws, obstacles)
        bounds = torch.tensor([f.bounds for f in floors], dtype=torch.float64)
        shapes = torch.stack([torch.ceil((bounds[:, 3] - bounds[:, 1]) / cell - 1e-9),
                              torch.ceil((bounds[:, 2] - bounds[:, 0]) / cell - 1e-9)], 1).long().clamp_min(1)
        B, H, W = len(floors), int(shapes[:, 0].max()), int(shapes[:, 1].max())
        rows, cols = torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64)
        x = bounds[:, 0, None, None] + (cols[None, None, :] + 0.5) * cell
        z = bounds[:, 1, None, None] + (rows[None, :, None] + 0.5) * cell
        self.centres = torch.stack(torch.broadcast_tensors(x, z), -1)  # (B, H, W, 2)
        self.inside = ((torch.arange(H)[None, :, None] < shapes[:, 0, None, None])
                       & (torch.arange(W)[None, None, :] < shapes[:, 1, None, None]))
        self.edges = floor_edges(floors)
        with torch.no_grad():
            # float32: the grid only picks the cells; their values are computed again in the geometry's dtype
            t, h, y = (g.detach().cpu().float() for g in (translations, half_sizes, yaws))
            points = self.centres.reshape(B, H * W, 2).float()
            self.to_objects = footprint_distances(points, t, h, y).permute(0, 2, 1).reshape(B, -1, H, W)
            objects = self.to_objects.masked_fill(~obstacles.cpu()[:, :, None, None], float("inf")).amin(1)
            walls = wall_distances(points, self.edges.float()).reshape(B, H, W)
            self.value = torch.minimum(objects, walls).masked_fill(~self.inside, float("-inf"))

    def clearance_at(self, cells: torch.Tensor) -> torch.Tensor:
        """``(B, K)`` clearance of the cells ``(B, K)`` (flat indices), exact, with the soft minimum's gradient."""
        points = self.centres.flatten(1, 2)[torch.arange(len(cells))[:, None], cells]
        t, h, y, obstacles = self.geometry
        return point_clearance(points.to(t), self.edges.to(t), t, h, y, obstacles.to(t.device))

    def widest_paths(self, radius: float) -> torch.Tensor:
        """``(B, H, W)`` the bottleneck (m) of the widest 4-connected path to each cell from the cell of greatest
        clearance of the scene's largest free region (cells with clearance >= ``radius``; the greatest cell of
        the scene when none is free). Cells at ``radius`` or more form exactly that region."""
        value = self.value
        B, H, W = value.shape
        source = value.flatten(1).argmax(1)
        free = (value >= radius).numpy()
        for b in range(B):
            labels, count = ndimage.label(free[b])
            if count:
                largest = np.bincount(labels.ravel())[1:].argmax() + 1
                source[b] = int(value[b].masked_fill(torch.as_tensor(labels != largest), float("-inf")).argmax())
        best = torch.full((B, H + 2, W + 2), float("-inf"))  # a border of -inf around every grid
        inner = best[:, 1:-1, 1:-1]
        inner[torch.arange(B), source // W, source % W] = value.flatten(1)[torch.arange(B), source]
        while True:
            before = inner.clone()
            for _ in range(16):
                step = torch.maximum(torch.maximum(best[:, :-2, 1:-1], best[:, 2:, 1:-1]),
                                     torch.maximum(best[:, 1:-1, :-2], best[:, 1:-1, 2:]))
                torch.maximum(inner, torch.minimum(step, value), out=step)
                inner.copy_(step)
            if torch.equal(inner, before):
                return inner.clone()


def _bottleneck_cells(grid: ClearanceGrid, best: torch.Tensor, ends: torch.Tensor) -> torch.Tensor:
    """``(B, K)`` flat index of the bottleneck cell of the widest path to each of the cells ``ends (B, K)``: of the
    cells whose clearance and widest path both equal the end's widest path (every cell on a path that is its
    bottleneck), the nearest to the end."""
    B, K = ends.shape
    flat_value, flat_best = grid.value.flatten(1), best.flatten(1)
    centres = grid.centres.flatten(1, 2)
    out = ends.clone()
    for b in range(B):
        width = flat_best[b, ends[b]]  # (K,)
        candidates = (flat_value[b, None] == width[:, None]) & (flat_best[b, None] == width[:, None])  # (K, HW)
        distance = torch.cdist(centres[b, ends[b]], centres[b]).masked_fill(~candidates, float("inf"))
        found = torch.isfinite(distance).any(1)
        out[b] = torch.where(found, distance.argmin(1), ends[b])
    return out


CHUNK = 32
"""Scenes gridded at once: a grid holds (scenes, objects, cells) distances (a 6 x 6 m room: 14,400 cells)."""


def _in_chunks(fn):
    """``fn(floors, translations, half_sizes, yaws, ground, *masks, ...)`` run on ``CHUNK`` scenes at a time and
    concatenated (bounded memory for a batch of any size); masks given as None stay None."""
    def chunked(floors, translations, half_sizes, yaws, ground, *args, **kwargs):
        if len(floors) <= CHUNK:
            return fn(floors, translations, half_sizes, yaws, ground, *args, **kwargs)
        parts = []
        for s in range(0, len(floors), CHUNK):
            part = slice(s, s + CHUNK)
            cut = [a[part] if isinstance(a, torch.Tensor) else a for a in args]
            kw = {k: v[part] if isinstance(v, torch.Tensor) else v for k, v in kwargs.items()}
            parts.append(fn(floors[part], translations[part], half_sizes[part], yaws[part], ground[part], *cut, **kw))
        return torch.cat(parts)
    chunked.__doc__, chunked.__name__ = fn.__doc__, fn.__name__
    return chunked


def reach_clearance(floors: Sequence[FloorPlan], translations, half_sizes, yaws, ground: torch.Tensor,
                    radius: float, cell: float = WALK_CELL) -> torch.Tensor:
    """``(B, N)`` reach clearance (m, module doc) of each ground object for an agent of ``radius``: the object is
    reachable (:func:`iarcs_env.relations.reachable`) exactly when it is at least ``radius``. Differentiable in
    the geometry; ``-radius`` (no gradient) for other slots and for objects with no grid cell beside them."""
    points = reach_points(floors, translations, half_sizes, yaws, ground, radius, cell)
    return clearance_of_points(floors, points, translations, half_sizes, yaws, ground, radius)


def clearance_of_points(floors: Sequence[FloorPlan], points: torch.Tensor, translations, half_sizes, yaws,
                        ground: torch.Tensor, radius: float) -> torch.Tensor:
    """``(B, N)`` :func:`point_clearance` of each object's point ``(B, N, 2)`` (:func:`reach_points`; NaN: none),
    ``-radius`` (no gradient) where it has none: the reach clearance of the geometry the points were found on, and
    of geometry moved a little since (the bottleneck points kept, so the grid is not searched every step)."""
    found = torch.isfinite(points[..., 0])
    t = translations
    value = point_clearance(torch.nan_to_num(points).to(t), floor_edges(floors).to(t), t, half_sizes, yaws,
                            ground.to(t.device))
    keep = (ground.cpu() & found.cpu()).to(value.device)
    return torch.where(keep, value, torch.full_like(value, -radius))


@_in_chunks
def reach_points(floors: Sequence[FloorPlan], translations, half_sizes, yaws, ground: torch.Tensor,
                 radius: float, cell: float = WALK_CELL) -> torch.Tensor:
    """``(B, N, 2)`` the point (x, z; m) of each object's reach clearance (module doc): the bottleneck cell's centre
    of the widest path to it; NaN for other slots and for objects with no grid cell beside them. No gradient."""
    grid = ClearanceGrid(floors, translations, half_sizes, yaws, ground, cell)
    best = grid.widest_paths(radius)
    with torch.no_grad():  # cells 8-adjacent to the footprint inflated by the radius
        inflated = (grid.to_objects < radius).float().flatten(0, 1)[:, None]
        beside = F.max_pool2d(inflated, 3, stride=1, padding=1).reshape(grid.to_objects.shape) > 0
        widths = best[:, None].expand_as(beside).masked_fill(~beside, float("-inf")).flatten(2)
        width, end = widths.max(-1)  # (B, N)
    cells = _bottleneck_cells(grid, best, end)
    points = grid.centres.flatten(1, 2)[torch.arange(len(cells))[:, None], cells]
    keep = ground.cpu() & torch.isfinite(width)
    return points.masked_fill(~keep[..., None], float("nan")).to(translations.dtype)


@_in_chunks
def disk_clearance(floors: Sequence[FloorPlan], translations, half_sizes, yaws, ground: torch.Tensor,
                   near: torch.Tensor | None = None, reach: float = float("inf"), middle: float | None = None,
                   cell: float = WALK_CELL) -> torch.Tensor:
    """``(B,)`` disk clearance (m, module doc): the greatest clearance of a cell centre at most ``reach`` m from a
    footprint of ``near (B, N)`` (anywhere when None) and, with ``middle``, at most that far from the frame's
    origin. A disk of radius r fits there (:func:`iarcs_env.relations.free_disk` with ``within = reach - r``)
    exactly when it is at least r. Differentiable in the geometry; -inf where no cell qualifies."""
    grid = ClearanceGrid(floors, translations, half_sizes, yaws, ground, cell)
    with torch.no_grad():
        allowed = grid.inside.clone()
        if near is not None:
            distance = grid.to_objects.masked_fill(~near.cpu()[:, :, None, None], float("inf")).amin(1)
            allowed &= distance <= reach + 1e-9
        if middle is not None:
            allowed &= torch.linalg.vector_norm(grid.centres, dim=-1) <= middle + 1e-9
        best, cells = grid.value.masked_fill(~allowed, float("-inf")).flatten(1).max(1)
    value = grid.clearance_at(cells[:, None])[:, 0]
    return torch.where(torch.isfinite(best).to(value.device), value, torch.full_like(value, float("-inf")))
