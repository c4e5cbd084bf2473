"""Built-in stereo simulator with exact ground truth (trajectory, per-pixel depth, surface map).

Indoor scenes that are hard the way the paper's sequences are (large uniform walls, weak texture,
a specular band, corridor cornering, pure rotation), rendered by exact ray casting in numpy::

    from mdr_slam.sim import make_scene, make_trajectory, Simulator, generate
    scene = make_scene("office", contrast=4.0, specular=True, seed=0)
    stamps, Ts = make_trajectory(scene, duration=10.0, rate=20.0)
    frame = Simulator(scene, sim_camera(scale=0.25)).render(Ts[0])   # left, right, depth, surface
    generate("/tmp/office", scene="office", duration=30.0)            # bag + ground truth files
    generate("/tmp/patrol", scene="garage", duration=60.0, laps=5)    # 5 laps of 60 s, one bag
    generate("/tmp/floor", scene="floor")          # the floor's ~105 m route at ~0.9 m/s
    generate_driver("/tmp/zed", "zed", compressed="jpeg", duration=30.0)  # as a ZED robot records
    robot = SimRobot(RobotConfig(scene="office"))  # a diff-drive base: cmd_vel in, pair + odometry out
"""
from __future__ import annotations

from .scene import (LABELS, LABEL_LOW_TEXTURE, LABEL_NONE, LABEL_SPECULAR, LABEL_TEXTURED, SCENES,
                    Rect, Scene, make_scene)
from .trajectory import KINDS, LOOP_KINDS, SimTrajectory, build_trajectory, make_trajectory
from .render import Simulator, sim_camera
from .generate import generate
from .driver import DRIVERS, generate_driver
from .robot import RobotConfig, SimRobot

__all__ = ["make_scene", "make_trajectory", "build_trajectory", "Simulator", "generate",
           "generate_driver", "DRIVERS", "RobotConfig", "SimRobot", "sim_camera", "Scene", "Rect",
           "SimTrajectory", "SCENES", "KINDS", "LOOP_KINDS", "LABELS",
           "LABEL_NONE", "LABEL_LOW_TEXTURE", "LABEL_TEXTURED", "LABEL_SPECULAR"]
