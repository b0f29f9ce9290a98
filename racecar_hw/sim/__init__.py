"""The loopback world: occupancy map, car model, lidar ray casting, scenarios."""
