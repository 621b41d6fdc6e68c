"""rosbag2 recordings with MCAP storage: container reading (on the ``mcap`` library)
and writing, columnar CDR decoding, and the recording API."""
