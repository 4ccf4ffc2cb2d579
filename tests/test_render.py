import numpy as np

from iarcs_env.render import ALL_CLASSES, PALETTE, Overlays, image_grid, render_layout
from conftest import L_SHAPE, make_layout

BED = ("double_bed", (1.0, 0.4, 1.0), (0.8, 0.4, 1.0), 0.0)
LAMP = ("pendant_lamp", (1.0, 2.3, 1.0), (0.3, 0.2, 0.3), 0.0)


def _pixel(img, x, z, extent, centre):
    size = img.shape[0]
    col = int((x - centre[0]) * size / (2 * extent) + size / 2)
    row = int((z - centre[1]) * size / (2 * extent) + size / 2)
    return tuple(img[row, col])


def test_objects_are_drawn_in_their_class_colour_where_they_stand():
    lay = make_layout([BED, LAMP], floor=L_SHAPE)
    img = render_layout(lay, size=256, extent=2.5)
    assert img.shape == (256, 256, 3) and img.dtype == np.uint8
    centre = lay.floor.centre
    # the bed's fill (away from its front tick and the lamp outline above it)
    assert _pixel(img, 0.5, 0.4, 2.5, centre) == PALETTE["double_bed"]
    # floor inside the L, background in its notch
    assert _pixel(img, 3.0, 1.0, 2.5, centre) == (222, 222, 222)
    assert _pixel(img, 3.0, 3.0, 2.5, centre) == (255, 255, 255)


def test_palette_is_fixed_and_distinct():
    colours = list(PALETTE.values())
    assert len(set(colours)) == len(colours) == len(ALL_CLASSES) == 34
    assert PALETTE["double_bed"] == (148, 103, 189)


def test_overlays_mark_issues():
    lay = make_layout([BED], floor=L_SHAPE)
    plain = render_layout(lay, size=128)
    marked = render_layout(lay, size=128, overlays=Overlays(colliding=[0]))
    assert (marked == (230, 0, 0)).all(-1).sum() > 50 and not (plain == (230, 0, 0)).all(-1).any()
    sunk = render_layout(lay, size=128, extent=2.5, overlays=Overlays(off_floor=[0]))
    blue = np.argwhere((sunk == (0, 70, 255)).all(-1))  # the footprint's diagonals cross at the bed's centre
    assert len(blue) > 50 and not (plain == (0, 70, 255)).all(-1).any()
    assert np.allclose(blue.mean(0), [(1.0 - 2.0) * 128 / 5 + 64] * 2, atol=3)
    grid = np.zeros((4, 4), bool)
    grid[1, 2] = True  # the cell at x = 1.0, z = 3.0: free floor in the L's upper arm
    cells = np.arange(4) * 0.5
    hatched = render_layout(lay, size=128, extent=2.5, overlays=Overlays(unreachable=(grid, cells, cells + 2.5)))
    orange = np.argwhere((hatched == (255, 140, 0)).all(-1))
    assert len(orange) > 0
    rows, cols = orange.mean(0)
    assert abs(cols - (1.0 - 2.0) * 128 / 5 - 64) < 3 and abs(rows - (3.0 - 2.0) * 128 / 5 - 64) < 3
