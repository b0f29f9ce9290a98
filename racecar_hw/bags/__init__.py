"""Bag I/O: the recorder (MCAP, sqlite3, ROS 1), the follower, bag info, crash recovery, and the
writers of the storage files (MCAP with the ``mcap`` library, sqlite3, ROS 1) in the real ROS
tools' layout. rosbags reads bags and provides the type definitions; it writes none of them."""
