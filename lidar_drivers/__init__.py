"""Lidar drivers: Hokuyo SCIP 2.0 (serial and Ethernet) and Slamtec RPLIDAR, with fake lidars."""
