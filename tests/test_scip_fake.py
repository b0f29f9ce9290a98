"""Every SCIP command against the fake Hokuyo over a real pty and real TCP, and hokuyolx as a peer."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest
from hokuyolx import HokuyoLX

from lidar_drivers.base import RoomRangeSource
from lidar_drivers.scip import (
    Command,
    InfoReply,
    ResponseDecoder,
    ScanCommand,
    ScanReply,
    StateReply,
    StatusReply,
    TimeCommand,
    TimeReply,
)
from lidar_drivers.scip_fake import FakeHokuyo
from lidar_drivers.scip_models import MODELS
from racecar_hw.base.link import Link, SerialLink, TcpLink


@pytest.fixture
def fake(device_thread, tmp_path):
    f = FakeHokuyo("ust-10lx", RoomRangeSource(8, 6), link=str(tmp_path / "hokuyo"),
                   tcp=("127.0.0.1", 0))
    device_thread.spawn(f.serve())
    assert f.ready.wait(10)
    return f


def open_link(fake: FakeHokuyo, transport: str) -> Link:
    if transport == "tcp":
        assert fake.tcp_address is not None
        return TcpLink(*fake.tcp_address)
    return SerialLink(fake.path)


class Client:
    """A bare SCIP host for tests: send a command, collect replies."""

    def __init__(self, link: Link) -> None:
        self.link = link
        self.decoder = ResponseDecoder()
        self.pending: list = []  # decoded but not yet asked for

    async def events(self, n: int, timeout: float = 10.0) -> list:
        """The next ``n`` events; any decoded beyond them wait for the next call."""
        out = self.pending
        deadline = time.monotonic() + timeout
        while True:
            out.extend(self.decoder)
            if len(out) >= n:
                break
            self.decoder.receive_data(await asyncio.wait_for(self.link.read(),
                                                             deadline - time.monotonic()))
        self.pending = out[n:]
        return out[:n]

    async def ask(self, cmd: Command | bytes):
        self.link.write(cmd if isinstance(cmd, bytes) else cmd.encode())
        [reply] = await self.events(1)
        return reply


def run_client(fake: FakeHokuyo, transport: str, scenario) -> None:
    async def main() -> None:
        link = open_link(fake, transport)
        await link.open()
        try:
            await scenario(Client(link))
        finally:
            link.close()

    asyncio.run(main())


@pytest.mark.parametrize("transport", ["pty", "tcp"])
def test_identity_parameters_and_status(fake, transport):
    async def scenario(c: Client) -> None:
        vv = await c.ask(Command("VV"))
        assert isinstance(vv, InfoReply) and vv.fields["PROD"] == "UST-10LX"
        assert set(vv.fields) == {"VEND", "PROD", "FIRM", "PROT", "SERI"}
        pp = await c.ask(Command("PP"))
        assert pp.fields == {"MODL": "UST-10LX", "DMIN": "20", "DMAX": "30000", "ARES": "1440",
                             "AMIN": "0", "AMAX": "1080", "AFRT": "540", "SCAN": "2400"}
        ii = await c.ask(Command("II", tag="t1"))
        assert ii.tag == "t1" and ii.fields["LASR"] == "OFF" and "STAT" in ii.fields

    run_client(fake, transport, scenario)


@pytest.mark.parametrize("transport", ["pty", "tcp"])
def test_laser_time_sync_and_single_scans(fake, transport):
    async def scenario(c: Client) -> None:
        gd = ScanCommand(name="GD", start=0, end=1080, cluster=1)
        off = await c.ask(gd)
        assert isinstance(off, StatusReply) and off.status == "10" and off.meaning == "laser is off"
        assert (await c.ask(Command("BM"))).status == "00"
        assert (await c.ask(Command("BM"))).status == "02"
        state = await c.ask(Command("%ST"))
        assert isinstance(state, StateReply) and state.state == "003"
        scan = await c.ask(gd)
        assert isinstance(scan, ScanReply) and scan.distances.size == 1081
        # straight ahead (step 540) the 8 x 6 room's wall is 4 m away; left (step 900) 3 m
        assert scan.distances[540] == 4000 and scan.distances[900] == 3000
        ge = await c.ask(ScanCommand(name="GE", start=500, end=580, cluster=2))
        assert ge.distances.size == 41 and ge.intensities is not None and ge.intensities.min() > 0
        assert (await c.ask(TimeCommand(code=1))).status == "04"
        assert (await c.ask(TimeCommand(code=2))).status == "03"
        assert (await c.ask(TimeCommand(code=0))).status == "00"
        assert (await c.ask(TimeCommand(code=0))).status == "02"
        t1 = await c.ask(TimeCommand(code=1))
        t2 = await c.ask(TimeCommand(code=1))
        assert isinstance(t1, TimeReply) and 0 <= t2.time_ms - t1.time_ms < 5000
        assert (await c.ask(TimeCommand(code=2))).status == "00"
        assert (await c.ask(Command("QT"))).ok
        assert (await c.ask(Command("RS"))).ok
        assert (await c.ask(b"TM5\n")).status == "01"
        assert (await c.ask(b"XY\n")).meaning == "unknown command"
        assert (await c.ask(ScanCommand(name="GD", start=0, end=1200))).status == "04"

    run_client(fake, transport, scenario)


@pytest.mark.parametrize("transport", ["pty", "tcp"])
def test_md_and_me_stream_counted_frames_at_the_scan_period(fake, transport):
    async def scenario(c: Client) -> None:
        md = ScanCommand(name="MD", start=0, end=1080, cluster=1, interval=0, count=3, tag="x")
        c.link.write(md.encode())
        ack, *frames = await c.events(4)
        assert isinstance(ack, StatusReply) and ack.echo == md.line and ack.status == "00"
        assert [f.request.count for f in frames] == [2, 1, 0]
        assert all(f.status == "99" and f.tag == "x" and f.distances.size == 1081 for f in frames)
        stamps = [f.timestamp_ms for f in frames]
        assert all(b > a for a, b in zip(stamps[:-1], stamps[1:], strict=True))
        me = ScanCommand(name="ME", start=100, end=199, cluster=1, interval=1, count=0)
        c.link.write(me.encode())
        ack, f1, f2 = await c.events(3)
        assert ack.ok and f1.request.count == 0 and f2.intensities.size == 100
        c.link.write(Command("QT").encode())  # a stream stops between frames
        while isinstance(reply := (await c.events(1))[0], ScanReply):
            assert reply.request.name == "ME"  # frames already on their way
        assert isinstance(reply, StatusReply) and reply.echo == "QT" and reply.ok

    run_client(fake, transport, scenario)


def test_models_match_the_reference():
    urg = MODELS["urg-04lx"]
    assert (urg.dmin, urg.dmax, urg.ares, urg.amin, urg.amax, urg.afrt, urg.scan_rpm) == (
        20, 5600, 1024, 44, 725, 384, 600)
    assert urg.scan_period_s == pytest.approx(0.1)
    utm = MODELS["utm-30lx"]
    assert (utm.dmin, utm.dmax, utm.ares, utm.amin, utm.amax, utm.afrt, utm.scan_rpm) == (
        23, 60000, 1440, 0, 1080, 540, 2400)
    assert MODELS["ust-10lx"].dmax == 30000 and MODELS["ust-20lx"].scan_period_s == pytest.approx(0.025)


def test_ranges_beyond_dmax_and_too_near_become_error_codes():
    class Walls:
        def ranges(self, angles, stamp_ns=0):
            r = np.full(len(angles), 2.5)
            r[:10] = np.inf
            r[10:20] = 40.0
            r[20:30] = 0.005
            return r

    f = FakeHokuyo("ust-10lx", Walls())
    dist, _ = f.measure(ScanCommand(name="GD", start=0, end=39), 0)
    assert dist[:20].tolist() == [1] * 20 and dist[20:30].tolist() == [2] * 10
    assert dist[30:].tolist() == [2500] * 10
    clustered, _ = f.measure(ScanCommand(name="GD", start=0, end=39, cluster=8), 0)
    # steps 16..23 hold codes 1 and 2; steps 24..31 end with two valid returns
    assert clustered.tolist() == [1, 1, 1, 2500, 2500]  # nearest valid step, else smallest code


def test_hokuyolx_reads_the_fake_ust10lx_over_tcp(fake):
    room = RoomRangeSource(8, 6)
    lx = HokuyoLX(addr=fake.tcp_address, buf=4096, timeout=10)
    try:
        assert lx.model == "UST-10LX" and lx.dmax == 30000 and lx.aforw == 540
        expected = np.rint(room.ranges(lx.get_angles()) * 1000).astype(int)
        _, scan = lx.get_dist()
        assert scan.tolist() == expected.tolist()
        # hokuyolx takes each socket read for one message, so a client held up past the next
        # frame would see two glued together; frames ten scan periods apart (250 ms) leave room.
        frames = list(lx.iter_dist(scans=3, skips=9))
        assert [pending for _, _, pending in frames] == [2, 1, 0]
        for scan, _, _ in frames:
            assert scan.tolist() == expected.tolist()
        _, both = lx.get_intens()
        assert both[:, 0].tolist() == expected.tolist() and (both[:, 1] > 0).all()
        assert lx.version()["PROD"] == "UST-10LX"
        assert lx.laser_state()[0] == 3
    finally:
        lx.close()
