"""racecar-hw: the hardware bridge daemon for 1/10-scale autonomous race cars."""

__version__ = "0.1.0"
