"""``racecar-hw calibrate``: find the ERPM gain, servo offset and steering gains with the car's own
lidar and IMU (:mod:`racecar_hw.sources.calibration`), on the real car or on the simulator's
miscalibrated one."""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.params import build
from racecar_hw.commands.calibrate_write import check_writable, configured, write
from racecar_hw.commands.daemon import add_config_options, run_daemon
from racecar_hw.commands.sim import _speed, offline_at_max_speed
from racecar_hw.config import Config, load_config
from racecar_hw.daemon import Daemon
from racecar_hw.runtime.extras import require_extra
from racecar_hw.runtime.signals import StopSignals, add_stop_handlers
from racecar_hw.sources.calibration import (
    CalibrationAborted,
    CalibrationParams,
    CalibrationProcedure,
    CalibrationResult,
    CarWatch,
)
from racecar_hw.sources.calibration_fit import Estimate

#: Fits poorer than these are shown and not written: relative standard error of the ERPM gain,
#: standard error of the servo offset, relative standard error of each steering gain.
MAX_ERPM_GAIN_ERROR = 0.01
MAX_OFFSET_ERROR = 0.003
MAX_STEERING_GAIN_ERROR = 0.02

CHECKLIST = """Before the car moves, check:
  - vesc.wheelbase_m is the measured wheelbase ({wheelbase:.3f} m now): the steering gain follows from it;
  - a flat wall faces the car squarely, {wall:.2f} m ahead of the lidar, and nothing else is within
    about 1.5 m of the car's path to it or beside it (the arcs swing about 0.6 m either way);
  - the floor is clear and flat, the battery charged;
  - you hold the deadman and can disarm: the procedure drives through mux input {input}, so the
    gamepad, the ground station and the safety controller stay in charge, and any stop aborts it."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibrate", help="measure the car's ERPM gain, servo offset and steering gains",
                       description="Drive a short, guided procedure (stand still, straight to a wall "
                                   "and back, arcs left and right) and fit speed_to_erpm_gain, "
                                   "steering_angle_to_servo_offset and steering_angle_to_servo_gain "
                                   "(each side's if they differ) from the lidar and the VESC's IMU. "
                                   "Prints each value with its uncertainty and a config snippet; "
                                   "--write puts them into a config file and shows the diff. "
                                   "See docs/vesc.md.")
    p.add_argument("--sim", action="store_true",
                   help="on the simulator's miscalibrated car (scenario 'miscalibrated'), printing "
                        "the simulated car's true value next to each value found")
    p.add_argument("--scenario", default="miscalibrated", metavar="NAME|FILE",
                   help="with --sim: the scenario (default miscalibrated)")
    p.add_argument("--scenario-set", dest="scenario_overrides", action="append", default=[],
                   metavar="KEY=VALUE", help="with --sim: override a scenario key")
    p.add_argument("--speed", type=_speed, metavar="N|max",
                   help="with --sim: run the daemon and the simulated car in lockstep on the "
                        "simulation's clock (as racecar-hw sim --speed does) at N times real time, or "
                        "max: as fast as the machine allows (default: real time over ptys and TCP)")
    p.add_argument("--wall-distance", type=float, default=3.0, metavar="M",
                   help="distance from the lidar to the wall ahead (default 3.0 m)")
    p.add_argument("--stop-distance", type=float, default=1.2, metavar="M",
                   help="how close to the wall the approach ends (default 1.2 m)")
    p.add_argument("--input", default="nav_0", help="mux input the procedure drives (default nav_0)")
    p.add_argument("--write", metavar="FILE", help="write the values into this config file")
    p.add_argument("--yes", action="store_true", help="the checklist is done: do not ask")
    add_config_options(p, default="config/car.yaml's defaults; with --sim the shipped sim config")
    p.set_defaults(func=cmd_calibrate)


@dataclass
class _Truth:
    """The simulated car's true values (with --sim)."""

    erpm_gain: float
    offset: float
    gain_left: float
    gain_right: float
    gyro_bias: float


def cmd_calibrate(args: argparse.Namespace) -> int:
    if args.write and not Path(args.write).is_file():
        raise ConfigError("--write", f"{args.write}: no such config file (copy config/car.yaml first)")
    if args.write:
        check_writable(Path(args.write))  # before the car moves, not after the drive
    if args.speed is not None and not args.sim:
        raise ConfigError("--speed", "the simulation's clock is for --sim; a real car runs in real time")
    if args.sim:
        result, truth = _run_sim(args)
    else:
        result, truth = _run_car(args), None
    if isinstance(result, str):
        print(f"racecar-hw calibrate: {result}", file=sys.stderr)
        return 1
    values, problems = _values(result)
    print(_report(result, truth))
    if problems:
        print("racecar-hw calibrate: not written, the fit is poor: " + "; ".join(problems), file=sys.stderr)
        return 1
    target = load_config(args.write) if args.write else load_config(args.config, args.overrides)
    shown = configured(values, target.vesc)  # as the config states them, its invert flags applied
    print("\nconfig snippet:\nvesc:\n" + "".join(f"  {k}: {'null' if v is None else v}\n"
                                                for k, v in shown.items()), end="")
    if args.write:
        write(Path(args.write), values)
    return 0


def _params(args: argparse.Namespace, config: Config) -> CalibrationParams:
    inputs = {i.name: i.topic for i in config.mux.inputs}
    if args.input not in inputs:
        raise ConfigError("--input", f"no mux input {args.input!r}; inputs: " + ", ".join(inputs))
    if not config.vesc.imu:
        raise ConfigError("vesc.imu", "calibration needs the VESC's IMU: set vesc.imu: true")
    return build(CalibrationParams, {
        "wall_distance_m": args.wall_distance, "stop_distance_m": args.stop_distance,
        "wheelbase_m": config.vesc.wheelbase_m, "input_topic": inputs[args.input],
        "input_name": args.input, "configured_erpm_gain": config.vesc.speed_to_erpm_gain,
        "invert_motor": config.vesc.invert_motor}, "calibrate")


def _watch(daemon: Daemon) -> CarWatch:
    def intervention() -> str | None:
        state = daemon.safety.state
        return state.reason if state.intervening else None

    return CarWatch(armed=lambda: daemon.arming.armed, source=lambda: daemon.mux.source,
                    intervention=intervention)


def _run_car(args: argparse.Namespace) -> CalibrationResult | str:
    config = load_config(args.config, args.overrides)
    params = _params(args, config)
    print(CHECKLIST.format(wheelbase=config.vesc.wheelbase_m, wall=params.wall_distance_m, input=args.input))
    if not args.yes:
        if not sys.stdin.isatty():
            raise ConfigError("--yes", "no terminal to confirm the checklist on: give --yes once it is done")
        if input("Done? [y/N] ").strip().lower() not in ("y", "yes"):
            return "cancelled"
    daemon = Daemon(config)
    procedure = CalibrationProcedure(daemon.bus, params, _watch(daemon), say=print)
    outcome: list[CalibrationResult | str] = []

    async def main() -> int:
        stop = asyncio.Event()
        daemon.add_task(_calibrate(procedure, outcome, then=stop.set))
        return await run_daemon(daemon, stop, noted=stops)

    with StopSignals() as stops:
        asyncio.run(main())
    return outcome[0] if outcome else "interrupted before the procedure ended"


async def _calibrate(procedure: CalibrationProcedure, outcome: list[CalibrationResult | str],
                     then: Callable[[], object]) -> None:
    """Run the procedure, put its result (or why it stopped) in ``outcome``, then ``then()``."""
    try:
        outcome.append(await procedure.run())
    except CalibrationAborted as err:
        outcome.append(str(err))
    finally:
        then()
        procedure.close()


def _run_sim(args: argparse.Namespace) -> tuple[CalibrationResult | str, _Truth]:
    require_extra("sim", "calibrate --sim (the simulator)")
    from racecar_hw.sim.loopback import Loopback  # noqa: PLC0415 - only the sim needs the world
    from racecar_hw.sim.scenario import load_scenario  # noqa: PLC0415

    scenario = load_scenario(args.scenario, args.scenario_overrides)
    outcome: list[CalibrationResult | str] = []
    truth: list[_Truth] = []

    def setup(loopback: Loopback) -> None:
        daemon = loopback.daemon
        assert daemon is not None and loopback.vesc is not None
        car = loopback.car_params
        truth.append(_Truth(abs(car.speed_to_erpm_gain), car.steering_angle_to_servo_offset,
                            car.steering_angle_to_servo_gain,
                            car.steering_angle_to_servo_gain_right or car.steering_angle_to_servo_gain,
                            math.radians(loopback.vesc.imu.errors.gyro_bias_dps)))
        procedure = CalibrationProcedure(daemon.bus, _params(args, daemon.config), _watch(daemon), say=print)
        daemon.add_task(_calibrate(procedure, outcome,
                                   then=lambda: loopback.request_stop("calibration ended")))

    lockstep = args.speed is not None
    overrides = offline_at_max_speed(args.speed, args.overrides, "racecar-hw calibrate")
    loopback = Loopback(scenario, config_path=args.config, overrides=overrides, duration_s=600.0,
                        setup=setup, lockstep=lockstep)

    async def main() -> None:
        remove = add_stop_handlers(asyncio.get_running_loop(), lambda _sig: loopback.request_stop("signal"),
                                   noted=stops)
        try:
            await loopback.run()
        finally:
            remove()

    with StopSignals() as stops:
        if lockstep:
            from racecar_hw.runtime import lockstep as virtual  # noqa: PLC0415 - with the option

            virtual.run(main(), None if math.isinf(args.speed) else args.speed)
        else:
            asyncio.run(main())
    return (outcome[0] if outcome else "interrupted before the procedure ended"), truth[0]


def _values(result: CalibrationResult) -> tuple[dict[str, float | None], list[str]]:
    """The measured values (physical signs; a right-turn gain of None: as the left), and why they
    should not be written (empty: good enough)."""
    gain, st = result.erpm_gain, result.steering
    problems = []
    if not gain.std_error <= MAX_ERPM_GAIN_ERROR * abs(gain.value):
        problems.append(f"speed_to_erpm_gain ±{gain.std_error:.0f} is over {MAX_ERPM_GAIN_ERROR:.0%}")
    if not st.offset.std_error <= MAX_OFFSET_ERROR:
        problems.append(f"steering_angle_to_servo_offset ±{st.offset.std_error:.4f} is over "
                        f"{MAX_OFFSET_ERROR}")
    for name, est in (("left", st.gain_left), ("right", st.gain_right)):
        if not est.std_error <= MAX_STEERING_GAIN_ERROR * abs(est.value):
            problems.append(f"the {name} steering gain ±{est.std_error:.3f} is over "
                            f"{MAX_STEERING_GAIN_ERROR:.0%}")
    values: dict[str, float | None] = {"speed_to_erpm_gain": round(gain.value, 1),
                                       "steering_angle_to_servo_offset": round(st.offset.value, 4)}
    if st.gains_differ:
        values["steering_angle_to_servo_gain"] = round(st.gain_left.value, 4)
        values["steering_angle_to_servo_gain_right"] = round(st.gain_right.value, 4)
    else:
        values["steering_angle_to_servo_gain"] = round(_mean(st.gain_left, st.gain_right), 4)
        values["steering_angle_to_servo_gain_right"] = None  # an earlier right gain no longer holds
    return values, problems


def _mean(a: Estimate, b: Estimate) -> float:
    wa, wb = 1 / max(a.std_error, 1e-9) ** 2, 1 / max(b.std_error, 1e-9) ** 2
    return (wa * a.value + wb * b.value) / (wa + wb)


def _report(result: CalibrationResult, truth: _Truth | None) -> str:
    st = result.steering

    def line(name: str, est: Estimate, fmt: str, true: float | None, residual: str) -> str:
        found = f"{est.value:{fmt}}"
        beside = f" (true: {true:{fmt}})" if true is not None else ""
        return f"{name}: {found}{beside}  ±{est.std_error:{fmt}}, {residual}"

    t = truth
    bias = result.gyro_bias
    return "\n".join([
        line("speed_to_erpm_gain", result.erpm_gain, ".1f", t.erpm_gain if t else None,
             f"wall fit residual {result.erpm_gain.residual_rms * 1000:.1f} mm"),
        line("steering_angle_to_servo_offset", st.offset, ".4f", t.offset if t else None,
             f"arc fit residual {st.offset.residual_rms:.4f}, {st.offset.samples} arcs"),
        line("steering_angle_to_servo_gain", st.gain_left, ".4f", t.gain_left if t else None, "left turns"),
        line("steering_angle_to_servo_gain_right", st.gain_right, ".4f", t.gain_right if t else None,
             "right turns" + (" (differs from left)" if st.gains_differ else " (same as left)")),
        line("gyro_bias_rad_s", bias, ".5f", t.gyro_bias if t else None,
             f"{math.degrees(bias.value):.2f} deg/s, learned again at every standstill"),
    ])
