"""The fake VESC's model, seen through a plain pyserial client over a real pty."""

from __future__ import annotations

import os
import time

import pytest
import serial
from conftest import wait_for

from vesc.codec import (
    Alive,
    FwVersion,
    FwVersionRequest,
    GetValuesRequest,
    Role,
    SetCurrent,
    SetCurrentBrake,
    SetDuty,
    SetRpm,
    SetServoPosition,
    Values,
    VescCodec,
)
from vesc.fake import STATUS_TIMEOUT, FakeVesc


class Client:
    """A blocking pyserial client using our host codec."""

    def __init__(self, path: str) -> None:
        self.ser = serial.Serial(path, 115200, timeout=0.05)
        self.codec = VescCodec(Role.HOST)

    def send(self, *packets) -> None:
        self.ser.write(b"".join(self.codec.send(p) for p in packets))

    def ask(self, packet, reply_type, timeout: float = 5.0):
        self.send(packet)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.codec.receive_data(self.ser.read(4096))
            for event in self.codec.events():
                if isinstance(event, FwVersion):
                    self.codec.firmware = event.version  # the layout, as the driver's handshake sets it
                if isinstance(event, reply_type):
                    return event
        raise AssertionError(f"no {reply_type.__name__} reply")

    def close(self) -> None:
        self.ser.close()


@pytest.fixture
def make(tmp_path, device_thread):
    clients: list[Client] = []

    def factory(firmware=(6, 2), **kw) -> tuple[FakeVesc, Client]:
        fake = FakeVesc(str(tmp_path / f"vesc{len(clients)}"), firmware, **kw).open()
        device_thread.spawn(fake.serve())
        assert fake.ready.wait(10)
        client = Client(fake.path)
        clients.append(client)
        return fake, client

    yield factory
    for c in clients:
        c.close()


@pytest.mark.parametrize(("firmware", "has_name", "has_uuid"), [
    ((2, 18), False, False), ((3, 7), True, False), ((3, 40), True, True), ((6, 5), True, True)])
def test_fw_version_reply_per_firmware(make, firmware, has_name, has_uuid):
    fake, client = make(firmware)
    reply = client.ask(FwVersionRequest(), FwVersion)
    assert reply.version == firmware
    assert (reply.hw_name == "60") is has_name
    assert (reply.uuid is not None) is has_uuid
    values = client.ask(GetValuesRequest(), Values)
    assert values.v_in == pytest.approx(16.8)
    assert fake.frames_rx == 2 and fake.frames_tx == 2


def test_rpm_follows_with_acceleration_limit_and_tachometer(make):
    fake, client = make(accel_erpm_s=30000.0, timeout_s=0.0)  # 0 disables the firmware timeout
    t0 = time.monotonic()
    client.send(SetRpm(15000))
    wait_for(lambda: fake.erpm >= 15000)
    assert time.monotonic() - t0 >= 0.45  # 15000 ERPM at 30000 ERPM/s takes 0.5 s
    v = client.ask(GetValuesRequest(), Values)
    assert v.erpm == 15000 and v.tachometer > 0 and v.tachometer_abs == v.tachometer
    client.send(SetRpm(-15000))
    wait_for(lambda: fake.erpm <= -15000)
    t1 = client.ask(GetValuesRequest(), Values).tachometer
    client.send(SetRpm(-15000))
    wait_for(lambda: client.ask(GetValuesRequest(), Values).tachometer < t1 - 100)
    assert client.ask(GetValuesRequest(), Values).tachometer_abs > v.tachometer_abs


def test_current_brake_and_duty_modes_and_battery_sag(make):
    fake, client = make()
    client.send(SetCurrent(20.0))
    sag = []
    wait_for(lambda: sag.append(client.ask(GetValuesRequest(), Values)) or sag[-1].erpm > 10000)
    assert any(v.v_in < 16.8 and v.current_input > 0 for v in sag)  # the battery sags under load
    assert fake.mode == "current"
    client.send(SetCurrentBrake(30.0))
    wait_for(lambda: fake.erpm == 0)
    assert fake.mode == "brake"
    client.send(SetDuty(0.1))
    wait_for(lambda: abs(fake.erpm - 0.1 * 3000 * 16.8) < 200)
    client.send(SetServoPosition(0.8))
    wait_for(lambda: fake.servo == 0.8)


def test_firmware_timeout_releases_the_motor_and_sets_status(make):
    fake, client = make(timeout_s=0.3)
    client.send(SetRpm(3000), SetServoPosition(0.3))
    wait_for(lambda: fake.erpm == 3000)
    # polling telemetry does not keep the motor engaged
    wait_for(lambda: client.ask(GetValuesRequest(), Values).status & STATUS_TIMEOUT)
    assert fake.timed_out and fake.mode == "released"
    wait_for(lambda: fake.erpm == 0)  # coasting down
    assert fake.servo == 0.3  # the timeout never touches the servo
    client.send(Alive())
    wait_for(lambda: not fake.timed_out)


def test_stall_holds_the_wheels(make):
    fake, client = make()
    client.send(SetRpm(5000))
    wait_for(lambda: fake.erpm == 5000)
    fake.stall()
    client.send(SetRpm(5000))
    wait_for(lambda: client.ask(GetValuesRequest(), Values).current_motor == pytest.approx(60.0))
    assert fake.erpm == 0 and client.ask(GetValuesRequest(), Values).erpm == 0
    fake.unstall()
    client.send(SetRpm(5000))
    wait_for(lambda: fake.erpm == 5000)


def test_unplug_and_replug(make):
    fake, client = make()
    path = fake.path
    fake.unplug()
    assert not os.path.exists(path) and not fake.plugged
    with pytest.raises(serial.SerialException):
        client.ser.read(10)
    fake.replug()
    assert os.path.exists(path)
    again = Client(path)
    try:
        assert again.ask(FwVersionRequest(), FwVersion).version == (6, 2)
    finally:
        again.close()


def test_fault_injection_is_seen_by_the_client(make):
    fake, client = make()
    fake.corrupt_next_crc()
    fake.split_replies(True)
    client.send(GetValuesRequest())

    def crc_error_seen() -> bool:
        client.codec.receive_data(client.ser.read(4096))
        client.codec.events()
        return client.codec.stats.crc_errors == 1

    wait_for(crc_error_seen)
    fake.inject_garbage(50)
    assert client.ask(GetValuesRequest(), Values).v_in > 0
    assert client.codec.stats.dropped_bytes >= 50
