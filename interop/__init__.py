"""The robot's data in ROS 2 / Foxglove tools: ROS 2 message definitions and CDR (``ros2``),
API messages as ROS 2 topics (``topics``), MCAP recording (``record``), replay (``replay``) and
the live Foxglove server (``foxglove``, behind ``guard``). Clients of the daemon's API, each in
its own process; optional dependencies in the ``record`` extra (docs/recording.md)."""
