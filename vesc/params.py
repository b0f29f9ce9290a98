"""Parameters of the VESC driver, Ackermann conversion and odometry.

Conversion defaults come from the F1TENTH stack (``f1tenth_stack/config/vesc.yaml`` in
f1tenth/f1tenth_system): ``speed_to_erpm_gain`` 4614, ``speed_to_erpm_offset`` 0,
``steering_angle_to_servo_gain`` -1.2135, ``steering_angle_to_servo_offset`` 0.5304,
``servo_min``/``servo_max`` 0.15/0.85, ``wheelbase`` 0.25 m. Unlike that stack, the speed and
steering limits are symmetric and in SI units (m/s, rad); servo_min/max stay a last clamp.
"""

from __future__ import annotations

from dataclasses import dataclass

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.params import param


@dataclass
class VescParams:
    """Everything the VESC driver needs; build with ``racecar_hw.base.params.build(VescParams, data)``."""

    # --- link
    port: str = param("/dev/vesc", "serial device path or pyserial URL (spy://, socket://); "
                      "'auto' finds the USB device by usb_vid_pid and usb_serial", nonempty=True)
    usb_vid_pid: str = param("0483:5740", "USB VID:PID (hex) searched when port is 'auto' "
                             "(STM32 virtual COM port, as the VESC enumerates)")
    usb_serial: str | None = param(None, "USB serial number to pick one VESC among several "
                                   "(port 'auto' only); null accepts any")
    baudrate: int = param(115200, "serial baud rate (ignored by the VESC's USB CDC port)",
                          unit="baud", min=1200, max=4_000_000)
    poll_rate_hz: float = param(50.0, "GET_VALUES telemetry poll rate; also the rate at which the "
                                "failsafe repeats brake and centre", unit="Hz", min=1.0, max=500.0)
    handshake_interval_s: float = param(0.1, "interval between FW_VERSION requests until the VESC "
                                        "answers", unit="s", min=0.01, max=5.0)
    reply_timeout_s: float = param(1.0, "after the handshake, no valid frame from the VESC for this "
                                   "long, with three polls or more unanswered, counts as a lost "
                                   "link: the driver says so and reopens the port", unit="s",
                                   min=0.05, max=60.0)
    reconnect_backoff_min_s: float = param(0.05, "first wait before reopening a lost port; doubles "
                                           "after each failure", unit="s", min=0.01, max=10.0)
    reconnect_backoff_max_s: float = param(0.5, "longest wait between reopen attempts; bounds how "
                                           "late the driver notices a replugged VESC",
                                           unit="s", min=0.01, max=60.0)

    # --- Ackermann -> VESC conversion (f1tenth_stack/config/vesc.yaml)
    speed_to_erpm_gain: float = param(4614.0, "ERPM per m/s of rear-axle speed",
                                      unit="ERPM/(m/s)", min=1.0, max=100000.0)
    speed_to_erpm_offset: float = param(0.0, "ERPM added to every non-zero speed command (a stop is 0 ERPM)",
                                        unit="ERPM", min=-10000.0, max=10000.0)
    steering_angle_to_servo_gain: float = param(-1.2135, "servo position per radian of steering "
                                                "angle (sign sets the direction)", unit="1/rad",
                                                min=-10.0, max=10.0)
    steering_angle_to_servo_offset: float = param(0.5304, "servo position for straight ahead",
                                                  min=0.0, max=1.0)
    steering_angle_to_servo_gain_right: float | None = param(
        None, "servo position per radian for right turns (negative angles), where a car's linkage "
        "turns one way more than the other (racecar-hw calibrate measures both); null: "
        "steering_angle_to_servo_gain both ways", unit="1/rad", min=-10.0, max=10.0)
    servo_min: float = param(0.15, "lowest servo position ever sent (mechanical stop)", min=0.0, max=1.0)
    servo_max: float = param(0.85, "highest servo position ever sent (mechanical stop)", min=0.0, max=1.0)
    speed_max_mps: float = param(5.0, "speed limit, both directions (F1TENTH's 23250 ERPM / 4614)",
                                 unit="m/s", min=0.0, max=30.0)
    steering_max_rad: float = param(0.26, "steering angle limit, both directions; 0.26 keeps the "
                                    "default servo_min/max from clipping one side", unit="rad",
                                    min=0.0, max=1.0)
    invert_motor: bool = param(False, "reverse the motor direction (negates the ERPM gain)")
    invert_servo: bool = param(False, "mirror the steering about the servo centre (negates the "
                               "servo gain)")
    wheelbase_m: float = param(0.25, "front to rear axle distance, for odometry", unit="m",
                               min=0.05, max=2.0)

    # --- failsafe
    command_timeout_s: float = param(0.05, "with no fresh drive command for this long the driver "
                                     "brakes and centres the servo (brake reaches the VESC within "
                                     "100 ms of the last command)", unit="s", min=0.01, max=0.09)
    brake_mode: str = param("rpm", "how the driver brakes: 'rpm' sends SET_RPM 0 (speed loop holds "
                            "the wheels), 'current' sends SET_CURRENT_BRAKE brake_current_a",
                            choices=("rpm", "current"))
    brake_current_a: float = param(20.0, "braking current when brake_mode is 'current' (at least "
                                         "1 A: SET_CURRENT_BRAKE 0 releases the motor, the car coasts)",
                                   unit="A", min=1.0, max=200.0)
    alive_interval_s: float = param(0.2, "while moving, send ALIVE when no motor command went out "
                                    "for this long (firmware timeout is 1 s)", unit="s",
                                    min=0.02, max=0.9)

    # --- odometry
    odom_frame_id: str = param("odom", "frame of the odometry pose (header.frame_id)", nonempty=True)
    base_frame_id: str = param("base_link", "frame of the car (child_frame_id)", nonempty=True)
    publish_tf: bool = param(True, "publish the odom -> base_link transform on /tf")
    pose_covariance_xy: float = param(0.2, "variance of x and y in the odometry pose", unit="m^2",
                                      min=0.0, max=1e6)
    pose_covariance_yaw: float = param(0.4, "variance of yaw in the odometry pose", unit="rad^2",
                                       min=0.0, max=1e6)
    twist_covariance_speed: float = param(0.05, "variance of the forward speed", unit="(m/s)^2",
                                          min=0.0, max=1e6)
    twist_covariance_yaw_rate: float = param(0.1, "variance of the yaw rate", unit="(rad/s)^2",
                                             min=0.0, max=1e6)

    odometry_yaw_rate: str = param(
        "steering", "where odometry's yaw rate comes from: 'steering' (v tan(delta) / wheelbase from "
        "the servo command) or 'imu' (the gyro's z rate, its bias learned at standstill; the "
        "steering model until the car has stood still for imu_bias_time_s)", choices=("steering", "imu"))

    # --- IMU (COMM_GET_IMU_DATA, firmware 3.52 and later; docs/vesc.md)
    imu: bool = param(True, "poll the VESC's IMU with the telemetry and publish sensor_msgs/Imu on "
                      "/imu (firmware before 3.52 has none: nothing is published)")
    imu_frame_id: str = param("imu", "frame of the IMU messages; give base_link -> imu in "
                              "static_transforms", nonempty=True)
    imu_orientation_variance: float = param(
        0.0012, "variance of roll and pitch (about (2 deg)^2: the firmware's accelerometer "
        "fusion on a vibrating car)", unit="rad^2", min=0.0, max=1e6)
    imu_yaw_variance: float = param(
        100.0, "variance of yaw: large, the heading is relative to the one at boot and drifts "
        "(no magnetometer)", unit="rad^2", min=0.0, max=1e6)
    imu_angular_velocity_variance: float = param(
        2e-6, "variance of each rate (BMI160: 0.008 deg/s/sqrt(Hz) over its 80 Hz bandwidth, "
        "0.07 deg/s)", unit="(rad/s)^2", min=0.0, max=1e6)
    imu_linear_acceleration_variance: float = param(
        2.5e-4, "variance of each acceleration (BMI160: 180 ug/sqrt(Hz) over 80 Hz, 1.6 mg; motor "
        "vibration adds more on a car)", unit="(m/s^2)^2", min=0.0, max=1e6)
    imu_bias_time_s: float = param(2.0, "time constant of the gyro bias estimate, learned while the "
                                   "motor stands still", unit="s", min=0.1, max=600.0)

    def __post_init__(self) -> None:
        if self.servo_min > self.servo_max:
            raise ConfigError("servo_min", f"{self.servo_min} is above servo_max {self.servo_max}")
        right = self.steering_angle_to_servo_gain_right
        if right is not None and (right == 0 or (right > 0) != (self.steering_angle_to_servo_gain > 0)):
            raise ConfigError("steering_angle_to_servo_gain_right", f"{right} must be non-zero and of the "
                              "sign of steering_angle_to_servo_gain")
        if self.reconnect_backoff_min_s > self.reconnect_backoff_max_s:
            raise ConfigError("reconnect_backoff_min_s", "is above reconnect_backoff_max_s")
        vid, sep, pid = self.usb_vid_pid.partition(":")
        try:
            int(vid, 16), int(pid, 16)
        except ValueError:
            sep = ""
        if not sep:
            raise ConfigError("usb_vid_pid", f"{self.usb_vid_pid!r} is not VID:PID in hex")

    @property
    def usb_ids(self) -> tuple[int, int]:
        """(vendor id, product id) from ``usb_vid_pid``."""
        vid, _, pid = self.usb_vid_pid.partition(":")
        return int(vid, 16), int(pid, 16)
