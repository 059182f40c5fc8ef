"""File formats: rosbag2/MCAP bags, coefficient files, rig YAML."""
