"""Floor plans: a simple polygon in the x-z plane (non-convex allowed), its boundary samples with inward
normals (the model's floor condition) and its rasterisation to an occupancy grid."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import Polygon


class FloorPlanError(ValueError):
    """A floor polygon that cannot be used: the message says what is wrong and how to fix it."""


#: Physical bounds of what is read as a room (metres): coordinates, and an object's full size along any axis.
MAX_COORDINATE = 1000.0
MAX_SIZE = 50.0


def _clean_vertices(vertices) -> np.ndarray:
    try:
        v = np.asarray(vertices, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise FloorPlanError(f"floor polygon must be a list of [x, z] pairs of numbers ({err})") from None
    if v.ndim != 2 or v.shape[1] != 2:
        raise FloorPlanError(
            f"floor polygon must have shape (M, 2) as [[x, z], ...]; got an array of shape {v.shape}"
        )
    if not np.all(np.isfinite(v)):
        bad = int(np.argwhere(~np.isfinite(v).all(1))[0, 0])
        raise FloorPlanError(f"floor polygon vertex {bad} is not a finite number: {v[bad].tolist()}")
    if np.abs(v).max(initial=0.0) > MAX_COORDINATE:
        bad = int(np.argwhere((np.abs(v) > MAX_COORDINATE).any(1))[0, 0])
        raise FloorPlanError(f"floor polygon vertex {bad} is {v[bad].tolist()}, more than {MAX_COORDINATE:g} m from the "
                             "origin: coordinates are metres")
    if len(v) > 1 and np.allclose(v[0], v[-1]):
        v = v[:-1]  # a closing vertex repeating the first one
    # drop consecutive duplicates
    keep = np.ones(len(v), dtype=bool)
    keep[1:] = np.any(np.abs(np.diff(v, axis=0)) > 1e-9, axis=1)
    v = v[keep]
    if len(v) < 3:
        raise FloorPlanError(f"floor polygon needs at least 3 distinct vertices; got {len(v)}")
    return v


@dataclass(frozen=True)
class FloorPlan:
    """A floor polygon with vertices ``(M, 2)`` as (x, z) in metres, in the order given (either winding).

    Construct it with :meth:`from_vertices`, which validates the polygon.
    """

    vertices: np.ndarray

    @classmethod
    def from_vertices(cls, vertices) -> "FloorPlan":
        v = _clean_vertices(vertices)
        poly = Polygon(v)
        if np.linalg.matrix_rank(v - v[0], tol=1e-9) < 2:
            raise FloorPlanError(f"floor polygon has zero area (its {len(v)} vertices lie on a line): {v.tolist()[:6]}")
        if not poly.is_valid:
            reason = shapely.is_valid_reason(poly)
            raise FloorPlanError(
                f"floor polygon is not simple ({reason}); list its vertices in order around the boundary, "
                "without the edges crossing"
            )
        if poly.area < 1e-6:
            raise FloorPlanError(f"floor polygon has zero area: {v.tolist()[:6]}")
        v.setflags(write=False)
        return cls(v)

    @classmethod
    def from_triangles(cls, vertices, faces) -> "FloorPlan":
        """From a triangle mesh (ATISS ``floor_plan_vertices`` (V, 3) with y up, ``floor_plan_faces``)."""
        verts = np.asarray(vertices, dtype=np.float64)
        faces = np.asarray(faces, dtype=np.int64)
        if verts.ndim != 2 or verts.shape[1] not in (2, 3) or faces.ndim != 2 or faces.shape[1] != 3:
            raise FloorPlanError(
                f"floor mesh needs vertices (V, 3) and faces (F, 3); got {verts.shape} and {faces.shape}"
            )
        if len(faces) == 0 or faces.min() < 0 or faces.max() >= len(verts):
            raise FloorPlanError("floor mesh faces are empty or index vertices that do not exist")
        xz = verts[:, [0, 2]] if verts.shape[1] == 3 else verts
        tris = [Polygon(xz[f]) for f in faces]
        merged = shapely.union_all([t for t in tris if t.area > 1e-12], grid_size=1e-6)
        if merged.geom_type == "MultiPolygon":
            merged = max(merged.geoms, key=lambda g: g.area)
        if merged.is_empty:
            raise FloorPlanError("floor mesh has no area")
        merged = shapely.simplify(merged, 1e-6)
        return cls.from_vertices(np.asarray(merged.exterior.coords))

    # --- geometry -------------------------------------------------------------------------------------
    @property
    def polygon(self) -> Polygon:
        return Polygon(self.vertices)

    @property
    def area(self) -> float:
        return abs(_signed_area(self.vertices))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, zmin, xmax, zmax)."""
        lo, hi = self.vertices.min(0), self.vertices.max(0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    @property
    def centre(self) -> np.ndarray:
        """Centre of the bounding box: the origin of scene coordinates (ATISS ``floor_plan_centroid``)."""
        lo, hi = self.vertices.min(0), self.vertices.max(0)
        return (lo + hi) / 2

    @property
    def is_rectangle(self) -> bool:
        return len(self.vertices) == 4 and abs(self.area - _bbox_area(self.vertices)) < 1e-6

    def translated(self, offset) -> "FloorPlan":
        return FloorPlan.from_vertices(self.vertices + np.asarray(offset, dtype=np.float64))

    def rotated(self, yaw: float) -> "FloorPlan":
        """Rotated about the origin by ``yaw`` about +y (the same R_y as objects)."""
        return FloorPlan.from_vertices(rotate_xz(self.vertices, yaw))

    def contains(self, x, z) -> np.ndarray:
        """Vectorised point-in-polygon test (boundary counts as inside)."""
        return shapely.intersects_xy(self.polygon, np.asarray(x, float), np.asarray(z, float))

    # --- model condition --------------------------------------------------------------------------------
    def boundary_points(self, n: int = 256) -> np.ndarray:
        """``n`` points evenly spaced along the boundary, each with the unit inward normal of its edge.

        Returns ``(n, 4)`` as (x, z, nx, nz), starting at the first vertex, in the vertices' order.
        """
        v = self.vertices
        edges = np.roll(v, -1, axis=0) - v
        lengths = np.linalg.norm(edges, axis=1)
        cum = np.concatenate([[0.0], np.cumsum(lengths)])
        s = np.arange(n) * (cum[-1] / n)
        idx = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(v) - 1)
        frac = (s - cum[idx]) / lengths[idx]
        pts = v[idx] + frac[:, None] * edges[idx]
        d = edges[idx] / lengths[idx][:, None]
        # counter-clockwise in (x, z): the interior is on the left of each edge, (-dz, dx); else the right
        side = 1.0 if _signed_area(v) > 0 else -1.0
        normals = side * np.stack([-d[:, 1], d[:, 0]], axis=1)
        return np.concatenate([pts, normals], axis=1)

    def rasterize(self, cell: float = 0.05, bounds=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Occupancy grid of the floor: True where a cell centre lies inside the polygon.

        Returns ``(grid, xs, zs)`` with ``grid[i, j]`` the cell at z = zs[i], x = xs[j]. ``bounds`` is
        (xmin, zmin, xmax, zmax), defaulting to the polygon's bounding box.
        """
        xmin, zmin, xmax, zmax = self.bounds if bounds is None else bounds
        xs = np.arange(xmin + cell / 2, xmax, cell)
        zs = np.arange(zmin + cell / 2, zmax, cell)
        gx, gz = np.meshgrid(xs, zs)
        grid = shapely.contains_xy(self.polygon, gx, gz)
        return grid, xs, zs

    def triangulate(self) -> tuple[np.ndarray, np.ndarray]:
        """Triangle mesh of the floor (ATISS ``floor_plan_vertices`` (V, 3) with y = 0, faces (F, 3))."""
        tris = shapely.constrained_delaunay_triangles(self.polygon)
        verts, faces, index = [], [], {}
        for tri in tris.geoms:
            face = []
            for x, z in list(tri.exterior.coords)[:3]:
                key = (round(x, 9), round(z, 9))
                if key not in index:
                    index[key] = len(verts)
                    verts.append([x, 0.0, z])
                face.append(index[key])
            faces.append(face)
        return np.asarray(verts, dtype=np.float64), np.asarray(faces, dtype=np.int64)


def rotate_xz(points, yaw: float) -> np.ndarray:
    """Rotate (x, z) points about +y: ``R_y = [[c, 0, s], [0, 1, 0], [-s, 0, c]]``."""
    p = np.asarray(points, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([c * p[..., 0] + s * p[..., 1], -s * p[..., 0] + c * p[..., 1]], axis=-1)


def _signed_area(v: np.ndarray) -> float:
    x, z = v[:, 0], v[:, 1]
    return 0.5 * float(np.dot(x, np.roll(z, -1)) - np.dot(np.roll(x, -1), z))


def _bbox_area(v: np.ndarray) -> float:
    ext = v.max(0) - v.min(0)
    return float(ext[0] * ext[1])
