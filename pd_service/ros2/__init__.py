"""ROS 2 adapter building blocks: rmw_zenoh key expressions and liveliness tokens, the rmw_zenoh
attachment, CDR messages through the ``rosbags`` typestore, and the conversions between ROS
messages and measurement / command / prediction vectors.

Everything here is pure (no network). The package may import ``pd_service.wire``,
``pd_service.errors`` and ``pd_service.estimation``; nothing of the project imports it. It needs
the ``ros2`` extra (``pip install 'pd-service[ros2]'``: rosbags, xxhash). docs/ros2.md describes
the formats and the sources they were taken from.
"""
