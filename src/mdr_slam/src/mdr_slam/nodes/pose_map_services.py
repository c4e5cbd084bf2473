"""The pose node's map files and services (a mixin of OrbNode): the map folder to start from
(``load_map``, or the autosave of a pose node of this ROS session that died), autosave, the
``~save_map``, ``~load_map`` and ``~reset`` services, and ``/initialpose`` (rviz's 2D Pose
Estimate). orb_slam_2_ros's ``load_map``/``save_map`` and RTAB-Map's database reuse serve the same.
"""
from __future__ import annotations

import os
import threading

import numpy as np
import rospy
from geometry_msgs.msg import PoseWithCovarianceStamped
from mdr_slam_msgs.srv import LoadMap, LoadMapResponse, SaveMap, SaveMapResponse
from std_srvs.srv import Trigger, TriggerResponse

from ..conversions import ConversionError, pose_to_matrix
from ..io.atomic import remove_stale_temporaries
from ..io.map_dir import (ROTATE_KEEP, MapPathError, after_rotation, check_folder_sessions,
                          default_map_dir, find_session, folder_lock, folder_sessions, map_files,
                          next_session_id, resolve_map_path, session_folder)
from ..pose import make_system
from ..pose.map_io import PoseMapError, check_pose_map, load_pose_map, save_pose_map
from .common import RunMarker, base_session

__all__ = ["PoseMapServices"]


class PoseMapServices:
    """Needs of the node: ``p`` (PoseNodeConfig), ``lock``, ``system``, ``camera``,
    ``tracker_cfg``, ``relay``, ``warn``, ``kf_poses``, ``T_map_odom``."""

    def _init_map_files(self) -> None:
        """The map folder to start from (``load_map``, or the autosave of a node of this session
        that died), the autosave folder and its marker, and the map services."""
        p = self.p
        self.map_dir = os.path.expanduser(p.map_dir or default_map_dir())
        # parameters are the operator's (launch file); only service paths are confined
        self.autosave_folder = resolve_map_path(p.map_path, self.map_dir, allow_outside=True)
        self.start_map = resolve_map_path(p.load_map, self.map_dir, True) if p.load_map else ""
        self.marker = RunMarker(os.path.join(self.autosave_folder, "pose_node.running"), "pose_node")
        # the mapping session the files are written in (mdr_slam.io.map_dir): the launch's, a
        # loaded map's, or (respawned) the dead node's, whose autosave it resumes
        self.session = base_session(p.session_id)
        if self.start_map:
            self._check_folder(self.start_map)
            self.session = folder_sessions(self.start_map).get("pose") or self.session
        if p.resume and self.marker.crashed_before(map_files(self.autosave_folder)["pose"]):
            self.session = self.marker.session() or \
                folder_sessions(self.autosave_folder).get("pose") or self.session
            self.start_map = find_session(self.autosave_folder, self.session, "pose") or \
                self.autosave_folder
            rospy.logwarn("pose_node: the previous pose node of this session did not shut down "
                          "cleanly: resuming its autosave %s and relocalizing in it",
                          self.start_map)
        # localization never changes a map: nothing to autosave
        self.autosaving = p.autosave and not (p.localization and self.start_map)
        if self.autosaving:
            self.marker.write(self.session)
            remove_stale_temporaries(map_files(self.autosave_folder)["pose"])
        self.relocalized_at = None
        self.map_load_error = ""
        self.save_lock = threading.Lock()
        # rviz's 2D Pose Estimate: where the robot is, when relocalization cannot tell
        self.sub_initialpose = rospy.Subscriber("initialpose", PoseWithCovarianceStamped,
                                                self.on_initialpose, queue_size=1)
        self.map_srvs = [rospy.Service("~save_map", SaveMap, self.on_save_map),
                         rospy.Service("~load_map", LoadMap, self.on_load_map),
                         rospy.Service("~reset", Trigger, self.on_reset)]
        self.autosave_timer = None
        if self.autosaving and p.autosave_period > 0:
            self.autosave_timer = rospy.Timer(rospy.Duration(p.autosave_period), self.on_autosave,
                                              reset=True)

    def _load_start_map(self, system) -> bool:
        """Load ``start_map`` into a new ``system`` (relocalized by the next frames); a bad map
        is logged, its reason kept in ``map_load_error``, and the system starts empty."""
        if not self.start_map:
            return False
        path = map_files(self.start_map)["pose"]
        try:
            info = load_pose_map(system, path)
        except PoseMapError as e:
            self.map_load_error = str(e)   # ~load_map's caller gets the reason, not only the log
            rospy.logerr("pose_node: could not load the sparse map: %s (%s)", e,
                         "starting a new map" if system is self.system
                         else "the current map is kept")
            return False
        rospy.loginfo("pose_node: loaded %s: %d keyframes, %d map points (%.1f MB) in %.2f s; "
                      "relocalizing", path, info["keyframes"], info["points"],
                      info["bytes"] / 1e6, info["seconds"])
        if self.p.localization:
            system.localization = True
            rospy.loginfo("pose_node: localization mode: no new keyframes, the map is not changed")
        return True

    def _save_map(self, folder: str, system=None):
        """The sparse map of ``system`` (default: the current one) into ``folder``, atomically:
        the saved summary. Not called with ``self.lock`` held unless ``system`` is given."""
        if system is None:
            with self.lock:
                system = self.system
        if system is None or getattr(system, "map", None) is None:
            raise PoseMapError("no map to save (nothing tracked yet, or a backend without one)")
        if not system.map.keyframes:
            raise PoseMapError("nothing mapped yet")
        with self.save_lock:
            os.makedirs(folder, exist_ok=True)
            return save_pose_map(system, map_files(folder)["pose"], session_id=self.session)

    def _autosave(self, system=None):
        """The sparse map into the autosave folder of its session (rotating the folder when
        another session's maps are there: mdr_slam.io.map_dir.session_folder): (folder, summary,
        whether the folder was rotated)."""
        if system is None:   # lock order: self.lock, then the folder's (as on_reset)
            with self.lock:
                system = self.system
        with folder_lock(self.autosave_folder):
            target, rotated = session_folder(self.autosave_folder, self.session, "pose")
            if rotated:
                rospy.loginfo("pose_node: %s held another session's maps: moved to %s.1 (%d "
                              "generations kept)", self.autosave_folder, self.autosave_folder,
                              ROTATE_KEEP)
            return target, self._save_map(target, system), rotated

    def _keep_before_clear(self, why: str):
        """Before a reset or a load replaces the map: save it (the autosave of its session, so a
        mistaken reset loses nothing; mdr_slam.io.map_dir): (note for the reply, rotated)."""
        system = self.system
        if not self.autosaving or getattr(system, "map", None) is None or \
                not system.map.keyframes:
            return "", False
        try:
            target, info, rotated = self._autosave(system)
        except (PoseMapError, IOError, OSError, ValueError) as e:
            rospy.logerr("pose_node: could not keep the map before the %s: %s", why, e)
            return "; the map before it could not be kept: %s" % e, False
        rospy.loginfo("pose_node: %s: the map before it (%d keyframes, session %s) is kept in %s",
                      why, info["keyframes"], self.session, target)
        return "; the map before it is kept in %s" % target, rotated

    def _new_session(self, session: str = "") -> None:
        """A new map begins: its files carry a new session id (``session``, else the next one)."""
        self.session = session or next_session_id(self.session)
        if self.autosaving:
            self.marker.write(self.session)

    def _check_folder(self, folder: str) -> str:
        """A warning when the folder's dense and sparse maps are of different sessions."""
        ok, note = check_folder_sessions(folder)
        if note:
            (rospy.loginfo if ok else rospy.logwarn)("pose_node: %s", note)
        return note

    def on_autosave(self, _event=None) -> None:
        try:
            self._autosave()
        except PoseMapError:
            pass   # nothing mapped yet
        except (IOError, OSError, ValueError) as e:
            self.warn("autosave", "autosave to %s failed: %s" % (self.autosave_folder, e),
                      level="err")

    def _service_folder(self, path: str) -> str:
        return resolve_map_path(path or self.p.map_path, self.map_dir, self.p.allow_any_map_path)

    def on_save_map(self, req):
        try:
            folder = self._service_folder(req.path)
            info = self._save_map(folder)
        except (MapPathError, PoseMapError, IOError, OSError, ValueError) as e:
            return SaveMapResponse(False, str(e), req.path, 0)
        return SaveMapResponse(True, "saved %d keyframes" % info["keyframes"],
                               map_files(folder)["pose"], info["points"])

    def on_load_map(self, req):
        """Start over from a saved map (the next frames relocalize in it)."""
        try:
            folder = self._service_folder(req.path)
        except MapPathError as e:
            return LoadMapResponse(False, str(e), 0)
        if not os.path.isfile(map_files(folder)["pose"]):
            return LoadMapResponse(False, "no sparse map in %s" % folder, 0)
        # only the sparse map is loaded here: a folder whose parts disagree loads with a warning
        # (the fusion node's load_map, which loads both, refuses it)
        note = self._check_folder(folder)
        note = "; warning: " + note if note else ""
        if self.camera is None:   # loaded with the first frame: check the file now
            try:
                check_pose_map(map_files(folder)["pose"])
            except PoseMapError as e:
                return LoadMapResponse(False, "could not load %s: %s" % (folder, e), 0)
        with self.lock:
            kept, rotated = self._keep_before_clear("load_map")
            if rotated:   # the folder asked for was a generation of the autosave: it moved
                folder = after_rotation(folder, self.autosave_folder, ROTATE_KEEP)
            old, self.start_map = self.start_map, folder
            system = None
            if self.camera is not None:
                args = dict(threads=bool(self.p.threads), T_map_cam0=self.relay.T_base_cam)
                system = make_system(self.camera, self.tracker_cfg, **args)
                if not self._load_start_map(system):
                    system.shutdown()
                    self.start_map = old
                    return LoadMapResponse(False, "could not load %s: %s"
                                           % (folder, self.map_load_error), 0)
            if self.system is not None:
                self.system.shutdown()
            self.system = system          # None: the map is loaded with the first frame
            self.kf_poses = {}
            self.relocalized_at = None
            # the loaded map's session goes on (the fusion node, loading the folder too, agrees)
            self._new_session(folder_sessions(folder).get("pose") or "")
        n = 0 if system is None else int(np.count_nonzero(~system.map.mp_bad[: system.map.n]))
        return LoadMapResponse(True, "loaded %s; relocalizing%s%s" % (folder, kept, note), n)

    def on_initialpose(self, msg) -> None:
        """A base pose in the map frame (rviz's 2D Pose Estimate), tried on the next frame while
        tracking is LOST, before relocalization by bag of words."""
        frame = msg.header.frame_id.lstrip("/")
        if frame and frame != self.p.map_frame:
            self.warn("initialpose", "initial pose in %r, not in %r: ignored"
                      % (frame, self.p.map_frame))
            return
        try:
            T_map_base = pose_to_matrix(msg.pose.pose)
        except ConversionError as e:
            self.warn("initialpose", "bad initial pose: %s" % e)
            return
        T_base_cam = self.relay.T_base_cam if self.relay.T_base_cam is not None else np.eye(4)
        with self.lock:
            if self.system is None or not hasattr(self.system, "set_pose_guess"):
                self.warn("initialpose", "initial pose ignored: no map yet")
                return
            self.system.set_pose_guess(T_map_base @ T_base_cam)
        rospy.loginfo("pose_node: initial pose received; tried when tracking is LOST")

    def on_reset(self, _req):
        """Start a new map with the next frame. The map there was is kept first (autosaved into
        its session's folder; the new session's autosave then rotates ``last`` to ``last.1``)."""
        with self.lock:
            kept, _ = self._keep_before_clear("reset")
            self._new_session()
            if self.system is not None:
                self.system.shutdown()
            self.system = None
            self.start_map = ""
            self.kf_poses = {}
            self.T_map_odom = np.eye(4)
            self.relocalized_at = None
        rospy.loginfo("pose_node: reset: a new map (session %s) starts with the next frame",
                      self.session)
        return TriggerResponse(True, "a new map starts with the next frame%s" % kept)

