"""The tests share one master: a node a test had to kill must not stay registered, or the next
node of its name makes the master shut down whatever process now holds the old node's port."""
from __future__ import annotations

import signal

import pytest

from conftest import forget_nodes, registered_nodes, wait_for

pytestmark = pytest.mark.ros


def test_a_killed_node_is_forgotten_by_the_shared_master(roscore, start_process):
    import rosgraph
    master = rosgraph.Master("/pytest_check", master_uri=roscore)
    talker = start_process(["rostopic", "pub", "-r", "2", "/stale_check", "std_msgs/Empty",
                            "__name:=stale_talker"], "talker")
    assert wait_for(lambda: "/stale_talker" in registered_nodes(roscore), 60, 0.2)
    talker.stop(sig=signal.SIGKILL)
    # killed, it could not unregister: the master still has it
    assert "/stale_talker" in registered_nodes(roscore)
    assert master.lookupNode("/stale_talker")
    forget_nodes(roscore, ["/stale_talker"])
    assert "/stale_talker" not in registered_nodes(roscore)
    with pytest.raises(rosgraph.MasterError):
        master.lookupNode("/stale_talker")
