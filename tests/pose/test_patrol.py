"""A patrol: the same room driven lap after lap (the simulator's office loop, a slightly different
path and fresh sensor noise each lap, half resolution). The sparse map must follow the area, not
the time: after the first lap the keyframes, map points, loop closures and the loop detector's
database stay where they were, and every frame is tracked."""
import numpy as np
import pytest

from mdr_slam.pose import System, TrackerConfig

LAPS = 3
LAP_S = 20.0
RATE = 10.0


@pytest.fixture(scope="module")
def patrol():
    """Per lap: keyframes alive, keyframes created, map point slots used, loops closed, global
    BAs run, BoW database entries, kept loop images, frames tracked; and the ATE of each lap."""
    from mdr_slam.pose.evaluate import ate_rmse
    from mdr_slam.io import Trajectory
    from mdr_slam.pipeline import load_params
    from mdr_slam.sim.render import Simulator, sim_camera
    from mdr_slam.sim.scene import make_scene
    from mdr_slam.sim.trajectory import make_trajectory
    scene = make_scene("office", seed=2)
    cam = sim_camera(scale=0.5)
    stamps, poses = make_trajectory(scene, LAP_S, RATE, seed=2, scene=scene, laps=LAPS)
    sim = Simulator(scene, cam, seed=2, noise=2.0)
    p = load_params("pose")
    p.update(n_features=1000)
    s = System(cam, config=TrackerConfig.pick(p), threads=False)
    n_lap = int(round(LAP_S * RATE))
    laps = []
    tracked = 0
    for i, (t, T) in enumerate(zip(stamps, poses)):
        im = sim.render(T, index=i, depth=False)
        tracked += s.track(float(t), im["left"], im["right"]).state in ("OK", "RELOCALIZED")
        if (i + 1) % n_lap == 0:
            mp, lc = s.map, s.loop_closing
            laps.append(dict(alive=len(mp.good_keyframes()), created=mp.next_kf_id,
                             slots=mp.n, points=mp.n_points, loops=mp.n_loop_closures,
                             gba=len(lc.global_ba_runs), db=len(lc.db.bows),
                             images=len(lc.images), tracked=tracked))
            tracked = 0
    traj = s.trajectory()
    s.shutdown()
    gt = Trajectory.from_matrices(stamps, poses)
    ts = traj.stamps
    for k, lap in enumerate(laps):
        sel = (ts >= stamps[k * n_lap]) & (ts <= stamps[(k + 1) * n_lap - 1])
        lap["ate"] = ate_rmse(Trajectory.from_matrices(ts[sel], traj.matrices()[sel]), gt)
    return laps


def test_patrol_is_tracked_every_lap(patrol):
    n_lap = int(round(LAP_S * RATE))
    assert all(lap["tracked"] >= n_lap - 2 for lap in patrol), patrol
    # a later lap is tracked in the map of the first: no worse than twice the first lap's ATE
    assert all(lap["ate"] <= max(2.0 * patrol[0]["ate"], 0.05) for lap in patrol), patrol


def test_patrol_keyframes_and_points_follow_the_area(patrol):
    first, last = patrol[0], patrol[-1]
    # measured: keyframes alive 1.0x, 3 keyframes and ~2 % more point slots over two more laps
    assert last["alive"] <= 1.15 * first["alive"], patrol
    assert last["created"] - first["created"] <= 0.15 * first["created"], patrol
    assert last["slots"] - first["slots"] <= 0.15 * first["slots"], patrol
    # the loop detector keeps only live keyframes
    assert last["db"] <= last["alive"] + 20 and last["images"] <= last["alive"] + 20, patrol


def test_patrol_does_not_close_the_same_place_again_every_lap(patrol):
    later = [b["loops"] - a["loops"] for a, b in zip(patrol, patrol[1:])]
    assert all(n <= 1 for n in later), patrol
    assert patrol[-1]["gba"] - patrol[0]["gba"] <= LAPS - 1, patrol
