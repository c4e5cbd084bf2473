"""The ``atrium`` scene: a hall whose faint walls stay beyond the stereo rig's convergence range
from its default loop, with textured furniture and rugs in the hall for the tracker."""
from __future__ import annotations

import subprocess

import numpy as np
import pytest

from mdr_slam.sim import (LABEL_LOW_TEXTURE, LABEL_TEXTURED, SCENES, Simulator, build_trajectory,
                          make_scene, sim_camera)

SEEDS = (0, 1, 5)


@pytest.fixture(scope="module")
def atriums():
    return {seed: make_scene("atrium", seed=seed) for seed in SEEDS}


def _walls(sc):
    return [r for r in sc.rects if r.name.startswith("atrium_wall")]


def _path(sc, seed):
    tr = build_trajectory(sc, duration=30.0, seed=seed)
    return tr, tr.poses(np.arange(0.0, 30.0, 0.02))[:, :3, 3]


def test_atrium_is_a_scene_with_far_faint_walls(atriums):
    assert "atrium" in SCENES
    for sc in atriums.values():
        lo, hi = sc.bounds
        assert np.all((hi - lo)[:2] >= 10.0) and 3.5 <= hi[2] - lo[2] <= 4.5
        walls = _walls(sc)
        assert len(walls) == 4
        # four faint walls, a few grey levels apart (not one flat grey)
        assert all(w.label == LABEL_LOW_TEXTURE and w.amp == sc.contrast for w in walls)
        bases = [w.base for w in walls]
        assert 1.0 < np.ptp(bases) < 20.0
        # opposite walls at least 10 m apart
        xs = sorted(w.origin[0] for w in walls if abs(w.normal[0]) > 0.5)
        ys = sorted(w.origin[1] for w in walls if abs(w.normal[1]) > 0.5)
        assert xs[1] - xs[0] >= 10.0 and ys[1] - ys[0] >= 10.0
        # only a few small textured panels on the walls (the signs): most of them is weak
        on_wall = [r for r in sc.rects if r.label == LABEL_TEXTURED and abs(r.normal[2]) < 0.5
                   and min(abs(r.origin[0] - lo[0]), abs(r.origin[0] - hi[0]),
                           abs(r.origin[1] - lo[1]), abs(r.origin[1] - hi[1])) < 0.05]
        assert 1 <= len(on_wall) <= 3
        assert sum(r.a * r.b for r in on_wall) < 0.02 * sum(w.a * w.b for w in walls)
        # textured furniture and rugs in the hall
        assert len(sc.params["furniture"]) >= 5
        assert sum(r.name == "rug" for r in sc.rects) >= 4


def test_atrium_loop_keeps_the_walls_far_and_misses_the_furniture(atriums):
    for seed, sc in atriums.items():
        tr, P = _path(sc, seed)
        assert tr.kind == sc.default_trajectory == "loop"
        lo, hi = sc.bounds
        assert np.all(P > lo) and np.all(P < hi)
        wall = np.minimum.reduce([P[:, 0] - lo[0], hi[0] - P[:, 0], P[:, 1] - lo[1],
                                  hi[1] - P[:, 1]])
        assert wall.min() >= 4.0 and wall.max() <= 6.0, (wall.min(), wall.max())
        # horizontal distance to every furniture footprint: the camera never enters a box
        for x0, y0, x1, y1, top in sc.params["furniture"]:
            assert x1 > x0 and y1 > y0 and top > 0
            dx = np.maximum(np.maximum(x0 - P[:, 0], P[:, 0] - x1), 0.0)
            dy = np.maximum(np.maximum(y0 - P[:, 1], P[:, 1] - y1), 0.0)
            assert np.hypot(dx, dy).min() > 1.0, (seed, (x0, y0, x1, y1))
        assert sc.distance_to_surfaces(P[::25]).min() > 1.0


def test_atrium_views_see_far_walls_and_near_texture(atriums):
    """Along the loop, every wall pixel is more than 4 m away (beyond the ~3.5 m the rig
    converges at) and the furniture and rugs fill part of most views, nearer."""
    sc = atriums[0]
    cam = sim_camera(scale=0.25)
    sim = Simulator(sc, cam, noise=0.0)
    tr = build_trajectory(sc, duration=30.0, seed=0)
    wall_ids = np.array([r.name.startswith("atrium_wall") for r in sc.rects] + [False])
    H, W = cam.size[1], cam.size[0]
    v, u = np.mgrid[0:H, 0:W]
    ray = np.sqrt(1.0 + ((u - cam.cx) / cam.fx) ** 2 + ((v - cam.cy) / cam.fy) ** 2)
    textured_views = 0
    for t in np.arange(0.0, 30.0, 2.5):
        f = sim.render(tr.poses([t])[0], hits=True)
        wall = wall_ids[f["pid"]]
        assert wall.mean() > 0.25
        assert (f["depth"][wall] * ray[wall]).min() > 4.0
        tex = f["surface"] == LABEL_TEXTURED
        if tex.mean() > 0.02 and np.median(f["depth"][tex]) < 3.5:
            textured_views += 1
    assert textured_views >= 9          # of 12


def test_atrium_seed_changes_the_layout(atriums):
    a, b = atriums[0], atriums[1]
    assert a.params["furniture"] != b.params["furniture"]
    assert [w.base for w in _walls(a)] != [w.base for w in _walls(b)]
    # the same seed builds the same hall
    again = make_scene("atrium", seed=1)
    assert again.params["furniture"] == b.params["furniture"]
    assert [(r.name, r.base) for r in again.rects] == [(r.name, r.base) for r in b.rects]
    # the trajectory's layout parameters do not depend on the seed (only its phase does)
    for k in ("center", "radii", "height"):
        assert a.params[k] == b.params[k]


def test_mdr_sim_accepts_the_atrium():
    r = subprocess.run(["mdr", "sim", "--help"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "atrium" in r.stdout
