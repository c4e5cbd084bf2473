"""The stereo input of the pose and depth nodes: left/right images as drivers publish them.

- ``left/image`` and ``right/image`` (remap them to the driver's topics) as sensor_msgs/Image, or
  with ``image_transport: compressed`` as sensor_msgs/CompressedImage on ``<topic>/compressed``
  (image_transport's naming: the suffix goes on the resolved, remapped name);
- ``left/camera_info`` and ``right/camera_info``, published before or after their image: a pair
  takes the latest info of each side (the calibration of a camera does not change per frame);
- pairing by :class:`mdr_slam.stereo_sync.StereoSync` (approximate time, ``sync_tolerance``),
  with a throttled warning naming the topics and the stamp offsets when images arrive but no pair
  forms (the counterpart of rtabmap_ros's "did not receive data since 5 seconds").
"""
from __future__ import annotations

import threading
import time
from typing import Callable

from ..stereo_sync import StereoSync

TRANSPORTS = ("raw", "compressed")


def to_mono8(msg):
    """Grey uint8 image of a sensor_msgs/Image or CompressedImage (raises ConversionError)."""
    from ..conversions import compressed_image_to_mono8, image_to_mono8
    if getattr(msg, "_type", "") == "sensor_msgs/CompressedImage":
        return compressed_image_to_mono8(msg)
    return image_to_mono8(msg)


class StereoInput:
    """Subscribes to a stereo pair and calls ``callback(left, right, left_info, right_info)`` for
    each pair (infos None when ``with_info`` is False: a calibration file is used instead)."""

    def __init__(self, node: str, callback: Callable, warn, tolerance: float = 0.0,
                 transport: str = "raw", with_info: bool = True, queue_size: int = 10):
        import rospy
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image
        if transport not in TRANSPORTS:
            raise ValueError("image_transport must be one of %s, got %r" % (TRANSPORTS, transport))
        self.node, self.callback, self.warn = node, callback, warn
        self.with_info = with_info
        self.sync = StereoSync(tolerance, queue_size)
        self.lock = threading.Lock()
        self.info = {"left": None, "right": None}
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
        self.timer = rospy.Timer(rospy.Duration(1.0), self._watch)

    @property
    def left_topic(self) -> str:
        return self.topics["left"]

    def _on_info(self, msg, side: str) -> None:
        self.info[side] = msg

    def _on_image(self, msg, side: str) -> None:
        with self.lock:
            pairs = self.sync.add(side, msg.header.stamp.to_sec(), msg, now=time.monotonic())
            for _tl, left, _tr, right in pairs:
                li, ri = self.info["left"], self.info["right"]
                if self.with_info and (li is None or ri is None):
                    missing = [s for s in ("left", "right") if self.info[s] is None]
                    self.warn("noinfo", "%s: stereo pair at %.3f skipped: no camera_info yet on %s"
                              % (self.node, left.header.stamp.to_sec(),
                                 " and ".join(self.info_topics[s] for s in missing)))
                    continue
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
