"""mdr_slam.bagio: stereo bags written and read back; pairing, camera_info, ground truth."""
from __future__ import annotations

import numpy as np

from mdr_slam import bagio
from mdr_slam.camera import StereoCamera
from mdr_slam.geometry import make_T, quat_to_R


def test_stereo_bag_roundtrip(tmp_path):
    cam = StereoCamera.from_rectified(64, 48, 50.0, 50.0, 32.0, 24.0, 0.1)
    path = str(tmp_path / "s.bag")
    rng = np.random.default_rng(0)
    imgs = [(rng.integers(0, 255, (48, 64), dtype=np.uint8),
             rng.integers(0, 255, (48, 64), dtype=np.uint8)) for _ in range(4)]
    Ts = [make_T(quat_to_R([0, 0, np.sin(0.05 * i), np.cos(0.05 * i)]), [0.1 * i, 0, 0]) for i in range(4)]
    with bagio.StereoBagWriter(path) as w:
        for i, ((l, r), T) in enumerate(zip(imgs, Ts)):
            w.write_ground_truth(10.0 + 0.05 * i, T)
            w.write_stereo(10.0 + 0.05 * i, l, r, cam)
        # an unpaired left image and a right image of another size: both skipped, with a reason
        w.write_stereo(10.5, imgs[0][0], np.zeros((10, 10), np.uint8))
    skipped = []
    frames = list(bagio.read_stereo_frames(path, on_skip=skipped.append))
    assert [f.index for f in frames] == [0, 1, 2, 3]
    for f, (l, r), T in zip(frames, imgs, Ts):
        np.testing.assert_array_equal(f.left, l)
        np.testing.assert_array_equal(f.right, r)
        np.testing.assert_allclose(f.T_map_cam_gt, T, atol=1e-9)
        assert abs(f.left_info.P[0, 0] - 50.0) < 1e-12
        assert abs(StereoCamera(f.left_info, f.right_info).baseline - 0.1) < 1e-12
    assert any("sizes differ" in s for s in skipped)
    gt = bagio.read_ground_truth(path)
    mid = gt.at(10.025)
    np.testing.assert_allclose(mid[:3, 3], [0.05, 0, 0], atol=1e-9)
    assert gt.at(11.0) is None
    assert len(list(bagio.read_stereo_frames(path, max_frames=2))) == 2
