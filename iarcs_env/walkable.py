"""The walkable grid of a batch of scenes, for R_walkable, R_reach, the accessibility reward and free-space
relations.

:func:`free_space`: cell centres inside the floor at least ``radius`` from its boundary and at least ``radius``
from every given footprint (the footprint inflated by a disk of that radius). The floors and the inflated
footprints are convex pieces, so every grid row meets each of them in one interval; the intervals are computed
analytically for all (row, piece) pairs at once and painted with a difference array and a cumulative sum. The
scenes' grids are packed into one 2D atlas (one-cell gaps between them), so connected components
(``scipy.ndimage.label``), the one-cell dilation and the distance transform are one C call per batch.

Grid cell ``(i, j)`` of a scene has its centre at ``(xmin + (j + 0.5) * cell, zmin + (i + 0.5) * cell)``,
with (xmin, zmin) the floor's bounding-box corner.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from scipy import ndimage

from .floorplan import FloorPlan
from .geometry import AGENT_RADIUS, WALK_CELL
from .scene import box_corners_xz

_BIG = 1e9


def _slab(alpha, beta, half):
    """Interval of dx with ``|alpha * dx + beta| <= half`` (elementwise); empty gives lo > hi."""
    nz = np.abs(alpha) > 1e-12
    a_safe = np.where(nz, alpha, 1.0)
    centre = -beta / a_safe
    width = half / np.abs(a_safe)
    inside = np.abs(beta) <= half
    lo = np.where(nz, centre - width, np.where(inside, -_BIG, _BIG))
    hi = np.where(nz, centre + width, np.where(inside, _BIG, -_BIG))
    return lo, hi


def _rect_row_interval(cx, cz, ux, uz, a, b, z):
    """x-interval where the row ``z`` crosses the rectangle centred (cx, cz) with unit axis u = (ux, uz),
    v = (-uz, ux) and half extents a (along u), b (along v)."""
    dz = z - cz
    lo1, hi1 = _slab(ux, uz * dz, a)
    lo2, hi2 = _slab(-uz, ux * dz, b)
    return cx + np.maximum(lo1, lo2), cx + np.minimum(hi1, hi2)


def _disk_row_interval(px, pz, r, z):
    d2 = r * r - (z - pz) ** 2
    root = np.sqrt(np.clip(d2, 0, None))
    ok = d2 > 0
    return np.where(ok, px - root, _BIG), np.where(ok, px + root, -_BIG)


def _union(intervals):
    """Union of overlapping row intervals of convex pieces of one convex set: [min lo, max hi] over the
    non-empty ones."""
    lo = np.full_like(intervals[0][0], _BIG)
    hi = np.full_like(intervals[0][0], -_BIG)
    for a, b in intervals:
        ok = a < b
        lo = np.where(ok, np.minimum(lo, a), lo)
        hi = np.where(ok, np.maximum(hi, b), hi)
    return lo, hi


def _ragged_rows(first, count):
    """For items with row ranges [first, first + count): (item index, row) for every row, flattened."""
    count = np.maximum(count, 0)
    item = np.repeat(np.arange(len(first)), count)
    starts = np.cumsum(count) - count
    row = first[item] + (np.arange(int(count.sum())) - starts[item])
    return item, row


@dataclass
class FreeSpace:
    """The walkable grid of a batch and its connected components.

    Per scene ``b``: ``free_cells[b]`` free cells, ``largest_cells[b]`` cells in the largest 4-connected free
    component, ``regions[b]`` free components, ``floor_cells[b]`` cells of the empty room's free space
    (floor eroded by the radius), ``reach[b, n]`` whether object n's inflated footprint touches (within one
    cell, 8-neighbourhood) the largest component, ``clearance[b]`` mean distance (m) from a free cell to
    the nearest blocked cell (``nan`` when not computed). Grids are packed in one atlas; use
    :meth:`scene_grid` for one scene's masks.
    """

    cell: float
    radius: float
    origins: np.ndarray  # (B, 2) grid corner (xmin, zmin)
    shapes: np.ndarray  # (B, 2) (H, W)
    offsets: np.ndarray  # (B, 2) atlas (row, col) of cell (0, 0)
    floor: np.ndarray  # atlas: floor eroded by the radius
    free: np.ndarray  # atlas: free cells
    labels: np.ndarray  # atlas: component labels (0 = not free)
    largest_label: np.ndarray  # (B,) label of the largest component (0 when none)
    floor_cells: np.ndarray
    free_cells: np.ndarray
    largest_cells: np.ndarray
    regions: np.ndarray
    reach: np.ndarray  # (B, N)
    clearance: np.ndarray

    @property
    def walkable_ratio(self) -> np.ndarray:
        """R_walkable per scene: largest component / free cells (0 when nothing is free)."""
        return np.where(self.free_cells > 0, self.largest_cells / np.maximum(self.free_cells, 1), 0.0)

    def scene_grid(self, b: int) -> dict:
        """One scene's masks: ``free``, ``largest``, ``unreachable`` (free but not in the largest
        component), ``floor`` (eroded), with ``xs``, ``zs`` cell-centre coordinates."""
        (oy, ox), (h, w) = self.offsets[b], self.shapes[b]
        sl = (slice(oy, oy + h), slice(ox, ox + w))
        free = self.free[sl]
        largest = (self.labels[sl] == self.largest_label[b]) & free & (self.largest_label[b] > 0)
        x0, z0 = self.origins[b]
        return {"free": free, "largest": largest, "unreachable": free & ~largest, "floor": self.floor[sl],
                "xs": x0 + (np.arange(w) + 0.5) * self.cell, "zs": z0 + (np.arange(h) + 0.5) * self.cell}


def _pack(shapes: np.ndarray, gap: int = 1) -> tuple[np.ndarray, tuple[int, int]]:
    """Shelf-pack rectangles ``(H, W)`` into an atlas with ``gap`` empty cells between them."""
    hs, ws = shapes[:, 0] + gap, shapes[:, 1] + gap
    width = int(max(ws.max(), np.ceil(np.sqrt((hs * ws).sum()) * 1.15)))
    offsets = np.zeros((len(shapes), 2), dtype=np.int64)
    x = y = shelf = 0
    for b in np.argsort(-hs, kind="stable"):
        if x + ws[b] > width:
            y, x, shelf = y + shelf, 0, 0
        offsets[b] = (y, x)
        x += ws[b]
        shelf = max(shelf, hs[b])
    return offsets, (int(y + shelf), width + 1)


def free_space(floors: Sequence[FloorPlan], translations, half_sizes, yaws, valid, cell: float = WALK_CELL,
               radius: float = AGENT_RADIUS, reach: bool = True, clearance: bool = False) -> FreeSpace:
    """Walkable grid of a batch (see the module docstring). ``valid (B, N)`` selects the obstacles (the
    ground objects); geometry may be torch tensors or arrays, in the floors' frame."""
    t = as_numpy(translations)
    h = as_numpy(half_sizes)
    y = as_numpy(yaws)
    valid = as_numpy(valid).astype(bool)
    B, N = valid.shape
    bounds = np.array([f.bounds for f in floors], dtype=np.float64)  # (B, 4)
    origins = bounds[:, :2]
    shapes = np.stack([np.ceil((bounds[:, 3] - bounds[:, 1]) / cell - 1e-9),
                       np.ceil((bounds[:, 2] - bounds[:, 0]) / cell - 1e-9)], 1).astype(np.int64)
    shapes = np.maximum(shapes, 1)
    offsets, (HA, WA) = _pack(shapes)
    stride = WA + 1

    def paint(item_scene, row, lo, hi, weight=None):
        """Difference-array entries painting cells lo < x_centre < hi of ``row`` of each item's scene."""
        b = item_scene
        x0 = origins[b, 0]
        js = np.floor((lo - x0) / cell - 0.5) + 1
        je = np.ceil((hi - x0) / cell - 0.5)
        js = np.clip(js, 0, shapes[b, 1]).astype(np.int64)
        je = np.clip(je, 0, shapes[b, 1]).astype(np.int64)
        keep = je > js
        base = (offsets[b, 0] + row) * stride + offsets[b, 1]
        return base[keep] + js[keep], base[keep] + je[keep], keep

    size = HA * stride

    def raster(starts, ends):
        d = np.bincount(starts, minlength=size) - np.bincount(ends, minlength=size)
        return np.cumsum(d.reshape(HA, stride), axis=1)[:, :WA]

    # --- floors: inside (crossing parity) and at least `radius` from every wall (edge capsules) -----
    verts = [f.vertices for f in floors]
    n_edges = np.array([len(v) for v in verts])
    A = np.concatenate(verts)
    Bv = np.concatenate([np.roll(v, -1, 0) for v in verts])
    # every (row, edge) pair of the same scene
    row_scene, row = _ragged_rows(np.zeros(B, dtype=np.int64), shapes[:, 0])
    row_scene = np.arange(B)[row_scene]
    edge_start = np.cumsum(n_edges) - n_edges
    pr, pe_local = _ragged_rows(np.zeros(len(row), dtype=np.int64), n_edges[row_scene])
    pe = edge_start[row_scene[pr]] + pe_local
    ps, prow = row_scene[pr], row[pr]
    z = origins[ps, 1] + (prow + 0.5) * cell
    ax, az, bx, bz = A[pe, 0], A[pe, 1], Bv[pe, 0], Bv[pe, 1]
    crosses = (az > z) != (bz > z)
    xc = ax + (z - az) * (bx - ax) / np.where(crosses, bz - az, 1.0)
    s1, e1, _ = paint(ps[crosses], prow[crosses], xc[crosses], np.full(crosses.sum(), _BIG))
    inside = (raster(s1, e1) % 2) == 1
    ex, ez = bx - ax, bz - az
    length = np.hypot(ex, ez)
    ux, uz = ex / length, ez / length
    lo, hi = _union([
        _rect_row_interval((ax + bx) / 2, (az + bz) / 2, ux, uz, length / 2, radius, z),
        _disk_row_interval(ax, az, radius, z), _disk_row_interval(bx, bz, radius, z)])
    s2, e2, _ = paint(ps, prow, lo, hi)
    floor = inside & (raster(s2, e2) == 0)

    # --- obstacles: footprints inflated by a disk of `radius` (rounded rectangles) ------------------
    ob, on = np.nonzero(valid)
    if len(ob):
        cx, cz = t[ob, on, 0], t[ob, on, 2]
        hx, hz = np.maximum(h[ob, on, 0], 0), np.maximum(h[ob, on, 2], 0)
        c, s = np.cos(y[ob, on]), np.sin(y[ob, on])
        ext_z = np.abs(s) * hx + np.abs(c) * hz + radius
        z0 = origins[ob, 1]
        first = np.ceil((cz - ext_z - z0) / cell - 0.5).astype(np.int64)
        last = np.floor((cz + ext_z - z0) / cell - 0.5).astype(np.int64)
        first = np.clip(first, 0, None)
        last = np.minimum(last, shapes[ob, 0] - 1)
        k, orow = _ragged_rows(first, last - first + 1)
        zr = z0[k] + (orow + 0.5) * cell
        # local x axis in the world is (c, -s); corners from box_corners_xz
        corners = box_corners_xz(np.stack([cx, cz], 1), np.stack([hx, hz], 1), y[ob, on])  # (K, 4, 2)
        pieces = [_rect_row_interval(cx[k], cz[k], c[k], -s[k], hx[k] + radius, hz[k], zr),
                  _rect_row_interval(cx[k], cz[k], c[k], -s[k], hx[k], hz[k] + radius, zr)]
        pieces += [_disk_row_interval(corners[k, q, 0], corners[k, q, 1], radius, zr) for q in range(4)]
        lo, hi = _union(pieces)
        s3, e3, keep = paint(ob[k], orow, lo, hi)
        occupied = raster(s3, e3) > 0
    else:
        occupied = np.zeros((HA, WA), dtype=bool)
        s3 = e3 = np.zeros(0, dtype=np.int64)
        k = keep = np.zeros(0, dtype=np.int64)

    free = floor & ~occupied
    labels, n_labels = ndimage.label(free)
    scene_atlas = np.full((HA, WA), -1, dtype=np.int64)
    for b in range(B):
        (oy, ox), (hh, ww) = offsets[b], shapes[b]
        scene_atlas[oy:oy + hh, ox:ox + ww] = b
    flat_labels = labels.ravel()
    sizes = np.bincount(flat_labels, minlength=n_labels + 1)
    label_scene = np.full(n_labels + 1, -1, dtype=np.int64)
    label_scene[flat_labels] = scene_atlas.ravel()
    comp_scene = label_scene[1:]
    regions = np.bincount(comp_scene, minlength=B) if n_labels else np.zeros(B, dtype=np.int64)
    largest_cells = np.zeros(B, dtype=np.int64)
    largest_label = np.zeros(B, dtype=np.int64)
    if n_labels:
        order = np.lexsort((-sizes[1:], comp_scene))  # by scene, then size descending
        first_of_scene = np.ones(len(order), dtype=bool)
        first_of_scene[1:] = comp_scene[order][1:] != comp_scene[order][:-1]
        best = order[first_of_scene]
        largest_label[comp_scene[best]] = best + 1
        largest_cells[comp_scene[best]] = sizes[best + 1]
    free_cells = np.bincount(scene_atlas[free], minlength=B)
    floor_cells = np.bincount(scene_atlas[floor], minlength=B)

    reach_out = np.zeros((B, N), dtype=bool)
    if reach and len(ob):
        is_largest = np.zeros(n_labels + 1, dtype=bool)
        is_largest[largest_label[largest_label > 0]] = True
        largest = is_largest[labels]
        near = ndimage.binary_dilation(largest, structure=np.ones((3, 3), dtype=bool))
        prefix = np.zeros((HA, stride), dtype=np.int64)
        prefix[:, 1:] = np.cumsum(near, axis=1)
        flat = prefix.ravel()
        hit = (flat[e3] - flat[s3]) > 0
        obj = k[keep]
        touched = np.bincount(obj[hit], minlength=len(ob)) > 0
        reach_out[ob, on] = touched
    clear = np.full(B, np.nan)
    if clearance:
        dist = ndimage.distance_transform_edt(free) * cell
        sums = np.bincount(scene_atlas[free], weights=dist[free], minlength=B)
        clear = np.where(free_cells > 0, sums / np.maximum(free_cells, 1), 0.0)
    return FreeSpace(cell, radius, origins, shapes, offsets, floor, free, labels, largest_label, floor_cells,
                     free_cells, largest_cells, regions, reach_out, clear)


def as_numpy(x) -> np.ndarray:
    """A tensor (boolean kept, else float64) or array-like as a NumPy array."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu()
        return x.numpy() if x.dtype == torch.bool else x.double().numpy()
    return np.asarray(x)
