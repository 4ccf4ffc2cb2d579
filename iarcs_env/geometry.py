"""Batched scene geometry shared by the evaluation metrics and the universal rewards.

Everything here works on whole batches at once: no Python loop over object pairs and no shapely object
per box (a per-pair shapely loop is only the tests' reference).

* :func:`convex_overlap_area` — exact intersection area of many pairs of convex polygons at once: the
  intersection of two convex polygons is the convex hull of (vertices of one inside the other) and (edge
  crossings), so we collect those candidate points with validity masks, sort them by angle about their
  mean and apply the shoelace formula. Torch, any device.
* :func:`box_overlap_volumes` — pairwise overlap volume of oriented 3D boxes (yaw about +y): footprint
  intersection area times vertical overlap, evaluated only on the pairs whose bounding circles and
  height intervals meet and that no separating axis splits. The footprint area is
  :func:`_rect_edge_terms`' edge integral (below), with one box's four edges over the other's rectangle.
* :func:`box_out_of_floor_area` — area of each box footprint outside a (possibly non-convex) floor
  polygon, used by R_out and the boundary reward: ``area(footprint) - area(footprint ∩ floor)``, the
  intersection as a sum of closed-form per-edge integrals in the box's frame over the (box, floor edge)
  pairs of the whole batch (:func:`_rect_edge_terms`). Exact, no triangulation, clipping or sorting.
* :func:`out_of_floor_area` — the same for footprints given as arbitrary convex quads ``(B, N, 4, 2)``:
  ``area(footprint) - sum_t area(footprint ∩ piece_t)`` over a convex decomposition of the floor
  (:func:`convex_overlap_area`). Exact but slower; the library's metrics and rewards use the box version.
* the walkable grid of a batch (free space, reachable objects) is :mod:`iarcs_env.walkable`.

Conventions: y is up, footprints live in the x-z plane, ``R_y = [[c, 0, s], [0, 1, 0], [-s, 0, c]]``, so a
local footprint corner (lx, lz) lands at ``(x + c*lx + s*lz, z - s*lx + c*lz)`` (see ``scene.box_corners_xz``).
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Sequence

import numpy as np
import shapely
import torch

from .floorplan import FloorPlan
from .scene import box_corners_xz, footprint_reach

#: Collision threshold of the metrics (m^3): two ground objects collide when their boxes overlap more.
COLLISION_VOLUME = 1e-6
#: Out-of-bound threshold of the metrics (m^2) and the per-side shrink applied first (m).
OUT_OF_BOUND_AREA = 1e-5
OUT_OF_BOUND_SHRINK = 0.05
#: Walkable grid defaults: cell size and agent radius (m).
WALK_CELL = 0.05
AGENT_RADIUS = 0.3
#: Floor contact (our addition): a ground object stands on the floor when its bottom is within this of y = 0 (m).
FLOOR_CONTACT_TOL = 0.05
#: Wall alignment (our addition): a ground object is aligned when its axes are within this of a wall's (degrees).
ALIGNMENT_TOL_DEG = 10.0



def floor_gaps(translations: torch.Tensor, half_sizes: torch.Tensor, ground: torch.Tensor) -> torch.Tensor:
    """(B, N) distance (m) of each ground object's bottom from the floor (y = 0), above or below it; 0 for
    the other slots. Every ground object of the real 3D-FRONT bedrooms stands on the floor (bottoms within
    0.09 m of it, 99.6% within 0.03 m)."""
    bottoms = translations[..., 1] - half_sizes[..., 1]
    return torch.where(ground, bottoms.abs(), torch.zeros_like(bottoms))


def wall_misalignment(yaws: torch.Tensor, floors: Sequence[FloorPlan], mask: torch.Tensor) -> torch.Tensor:
    """(B, N) angle (degrees, in [0, 45]) between the axes of each object in ``mask`` and the nearest wall
    direction of its floor (any edge of the polygon, taken modulo 90 degrees); 0 for the other slots. An
    object's local x axis points along ``(cos yaw, -sin yaw)`` on the floor, so it is parallel to an edge of
    angle ``a`` (``atan2(dz, dx)``) when ``yaw + a`` is a multiple of 90 degrees."""
    B, N = mask.shape
    walls = torch.zeros(B, N, dtype=torch.float64)
    y = yaws.detach().double().cpu()  # one transfer, not one per scene
    for b, floor in enumerate(floors):
        v = np.asarray(floor.vertices, dtype=np.float64)
        d = np.roll(v, -1, 0) - v
        a = torch.from_numpy(np.arctan2(d[:, 1], d[:, 0]))
        off = torch.remainder(torch.rad2deg(y[b][:, None] + a[None, :]), 90.0)  # (N, edges)
        walls[b] = torch.minimum(off, 90.0 - off).min(1).values
    return torch.where(mask, walls.to(yaws.device, yaws.dtype), torch.zeros_like(yaws))


@contextmanager
def single_thread():
    """Run torch's CPU ops single-threaded for a while (restored afterwards). The tensors here are small
    (thousands of pairs): intra-op threads bring nothing, and on a busy 2-core machine they spin against
    other processes and run tens of times slower. Also usable as a decorator: ``@single_thread()``."""
    before = torch.get_num_threads()
    if before == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


# ------------------------------------------------------------------------------------------------------
# polygons (torch)
# ------------------------------------------------------------------------------------------------------
def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def polygon_area(poly: torch.Tensor) -> torch.Tensor:
    """Signed shoelace area of polygons ``(..., p, 2)`` (positive when counter-clockwise in (x, z))."""
    nxt = poly.roll(-1, dims=-2)
    return 0.5 * _cross(poly, nxt).sum(-1)


def _ccw(poly: torch.Tensor) -> torch.Tensor:
    flip = polygon_area(poly) < 0
    if bool(flip.any()):
        poly = torch.where(flip[..., None, None], poly.flip(-2), poly)
    return poly


@single_thread()
def convex_overlap_area(P: torch.Tensor, Q: torch.Tensor, eps: float = 1e-9) -> torch.Tensor:
    """Exact area of ``P ∩ Q`` for batches of convex polygons ``P (..., p, 2)`` and ``Q (..., q, 2)``.

    Either winding is accepted; repeated vertices (padding) are fine; degenerate polygons (zero area)
    give 0. The intersection is the convex hull of the vertices of each polygon lying in the other (within
    ``eps`` metres) and of all edge-edge crossings: those candidates are sorted by (pseudo-)angle about
    their mean and summed with the shoelace formula. Coordinates are taken relative to P's mean first.
    """
    P, Q = _broadcast_lead(P, Q)
    P, Q = _ccw(P), _ccw(Q)
    ox, oz = P[..., 0].mean(-1, keepdim=True), P[..., 1].mean(-1, keepdim=True)
    px, pz = P[..., 0] - ox, P[..., 1] - oz
    qx, qz = Q[..., 0] - ox, Q[..., 1] - oz
    pdx, pdz = px.roll(-1, -1) - px, pz.roll(-1, -1) - pz
    qdx, qdz = qx.roll(-1, -1) - qx, qz.roll(-1, -1) - qz
    pl = torch.hypot(pdx, pdz)
    ql = torch.hypot(qdx, qdz)
    # r[i, j] = p_i - q_j
    rx = px[..., :, None] - qx[..., None, :]
    rz = pz[..., :, None] - qz[..., None, :]
    # signed distances (> 0 inside): P's vertex i to Q's edge j, Q's vertex j to P's edge i
    d_pq = (qdx[..., None, :] * rz - qdz[..., None, :] * rx) / ql.clamp_min(1e-300)[..., None, :]
    d_qp = (pdz[..., :, None] * rx - pdx[..., :, None] * rz) / pl.clamp_min(1e-300)[..., :, None]
    in_p = (d_pq >= -eps).all(-1)
    in_q = (d_qp >= -eps).all(-2)
    # crossings of P's edge i (p_i + t dp_i) with Q's edge j (q_j + u dq_j)
    den = pdx[..., :, None] * qdz[..., None, :] - pdz[..., :, None] * qdx[..., None, :]
    ok = den.abs() > 1e-12 * (pl[..., :, None] * ql[..., None, :])
    den = torch.where(ok, den, torch.ones_like(den))
    t = (rz * qdx[..., None, :] - rx * qdz[..., None, :]) / den
    u = (rz * pdx[..., :, None] - rx * pdz[..., :, None]) / den
    tol = 1e-12
    ok = ok & (t >= -tol) & (t <= 1 + tol) & (u >= -tol) & (u <= 1 + tol)
    lead = t.shape[:-2]
    X = torch.cat([px, qx, (px[..., :, None] + t * pdx[..., :, None]).reshape(*lead, -1)], -1)
    Z = torch.cat([pz, qz, (pz[..., :, None] + t * pdz[..., :, None]).reshape(*lead, -1)], -1)
    valid = torch.cat([in_p, in_q, ok.reshape(*lead, -1)], -1)
    w = valid.to(X.dtype)
    count = w.sum(-1, keepdim=True)
    X = X - (X * w).sum(-1, keepdim=True) / count.clamp_min(1)
    Z = Z - (Z * w).sum(-1, keepdim=True) / count.clamp_min(1)
    # pseudo-angle in [0, 4), monotone in the polar angle (no atan2)
    ratio = X / (X.abs() + Z.abs()).clamp_min(1e-300)
    ang = torch.where(Z >= 0, 1 - ratio, 3 + ratio).masked_fill(~valid, 10.0)
    order = ang.argsort(-1)
    X, Z, valid = X.gather(-1, order), Z.gather(-1, order), valid.gather(-1, order)
    X = torch.where(valid, X, X[..., :1])  # pad with the first point: no area
    Z = torch.where(valid, Z, Z[..., :1])
    area = 0.5 * (X * Z.roll(-1, -1) - X.roll(-1, -1) * Z).sum(-1).abs()
    degenerate = (polygon_area(P).abs() < 1e-14) | (polygon_area(Q).abs() < 1e-14)
    return torch.where((count[..., 0] >= 3) & ~degenerate, area, torch.zeros_like(area))


def _broadcast_lead(P: torch.Tensor, Q: torch.Tensor):
    lead = torch.broadcast_shapes(P.shape[:-2], Q.shape[:-2])
    return P.expand(*lead, *P.shape[-2:]), Q.expand(*lead, *Q.shape[-2:])


# ------------------------------------------------------------------------------------------------------
# boxes
# ------------------------------------------------------------------------------------------------------
@single_thread()
def footprints(translations: torch.Tensor, half_sizes: torch.Tensor, yaws: torch.Tensor,
               shrink: float = 0.0) -> torch.Tensor:
    """Footprint corners ``(..., 4, 2)`` of boxes, each side moved in by ``shrink`` metres (clamped at 0)."""
    half = half_sizes[..., 0:3:2]
    if shrink:
        half = (half - shrink).clamp_min(0.0)
    return box_corners_xz(translations[..., 0:3:2], half, yaws)


def bounds_overlaps(translations: torch.Tensor, half_sizes: torch.Tensor, yaws: torch.Tensor) -> torch.Tensor:
    """``(B, N, N, 3)`` overlap lengths along x, y and z of each pair of boxes' axis-aligned bounds (the bounds
    of the turned footprints): differentiable, exact for axis-aligned furniture, for the losses that move
    boxes apart. :func:`box_overlap_volumes` is the exact oriented measure the metrics use."""
    return bounds_separations(translations, half_sizes, yaws).clamp_min(0)


def bounds_separations(translations: torch.Tensor, half_sizes: torch.Tensor, yaws: torch.Tensor) -> torch.Tensor:
    """:func:`bounds_overlaps` before clamping: ``(B, N, N, 3)``, positive where the bounds overlap along an axis,
    minus the gap between them (m) where they do not."""
    reach = footprint_reach(half_sizes[..., 0:3:2], torch.cos(yaws), torch.sin(yaws))
    bound = torch.stack([reach[..., 0], half_sizes[..., 1], reach[..., 1]], -1)
    lo, hi = translations - bound, translations + bound
    return torch.minimum(hi[:, :, None], hi[:, None]) - torch.maximum(lo[:, :, None], lo[:, None])


@single_thread()
def box_overlap_volumes(translations: torch.Tensor, half_sizes: torch.Tensor, yaws: torch.Tensor,
                        valid: torch.Tensor) -> torch.Tensor:
    """Pairwise overlap volume (m^3) of oriented boxes: ``(B, N, N)``, symmetric, zero on the diagonal and
    for pairs involving an invalid slot. Computed in float64 on the candidate pairs only (both valid,
    bounding circles in x-z and height intervals overlapping, not separated along a box axis)."""
    B, N = valid.shape
    dev = translations.device
    out = torch.zeros(B, N, N, dtype=torch.float64, device=dev)
    if N < 2:
        return out
    i, j = torch.triu_indices(N, N, 1, device=dev)
    b, k = (valid[:, i] & valid[:, j]).nonzero(as_tuple=True)
    if len(b) == 0:
        return out
    i, j = i[k], j[k]
    y = yaws.double()
    # per slot: x, y, z, hx, hy, hz, cos, sin, bounding radius
    h = half_sizes.double()
    feats = torch.cat([translations.double(), h, torch.cos(y)[..., None], torch.sin(y)[..., None],
                       torch.hypot(h[..., 0], h[..., 2])[..., None]], -1)
    fi, fj = feats[b, i], feats[b, j]  # (K, 9)
    gap2 = (fi[:, 0] - fj[:, 0]) ** 2 + (fi[:, 2] - fj[:, 2]) ** 2
    reach = fi[:, 8] + fj[:, 8]
    yov = (torch.minimum(fi[:, 1] + fi[:, 4], fj[:, 1] + fj[:, 4])
           - torch.maximum(fi[:, 1] - fi[:, 4], fj[:, 1] - fj[:, 4])).clamp_min(0)
    keep = (gap2 < reach * reach) & (yov > 0)
    keep &= ~_separated(fi, fj)
    keep = keep.nonzero(as_tuple=True)[0]
    if len(keep) == 0:
        return out
    b, i, j, yov, fi, fj = b[keep], i[keep], j[keep], yov[keep], fi[keep], fj[keep]
    vol = _rect_overlap_area(fi, fj) * yov
    out[b, i, j] = vol
    out[b, j, i] = vol
    return out


def _corners(f: torch.Tensor) -> torch.Tensor:
    """Footprint corners (K, 4, 2) from packed features (x, y, z, hx, hy, hz, cos, sin, ...)."""
    sx = f.new_tensor([-1.0, 1.0, 1.0, -1.0])
    sz = f.new_tensor([-1.0, -1.0, 1.0, 1.0])
    lx, lz = f[:, 3:4] * sx, f[:, 5:6] * sz
    c, s = f[:, 6:7], f[:, 7:8]
    return torch.stack([f[:, 0:1] + c * lx + s * lz, f[:, 2:3] - s * lx + c * lz], -1)


def _rect_overlap_area(fi: torch.Tensor, fj: torch.Tensor) -> torch.Tensor:
    """Exact footprint intersection areas ``(K,)`` of pairs of boxes from packed features: box j's four
    (counter-clockwise) footprint edges integrated over box i's rectangle (:func:`_rect_edge_terms`), no
    clipping or sorting. A pair where no edge of j enters i is exactly 0 or i's whole area."""
    cj = _corners(fj)  # (K, 4, 2)
    ax, az = cj[..., 0] - fi[:, 0:1], cj[..., 1] - fi[:, 2:3]
    bx, bz = ax.roll(-1, 1), az.roll(-1, 1)
    hx, hz = fi[:, 3:4], fi[:, 5:6]
    term, enters = _rect_edge_terms(fi[:, 6:7], fi[:, 7:8], hx, hz, ax, az, bx, bz)
    inside = term.sum(1)
    area = 4 * fi[:, 3] * fi[:, 5]
    snapped = torch.where(inside > 0.5 * area, area, torch.zeros_like(area))
    return torch.where(enters.any(1), inside.clamp(min=0.0).minimum(area), snapped)


def _separated(fi: torch.Tensor, fj: torch.Tensor) -> torch.Tensor:
    """Separating-axis test of two footprints from packed features: strictly apart along one of the four
    edge normals."""
    c1, s1, c2, s2 = fi[:, 6], fi[:, 7], fj[:, 6], fj[:, 7]
    dx, dz = fj[:, 0] - fi[:, 0], fj[:, 2] - fi[:, 2]
    # axes: local x is (c, -s) in the world, local z is (s, c); cross terms between the two boxes
    cc = (c1 * c2 + s1 * s2).abs()  # |u1.u2| = |v1.v2|
    cs = (c1 * s2 - s1 * c2).abs()  # |u1.v2| = |v1.u2|
    h1x, h1z, h2x, h2z = fi[:, 3], fi[:, 5], fj[:, 3], fj[:, 5]
    d_u1, d_v1 = (c1 * dx - s1 * dz).abs(), (s1 * dx + c1 * dz).abs()
    d_u2, d_v2 = (c2 * dx - s2 * dz).abs(), (s2 * dx + c2 * dz).abs()
    tol = 1e-12

    def apart(d, r):
        return d > r * (1 + tol) + tol

    return (apart(d_u1, h1x + h2x * cc + h2z * cs) | apart(d_v1, h1z + h2x * cs + h2z * cc)
            | apart(d_u2, h2x + h1x * cc + h1z * cs) | apart(d_v2, h2z + h1x * cs + h1z * cc))


# ------------------------------------------------------------------------------------------------------
# floors
# ------------------------------------------------------------------------------------------------------
_PIECE_CACHE: dict[bytes, np.ndarray] = {}


def _signed(poly: np.ndarray) -> float:
    x, z = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(z, -1)) - np.dot(np.roll(x, -1), z))


def _is_convex(poly: np.ndarray) -> bool:
    e = np.roll(poly, -1, 0) - poly
    turn = e[:, 0] * np.roll(e, -1, 0)[:, 1] - e[:, 1] * np.roll(e, -1, 0)[:, 0]
    return bool(np.all(turn >= -1e-12))


def floor_pieces(floor: FloorPlan) -> np.ndarray:
    """Convex counter-clockwise pieces partitioning the floor polygon, ``(T, V, 2)`` (short pieces padded
    by repeating their last vertex), cached per polygon. A convex floor is one piece; otherwise the
    constrained Delaunay triangles are merged greedily while the union stays convex (Hertel-Mehlhorn)."""
    key = floor.vertices.tobytes()
    out = _PIECE_CACHE.get(key)
    if out is not None:
        return out
    v = np.asarray(floor.vertices, dtype=np.float64)
    if _signed(v) < 0:
        v = v[::-1]
    if _is_convex(v):
        pieces = [v]
    else:
        parts = shapely.get_parts(shapely.constrained_delaunay_triangles(floor.polygon))
        tris = shapely.get_coordinates(parts).reshape(len(parts), 4, 2)[:, :3]
        pieces = []
        for tri in tris:
            a = _signed(tri)
            if abs(a) > 1e-14:
                pieces.append(tri if a > 0 else tri[::-1])
        merged = True
        while merged:
            merged = False
            for a in range(len(pieces)):
                for b in range(a + 1, len(pieces)):
                    m = _merge(pieces[a], pieces[b])
                    if m is not None and _is_convex(m):
                        pieces[a] = m
                        del pieces[b]
                        merged = True
                        break
                if merged:
                    break
    width = max(len(p) for p in pieces)
    out = np.stack([np.concatenate([p, np.repeat(p[-1:], width - len(p), 0)]) for p in pieces])
    if len(_PIECE_CACHE) > 20000:
        _PIECE_CACHE.clear()
    _PIECE_CACHE[key] = out
    return out


def _merge(p: np.ndarray, q: np.ndarray, tol: float = 1e-9):
    """Union of two counter-clockwise polygons sharing one edge (p_i -> p_i+1 == q_j+1 -> q_j), or None."""
    n, m = len(p), len(q)
    for i in range(n):
        a, b = p[i], p[(i + 1) % n]
        for j in range(m):
            if np.abs(q[j] - b).max() < tol and np.abs(q[(j + 1) % m] - a).max() < tol:
                # walk p from b around to a, then q from a (q_j+1) around to b (q_j), excluding the shared ends
                p_part = [p[(i + 1 + k) % n] for k in range(n)]  # b ... a
                q_part = [q[(j + 2 + k) % m] for k in range(m - 2)]  # after a, before b
                return np.array(p_part + q_part)
    return None


_BATCH_CACHE: dict = {}


def _batch_pieces(floors: Sequence[FloorPlan], device) -> dict:
    """All convex pieces of a batch's floors, flattened: ``pieces (P, V, 2)``, ``count (B,)`` and
    ``first (B,)`` (index of each floor's first piece), ``ex``/``ez`` edge vectors; cached for the last
    few batches of floor plans (in training the same floors come back)."""
    keys = tuple(f.vertices.tobytes() for f in floors)
    key = (hash(keys), str(device))
    hit = _BATCH_CACHE.get(key)
    if hit is not None and hit["keys"] == keys:
        return hit
    per = [floor_pieces(f) for f in floors]
    V = max(p.shape[1] for p in per)
    arr = np.concatenate([np.concatenate([p, np.repeat(p[:, -1:], V - p.shape[1], 1)], 1) for p in per])
    count = np.array([len(p) for p in per])
    # vertices per piece before the padding (repeated last vertices)
    nv = np.concatenate([np.full(len(p), p.shape[1]) - (np.abs(np.diff(p, axis=1)).sum(-1) == 0).sum(1) for p in per])
    pieces = torch.from_numpy(arr).to(device)
    ex = pieces[..., 0].roll(-1, -1) - pieces[..., 0]
    ez = pieces[..., 1].roll(-1, -1) - pieces[..., 1]
    entry = {"keys": keys, "pieces": pieces, "ex": ex, "ez": ez, "nv": torch.from_numpy(nv).to(device),
             "count": torch.from_numpy(count).to(device),
             "first": torch.from_numpy(np.cumsum(count) - count).to(device),
             "convex": bool((count == 1).all())}
    if len(_BATCH_CACHE) >= 8:
        _BATCH_CACHE.pop(next(iter(_BATCH_CACHE)))
    _BATCH_CACHE[key] = entry
    return entry


@single_thread()
def out_of_floor_area(corners: torch.Tensor, floors: Sequence[FloorPlan], valid: torch.Tensor) -> torch.Tensor:
    """Area (m^2) of each footprint ``corners (B, N, 4, 2)`` lying outside its scene's floor polygon.

    ``area(footprint) - sum over the floor's convex pieces of area(footprint ∩ piece)``, exact up to
    rounding. A footprint whose four corners lie in one convex piece is inside (area 0 outside) without
    clipping; only the others are clipped. ``(B, N)`` float64, 0 for invalid slots.
    """
    corners = corners.double()
    B, N = valid.shape
    dev = corners.device
    result = torch.zeros(B, N, dtype=torch.float64, device=dev)
    b, n = valid.nonzero(as_tuple=True)
    if len(b) == 0:
        return result
    table = _batch_pieces(floors, dev)
    fp = corners[b, n]  # (K, 4, 2)
    K = len(b)
    if table["convex"]:
        obj = torch.arange(K, device=dev)
        piece = table["first"][b]
    else:
        cnt = table["count"][b]
        obj = torch.repeat_interleave(torch.arange(K, device=dev), cnt)
        start = torch.cumsum(cnt, 0) - cnt
        piece = table["first"][b][obj] + torch.arange(len(obj), device=dev) - start[obj]
    q = table["pieces"][piece]  # (P, V, 2)
    ex, ez = table["ex"][piece], table["ez"][piece]
    fk = fp[obj]
    rx = fk[..., 0][:, :, None] - q[..., 0][:, None, :]
    rz = fk[..., 1][:, :, None] - q[..., 1][:, None, :]
    contained = ((ex[:, None, :] * rz - ez[:, None, :] * rx) >= 0).flatten(1).all(-1)  # (P,)
    whole = torch.zeros(K, dtype=torch.bool, device=dev)
    whole[obj[contained]] = True
    out_area = polygon_area(fp).abs()
    exact = (~whole[obj]).nonzero(as_tuple=True)[0]
    if len(exact):
        fe, qe = fk[exact], q[exact]
        if not table["convex"]:  # only the pieces that the footprint's bounding box meets
            meet = ((fe.amin(1) <= qe.amax(1)) & (qe.amin(1) <= fe.amax(1))).all(-1)
            exact, fe, qe = exact[meet], fe[meet], qe[meet]
        width = int(table["nv"][piece[exact]].max()) if len(exact) else 0
        inside = torch.zeros(K, dtype=torch.float64, device=dev)
        if len(exact):
            inside.index_add_(0, obj[exact], convex_overlap_area(fe, qe[:, :width]))
        out_area = (out_area - inside).clamp_min(0.0)
    result[b, n] = out_area.masked_fill(whole, 0.0)
    return result


_EDGE_CACHE: dict = {}


def _batch_floor_edges(floors: Sequence[FloorPlan], device) -> dict:
    """The edges of a batch's floor polygons, oriented counter-clockwise and flattened: ``edges (E, 4)``
    rows ``(ax, az, bx, bz)`` for edge a -> b, with ``count (B,)`` edges per floor and ``first (B,)`` the
    index of each floor's first edge. Cached for the last few batches of floor plans, keyed by the vertices
    (in training the same floors come back), so a warm call costs only building the key."""
    keys = tuple(f.vertices.tobytes() for f in floors)
    key = (hash(keys), str(device))
    hit = _EDGE_CACHE.get(key)
    if hit is not None and hit["keys"] == keys:
        return hit
    polys = []
    for f in floors:
        v = np.asarray(f.vertices, dtype=np.float64)
        polys.append(v[::-1] if _signed(v) < 0 else v)
    edges = np.concatenate([np.concatenate([v, np.roll(v, -1, 0)], 1) for v in polys])
    count = np.array([len(v) for v in polys], dtype=np.int64)
    entry = {"keys": keys, "edges": torch.from_numpy(edges).to(device),
             "count": torch.from_numpy(count).to(device),
             "first": torch.from_numpy(np.cumsum(count) - count).to(device)}
    if len(_EDGE_CACHE) >= 8:
        _EDGE_CACHE.pop(next(iter(_EDGE_CACHE)))
    _EDGE_CACHE[key] = entry
    return entry


def _positive_part_mean(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """``∫_0^1 max(0, p + t (q - p)) dt`` elementwise: the mean of the positive part of a linear function
    with end values ``p`` and ``q``. Written as ``(p+ + q+) / 2`` minus a correction that is nonzero only
    when the signs differ, ``p+ q- + q+ p-`` over ``2 |p - q|`` (no division of nearly equal values and no
    branch: ``|p - q| = |p| + |q|`` whenever the numerator is not 0)."""
    pp, qp = p.clamp_min(0), q.clamp_min(0)
    corr = (pp * (qp - q) + qp * (pp - p)) / (2 * (p - q).abs()).clamp_min(1e-300)
    return 0.5 * (pp + qp) - corr


def _rect_edge_terms(c, s, hx, hz, ax, az, bx, bz):
    """Per edge ``a -> b`` of a polygon, its term of ``area(polygon ∩ R)`` for the rectangle ``R`` of half
    extents ``hx``, ``hz`` centred at the origin with yaw (cos, sin) = (``c``, ``s``), and whether the edge
    enters ``R``'s interior. Coordinates are relative to ``R``'s centre; all arguments broadcast.

    In ``R``'s own frame (the inverse of ``box_corners_xz``) ``R = [-hx, hx] x [-hz, hz]`` and, for a
    counter-clockwise polygon ``P``,

        area(P ∩ R) = - sum over P's edges e of  ∫_{x along e, |x| <= hx} g(z_e(x)) dx,
        g(z) = clamp(z, -hz, hz) + hz = (z + hz)+ - (z - hz)+

    (every vertical line through ``R`` meets ``P`` in intervals bounded below by edges going +x and above
    by edges going -x, and ``g`` measures the part of ``R``'s column below ``z``). The edges are straight,
    so each term is a closed form (:func:`_positive_part_mean`). Exact for any simple polygon, non-convex
    included; no clipping, sorting or triangulation. Polygon edges not entering ``R`` (``enters`` False for
    all of them) mean ``R`` is wholly inside or wholly outside ``P``.
    """
    x0, z0 = c * ax - s * az, s * ax + c * az
    x1, z1 = c * bx - s * bz, s * bx + c * bz
    run, rise = x1 - x0, z1 - z0
    vertical = run == 0
    inv = run / (run * run).clamp_min(1e-300)  # 1 / run, and 0 for vertical edges
    # the part of the edge over [-hx, hx]: its ends' z (za at the left end) and its width
    lo = torch.minimum(torch.maximum(torch.minimum(x0, x1), -hx), hx)
    hi = torch.minimum(torch.maximum(torch.maximum(x0, x1), -hx), hx)
    width = hi - lo
    za = z0 + (lo - x0) * inv * rise
    zb = z0 + ((hi - x0) * inv + vertical) * rise  # a vertical edge's ends: z0, z1
    # ∫ g over the part = width * (mean (z + hz)+ - mean (z - hz)+); edges going -x count positive
    shift = torch.stack(torch.broadcast_tensors(hz, -hz))
    m = _positive_part_mean(za + shift, zb + shift)
    term = -torch.sign(run) * width * (m[0] - m[1])
    over = (width > 0) | (vertical & (x0.abs() < hx))
    enters = over & (torch.maximum(za, zb) > -hz) & (torch.minimum(za, zb) < hz)
    return term, enters


@single_thread()
def box_out_of_floor_area(translations: torch.Tensor, half_sizes: torch.Tensor, yaws: torch.Tensor,
                          floors: Sequence[FloorPlan], valid: torch.Tensor, shrink: float = 0.0) -> torch.Tensor:
    """Area (m^2) of each box footprint (each side moved in by ``shrink`` m, clamped at 0) lying outside its
    scene's floor polygon (any simple polygon, non-convex included): ``(B, N)`` float64, 0 for invalid slots.

    Exact, with no triangulation and no polygon clipping (:func:`_rect_edge_terms`): one vectorised pass
    over the (object, edge of its floor) pairs of the whole batch, flattened (no padding). A footprint that
    no floor edge enters (the usual case) is wholly inside or wholly outside; its result is snapped to
    exactly 0 or to its area.
    """
    B, N = valid.shape
    dev = translations.device
    result = torch.zeros(B, N, dtype=torch.float64, device=dev)
    b, n = valid.nonzero(as_tuple=True)
    K = len(b)
    if K == 0:
        return result
    table = _batch_floor_edges(floors, dev)
    y = yaws[b, n].double()
    t = translations[b, n].double()
    half = half_sizes[b, n].double()
    if shrink:
        half = (half - shrink).clamp_min(0.0)
    # per object: centre x, z, cos, sin, hx, hz
    feats = torch.stack([t[:, 0], t[:, 2], torch.cos(y), torch.sin(y), half[:, 0], half[:, 2]], 1)
    # every (object, edge of the object's floor) pair
    cnt = table["count"][b]
    obj = torch.repeat_interleave(torch.arange(K, device=dev), cnt)
    edge = (table["first"][b] - (torch.cumsum(cnt, 0) - cnt))[obj] + torch.arange(len(obj), device=dev)
    ox, oz, c, s, hx, hz = feats[obj].unbind(1)
    ax, az, bx, bz = table["edges"][edge].unbind(1)
    term, enters = _rect_edge_terms(c, s, hx, hz, ax - ox, az - oz, bx - ox, bz - oz)
    inside = term.new_zeros(K).index_add(0, obj, term)  # differentiable, unlike bincount
    crossed = torch.bincount(obj[enters], minlength=K) > 0
    area = 4 * feats[:, 4] * feats[:, 5]
    snapped = torch.where(inside > 0.5 * area, torch.zeros_like(area), area)
    result[b, n] = torch.where(crossed, torch.minimum((area - inside).clamp_min(0.0), area), snapped)
    return result
