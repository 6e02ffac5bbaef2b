"""The benchmarks (``hilsim bench``), each figure a ratio against a baseline measured in the same run:
the distributed pipeline's step against in-process and bare stepping, and the rover (``bench loop``,
``bench rover``: :mod:`.pipeline`), with the transport floor of a bare Zenoh ring (:mod:`.ring`) and what
the bag costs the recorder (:mod:`.bag`); what each more robot costs (``bench scale``, :mod:`.scale`);
what a realtime recording misses when runs share the machine (``bench loss``, :mod:`.loss`); and the
ROS 2 bridge's DDS writer against rclpy (``bench ros2``, :mod:`.ros2`, with :mod:`.ros2_probe`, the
script the ROS 2 Python runs)."""
