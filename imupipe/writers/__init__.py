"""Writers: canonical recordings back to standard file formats (MCAP with ROS 2 messages)."""
