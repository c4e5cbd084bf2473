"""Thin rospy shells around the core: parameters, subscriptions, conversions, publishing.

Each module has a ``main()`` that the executables in ``src/mdr_slam/nodes/`` call. No algorithm
lives here: a node converts messages with mdr_slam.conversions, calls the core, and publishes.
"""
