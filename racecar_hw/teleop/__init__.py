"""Teleoperation: arming, the gamepad, the keyboard and the MAVLink ground station link."""
