"""The parameter services over Zenoh in rmw_zenoh's format, with a raw Zenoh session as the client:
the service key, the reply's attachment (the request's sequence number and the client's GID, which
rmw_zenoh's client matches requests by), the ``SS`` liveliness tokens, and hostile queries counted,
never raised."""

from __future__ import annotations

import asyncio
import logging

import zenoh
from conftest import async_wait_for
from zenoh_util import endpoint, free_port

from mux.params import MuxParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.parameter_messages import (
    GetParametersRequest,
    GetParametersResponse,
    SetParametersRequest,
)
from racecar_hw.net import rmw
from racecar_hw.net.parameters import ParameterService
from racecar_hw.net.topics import topic_table
from racecar_hw.net.zenoh_bridge import ZenohBridge
from racecar_hw.net.zenoh_config import ZenohParams, session_config
from racecar_hw.rosmsg.typestore import ros2_types
from safety.params import SafetyParams

SRV = "rcl_interfaces/srv/GetParameters"
SET_SRV = "rcl_interfaces/srv/SetParameters"


def test_a_call_is_answered_on_the_service_key_with_rmw_zenohs_attachment(caplog):
    async def run() -> tuple[list, list[str], object]:
        bus = Bus()
        port = free_port()
        rows = topic_table(MuxParams(), SafetyParams())
        params = ParameterService({"mux": {"rate_hz": 50.0}})
        bridge = ZenohBridge(bus, ZenohParams(listen=[endpoint(port)], namespace="/car1"), rows,
                             parameters=params)
        loop = asyncio.get_running_loop()
        bus.bind_loop(loop)
        await loop.run_in_executor(None, bridge.open, loop)
        peer = zenoh.open(session_config("client", [], [endpoint(port)]))
        key = rmw.topic_key(0, "/car1/racecar_hw/get_parameters", SRV, rmw.type_hash(SRV))
        request = ros2_types().serialize(GetParametersRequest(["mux.rate_hz"]))
        gid = bytes(range(16))

        def call(**kwargs) -> list:
            return [(r.ok.payload.to_bytes(), r.ok.attachment.to_bytes() if r.ok.attachment else None,
                     str(r.ok.key_expr)) for r in peer.get(key, timeout=10, **kwargs) if r.ok is not None]

        try:
            replies = await loop.run_in_executor(None, lambda: call(
                payload=request, attachment=rmw.Attachment(7, 1, gid).encode()))
            # hostile: no attachment, a wrong one, bytes that are no request, a request too large
            too_many = ros2_types().serialize(GetParametersRequest(["mux.rate_hz"] * 1025))
            for kwargs in (dict(payload=request), dict(payload=request, attachment=b"\x01"),
                           dict(payload=b"\xff" * 9, attachment=rmw.Attachment(8, 1, gid).encode()),
                           dict(payload=too_many, attachment=rmw.Attachment(9, 1, gid).encode())):
                assert await loop.run_in_executor(None, lambda kw=kwargs: call(**kw)) == []
            await async_wait_for(lambda: bridge.stats.service_errors >= 4, timeout=20)
            # set_parameters: malformed calls are refusals, answered ones logged sparingly
            set_key = rmw.topic_key(0, "/car1/racecar_hw/set_parameters", SET_SRV, rmw.type_hash(SET_SRV))
            set_request = ros2_types().serialize(SetParametersRequest())

            def set_calls() -> None:
                for n in range(30):
                    list(peer.get(set_key, payload=b"\xff" * 3, timeout=10,
                                  attachment=rmw.Attachment(100 + n, 1, gid).encode()))
                    list(peer.get(set_key, payload=set_request, timeout=10,
                                  attachment=rmw.Attachment(200 + n, 1, gid).encode()))

            with caplog.at_level(logging.INFO, logger="racecar_hw.net.zenoh_services"):
                await loop.run_in_executor(None, set_calls)
                await async_wait_for(lambda: bridge.stats.set_calls >= 30, timeout=20)
            tokens = [str(r.ok.key_expr) for r in peer.liveliness().get(rmw.liveliness_pattern(0), timeout=5)
                      if r.ok is not None]
            return replies, tokens, bridge.stats
        finally:
            peer.close()
            await loop.run_in_executor(None, bridge.close)

    replies, tokens, stats = asyncio.run(run())
    ((payload, attachment, key),) = replies
    dds = "rcl_interfaces::srv::dds_::GetParameters_"
    assert key == f"0/car1/racecar_hw/get_parameters/{dds}/{rmw.type_hash(SRV)}"
    response = ros2_types().deserialize(payload, GetParametersResponse)
    assert [v.double_value for v in response.values] == [50.0]
    back = rmw.Attachment.decode(attachment)
    assert back.sequence_number == 7 and back.gid == bytes(range(16)) and back.source_timestamp_ns > 1
    assert stats.service_calls == 1 + 30 and stats.service_errors == 4 + 30 and stats.set_calls == 30
    set_lines = [r.getMessage() for r in caplog.records if "set_parameters: refused" in r.getMessage()]
    assert len(set_lines) == 2 and set_lines[-1].endswith("(10 so far)"), set_lines  # the 1st and the 10th
    servers = [rmw.parse_token(t) for t in tokens if "/SS/" in t]
    assert sorted(e.topic for e in servers) == [
        f"/car1/racecar_hw/{n}" for n in ("describe_parameters", "get_parameter_types", "get_parameters",
                                          "list_parameters", "set_parameters", "set_parameters_atomically")]
    assert {e.node for e in servers} == {"/car1/racecar_hw"}
    assert {rmw.qos_to_string(e.qos) for e in servers} == {"::,10:,:,:,,"}  # services' default QoS
