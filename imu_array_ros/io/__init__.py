"""Input and output: rosbag2/MCAP recordings, OpenShoe serial captures, atomic writes."""
