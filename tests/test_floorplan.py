import numpy as np
import pytest

from iarcs_env import FloorPlan, FloorPlanError
from conftest import L_SHAPE


@pytest.mark.parametrize("winding", [1, -1])
def test_boundary_points_have_unit_inward_normals(winding):
    floor = FloorPlan.from_vertices(np.array(L_SHAPE)[::winding])
    pts = floor.boundary_points(256)
    assert pts.shape == (256, 4)
    np.testing.assert_allclose(np.linalg.norm(pts[:, 2:], axis=1), 1.0, atol=1e-12)
    # a small step along the normal goes inside, a step against it goes outside (away from corners)
    corner_dist = np.linalg.norm(pts[:, None, :2] - floor.vertices[None], axis=2).min(1)
    p = pts[corner_dist > 0.02]
    assert floor.contains(p[:, 0] + 0.01 * p[:, 2], p[:, 1] + 0.01 * p[:, 3]).all()
    assert not floor.contains(p[:, 0] - 0.01 * p[:, 2], p[:, 1] - 0.01 * p[:, 3]).any()
    # evenly spaced along the perimeter (length 16 m for the L shape)
    steps = np.linalg.norm(np.diff(pts[:, :2], axis=0), axis=1)
    assert steps.max() <= 16 / 256 + 1e-9
    assert np.isclose(floor.area, 12.0)


def test_normals_of_a_rectangle_point_to_its_centre():
    floor = FloorPlan.from_vertices([(-2, -1), (2, -1), (2, 1), (-2, 1)])
    pts = floor.boundary_points(64)
    to_centre = -pts[:, :2]
    assert (np.sum(to_centre * pts[:, 2:], axis=1) > 0).all()


def test_rasterize_counts_cells_of_known_area():
    floor = FloorPlan.from_vertices(L_SHAPE)
    grid, xs, zs = floor.rasterize(cell=0.05)
    assert grid.shape == (80, 80)
    assert grid.sum() * 0.05 ** 2 == pytest.approx(12.0)
    # the notch (x > 2, z > 2) is empty, the corner cell (0.025, 0.025) is full
    assert not grid[zs > 2][:, xs > 2].any()
    assert grid[0, 0]


def test_rasterize_on_given_bounds():
    floor = FloorPlan.from_vertices([(0, 0), (1, 0), (1, 1), (0, 1)])
    grid, xs, zs = floor.rasterize(cell=0.5, bounds=(-1, -1, 2, 2))
    assert grid.shape == (6, 6) and grid.sum() == 4


def test_triangulation_round_trip_of_non_convex_floor():
    floor = FloorPlan.from_vertices(L_SHAPE)
    verts, faces = floor.triangulate()
    assert verts.shape[1] == 3 and np.all(verts[:, 1] == 0)
    back = FloorPlan.from_triangles(verts, faces)
    assert back.polygon.symmetric_difference(floor.polygon).area < 1e-9


def test_closing_vertex_and_duplicates_are_dropped():
    floor = FloorPlan.from_vertices([(0, 0), (1, 0), (1, 0), (1, 1), (0, 1), (0, 0)])
    assert len(floor.vertices) == 4


@pytest.mark.parametrize("vertices, message", [
    ([(0, 0), (1, 0)], "at least 3"),
    ([(0, 0), (1, 0), (2, 0)], "zero area"),
    ([(0, 0), (1, 1), (1, 0), (0, 1)], "not simple"),
    ([(0, 0), (1, float("nan")), (1, 1)], "not a finite number"),
    ([(0, 0, 0), (1, 0, 0), (1, 1, 0)], "shape"),
    ("floor", "list of"),
])
def test_bad_polygons_raise_clear_errors(vertices, message):
    with pytest.raises(FloorPlanError, match=message):
        FloorPlan.from_vertices(vertices)
