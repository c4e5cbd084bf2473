"""`mdr bench --navigate` sends each goal through move_base's action interface. move_base can
report a goal SUCCEEDED at once, with the base still far from it (its plan thread's plan for the
previous goal taken for the new one); the bench then sends the goal again, once. An action server
that answers the way move_base does stands in for it here."""
from __future__ import annotations

import threading

import numpy as np
import pytest

pytest.importorskip("actionlib")
pytest.importorskip("move_base_msgs")


class _MoveBase:
    """A MoveBaseAction server: ``stale`` goals (by arrival index) succeed at once without moving
    the base; the others move it onto the goal, then succeed; ``never`` leaves it running."""

    def __init__(self, rospy, ns, stale=(), never=False):
        import actionlib
        from move_base_msgs.msg import MoveBaseAction
        self.rospy, self.stale, self.never = rospy, set(stale), never
        self.base = np.zeros(2)
        self.n_goals = 0
        self.lock = threading.Lock()
        self.server = actionlib.SimpleActionServer(ns, MoveBaseAction, self.execute,
                                                   auto_start=False)
        self.server.start()

    def close(self):
        """Stop the server's (non-daemon) execute thread, which would hold the test process, and
        its status timer, which would publish on a closed topic once rospy shuts down."""
        with self.server.terminate_mutex:
            self.server.need_to_terminate = True
        self.server.execute_thread.join(10.0)
        self.server.action_server.stop()

    def execute(self, goal):
        with self.lock:
            k = self.n_goals
            self.n_goals += 1
        if k in self.stale:
            self.server.set_succeeded()
            return
        while self.never and not self.server.is_preempt_requested():
            self.rospy.sleep(0.05)
        if self.server.is_preempt_requested():
            self.server.set_preempted()
            return
        p = goal.target_pose.pose.position
        self.base = np.array([p.x, p.y])
        self.server.set_succeeded()


@pytest.fixture
def move_base(rospy_client):
    """Makes fake move_base servers; closes them after the test."""
    made = []

    def make(ns, **kw):
        made.append(_MoveBase(rospy_client, ns, **kw))
        return made[-1]
    yield make
    for m in made:
        m.close()


def _goal(x, y):
    from move_base_msgs.msg import MoveBaseGoal
    g = MoveBaseGoal()
    g.target_pose.header.frame_id = "map"
    g.target_pose.pose.position.x, g.target_pose.pose.position.y = x, y
    g.target_pose.pose.orientation.w = 1.0
    return g


def _client(rospy, ns, server):
    """A client of ``server`` whose result subscription is connected: the result topic is not
    latched, so a goal that succeeds at once would otherwise lose its result on a loaded machine
    (and the client would wait for it forever)."""
    import time

    import actionlib
    from move_base_msgs.msg import MoveBaseAction
    client = actionlib.SimpleActionClient(ns, MoveBaseAction)
    assert client.wait_for_server(rospy.Duration(30.0))
    deadline = time.monotonic() + 60.0
    while server.server.action_server.result_pub.get_num_connections() < 1:
        assert time.monotonic() < deadline, "the client never subscribed to %s/result" % ns
        time.sleep(0.05)
    return client


@pytest.mark.parametrize("stale, expect_resent, expect_reached", [
    ((), 0, True),         # move_base reached it: sent once
    ((0,), 1, True),       # the race: SUCCEEDED at once, 2 m away; sent again, then reached
    ((0, 1), 1, False),    # SUCCEEDED at once twice: sent twice only, the miss is reported
])
def test_a_success_far_from_the_goal_sends_it_again_once(rospy_client, move_base, stale,
                                                          expect_resent, expect_reached):
    from actionlib_msgs.msg import GoalStatus
    from mdr_slam.cli.bench_navigate import _drive_to
    ns = "fake_move_base_%d" % len(stale)
    server = move_base(ns, stale=stale)
    client = _client(rospy_client, ns, server)
    target = np.array([2.0, 0.0])
    state, resent = _drive_to(client, _goal(*target), GoalStatus.SUCCEEDED, lambda: False,
                              lambda: float(np.linalg.norm(server.base - target)))
    assert state == GoalStatus.SUCCEEDED
    assert resent == expect_resent
    assert server.n_goals == 1 + expect_resent
    assert (np.linalg.norm(server.base - target) < 1e-6) == expect_reached


def test_an_unknown_base_pose_is_not_taken_for_the_race_and_give_up_cancels(rospy_client,
                                                                            move_base):
    from actionlib_msgs.msg import GoalStatus
    from mdr_slam.cli.bench_navigate import _drive_to
    server = move_base("fake_move_base_unknown", stale=(0,))
    client = _client(rospy_client, "fake_move_base_unknown", server)
    state, resent = _drive_to(client, _goal(2.0, 0.0), GoalStatus.SUCCEEDED, lambda: False,
                              lambda: None)     # no tf map -> base_link: nothing to judge by
    assert (state, resent, server.n_goals) == (GoalStatus.SUCCEEDED, 0, 1)

    server = move_base("fake_move_base_never", never=True)
    client = _client(rospy_client, "fake_move_base_never", server)
    calls = []

    def give_up():
        calls.append(1)
        return len(calls) >= 3

    state, resent = _drive_to(client, _goal(2.0, 0.0), GoalStatus.SUCCEEDED, give_up, lambda: 0.0)
    assert (state, resent) == ("timeout", 0)
    assert client.wait_for_result(rospy_client.Duration(30.0))
    assert client.get_state() == GoalStatus.PREEMPTED
