"""The stereo input of the pose and depth nodes: left/right images as drivers publish them.

- ``left/image`` and ``right/image`` (remap them to the driver's topics) as sensor_msgs/Image, or
  with ``image_transport: compressed`` as sensor_msgs/CompressedImage on ``<topic>/compressed``
  (image_transport's naming: the suffix goes on the resolved, remapped name);
- ``left/camera_info`` and ``right/camera_info``, published before or after their image, or
  only now and then: a pair takes the info stamped as its image when the driver stamps them so
  (waiting for it until the next pair), else the latest one;
- pairing by :class:`mdr_slam.stereo_sync.StereoSync` (approximate time, ``sync_tolerance``),
  with a throttled warning naming the topics and the stamp offsets when images arrive but no pair
  forms (the counterpart of rtabmap_ros's "did not receive data since 5 seconds");
- bounded input (mdr_slam.msg_checks): an image larger than MAX_IMAGE_DIM, or whose size
  disagrees with its side's camera_info, and an absurd camera_info are refused on arrival with
  a throttled warning, before they reach the pairing queues.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Callable

import rospy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from ..msg_checks import camera_info_problem, image_problem
from ..stereo_sync import StereoSync

TRANSPORTS = ("raw", "compressed")


class StereoInput:
    """Subscribes to a stereo pair and calls ``callback(left, right, left_info, right_info)`` for
    each pair (infos None when ``with_info`` is False: a calibration file is used instead)."""

    def __init__(self, node: str, callback: Callable, warn, tolerance: float = 0.0,
                 transport: str = "raw", with_info: bool = True, queue_size: int = 10):
        if transport not in TRANSPORTS:
            raise ValueError("image_transport must be one of %s, got %r" % (TRANSPORTS, transport))
        self.node, self.callback, self.warn = node, callback, warn
        self.with_info = with_info
        self.sync = StereoSync(tolerance, queue_size)
        self.lock = threading.RLock()   # pairs go out in order, one at a time
        self.infos = {"left": deque(maxlen=10), "right": deque(maxlen=10)}   # (stamp, msg)
        self.exact = {"left": False, "right": False}   # the last pair had infos of its stamps
        self._held = None   # a pair waiting for its camera_info
        self.topics = {}
        self.info_topics = {s: rospy.resolve_name(s + "/camera_info") for s in ("left", "right")}
        kind = CompressedImage if transport == "compressed" else Image
        self.subs = []
        for side in ("left", "right"):
            topic = rospy.resolve_name(side + "/image")   # the remapped name, then the suffix
            if transport == "compressed":
                topic += "/compressed"
            self.topics[side] = topic
            self.subs.append(rospy.Subscriber(topic, kind, self._on_image, side, queue_size=2,
                                              buff_size=1 << 24))
            if with_info:
                self.subs.append(rospy.Subscriber(side + "/camera_info", CameraInfo, self._on_info,
                                                  side, queue_size=5))
        self.timer = rospy.Timer(rospy.Duration(1.0), self._watch, reset=True)   # survives a bag loop

    @property
    def left_topic(self) -> str:
        return self.topics["left"]

    def _on_info(self, msg, side: str) -> None:
        why = camera_info_problem(msg)
        if why:
            self.warn("badinfo", "%s: %s camera_info refused: %s" % (self.node, side, why))
            return
        with self.lock:
            self.infos[side].append((msg.header.stamp.to_sec(), msg))
            held, self._held = self._held, None
            if held is not None:   # a pair whose camera_info comes after its images
                self._deliver(*held)

    def _on_image(self, msg, side: str) -> None:
        q = self.infos[side] if self.with_info else ()
        why = image_problem(msg, q[-1][1] if q else None)
        if why:
            self.warn("badimage", "%s: %s image refused: %s" % (self.node, side, why))
            return
        with self.lock:
            pairs = self.sync.add(side, msg.header.stamp.to_sec(), msg, now=time.monotonic())
            for _tl, left, _tr, right in pairs:
                if self._held is not None:   # its info never came: the latest one will do
                    held, self._held = self._held, None
                    self._deliver(*held, wait=False)
                self._deliver(left, right)

    def _info_for(self, side: str, stamp: float):
        """(info stamped as the image, True), else (the latest info, False), else (None, False)."""
        q = self.infos[side]
        for s, m in reversed(q):
            if abs(s - stamp) < 1e-6:
                return m, True
        return (q[-1][1] if q else None), False

    def _deliver(self, left, right, wait: bool = True) -> None:
        if not self.with_info:
            self.callback(left, right, None, None)
            return
        li, l_exact = self._info_for("left", left.header.stamp.to_sec())
        ri, r_exact = self._info_for("right", right.header.stamp.to_sec())
        # a driver that stamps each camera_info as its image publishes it right after the image:
        # wait for it (until the next pair) rather than take the previous frame's
        late = (self.exact["left"] and not l_exact) or (self.exact["right"] and not r_exact)
        missing = li is None or ri is None
        if missing or (late and wait):
            if missing and not wait:
                sides = [s for s, i in (("left", li), ("right", ri)) if i is None]
                self.warn("noinfo", "%s: stereo pair at %.3f skipped: no camera_info yet on %s"
                          % (self.node, left.header.stamp.to_sec(),
                             " and ".join(self.info_topics[s] for s in sides)))
                return
            self._held = (left, right)
            return
        self.exact = {"left": l_exact, "right": r_exact}
        self.callback(left, right, li, ri)

    def _watch(self, _event=None) -> None:
        with self.lock:
            report = self.sync.stall_report(time.monotonic())
        if report:
            self.warn("nosync", "%s: %s on %s and %s (set sync_tolerance if the stamps of a "
                      "pair differ by more)" % (self.node, report, self.topics["left"],
                                                self.topics["right"]))

    def counts(self) -> dict:
        s = self.sync
        return {"pairs": s.pairs, "unpaired_left": s.dropped["left"],
                "unpaired_right": s.dropped["right"]}
