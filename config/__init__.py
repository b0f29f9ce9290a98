"""Shipped data (configs, scenarios, maps, systemd unit, udev rules); installed as racecar_hw.shipped."""
