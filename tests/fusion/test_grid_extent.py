"""The published grid's extent (mdr_slam.fusion.GridExtent, nav.map_products): it grows in whole
lattice steps, never shrinks, holds the camera with a margin and keeps the content cell for cell,
so that move_base's global costmap, which the static layer resizes to every new extent, is rarely
resized and always holds the robot; and the cells under the robot's base are free
(free_footprint)."""
from __future__ import annotations

import numpy as np

from mdr_slam.fusion import GridExtent, occupancy_grid

RES = 0.05


def _corridor(x_end):
    """Two walls 2 m apart up to ``x_end`` (a robot driving east maps them) and the camera 1 m
    behind their end."""
    x = np.arange(0.0, x_end, 0.02)
    z = np.arange(0.1, 1.5, 0.1)
    X, Z = np.meshgrid(x, z)
    pts = np.vstack([np.c_[X.ravel(), np.full(X.size, y), Z.ravel()] for y in (-1.0, 1.0)])
    return pts, np.array([x_end - 1.0, 0.0, 0.8])


def test_extent_grows_in_steps_and_keeps_the_content():
    ext = GridExtent(RES, step=5.0, margin=2.0)
    boxes, tight = [], []
    for x_end in np.arange(1.0, 25.0, 0.25):         # 96 map updates, the map 1 -> 25 m long
        pts, cam = _corridor(x_end)
        g, origin, _ = occupancy_grid(pts, RES, 0.1, 1.5)
        out, o = ext.apply(g, origin, cam[None, :2])
        tight.append((g.shape, origin))
        boxes.append((out.shape, o))
        # content cell for cell at the same place, unknown around it
        r0 = int(round((origin[1] - o[1]) / RES))
        c0 = int(round((origin[0] - o[0]) / RES))
        assert r0 >= 0 and c0 >= 0
        np.testing.assert_array_equal(out[r0:r0 + g.shape[0], c0:c0 + g.shape[1]], g)
        rest = out.copy()
        rest[r0:r0 + g.shape[0], c0:c0 + g.shape[1]] = -1
        assert (rest == -1).all()
        # on the lattice of the step, the camera 2 m or more inside
        assert np.allclose(np.array(o) / 5.0, np.round(np.array(o) / 5.0))
        size = np.array(out.shape) * RES / 5.0
        assert np.allclose(size, np.round(size))
        lo, hi = np.array(o), np.array(o) + RES * np.array(out.shape[::-1])
        assert (cam[:2] - 2.0 >= lo - 1e-9).all() and (cam[:2] + 2.0 <= hi + 1e-9).all()
    changes = sum(a != b for a, b in zip(boxes, boxes[1:]))
    tight_changes = sum(a != b for a, b in zip(tight, tight[1:]))
    print("a corridor mapped 1 -> 25 m in 96 updates: the bounding box changed %d times, the "
          "extent %d times (last %s cells at %s)" % (tight_changes, changes, boxes[-1][0],
                                                      boxes[-1][1]))
    assert tight_changes >= 90
    assert changes <= 6                     # 25 m of growth, 5 m steps
    # never shrinks: a smaller map later (points cleaned) keeps the extent
    pts, cam = _corridor(3.0)
    g, origin, _ = occupancy_grid(pts, RES, 0.1, 1.5)
    out, o = ext.apply(g, origin, cam[None, :2])
    assert (out.shape, o) == boxes[-1]


def _corridor_map():
    """The corridor as a fusion map snapshot (every point confident), map_products' parameters
    and the camera."""
    pts, cam = _corridor(4.0)
    n = len(pts)
    cloud = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "intensity": np.zeros(n),
             "confidence": np.full(n, 5.0)}
    p = {"publish_grid": True, "grid_resolution": RES, "grid_z_min": 0.1, "grid_z_max": 1.5,
         "grid_up_axis": "z", "grid_free_band": 0.3, "display_voxel": 0.0,
         "display_min_confidence": 3, "grid_min_confidence": 3}
    return cloud, p, cam


def test_no_step_is_the_bounding_box():
    pts, cam = _corridor(4.0)
    g, origin, _ = occupancy_grid(pts, RES, 0.1, 1.5)
    out, o = GridExtent(RES, step=0.0, margin=2.0).apply(g, origin, cam[None, :2])
    assert out is g and o == origin


def test_map_products_pads_the_grid_around_the_camera():
    from mdr_slam.nav import map_products
    cloud, p, cam = _corridor_map()
    _, (g, origin, res) = map_products(cloud, p)
    far = np.array([[12.0, 0.0, 0.8]])                # the camera drove on without seeing more
    _, (gp, op, _) = map_products(cloud, p, GridExtent(RES, 5.0, 2.0), far)
    assert res == RES and op == (0.0, -5.0) and gp.shape == (200, 300)    # x 0..15, y -5..5
    assert (gp == 100).sum() == (g == 100).sum() and (gp == 0).sum() == (g == 0).sum()


def test_free_footprint_frees_the_disc_around_the_base_only():
    from mdr_slam.fusion import free_footprint
    g = np.full((40, 60), 100, np.int8)
    g[:5] = -1                                        # unknown rows: free under the base too
    origin = (-1.0, -0.5)
    base = np.array([[0.0, 0.0]])
    freed = free_footprint(g, origin, RES, base, 0.3)
    ys, xs = np.mgrid[0:40, 0:60]
    d = np.hypot(origin[0] + (xs + 0.5) * RES, origin[1] + (ys + 0.5) * RES)
    assert (g[d <= 0.3] == 0).all()
    assert (g[(d > 0.3) & (ys >= 5)] == 100).all() and (g[(d > 0.3) & (ys < 5)] == -1).all()
    assert freed == int(((d <= 0.3) & (ys >= 5)).sum())
    # a base off the grid, NaN, or radius 0 leaves it alone
    h = g.copy()
    assert free_footprint(h, origin, RES, [[20.0, 20.0], [np.nan, 0.0]], 0.3) == 0
    assert free_footprint(h, origin, RES, base, 0.0) == 0 and (h == g).all()


def test_map_products_frees_the_base_footprint_after_padding():
    """A wall under the base (mapped at a wrong pose) is cut where the base stands, in the padded
    grid move_base gets, and nowhere else; without a base (no tf) the grid is unchanged."""
    from mdr_slam.nav import map_products
    cloud, p, cam = _corridor_map()
    p["grid_footprint_radius"] = 0.3
    base = np.array([[2.0, 1.0, 0.0]])                # on the wall at y = 1
    _, (g0, o0, _) = map_products(cloud, p, GridExtent(RES, 5.0, 2.0), cam[None])
    _, (g1, o1, _) = map_products(cloud, p, GridExtent(RES, 5.0, 2.0), cam[None], base)
    assert o0 == o1 and g0.shape == g1.shape
    c = np.floor((base[0, :2] - np.array(o1)) / RES).astype(int)
    assert g0[c[1], c[0]] == 100 and g1[c[1], c[0]] == 0
    changed = np.argwhere(g0 != g1)
    assert len(changed) and (np.hypot(*((changed[:, ::-1] + 0.5) * RES + o1 - base[0, :2]).T)
                             <= 0.3 + 1e-9).all()
    assert ((g0 != g1) <= (g0 == 100) | (g0 == -1)).all()
