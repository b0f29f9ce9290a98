"""ROS message types and serialization: the typestores and the direct CDR / ROS 1 serializers.

One serializer for bags and for live topics: the recorder and the network interfaces both use it.
"""
