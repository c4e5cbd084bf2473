"""``mdr mesh``: fuse a saved map into a TSDF volume and write a triangle mesh (paper Fig. 8a).

    mdr mesh output/map.ply -o output/mesh.ply                      # automatic views
    mdr mesh output/map.ply -o mesh.ply --trajectory output/traj.tum --width 752 --height 480 \
        --fx 458.6 --fy 457.3 --cx 367.2 --cy 248.4                 # the run's camera poses

The map's points are rendered into depth images from each viewpoint (z-buffer splatting) and fused
with Open3D's ScalableTSDFVolume (see mdr_slam.fusion.mesh).
"""
from __future__ import annotations

import sys

import numpy as np

from ..io import read_cloud


def add_parser(subparsers, name="mesh", help_text=""):
    p = subparsers.add_parser(name, help=help_text, description=__doc__.split("\n\n")[0])
    p.add_argument("map", help="map file (PLY or PCD written by the fusion node / mdr run)")
    p.add_argument("-o", "--output", required=True, help="mesh file to write (.ply)")
    p.add_argument("--trajectory", help="camera poses to render from (TUM, KITTI or EuRoC); "
                   "default: automatic views inside and around the map")
    p.add_argument("--voxel", type=float, default=0.02, help="TSDF voxel length (m), default 0.02")
    p.add_argument("--sdf-trunc", type=float, default=0.0, help="TSDF truncation (m), default 4 voxels")
    p.add_argument("--point-size", type=float, default=0.0,
                   help="splat size of a map point (m), default the TSDF voxel")
    p.add_argument("--min-confidence", type=int, default=0, help="use points with at least this confidence")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--fx", type=float, default=0.0, help="focal length (px); default a 90 deg view")
    p.add_argument("--fy", type=float, default=0.0)
    p.add_argument("--cx", type=float, default=0.0)
    p.add_argument("--cy", type=float, default=0.0)
    p.add_argument("--depth-trunc", type=float, default=8.0, help="ignore rendered depth beyond (m)")
    p.add_argument("--up-axis", default="z", help="map up axis for automatic views (z, -y, ...)")
    p.add_argument("--min-view-distance", type=float, default=0.2,
                   help="trajectory poses closer than this (m, and 10 deg) to the last used are skipped")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    # fusion when the command runs: `mdr --help` imports this module
    from ..fusion.mesh import default_K, mesh_from_map, views_from_trajectory, write_mesh
    cloud = read_cloud(args.map)
    if not len(cloud.get("x", [])):
        print("mdr mesh: %s has no points" % args.map, file=sys.stderr)
        return 1
    K = default_K(args.width, args.height)
    if args.fx > 0:
        K = np.array([[args.fx, 0, args.cx or (args.width - 1) / 2.0],
                      [0, args.fy or args.fx, args.cy or (args.height - 1) / 2.0], [0, 0, 1.0]])
    views = None
    if args.trajectory:
        views = views_from_trajectory(args.trajectory, args.min_view_distance)
    mesh, n_views = mesh_from_map(cloud, views, K, args.width, args.height, args.voxel,
                                  args.point_size or None, args.min_confidence, args.up_axis,
                                  args.depth_trunc, args.sdf_trunc or None)
    if len(mesh.triangles) == 0:
        print("mdr mesh: the TSDF produced no surface (check the views / --up-axis)", file=sys.stderr)
        return 1
    nv, nt = write_mesh(args.output, mesh)
    print("mdr mesh: %d views, %d vertices, %d triangles -> %s" % (n_views, nv, nt, args.output))
    return 0
