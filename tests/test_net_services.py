"""The parameter services over Zenoh in rmw_zenoh's format, with a raw Zenoh session as the client:
the service key, the reply's attachment (the request's sequence number and the client's GID, which
rmw_zenoh's client matches requests by), the ``SS`` liveliness tokens, and hostile queries counted,
never raised."""

from __future__ import annotations

import asyncio

import zenoh
from conftest import async_wait_for
from zenoh_util import endpoint, free_port

from mux.params import MuxParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.parameter_messages import GetParametersRequest, GetParametersResponse
from racecar_hw.net import rmw
from racecar_hw.net.parameters import ParameterService
from racecar_hw.net.topics import topic_table
from racecar_hw.net.zenoh_bridge import ZenohBridge
from racecar_hw.net.zenoh_config import ZenohParams, session_config
from racecar_hw.rosmsg.typestore import ros2_types
from safety.params import SafetyParams

SRV = "rcl_interfaces/srv/GetParameters"


def test_a_call_is_answered_on_the_service_key_with_rmw_zenohs_attachment():
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
            # hostile: no attachment, a wrong one, bytes that are no request
            for kwargs in (dict(payload=request), dict(payload=request, attachment=b"\x01"),
                           dict(payload=b"\xff" * 9, attachment=rmw.Attachment(8, 1, gid).encode())):
                assert await loop.run_in_executor(None, lambda kw=kwargs: call(**kw)) == []
            await async_wait_for(lambda: bridge.stats.service_errors >= 3, timeout=20)
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
    assert stats.service_calls == 1 and stats.service_errors == 3
    servers = [rmw.parse_token(t) for t in tokens if "/SS/" in t]
    assert sorted(e.topic for e in servers) == [
        f"/car1/racecar_hw/{n}" for n in ("describe_parameters", "get_parameter_types", "get_parameters",
                                          "list_parameters", "set_parameters", "set_parameters_atomically")]
    assert {e.node for e in servers} == {"/car1/racecar_hw"}
    assert {rmw.qos_to_string(e.qos) for e in servers} == {"::,10:,:,:,,"}  # services' default QoS
