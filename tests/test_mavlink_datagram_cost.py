"""What one hostile datagram may cost the MAVLink link, counted in work, not in time.

A reviewer's 65,507-byte datagram of ``FD FF 00 00 00`` cost the decoder some 13,000 CRCs (64 ms),
and one packed with 4,679 PARAM_REQUEST_LISTs made the link send 18,716 PARAM_VALUEs; 20 and 2
such datagrams a second held the event loop for seconds. Ground stations send one frame or a few
per datagram (a MAVLink 2 frame is at most 280 bytes): a longer datagram is refused before any
CRC, a shorter one is decoded with a bounded number of frame starts and frames, the socket's drain
budget is looked at after every datagram, and parameter lists go out at most once a tick.
"""

from __future__ import annotations

import asyncio
import os
import socket
import time
from pathlib import Path
from typing import Any

from conftest import async_wait_for
from test_mavlink_security import Packer, Station, mav, run_signed, started

from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import wall_ns
from racecar_hw.teleop.arming import Arming
from racecar_hw.teleop.mavlink_gcs import MavlinkGcs, MavlinkParams, signing_timestamp
from racecar_hw.teleop.mavlink_rx import MAX_CANDIDATES, MAX_DATAGRAM, MAX_FRAMES, MavlinkRx
from racecar_hw.teleop.mavlink_signing import Tally
from racecar_hw.teleop.mavlink_socket import DRAIN_BUDGET_NS, MavlinkSocket

#: The reviewer's datagram: every fifth byte an FD whose header names HEARTBEAT with 255 bytes of
#: payload, so every one of them is a CRC over 265 bytes.
HOSTILE = (bytes((0xFD, 0xFF, 0, 0, 0)) * 13_102)[:65_507]


def param_request_lists(count: int) -> bytes:
    p = Packer()
    return b"".join(_param_request_list(p) for _ in range(count))


def _param_request_list(p: Packer) -> bytes:
    p.mav.param_request_list_send(1, 1)
    return p.out.pop()


def test_a_datagram_longer_than_a_ground_station_sends_is_refused_before_any_crc():
    for key in (None, os.urandom(32)):
        rx = MavlinkRx(key, signing_timestamp(wall_ns()))
        assert rx.refuse_cheaply(HOSTILE) is None  # not one frame: the decoder's, which refuses it whole
        assert rx.decode(HOSTILE) == []
        assert rx.refused == ["oversized"] and rx.counters["oversized"] == 1
        assert rx.counters["candidates"] == rx.counters["crcs"] == 0
        one_more = Packer().heartbeat() + bytes(MAX_DATAGRAM + 1 - 21)
        assert rx.decode(one_more) == [] and rx.counters["oversized"] == 2


def test_the_decoders_work_per_datagram_is_bounded():
    """The hostile pattern cut to the longest datagram decoded: at most MAX_CANDIDATES frame
    starts and CRCs (it was some 290 at this length), and the rest of it is dropped."""
    for key in (None, os.urandom(32)):
        rx = MavlinkRx(key, signing_timestamp(wall_ns()))
        assert rx.decode(HOSTILE[:MAX_DATAGRAM]) == []
        assert rx.counters["candidates"] == MAX_CANDIDATES and rx.counters["crcs"] == MAX_CANDIDATES
        assert rx.refused.count("overfull") == 1 and rx.counters["overfull"] == 1
        rx.decode(b"\xfd" * MAX_DATAGRAM)  # starts that fail before a CRC count too
        assert rx.counters["candidates"] == 2 * MAX_CANDIDATES


def test_a_few_frames_in_one_datagram_are_heard_and_more_are_dropped():
    """A ground station's few frames in one datagram all come out; past MAX_FRAMES the rest of
    the datagram is dropped and counted, however short the frames."""
    rx = MavlinkRx()
    assert len(rx.decode(param_request_lists(MAX_FRAMES))) == MAX_FRAMES
    assert rx.counters["overfull"] == 0
    packed = param_request_lists(MAX_DATAGRAM // 30)
    assert len(packed) <= MAX_DATAGRAM
    assert len(rx.decode(packed)) == MAX_FRAMES and rx.refused == ["overfull"]
    assert rx.counters["candidates"] == 2 * MAX_FRAMES


def test_the_reviewers_datagrams_reach_the_link_as_one_refusal_each(tmp_path: Path):
    """Over the real socket (which reads one byte more than the decoder takes, so a cut datagram
    is still seen to be too long): each hostile datagram is one refusal, named in the link's
    refusals, and the station's heartbeat behind them is heard."""
    async def scenario(link: MavlinkGcs, gs: Station, arming: Arming, key: bytes) -> None:
        attacker = Station()
        attacker.send(link, HOSTILE, param_request_lists(4679))
        await async_wait_for(lambda: link.counters["oversized"] == 2)
        gs.send(link, Packer(key=key).heartbeat())
        await async_wait_for(lambda: link.gcs_alive)
        # the heartbeat's only: one CRC in the cheap refusal, one in the decoder
        assert link.rx.counters["candidates"] == 1 and link.rx.counters["crcs"] == 2
        assert link.refusals.by_source() == {
            ("mavlink", attacker.address, f"datagram longer than {MAX_DATAGRAM} bytes"): 2}
        attacker.close()

    run_signed(tmp_path, scenario)


def test_the_drain_budget_is_looked_at_after_every_datagram():
    """Datagrams each costing the whole budget: every wake-up of the reader handles one, then the
    socket rests; none is lost (what a spent budget left of a batch is handled when it reads
    again). Before, a batch of 64 was handled whatever it cost."""
    async def main() -> None:
        handled: list[bytes] = []
        wakeups: list[int] = []

        def costly(data: bytes, addr: tuple[Any, ...], tally: Tally) -> None:
            handled.append(data)
            spent = time.monotonic_ns() + DRAIN_BUDGET_NS
            while time.monotonic_ns() < spent:  # stands for a datagram that costs the budget
                pass

        counters = dict.fromkeys(("tx", "send_errors", "datagrams", "station_datagrams", "drain_rests"), 0)
        udp = MavlinkSocket(("127.0.0.1", 0), None, counters, costly,
                            lambda tally: wakeups.append(len(handled)))
        await udp.start()
        sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for i in range(10):
            sender.sendto(bytes((i,)), ("127.0.0.1", udp.port))
        try:
            await async_wait_for(lambda: len(handled) == 10)
        finally:
            udp.close()
            sender.close()
        per_wakeup = [b - a for a, b in zip([0, *wakeups], wakeups, strict=False)]
        assert max(per_wakeup) == 1, per_wakeup
        assert handled == [bytes((i,)) for i in range(10)]  # in order, none lost
        assert counters["datagrams"] == 10 and counters["drain_rests"] >= 9

    asyncio.run(main())


def test_parameter_lists_go_out_once_a_tick_however_many_were_asked_for():
    """200 PARAM_REQUEST_LISTs between two ticks: the four parameters go out once (the link used
    to send the whole list for each request at once: 800 PARAM_VALUEs)."""
    async def main() -> None:
        gs = Station()
        link = await started(MavlinkParams(enabled=True, gcs_address=gs.address, bind_port=0), Arming())
        try:
            addr = gs.sock.getsockname()
            for _ in range(200 // MAX_FRAMES):
                link.handle_datagram(param_request_lists(MAX_FRAMES), addr)
            assert link.counters["rx"] == 200 and not gs.find("PARAM_VALUE")
            link.tick()
            link.tick()  # nothing asked since the last tick: nothing more
            await async_wait_for(lambda: len(gs.find("PARAM_VALUE")) >= 4)
            # a marker: once its answer is in, everything sent before it has come
            marker = Packer().command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_HEARTBEAT)
            link.handle_datagram(marker, addr)
            await gs.wait("COMMAND_ACK")
            assert sorted(m.param_index for m in gs.find("PARAM_VALUE")) == [0, 1, 2, 3]
        finally:
            link.close()
            gs.close()

    asyncio.run(main())


def test_a_station_sending_one_frame_a_datagram_is_decoded_with_one_crc_a_frame():
    """The bounds leave a ground station's traffic alone: one frame per datagram, as QGroundControl,
    MAVProxy and pymavlink send, is decoded with one frame start and one CRC each."""
    link = MavlinkGcs(Bus(), MavlinkParams(), Arming())
    p = Packer()
    for datagram in (p.heartbeat(), p.manual(0), p.arm(False), _param_request_list(p)):
        link.handle_datagram(datagram, ("127.0.0.1", 14550))
    assert link.counters["rx"] == 4 and link.gcs_alive
    assert link.rx.counters["candidates"] == link.rx.counters["crcs"] == 4
    assert link.counters["oversized"] == link.counters["overfull"] == link.counters["bad_data"] == 0
