"""The ``mdr`` command line: one short ``main_<command>.py`` per subcommand (evo's shape).

Each ``main_<command>`` module defines ``add_parser(subparsers)`` returning its parser with
``set_defaults(func=run)``; a command whose module is not there yet says so and exits 2.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from .. import __version__

# (command, module, one-line help)
COMMANDS = [
    ("sim", "main_sim", "render a simulated stereo sequence with exact ground truth to a bag"),
    ("import", "main_import", "convert an EuRoC (ASL) or KITTI odometry folder to a bag"),
    ("run", "main_run", "run the pipeline offline on every frame of a bag (deterministic)"),
    ("eval", "main_eval", "metrics: trajectory ATE, map RMSE/completeness, depth errors"),
    ("bench", "main_bench", "benchmarks: live rates, CPU, RSS and the paper's ablation"),
    ("mesh", "main_mesh", "fuse a map or keyframe depth into a TSDF and write a mesh"),
    ("vocab", "main_vocab", "train the bag-of-words ORB vocabulary for loop closure"),
    ("demo", "main_demo", "map the built-in sample sequence: map, report and pictures in output/"),
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mdr", description="MDR-SLAM: modular decoupled stereo dense mapping (ROS 1).")
    parser.add_argument("--version", action="version", version="mdr_slam " + __version__)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module, help_text in COMMANDS:
        try:
            mod = importlib.import_module("." + module, __name__)
        except ModuleNotFoundError as e:
            if e.name != __name__ + "." + module:
                raise
            p = sub.add_parser(name, help=help_text + " [not implemented yet]",
                               description=help_text)
            p.set_defaults(func=_not_implemented(name))
            continue
        mod.add_parser(sub, name, help_text)
    return parser


def mdr_command():
    """argv that runs ``mdr`` with this very interpreter (subcommands that start other subcommands
    use it, so they work without the catkin devel space on PATH too)."""
    return [sys.executable, "-c", "import sys; from mdr_slam.cli import main; sys.exit(main())"]


def _not_implemented(name):
    def run(args):
        print("mdr %s: not implemented yet" % name, file=sys.stderr)
        return 2
    return run


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0 if argv is None and len(sys.argv) == 1 else 2
    return int(args.func(args) or 0)
