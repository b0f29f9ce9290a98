"""The live view's services: ``/racecar/estop``, ``/racecar/release``, ``/racecar/arm``, ``/racecar/disarm``.

Each is a ``std_srvs/srv/Trigger`` (answered in CDR, or JSON when the client asks so). The SDK
calls a handler from its threads; the action runs in the event loop (``call_soon_threadsafe``) and
the handler waits for its answer at most :data:`SERVICE_TIMEOUT_S`.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import logging
from collections.abc import Callable

from foxglove import MessageSchema, Schema, Service, ServiceRequest, ServiceSchema

from mux.estop import Origin
from racecar_hw.net.control import CarControl

log = logging.getLogger(__name__)

SERVICE_PREFIX = "/racecar/"
#: How long a service call waits for the event loop (s).
SERVICE_TIMEOUT_S = 2.0
_TRIGGER_RESPONSE = "bool success\nstring message\n"

#: A service's action: who asks -> (success, message).
Action = Callable[[str], tuple[bool, str]]


def trigger_response(success: bool, message: str) -> bytes:
    """``std_srvs/srv/Trigger_Response`` in CDR (little endian, with the encapsulation header)."""
    text = message.encode()
    return (b"\x00\x01\x00\x00" + bytes([1 if success else 0]) + b"\x00\x00\x00"
            + (len(text) + 1).to_bytes(4, "little") + text + b"\x00")


class TriggerServices:
    """The e-stop and arming services on ``control``, run in ``loop``."""

    def __init__(self, control: CarControl, loop: asyncio.AbstractEventLoop) -> None:
        self.control = control
        self.loop = loop

    def services(self) -> list[Service]:
        """The SDK's service definitions."""
        control = self.control
        actions: dict[str, tuple[str, Action]] = {
            "estop": ("latch the mux e-stop: the car brakes and stays braked until release",
                      lambda who: (True, control.engage_estop(Origin("foxglove", who)))),
            "release": ("release the latched e-stop",
                        lambda who: control.release_estop(Origin("foxglove", who))),
            "arm": ("arm the car", control.arm),
            "disarm": ("disarm the car: every source is stopped", control.disarm),
        }
        schema = ServiceSchema(
            "std_srvs/srv/Trigger",
            request=MessageSchema(encoding="cdr", schema=Schema(name="std_srvs/srv/Trigger_Request",
                                                                 encoding="ros2msg", data=b"")),
            response=MessageSchema(encoding="cdr", schema=Schema(
                name="std_srvs/srv/Trigger_Response", encoding="ros2msg", data=_TRIGGER_RESPONSE.encode())))
        return [Service(SERVICE_PREFIX + name, schema=schema, handler=self._handler(name, action))
                for name, (_, action) in actions.items()]

    def _handler(self, name: str, action: Action) -> Callable[[ServiceRequest], bytes]:
        def handle(request: ServiceRequest) -> bytes:
            done: concurrent.futures.Future[tuple[bool, str]] = concurrent.futures.Future()
            who = f"foxglove client {request.client_id}"

            def run() -> None:
                if not done.set_running_or_notify_cancel():
                    return  # the caller was told it failed (timed out): it must not happen later
                try:
                    done.set_result(action(who))
                except Exception as err:  # noqa: BLE001 - reported to the caller
                    done.set_exception(err)

            self.loop.call_soon_threadsafe(run)
            try:
                success, message = done.result(SERVICE_TIMEOUT_S)
            except concurrent.futures.TimeoutError:
                if not done.cancel():  # it has just started: its answer comes at once
                    success, message = done.result()
                else:
                    log.warning("foxglove: %s%s from %s: not done: the daemon was busy for %.0f s",
                                SERVICE_PREFIX, name, who, SERVICE_TIMEOUT_S)
                    raise TimeoutError(f"not done: the daemon was busy for {SERVICE_TIMEOUT_S:.0f} s; "
                                       "nothing was changed, call again") from None
            log.info("foxglove: %s%s from %s: %s", SERVICE_PREFIX, name, who, message)
            if request.encoding == "json":
                return json.dumps({"success": success, "message": message}).encode()
            return trigger_response(success, message)
        return handle


__all__ = ["SERVICE_PREFIX", "SERVICE_TIMEOUT_S", "TriggerServices", "trigger_response"]
