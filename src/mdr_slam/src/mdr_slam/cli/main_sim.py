"""``mdr sim``: render a simulated stereo sequence with exact ground truth to a bag.

    mdr sim --scene office|corridor|garage|floor|atrium [--duration SEC] [--laps N] --out DIR
            [--seed 0] [--rate 20] [--distort]
            [--contrast C] [--no-specular] [--noise S] [--save-depth [EVERY]] [--max-range 8]
            [--driver zed|realsense|stereo_image_proc [--compressed jpeg|png]
             [--right-lag MS] [--no-odom] [--odom-drift SCALE YAW_DEG_PER_M] [--odom-rate HZ]]

Without --driver the bag holds mono8 pairs, camera_info, /ground_truth/pose and /tf map ->
ground_truth_camera. With --driver it holds only what that camera driver and a wheeled base record
(mdr_slam.sim.driver; topics, frames and T_base_cam in DIR/driver.yaml); the ground truth stays in
groundtruth.tum, gt_map.ply and scene.yaml.

--duration is the duration of ONE lap (default 30 s; the floor's ~105 m route: its whole length
at 0.9 m/s, slower in turns, about 128 s). --laps N drives a loop trajectory (office, garage,
floor, atrium) N times end to end, each later lap on a slightly different path, so the sequence
lasts N x duration; scene.yaml lists every lap's stamps and frames. A corridor drive is not a
loop: --laps refuses it.
"""
from __future__ import annotations

import sys
import time


def add_parser(subparsers, name: str = "sim", help_text: str = ""):
    from ..sim.scene import SCENES   # the scene names (the simulator package: ~0.07 s)
    p = subparsers.add_parser(
        name, help=help_text, description=help_text + ". Writes DIR/sequence.bag, "
        "groundtruth.tum, gt_map.ply, scene.yaml and optionally gt_depth/%%06d.npz.")
    p.add_argument("--scene", default="office", choices=list(SCENES),
                   help="scene (default office; floor: a 32 x 20 m building floor, corridor "
                        "ring and two rooms, walked along a ~105 m route; atrium: a 14.6 x "
                        "12.4 m hall whose faint walls stay 4-5 m from its loop, textured "
                        "furniture in the middle)")
    p.add_argument("--duration", type=float, default=None,
                   help="seconds of ONE lap (default 30; floor: the whole route at 0.9 m/s, "
                        "slower in turns, ~128 s; a shorter one walks the route's start only)")
    p.add_argument("--laps", type=int, default=1, metavar="N",
                   help="patrol: drive the scene's loop N times end to end, each lap on a "
                        "slightly different path, fresh noise (N x duration seconds; office, "
                        "garage, floor, atrium; default 1)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--seed", type=int, default=0, help="scene/trajectory/noise seed (default 0)")
    p.add_argument("--rate", type=float, default=20.0, help="frame rate, Hz (default 20)")
    p.add_argument("--trajectory", default=None,
                   choices=["loop", "pure_rotation", "loop+pure_rotation", "corner", "route"],
                   help="trajectory kind (default: the scene's: office/garage loop+pure_rotation,"
                        " corridor corner, floor route, atrium loop)")
    p.add_argument("--distort", action="store_true",
                   help="write RAW images with EuRoC-like radial-tangential distortion; "
                        "camera_info D, K, R, P rectify them")
    p.add_argument("--contrast", type=float, default=4.0,
                   help="texture contrast of the large low-texture surfaces, grey levels "
                        "(default 4)")
    p.add_argument("--no-specular", dest="specular", action="store_false",
                   help="no specular light band")
    p.add_argument("--noise", type=float, default=2.0, help="sensor noise sigma, grey levels")
    p.add_argument("--exposure", action="store_true", help="vary the exposure gain per frame")
    p.add_argument("--blur", type=int, default=0, metavar="K",
                   help="motion blur: average K sub-poses per frame (default 0: off)")
    p.add_argument("--save-depth", type=int, nargs="?", const=1, default=0, metavar="EVERY",
                   help="write gt_depth/%%06d.npz every EVERY frames (default every frame when "
                        "given without a value)")
    p.add_argument("--max-range", type=float, default=8.0,
                   help="metres; gt_map keeps surfaces seen within this depth (default 8)")
    p.add_argument("--map-cell", type=float, default=None, metavar="M",
                   help="gt_map sample spacing, metres (default 0.01, floor 0.02; the garage "
                        "hall is ~5M points at 1 cm)")
    p.add_argument("--scale", type=float, default=1.0,
                   help="shrink the 752x480 camera (0.25: 188x120, for quick tests)")
    p.add_argument("--workers", type=int, default=None,
                   help="render processes (default: min(2, CPUs))")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    g = p.add_argument_group(
        "driver-like bags", "record the bag as a real driver on a wheeled base would (no ground "
        "truth in it; DIR/driver.yaml lists topics, frames and T_base_cam)")
    g.add_argument("--driver", default="none",
                   choices=["none", "zed", "realsense", "stereo_image_proc"],
                   help="zed: bgr8 /zed/zed_node/*/image_rect_color; realsense: mono8 "
                        "/camera/infra{1,2}/image_rect_raw; stereo_image_proc: mono8 "
                        "/stereo/*/image_rect with a raw calibration in camera_info "
                        "(default none: the ground-truth bag)")
    g.add_argument("--compressed", choices=["jpeg", "png"], default=None,
                   help="images as sensor_msgs/CompressedImage on <topic>/compressed "
                        "(default: raw Image)")
    g.add_argument("--jpeg-quality", type=int, default=80, metavar="Q",
                   help="jpeg quality with --compressed jpeg (default 80, as "
                        "compressed_image_transport)")
    g.add_argument("--right-lag", type=float, default=None, metavar="MS",
                   help="right image stamps this many ms after the left (default: zed 3, "
                        "others 0)")
    g.add_argument("--odom", dest="odom", action="store_true", default=True,
                   help="wheel odometry on /odom and /tf odom -> base_link (default)")
    g.add_argument("--no-odom", dest="odom", action="store_false", help="no wheel odometry")
    g.add_argument("--odom-drift", type=float, nargs=2, default=[0.02, 1.0],
                   metavar=("SCALE", "YAW_DEG_PER_M"),
                   help="odometry's systematic error: translation scale error and yaw drift in "
                        "degrees per metre travelled (default 0.02 1.0: 2%% long, 1 deg/m "
                        "counter-clockwise)")
    g.add_argument("--odom-rate", type=float, default=50.0, metavar="HZ",
                   help="odometry rate on its own clock (default 50; 0: at the image stamps)")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    # the simulator when the command runs: `mdr --help` imports this module
    from ..sim import generate, generate_driver
    if any(v is not None and v <= 0 for v in (args.duration, args.rate, args.map_cell,
                                               args.scale, args.laps)):
        print("mdr sim: --duration, --rate, --map-cell, --scale and --laps must be positive",
              file=sys.stderr)
        return 2
    last = [time.time()]

    def progress(i, n):
        if not args.quiet and (i == n or time.time() - last[0] > 2.0):
            last[0] = time.time()
            print("  frame %d/%d" % (i, n), file=sys.stderr)

    kwargs = dict(scene=args.scene, duration=args.duration, seed=args.seed,
                  rate=args.rate, distort=args.distort, contrast=args.contrast,
                  specular=args.specular, noise=args.noise, save_depth=args.save_depth,
                  max_range=args.max_range, scale=args.scale, trajectory=args.trajectory,
                  exposure=args.exposure, blur=args.blur, workers=args.workers,
                  map_cell=args.map_cell, progress=progress, laps=args.laps)
    driver = getattr(args, "driver", "none")
    if driver == "none" and (args.compressed or args.right_lag is not None):
        print("mdr sim: --compressed and --right-lag need --driver", file=sys.stderr)
        return 2
    try:
        if driver == "none":
            s = generate(args.out, **kwargs)
        else:
            s = generate_driver(args.out, driver, compressed=args.compressed,
                                jpeg_quality=args.jpeg_quality, right_lag_ms=args.right_lag,
                                odom=args.odom, odom_scale_error=args.odom_drift[0],
                                odom_yaw_drift=args.odom_drift[1], odom_rate=args.odom_rate,
                                **kwargs)
    except ValueError as e:
        print("mdr sim: %s" % e, file=sys.stderr)
        return 2
    t = s["timing"]
    print("%s: %d frames (%s%s, %s) -> %s\n  gt_map %d points; wall %.1f s, render %.1f ms/frame "
          "(median, %d workers)" % (s["scene"], s["n_frames"], s["trajectory"],
                                    " x %d laps of %.1f s" % (len(s["laps"]), s["lap_duration"])
                                    if len(s["laps"]) > 1 else "",
                                    "raw distorted" if args.distort else "rectified",
                                    s["out_dir"], s["n_map_points"], t["wall_s"],
                                    t["render_ms_per_frame_median"], t["workers"]))
    if driver != "none":
        d = s["driver"]
        print("  driver %s (%s images): %s, %s; right lag %g ms; odometry %s\n  %s" % (
            driver, d["compressed_format"] or "raw", d["bag_topics"]["left_image"],
            d["bag_topics"]["right_image"], d["right_lag_ms"],
            "on /odom" if d["odometry"]["enabled"] else "off", s["driver_yaml"]))
    return 0
