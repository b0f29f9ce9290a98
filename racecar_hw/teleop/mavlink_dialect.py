"""The MAVLink 2 dialect the ground-station link speaks and the vehicle it plays.

The car speaks as an ArduPilot Rover: MAV_TYPE_GROUND_ROVER, MAV_AUTOPILOT_ARDUPILOTMEGA, custom
modes numbered as ArduPilot Rover numbers them (MANUAL 0, HOLD 4, GUIDED 15). Every module of the
link imports pymavlink's dialect from here, so ``MAVLINK20`` is set before pymavlink is imported.
"""

from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"  # before pymavlink is imported anywhere: the MAVLink 2 dialects
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from racecar_hw.teleop.mavlink_params import MODE_NAMES, MODES  # noqa: E402, F401 - with the dialect

#: The HEARTBEAT autopilot: QGroundControl picks its ArduPilot Rover plugin, which names ArduPilot
#: Rover's custom modes, only for ARDUPILOTMEGA (src/FirmwarePlugin/APM/APMFirmwarePluginFactory.cc);
#: MAVProxy names them from the vehicle type for any autopilot but PX4 (pymavlink's
#: mavutil.mode_string_v10 and mode_mapping_rover).
AUTOPILOT = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
UINT16_MAX = 65535
INT16_MAX = 32767

__all__ = ["AUTOPILOT", "INT16_MAX", "MODES", "MODE_NAMES", "UINT16_MAX", "mavlink"]
