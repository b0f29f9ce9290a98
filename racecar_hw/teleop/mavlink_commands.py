"""The ground station's commands: arming, modes, message and parameter requests, acknowledgements.

COMMAND_LONG / COMMAND_INT ARM_DISARM (400) and DO_SET_MODE (176), and SET_MODE, change the arming
and the mode; REQUEST_AUTOPILOT_CAPABILITIES and REQUEST_MESSAGE are answered with the message
asked for; any other command is acknowledged UNSUPPORTED. Every command gets a COMMAND_ACK.
Parameter requests are answered from a small read-only list (a PARAM_SET gets the unchanged value);
the whole list goes out at the link's next tick (:meth:`Commands.send_due`), once however many
PARAM_REQUEST_LISTs came since the last one, so that a datagram packed with them (any local
process on an unsigned loopback link) cannot multiply the work: one such datagram of 4,679
requests once sent 18,716 PARAM_VALUEs and held the event loop for seconds.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from racecar_hw.teleop.arming import Arming
from racecar_hw.teleop.mavlink_dialect import MODE_NAMES, MODES, mavlink
from racecar_hw.teleop.mavlink_sticks import Sticks
from racecar_hw.teleop.mavlink_telemetry import Telemetry

if TYPE_CHECKING:
    from racecar_hw.teleop.mavlink_params import MavlinkParams

log = logging.getLogger(__name__)

#: The commands this link acts on; any other is acknowledged UNSUPPORTED.
ACTED_ON = frozenset((mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_DO_SET_MODE,
                      mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, mavlink.MAV_CMD_REQUEST_MESSAGE))
#: The float parameters of each command message (COMMAND_INT's x and y are integers).
_FLOAT_PARAMS = {"COMMAND_LONG": tuple(f"param{i}" for i in range(1, 8)),
                 "COMMAND_INT": ("param1", "param2", "param3", "param4", "z")}
#: COMMAND_ACK ``command`` for a SET_MODE message (its message id, as ArduPilot answers).
SET_MODE_ACK = mavlink.MAVLINK_MSG_ID_SET_MODE
FORCE_ARM_MAGIC = 21196


@dataclass(frozen=True)
class ReadOnlyParam:
    """One parameter shown to the ground station (it cannot be set)."""

    name: str
    value: float
    type: int


class Commands:
    """Acts on the ground station's commands addressed to us and acknowledges each; owns the mode.

    ``sticks`` is asked whether the throttle is centred before arming; ``telemetry`` sends what a
    request asks for and the STATUSTEXTs. ``counters`` (the link's): ``commands``, ``acks``.
    """

    def __init__(self, params: MavlinkParams, mav: Any, arming: Arming, sticks: Sticks,
                 telemetry: Telemetry, counters: dict[str, int], clock: Callable[[], int]) -> None:
        self.mav = mav
        self.arming = arming
        self.sticks = sticks
        self.telemetry = telemetry
        self.counters = counters
        self._clock = clock
        self.mode = MODES[params.start_mode]
        #: a PARAM_REQUEST_LIST came since the list last went out
        self.param_list_due = False
        self.parameters = [
            ReadOnlyParam("SYSID_THISMAV", params.system_id, mavlink.MAV_PARAM_TYPE_INT32),
            ReadOnlyParam("FS_GCS_TIMEOUT", params.heartbeat_timeout_s, mavlink.MAV_PARAM_TYPE_REAL32),
            ReadOnlyParam("TELEOP_MAX_SPD", params.max_speed_mps, mavlink.MAV_PARAM_TYPE_REAL32),
            ReadOnlyParam("TELEOP_MAX_STR", params.max_steering_rad, mavlink.MAV_PARAM_TYPE_REAL32),
        ]

    def on_command(self, msg: Any, now: int) -> None:
        """A COMMAND_LONG or COMMAND_INT: act, acknowledge, then send what a request asked for."""
        self.counters["commands"] += 1
        try:
            result = self._command(msg, now)
        except Exception:
            log.exception("MAVLink command %s failed", msg.command)
            result = mavlink.MAV_RESULT_FAILED
        self._ack(msg.command, result, msg)
        self._send_requested(msg, result)

    def on_set_mode(self, msg: Any) -> None:
        """A SET_MODE message: acknowledged with its message id as the command."""
        self.counters["commands"] += 1
        self._ack(SET_MODE_ACK, self.set_mode(msg.custom_mode), msg)

    def on_param_request_list(self) -> None:
        """PARAM_REQUEST_LIST: the whole list goes out at the next :meth:`send_due`."""
        self.param_list_due = True

    def send_due(self) -> None:
        """Called on every tick of the link: the parameter list, once, if it was asked for since
        the last tick (at most ``rate_hz`` lists a second, whatever the requests)."""
        if self.param_list_due:
            self.param_list_due = False
            for index in range(len(self.parameters)):
                self._send_param(index)

    def on_param_request(self, name: str | bytes, index: int) -> None:
        """PARAM_REQUEST_READ (by name, or by ``index`` >= 0) or PARAM_SET (``index`` -1: read-only,
        the unchanged value says "refused")."""
        found = self._param_index(name, index)
        if found is not None:
            self._send_param(found)

    def set_mode(self, custom_mode: int) -> int:
        """Change to ``custom_mode`` (ArduPilot Rover numbering); the MAV_RESULT."""
        if custom_mode not in MODE_NAMES:
            self.telemetry.statustext(f"Mode {custom_mode} not supported", mavlink.MAV_SEVERITY_WARNING)
            return mavlink.MAV_RESULT_DENIED
        if custom_mode != self.mode:
            self.mode = custom_mode
            self.telemetry.statustext(f"Mode {MODE_NAMES[custom_mode]}", mavlink.MAV_SEVERITY_NOTICE)
        return mavlink.MAV_RESULT_ACCEPTED

    def _param_index(self, name: str | bytes, index: int) -> int | None:
        if isinstance(name, bytes):
            name = name.decode("ascii", "replace")
        name = name.rstrip("\x00")
        if index >= 0:
            return index if index < len(self.parameters) else None
        for i, p in enumerate(self.parameters):
            if p.name == name:
                return i
        return None

    def _send_param(self, index: int) -> None:
        p = self.parameters[index]
        self.mav.param_value_send(p.name.encode("ascii"), float(p.value), p.type, len(self.parameters), index)

    def _command(self, msg: Any, now: int) -> int:
        """The result of a COMMAND_LONG / COMMAND_INT (every one is acknowledged). A command we act
        on is DENIED, and changes nothing, when any of its float parameters, used or not, is NaN or
        infinite (none of them has NaN as its default in MAVLink's common.xml)."""
        command, param1, param2 = msg.command, msg.param1, msg.param2
        if command not in ACTED_ON:
            return mavlink.MAV_RESULT_UNSUPPORTED
        if not all(math.isfinite(getattr(msg, name)) for name in _FLOAT_PARAMS[msg.get_type()]):
            self.telemetry.statustext(f"Command {command} denied: NaN/inf parameter",
                                      mavlink.MAV_SEVERITY_WARNING)
            return mavlink.MAV_RESULT_DENIED
        if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            return self._arm_disarm(param1, param2, now)
        if command == mavlink.MAV_CMD_DO_SET_MODE:
            return self.set_mode(round(param2))
        if command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return mavlink.MAV_RESULT_ACCEPTED if param1 == 1.0 else mavlink.MAV_RESULT_DENIED
        # MAV_CMD_REQUEST_MESSAGE
        return (mavlink.MAV_RESULT_ACCEPTED if round(param1) in self._requestable
                else mavlink.MAV_RESULT_UNSUPPORTED)

    def _arm_disarm(self, param1: float, param2: float, now: int) -> int:
        """ARM_DISARM: arming is refused while the station's fresh throttle is not centred (unless
        forced with ArduPilot's magic number in ``param2``)."""
        if param1 == 1.0:
            manual = self.sticks.live(now)
            if (self.sticks.fresh(manual, now) and manual is not None and manual.speed != 0.0
                    and param2 != FORCE_ARM_MAGIC):
                self.telemetry.statustext("Arm refused: GCS throttle not centred",
                                          mavlink.MAV_SEVERITY_WARNING)
                return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
            self.arming.arm("gcs", "armed by the ground station")
            return mavlink.MAV_RESULT_ACCEPTED
        if param1 == 0.0:
            self.arming.disarm("gcs", "disarmed by the ground station")
            return mavlink.MAV_RESULT_ACCEPTED
        return mavlink.MAV_RESULT_DENIED

    @property
    def _requestable(self) -> dict[int, Callable[[], None]]:
        """Messages MAV_CMD_REQUEST_MESSAGE can ask for, by message id."""
        now = self._clock()
        telemetry = self.telemetry
        return {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: telemetry.send_heartbeat,
            mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: telemetry.send_autopilot_version,
            mavlink.MAVLINK_MSG_ID_SYS_STATUS: lambda: telemetry.send_power(now),
            mavlink.MAVLINK_MSG_ID_VFR_HUD: telemetry.send_vfr_hud,
        }

    def _send_requested(self, msg: Any, result: int) -> None:
        """After an accepted request's ACK: the message it asked for."""
        if result != mavlink.MAV_RESULT_ACCEPTED:
            return
        if msg.command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self.telemetry.send_autopilot_version()
        elif msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            self._requestable[round(msg.param1)]()

    def _ack(self, command: int, result: int, msg: Any) -> None:
        self.counters["acks"] += 1
        self.mav.command_ack_send(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())


__all__ = ["ACTED_ON", "FORCE_ARM_MAGIC", "SET_MODE_ACK", "Commands", "ReadOnlyParam"]
