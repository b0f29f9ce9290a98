"""Bag I/O: the recorder (MCAP, sqlite3, ROS 1), the follower, bag info, crash recovery, the MCAP
appender, and rosbags' writers with the real ROS tools' file layout."""
