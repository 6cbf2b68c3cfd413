"""The streaming front end shared by the ROS node and the bag tools: :mod:`.adapter` (the
message-level rules, :class:`~mkf_ros.stream.adapter.StreamAdapter`), :mod:`.kernel` (the same
rules compiled, one event loop) and :mod:`.rep145` (the REP-145 output conventions)."""
