"""Helpers shared by the nodes: parameters, throttled warnings, time checks, tf."""
from __future__ import annotations

import os
import re
import time

import numpy as np
import rospy
import rospy.rostime
import tf2_ros
import yaml

from ..config import ConfigError


def get_params(defaults: dict, ns: str = "~") -> dict:
    """Read every key of ``defaults`` from the parameter server (private namespace by default)."""
    return {k: rospy.get_param(ns + k, v) for k, v in defaults.items()}


def read_config(node: str, *configs):
    """The node's private parameters as instances of ``configs`` (Config classes, one per
    component the node drives), each key read from the parameter server with the class's default.
    Private parameters no class names are logged as errors (:func:`unknown_params`); a value of
    the wrong type is logged and its default used, so a typo never stops the node."""
    defaults = {}
    for c in configs:
        defaults.update(c.defaults())
    unknown_params(defaults, node)
    values = get_params(defaults)
    out = []
    for c in configs:
        mine = {k: values[k] for k in c.keys()}
        for k in c.keys():
            try:
                c.from_dict({k: mine[k]})
            except ConfigError as e:
                rospy.logerr("%s: ~%s: %s; using the default %r", node, k, e, defaults[k])
                mine[k] = defaults[k]
        out.append(c.from_dict(mine))
    return out


def unknown_params(known, node: str) -> list:
    """Private parameters of this node that no default names (a typo in a YAML file or on the
    command line would otherwise be ignored in silence): logged as an error, and returned.
    A key whose default is a dict (``elas``) covers its sub-keys."""
    base = rospy.get_name()
    have = set()
    for name in rospy.get_param_names():
        if name.startswith(base + "/"):
            have.add(name[len(base) + 1:].split("/", 1)[0])
    bad = sorted(have - set(known))
    if bad:
        rospy.logerr("%s: unknown parameters %s are not read (typo? see config/%s.yaml)", node,
                     ", ".join("~" + k for k in bad), node.replace("_node", ""))
    return bad


class RunMarker:
    """"Running, not yet saved on a clean exit": a file a node keeps beside its autosave while it
    runs. A node started while an earlier node of the same ROS session (``/run_id``) left its
    marker knows that node died (e.g. respawned by roslaunch) and resumes its autosave."""

    def __init__(self, path: str, node: str):
        self.path = path
        self.node = node
        self.run_id = str(rospy.get_param("/run_id", ""))

    def crashed_before(self, autosave: str) -> bool:
        """An earlier node of this session left the marker, and its autosave ``autosave`` exists."""
        try:
            with open(self.path) as f:
                words = f.read().split()
        except (IOError, OSError):
            return False
        return bool(words) and words[0] == self.run_id and os.path.exists(autosave)

    def session(self) -> str:
        """The mapping session the marker's node was in ("" when it did not say)."""
        try:
            with open(self.path) as f:
                words = f.read().split()
        except (IOError, OSError):
            return ""
        return words[2] if len(words) > 2 else ""

    def write(self, session: str = "") -> bool:
        try:
            d = os.path.dirname(self.path)
            if d and not os.path.isdir(d):
                os.makedirs(d)
            with open(self.path, "w") as f:
                f.write("%s %d %s\n" % (self.run_id, os.getpid(), session or "-"))
            return True
        except (IOError, OSError) as e:
            rospy.logwarn("%s: cannot write %s (%s): no resume after a crash", self.node,
                          self.path, e)
            return False

    def clear(self) -> None:
        """A clean exit: nothing to resume."""
        try:
            os.unlink(self.path)
        except OSError:
            pass


def base_session(param: str = "") -> str:
    """The mapping session a node starts in: its ``~session_id`` parameter (mdr.launch gives both
    nodes one id per launch), else the ROS session's ``/run_id`` (shared by every node of a
    roscore), else a fresh id. A reset moves on to ``next_session_id`` (mdr_slam.io.map_dir)."""
    from ..io.map_dir import new_session_id
    s = str(param or "").strip() or str(rospy.get_param("/run_id", "") or "").strip()
    return "".join(c for c in s if not c.isspace()) or new_session_id()


class Throttled:
    """rospy log calls limited to one per ``period`` seconds per key (logwarn_throttle keys on the
    call site only; here the key is the message kind, so distinct problems are all reported)."""

    def __init__(self, period: float = 5.0):
        self.period = period
        self._last = {}
        self.counts = {}

    def __call__(self, key: str, text: str, level: str = "warn") -> None:
        self.counts[key] = self.counts.get(key, 0) + 1
        now = time.monotonic()
        # throttled per kind and wording (numbers aside): a truncated image does not hide a wrong
        # encoding reported under the same kind a moment later
        slot = key + "|" + re.sub(r"[-+]?[0-9][0-9.eE+-]*", "#", text)[:80]
        if now - self._last.get(slot, -1e9) >= self.period:
            if len(self._last) > 500:   # wordings that never repeat must not grow without bound
                self._last.clear()
            self._last[slot] = now
            n = self.counts[key]
            suffix = " (%d times so far)" % n if n > 1 else ""
            getattr(rospy, "log" + level)("%s%s", text, suffix)


class StampGuard:
    """Detects time going backwards (a looping bag, a restarted clock) and duplicated stamps."""

    def __init__(self):
        self.last = None

    def check(self, t: float) -> str:
        """'ok', 'duplicate' or 'backwards' (after which the guard restarts from ``t``)."""
        if self.last is None or t > self.last:
            self.last = t
            return "ok"
        if t == self.last:
            return "duplicate"
        self.last = t
        return "backwards"


class StampRateLimiter:
    """Keeps at most ``rate`` Hz of a stream, chosen by message stamps (so it follows sim time and
    a bag played faster or slower): an item is due once its stamp reaches ``next_due``, which then
    advances by one period (20 Hz in, 12 Hz out: 3 of every 5 pairs, evenly spread). A stamp more
    than a second before the previous one (a looping bag) starts again. ``rate <= 0``: keep all."""

    def __init__(self, rate: float):
        self.period = 1.0 / float(rate) if float(rate) > 0 else 0.0
        self.next_due = None
        self.last = None

    def skip(self, t: float) -> bool:
        if self.last is not None and t < self.last - 1.0:
            self.next_due = None
        self.last = t
        if self.period <= 0:
            return False
        if self.next_due is not None and t < self.next_due - 0.2 * self.period:
            return True
        nxt = t if self.next_due is None else max(self.next_due, t - self.period)
        self.next_due = nxt + self.period
        return False


class ClockWatch:
    """Detects ROS time itself jumping back (a looping bag, a restarted sim clock): only then is
    an older stamp a new timeline (reset); without it an older stamp is one stale message (skip).
    The first message of a new lap can arrive just before the clock jumps: it is skipped as
    stale and the reset comes with the next one."""

    def __init__(self):
        self.last = -np.inf

    def jumped(self) -> bool:
        now = rospy.Time.now().to_sec()
        j = now < self.last - 1e-3
        self.last = now
        return j


def seconds_ahead_of_clock(stamp: float, max_future: float) -> float:
    """How far ``stamp`` is ahead of the ROS clock, when by more than ``max_future`` s (else 0).

    A message stamped well in the future of the clock belongs to a timeline the clock has left:
    with a looping bag the last messages of a lap (a pose, a cloud, a tf) can be delivered after
    the clock jumped back to the start, under CPU load by up to a second. Used with a pose
    looked up in the new lap, such a message is placed wrongly: tf2 interpolates between the new
    lap's latest pose and the stale one (measured: a cloud of the old lap's end integrated 0.65 m
    and 34 deg off, 15 k stray points at once, under bursty load). Only with a simulated clock
    (``/use_sim_time``), the clock that jumps back: on wall time a stamp ahead of ours is another
    machine's clock skew, not a stale message. ``max_future <= 0`` or a sim clock that has not
    started (before the first /clock): no check.
    """
    if max_future <= 0:
        return 0.0
    if rospy.rostime.is_wallclock():
        return 0.0
    now = rospy.Time.now().to_sec()
    ahead = float(stamp) - now
    return ahead if now > 0 and ahead > max_future else 0.0


def skip_future_stamp(t: float, max_future: float, warn: "Throttled", what: str) -> bool:
    """True (and a throttled warning) when ``t`` is more than ``max_future`` s ahead of the
    clock (:func:`seconds_ahead_of_clock`): the caller drops the message."""
    ahead = seconds_ahead_of_clock(t, max_future)
    if ahead > 0:
        warn("future", "%s stamp %.3f is %.2f s ahead of the clock (from before it jumped "
             "back?); skipped" % (what, t, ahead))
    return ahead > 0


def transform_listener(buffer, max_future: float, warn: "Throttled", node: str, on_transform=None):
    """A ``tf2_ros.TransformListener`` for ``buffer`` that drops transforms stamped more than
    ``max_future`` s ahead of the ROS clock (:func:`seconds_ahead_of_clock`).

    tf2_ros clears its buffer when the clock jumps back, but a transform of the old lap that
    arrives after the jump is stored in the new lap's buffer and stays there for the whole cache
    time; a lookup at a stamp the pose node has not published yet then interpolates towards it
    instead of waiting (and failing cleanly after ``tf_timeout``). Static transforms are kept.
    """

    class _Listener(tf2_ros.TransformListener):
        def callback(self, data):
            reset = getattr(self, "check_for_reset", None)
            if reset is not None:
                reset()
            who = data._connection_header.get("callerid", "default_authority")
            for tr in data.transforms:
                if on_transform is not None:
                    on_transform(tr, who)
                ahead = seconds_ahead_of_clock(tr.header.stamp.to_sec(), max_future)
                if ahead > 0:
                    warn("tffuture", "%s: tf %s <- %s stamped %.3f s ahead of the clock (from "
                         "before it jumped back, or a clock ahead of ours); dropped"
                         % (node, tr.header.frame_id, tr.child_frame_id, ahead))
                    continue
                self.buffer.set_transform(tr, who)

    rospy.logdebug("%s: tf listener drops transforms > %.1f s ahead of the clock", node, max_future)
    return _Listener(buffer)


def frame_root(buffer, frame: str) -> str:
    """The root of ``frame``'s tree in a tf2 buffer (``frame`` itself when it has no parent)."""
    try:
        frames = yaml.safe_load(buffer.all_frames_as_yaml()) or {}
    except Exception:   # noqa: BLE001  (an empty buffer gives "[]")
        return frame
    if not isinstance(frames, dict):
        return frame
    seen = set()
    while frame in frames and frame not in seen:
        seen.add(frame)
        frame = frames[frame].get("parent", frame)
    return frame
