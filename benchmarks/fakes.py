"""The fake car the daemon benchmarks run against: the fake VESC on a pty, a fake UST-10LX on a
free loopback TCP port seeing the shipped room from where the car is, and the world moving them
at 200 Hz, each served by a device thread of its own (not the daemon's event loop)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from lidar_drivers.scip_fake import FakeHokuyo
from racecar_hw.runtime.devicethread import DeviceThread
from racecar_hw.sim.occupancy import load_shipped_map
from racecar_hw.sim.world import World
from vesc.fake import FakeVesc


@contextmanager
def room_fakes(folder: str, open_vesc: bool = False) -> Iterator[tuple[FakeVesc, FakeHokuyo]]:
    """The fakes serving until the block ends: ``(vesc, lidar)``, the VESC's pty at ``folder/vesc``
    (created before this returns with ``open_vesc``), the lidar listening at ``lidar.tcp_address``."""
    with (DeviceThread("bench-vesc") as vesc_thread, DeviceThread("bench-lidar") as lidar_thread,
          DeviceThread("bench-world") as world_thread):
        vesc = FakeVesc(f"{folder}/vesc")
        if open_vesc:
            vesc.open()
        world = World(load_shipped_map("room"), erpm_source=lambda: vesc.erpm,
                      servo_source=lambda: vesc.servo, seed=1, on_collision=vesc.stall)
        lidar = FakeHokuyo("ust-10lx", world.range_source(max_range=10.0), tcp=("127.0.0.1", 0))
        vesc_thread.spawn(vesc.serve())
        lidar_thread.spawn(lidar.serve())
        world_thread.spawn(world.run(200.0))
        if not lidar.ready.wait(10):
            raise RuntimeError("fake lidar did not start")
        yield vesc, lidar
