"""Batched spatial relations between objects, shared by the task checkers (:mod:`iarcs_env.tasks`) and the
reward programs' scene API (:mod:`rewards.scene_api`). Torch in, torch out; no loop over objects or pairs.

Conventions (ATISS / 3D-FRONT, checked on the real bedrooms: bed headboards are against a wall, behind
the bed): y is up and the floor is the x-z plane; an object's FRONT is its local +z axis, in world (x, z)
``forward = (sin yaw, cos yaw)``; its LEFT, for someone standing at the object looking forward, is its
local +x axis, ``left = (cos yaw, -sin yaw)``. Pairwise results are ``(B, N, N)`` with ``[b, i, j]`` the
relation of object j to object i. Values for empty slots are computed like any other (finite, meaningless):
select objects with masks.

Free-space relations reuse the walkable grid of :func:`iarcs_env.walkable.free_space` (0.05 m cells; a
cell is free for an agent of radius r when its centre is inside the floor at least r from the walls and
at least r from every ground footprint).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from . import geometry as geo
from .walkable import FreeSpace, as_numpy, free_space
from .floorplan import FloorPlan
from .rooms import CEILING_CLASSES, ROOMS
from .scene import box_corners_xz

# ------------------------------------------------------------------------------------------------------
# class groups (one place for the scene API and the task checkers)
# ------------------------------------------------------------------------------------------------------
ALL_CLASSES: tuple[str, ...] = tuple(sorted({c for spec in ROOMS.values() for c in spec.classes}))
BEDS = ("double_bed", "single_bed", "kids_bed")
TABLES = ("table", "desk", "nightstand", "coffee_table", "console_table", "corner_side_table", "round_end_table",
          "dining_table", "dressing_table")
SOFAS = ("sofa", "chaise_longue_sofa", "l_shaped_sofa", "lazy_sofa", "loveseat_sofa", "multi_seat_sofa")
#: name -> classes. Every name works in every room type (classes the room lacks simply never occur).
CLASS_GROUPS: dict[str, tuple[str, ...]] = {
    "bed": BEDS,
    "table": TABLES,
    "support_surface": TABLES + ("cabinet", "children_cabinet", "wine_cabinet", "shelf", "bookshelf", "tv_stand",
                                 "wardrobe") + BEDS,
    "seat": ("chair", "stool", "dressing_chair", "armchair", "dining_chair", "lounge_chair", "chinese_chair") + SOFAS,
    "sofa": SOFAS,
    "lamp": tuple(sorted(CEILING_CLASSES)),
    "ground": tuple(c for c in ALL_CLASSES if c not in CEILING_CLASSES),
    "any": ALL_CLASSES,
}


def class_mask(labels: torch.Tensor, classes: Sequence[str], names: Sequence[str]) -> torch.Tensor:
    """``(B, N)`` bool: slots whose class is one of ``names`` (class names or :data:`CLASS_GROUPS` names).

    ``classes`` is the room's class list (label ``k`` is ``classes[k]``; larger labels, e.g. ``empty``, never
    match). A known name absent from this room type matches nothing; an unknown name raises ValueError.
    """
    wanted: set[str] = set()
    for name in names:
        if name in CLASS_GROUPS:
            wanted.update(CLASS_GROUPS[name])
        elif name in ALL_CLASSES:
            wanted.add(name)
        else:
            raise ValueError(
                f"unknown object class or group {name!r}; groups: {', '.join(CLASS_GROUPS)}; "
                f"classes: {', '.join(ALL_CLASSES)}")
    table = torch.tensor([c in wanted for c in classes] + [False], dtype=torch.bool, device=labels.device)
    return table[labels.clamp(0, len(classes))]


# ------------------------------------------------------------------------------------------------------
# frames and pairwise relations
# ------------------------------------------------------------------------------------------------------
def forward_xz(yaws: torch.Tensor) -> torch.Tensor:
    """Unit facing direction (local +z) in world (x, z): ``(sin yaw, cos yaw)``, shape ``(..., 2)``."""
    return torch.stack([torch.sin(yaws), torch.cos(yaws)], -1)


def left_xz(yaws: torch.Tensor) -> torch.Tensor:
    """Unit left direction (local +x) in world (x, z): ``(cos yaw, -sin yaw)``, shape ``(..., 2)``."""
    return torch.stack([torch.cos(yaws), -torch.sin(yaws)], -1)


def centre_distance(xz: torch.Tensor) -> torch.Tensor:
    """``(B, N, N)`` floor distance between centres ``xz (B, N, 2)``."""
    d = xz[:, None, :, :] - xz[:, :, None, :]
    return torch.linalg.vector_norm(d, dim=-1)


def local_offset(xz: torch.Tensor, yaws: torch.Tensor) -> torch.Tensor:
    """``(B, N, N, 2)``: centre of j in i's frame, ``[..., 0]`` lateral (+ = i's left), ``[..., 1]`` forward
    (+ = in front of i)."""
    d = xz[:, None, :, :] - xz[:, :, None, :]  # [b, i, j] = xz_j - xz_i
    lat = (d * left_xz(yaws)[:, :, None, :]).sum(-1)
    fwd = (d * forward_xz(yaws)[:, :, None, :]).sum(-1)
    return torch.stack([lat, fwd], -1)


def facing_angle(xz: torch.Tensor, yaws: torch.Tensor) -> torch.Tensor:
    """``(B, N, N)`` angle (rad, 0..pi) between i's forward and the direction from i to j (0: i faces j).
    0 when the centres coincide (the diagonal included)."""
    off = local_offset(xz, yaws)
    return torch.atan2(off[..., 0].abs(), off[..., 1])


def _point_segment_distance(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Distance from points ``p`` to segments ``a -> b`` (all ``(..., 2)``, broadcast)."""
    ab = b - a
    t = ((p - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-18)
    closest = a + t.clamp(0, 1)[..., None] * ab
    return torch.linalg.vector_norm(p - closest, dim=-1)


def _segments_cross(a, b, c, d) -> torch.Tensor:
    """Whether segments ``a -> b`` and ``c -> d`` intersect (touching counts), all ``(..., 2)``."""
    def orient(p, q, r):
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])

    d1, d2 = orient(c, d, a), orient(c, d, b)
    d3, d4 = orient(a, b, c), orient(a, b, d)
    return (d1 * d2 <= 0) & (d3 * d4 <= 0)


def footprint_gap(translations: torch.Tensor, half_sizes: torch.Tensor, yaws: torch.Tensor) -> torch.Tensor:
    """``(B, N, N)`` shortest floor distance between the footprints of i and j (0 when they touch or
    overlap; the diagonal is 0). Exact for the oriented rectangles: separating-axis test for the overlap,
    otherwise the smallest corner-to-edge distance in either direction."""
    c = box_corners_xz(translations[..., 0:3:2], half_sizes[..., 0:3:2], yaws)  # (B, N, 4, 2)
    ci = c[:, :, None, :, None, :]  # corners of i
    cj = c[:, None, :, :, None, :]  # corners of j
    ai, bi = c[:, :, None, None], c.roll(-1, 2)[:, :, None, None]  # (B, N, 1, 1, 4, 2): edges of i
    aj, bj = c[:, None, :, None], c.roll(-1, 2)[:, None, :, None]
    d_ji = _point_segment_distance(cj, ai, bi).flatten(-2).amin(-1)  # corners of j to edges of i
    d_ij = _point_segment_distance(ci, aj, bj).flatten(-2).amin(-1)
    dist = torch.minimum(d_ji, d_ij)
    # separating axes: the two local axes of each box
    axes = torch.stack([left_xz(yaws), forward_xz(yaws)], 2)  # (B, N, 2, 2)
    ax = torch.cat([axes[:, :, None].expand(-1, -1, c.shape[1], -1, -1),
                    axes[:, None, :].expand(-1, c.shape[1], -1, -1, -1)], 3)  # (B, N, N, 4, 2)
    pi = (c[:, :, None, None, :, :] * ax[..., None, :]).sum(-1)  # (B, N, N, 4 axes, 4 corners)
    pj = (c[:, None, :, None, :, :] * ax[..., None, :]).sum(-1)
    apart = (pi.amax(-1) < pj.amin(-1)) | (pj.amax(-1) < pi.amin(-1))
    return torch.where(apart.any(-1), dist, torch.zeros_like(dist))


# ------------------------------------------------------------------------------------------------------
# walls
# ------------------------------------------------------------------------------------------------------
def floor_edges(floors: Sequence[FloorPlan], device=None, dtype=torch.float64) -> torch.Tensor:
    """``(B, E, 4)`` floor boundary edges ``(ax, az, bx, bz)``, padded with zero-length edges at a vertex
    (harmless: never crossed, and never nearer than the boundary itself)."""
    E = max(len(f.vertices) for f in floors)
    out = np.zeros((len(floors), E, 4))
    for b, f in enumerate(floors):
        v = np.asarray(f.vertices, dtype=np.float64)
        out[b, :, :2] = out[b, :, 2:] = v[0]
        out[b, :len(v), :2], out[b, :len(v), 2:] = v, np.roll(v, -1, 0)
    return torch.as_tensor(out, dtype=dtype, device=device)


def inside_floor(points: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """``(B, N)`` bool: points ``(B, N, 2)`` inside their scene's floor (crossing parity; ``edges`` from
    :func:`floor_edges`)."""
    px, pz = points[..., 0:1], points[..., 1:2]  # (B, N, 1)
    ax, az, bx, bz = (edges[:, None, :, k] for k in range(4))  # (B, 1, E)
    crosses = (az > pz) != (bz > pz)
    xc = ax + (pz - az) * (bx - ax) / torch.where(crosses, bz - az, torch.ones_like(az))
    return ((crosses & (xc > px)).sum(-1) % 2) == 1


def wall_distance(translations: torch.Tensor, half_sizes: torch.Tensor, yaws: torch.Tensor,
                  edges: torch.Tensor) -> torch.Tensor:
    """``(B, N)`` shortest distance from each footprint to its floor's boundary (walls); 0 when the
    footprint touches or crosses the boundary or its centre lies outside the floor."""
    c = box_corners_xz(translations[..., 0:3:2], half_sizes[..., 0:3:2], yaws).to(edges.dtype)  # (B, N, 4, 2)
    fa, fb = c[:, :, :, None], c.roll(-1, 2)[:, :, :, None]  # footprint edges (B, N, 4, 1, 2)
    wa, wb = edges[:, None, None, :, :2], edges[:, None, None, :, 2:]  # walls (B, 1, 1, E, 2)
    d = torch.stack([_point_segment_distance(fa, wa, wb), _point_segment_distance(fb, wa, wb),
                     _point_segment_distance(wa, fa, fb), _point_segment_distance(wb, fa, fb)], -1).amin(-1)
    d = d.flatten(-2).amin(-1)
    cross = _segments_cross(fa, fb, wa, wb).flatten(-2).any(-1)
    inside = inside_floor(translations[..., 0:3:2].to(edges.dtype), edges)
    return torch.where(cross | ~inside, torch.zeros_like(d), d)


def back_to_wall(translations: torch.Tensor, half_sizes: torch.Tensor, yaws: torch.Tensor,
                 edges: torch.Tensor) -> torch.Tensor:
    """``(B, N)`` distance from the midpoint of each object's back edge to the floor boundary straight behind
    it (along -forward). Negative when that midpoint is outside the floor (minus how far it pokes through)."""
    f = forward_xz(yaws).to(edges.dtype)
    p = translations[..., 0:3:2].to(edges.dtype) - f * half_sizes[..., 2:3].to(edges.dtype)  # (B, N, 2)
    back = -f
    a, b = edges[:, None, :, :2], edges[:, None, :, 2:]  # (B, 1, E, 2)
    e = b - a
    r = a - p[:, :, None]  # (B, N, E, 2)
    den = back[:, :, None, 0] * e[..., 1] - back[:, :, None, 1] * e[..., 0]
    ok = den.abs() > 1e-12
    den = torch.where(ok, den, torch.ones_like(den))
    t = (r[..., 0] * e[..., 1] - r[..., 1] * e[..., 0]) / den  # along the ray
    u = (r[..., 0] * back[:, :, None, 1] - r[..., 1] * back[:, :, None, 0]) / den  # along the edge
    ok = ok & (u >= 0) & (u <= 1)
    big = torch.full_like(t, 1e3)
    ahead = torch.where(ok & (t >= 0), t, big).amin(-1)
    behind = torch.where(ok & (t < 0), -t, big).amin(-1)
    return torch.where(inside_floor(p, edges), ahead, -behind)


def wall_offset(translations: torch.Tensor, yaws: torch.Tensor, half_sizes: torch.Tensor,
                edges: torch.Tensor) -> torch.Tensor:
    """``(B, N)`` distance along the wall straight behind each object (the first boundary edge the ray from its
    back edge's midpoint along -forward meets) from the middle of that edge to the object's centre; ``inf`` when
    the ray meets no edge."""
    f = forward_xz(yaws).to(edges.dtype)
    c = translations[..., 0:3:2].to(edges.dtype)
    p = c - f * half_sizes[..., 2:3].to(edges.dtype)
    a, b = edges[:, None, :, :2], edges[:, None, :, 2:]  # (B, 1, E, 2)
    e = b - a
    r = a - p[:, :, None]
    den = -f[:, :, None, 0] * e[..., 1] + f[:, :, None, 1] * e[..., 0]
    ok = den.abs() > 1e-12
    den = torch.where(ok, den, torch.ones_like(den))
    t = (r[..., 0] * e[..., 1] - r[..., 1] * e[..., 0]) / den
    u = (-r[..., 0] * f[:, :, None, 1] + r[..., 1] * f[:, :, None, 0]) / den
    t = torch.where(ok & (u >= 0) & (u <= 1) & (t >= -0.05), t, torch.full_like(t, float("inf")))
    hit = t.argmin(-1)  # (B, N)

    def pick(x):  # (B, 1, E, 2) -> (B, N, 2): the hit edge's
        return torch.gather(x.expand(-1, hit.shape[1], -1, -1), 2, hit[..., None, None].expand(-1, -1, 1, 2)).squeeze(2)

    mid, direction = pick((a + b) / 2), pick(e)
    along = ((c - mid) * direction).sum(-1).abs() / torch.linalg.vector_norm(direction, dim=-1).clamp_min(1e-9)
    return torch.where(torch.isfinite(t.amin(-1)), along, torch.full_like(along, float("inf")))


# ------------------------------------------------------------------------------------------------------
# free space (walkable grid)
# ------------------------------------------------------------------------------------------------------
def free_grid(floors: Sequence[FloorPlan], translations, half_sizes, yaws, ground, radius: float,
              cell: float = geo.WALK_CELL, reach: bool = True) -> FreeSpace:
    """The walkable grid for an agent (or disk) of ``radius`` with the ``ground`` footprints as obstacles
    (:func:`iarcs_env.walkable.free_space`)."""
    return free_space(floors, translations, half_sizes, yaws, ground, cell=cell, radius=radius, reach=reach)


def reachable(space: FreeSpace, ground: torch.Tensor) -> torch.Tensor:
    """``(B, N)`` bool: ground objects whose footprint inflated by the agent radius touches (within one cell)
    the largest free region, i.e. reached by free paths ``2 * radius`` wide."""
    return torch.as_tensor(space.reach, device=ground.device) & ground


def free_disk(space: FreeSpace, translations, half_sizes, yaws, near: torch.Tensor | None,
              within: float, centre_within: float | None = None) -> torch.Tensor:
    """``(B,)`` bool: a disk of radius ``space.radius`` fits on free floor (its centre on a free cell of
    ``space``: inside the floor and outside every obstacle footprint by at least the radius), and, when
    ``near (B, N)`` is given, its edge is within ``within`` m of a footprint in ``near`` (the centre within
    ``radius + within`` of that footprint; point-to-rectangle distances, exact at the cell centres). With
    ``centre_within``, the disk's centre is at most that far from the frame's origin (in a
    :class:`SceneBatch`, the centre of the floor's bounding box: the middle of the room)."""
    B = len(space.shapes)
    rows, cols = np.nonzero(space.free)
    scene = _atlas_scenes(space)[rows, cols]
    x = space.origins[scene, 0] + (cols - space.offsets[scene, 1] + 0.5) * space.cell
    z = space.origins[scene, 1] + (rows - space.offsets[scene, 0] + 0.5) * space.cell
    if centre_within is not None:
        keep = np.hypot(x, z) <= centre_within + 1e-9
        scene, x, z = scene[keep], x[keep], z[keep]
    out = np.zeros(B, dtype=bool)
    if near is None:
        out[scene] = True
        return torch.as_tensor(out)
    t, h, y = as_numpy(translations), as_numpy(half_sizes), as_numpy(yaws)
    near = as_numpy(near).astype(bool)
    limit = space.radius + within
    for start in range(0, len(scene), 200_000):  # cells x objects in chunks (bounded memory)
        s = scene[start:start + 200_000]
        dx = x[start:start + 200_000, None] - t[s, :, 0]
        dz = z[start:start + 200_000, None] - t[s, :, 2]
        c, sn = np.cos(y[s]), np.sin(y[s])
        lx = np.abs(c * dx - sn * dz) - h[s, :, 0]  # along local x = (c, -s)
        lz = np.abs(sn * dx + c * dz) - h[s, :, 2]  # along local z = (s, c)
        dist = np.hypot(np.maximum(lx, 0), np.maximum(lz, 0))
        ok = ((dist <= limit + 1e-9) & near[s]).any(1)
        out[s[ok]] = True
    return torch.as_tensor(out)


def _atlas_scenes(space: FreeSpace) -> np.ndarray:
    """Scene index of every atlas cell (-1 in the gaps)."""
    atlas = np.full(space.free.shape, -1, dtype=np.int64)
    for b, ((oy, ox), (h, w)) in enumerate(zip(space.offsets, space.shapes)):
        atlas[oy:oy + h, ox:ox + w] = b
    return atlas


#: The zones of :func:`free_share` around an object, as (lateral sign, forward sign): beyond its front, back,
#: left or right edge.
ZONES = {"front": ((0, 1),), "back": ((0, -1),), "sides": ((1, 0), (-1, 0)),
         "around": ((0, 1), (0, -1), (1, 0), (-1, 0))}


def free_share(translations: torch.Tensor, half_sizes: torch.Tensor, yaws: torch.Tensor, ground: torch.Tensor,
               edges: torch.Tensor, depth: float, zone: str, samples: int = 5) -> torch.Tensor:
    """``(B, N)`` share (0..1) of the floor strip ``depth`` m wide along the object's edges of ``zone``
    (:data:`ZONES`: the strip as wide as the edge, beyond it) that is free: inside the floor and outside every
    other ground footprint. Measured at ``samples`` x ``samples`` points per strip (cell centres)."""
    t, h, y = translations.to(edges.dtype), half_sizes.to(edges.dtype), yaws.to(edges.dtype)
    grid = (torch.arange(samples, dtype=edges.dtype, device=edges.device) + 0.5) / samples  # (S,) in (0, 1)
    across = (2 * grid - 1)[:, None].expand(samples, samples).flatten()  # -1..1 along the edge
    out_of = grid[None, :].expand(samples, samples).flatten()             # 0..1 away from the edge
    points = []
    for lat_sign, fwd_sign in ZONES[zone]:
        if fwd_sign:
            lat = across[None, None] * h[..., 0:1]
            fwd = fwd_sign * (h[..., 2:3] + out_of[None, None] * depth)
        else:
            lat = lat_sign * (h[..., 0:1] + out_of[None, None] * depth)
            fwd = across[None, None] * h[..., 2:3]
        points.append(t[..., None, 0:3:2] + lat[..., None] * left_xz(y)[:, :, None] + fwd[..., None]
                      * forward_xz(y)[:, :, None])
    p = torch.cat(points, 2)  # (B, N, P, 2)
    B, N, P, _ = p.shape
    inside = inside_floor(p.reshape(B, N * P, 2), edges).reshape(B, N, P)
    # p in the frame of every object k: inside k's footprint?
    d = p[:, :, None] - t[:, None, :, None, 0:3:2]  # (B, N, K, P, 2)
    lx = (d * left_xz(y)[:, None, :, None]).sum(-1).abs() <= h[:, None, :, None, 0]
    lz = (d * forward_xz(y)[:, None, :, None]).sum(-1).abs() <= h[:, None, :, None, 2]
    others = ground[:, None, :] & ~torch.eye(N, dtype=torch.bool, device=ground.device)
    blocked = (lx & lz & others[..., None]).any(2)
    return (inside & ~blocked).to(edges.dtype).mean(-1)
