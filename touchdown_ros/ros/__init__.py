"""ROS 2 adapters: the live node and the bag replayer."""
