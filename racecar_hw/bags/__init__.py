"""Bag I/O: the recorder (MCAP, sqlite3, ROS 1), the follower, crash recovery, the MCAP appender."""
