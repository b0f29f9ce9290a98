"""The control path and what the daemon reads of the car.

:class:`~racecar_hw.control.path.ControlPath` owns a command's way from arrival to the VESC write;
:class:`~racecar_hw.control.stats.ControlStats` counts its ticks and times its scan path.
"""
