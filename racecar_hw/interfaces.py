"""The daemon's interfaces to other programs, built from the config.

ROS 2 over Zenoh and DDS (both behind the one network :class:`~racecar_hw.net.inbox.Inbox`, which
hands commands to the control path once per input and tick), ``/cmd_vel``, the daemon's log on
``/rosout``, the read-only parameter services, the Foxglove live view and the status page.

Each follows the component protocol of the daemon (docs/architecture.md, "Components"): built
here (nothing listens yet), opened or started in :meth:`Interfaces.open` and
:meth:`Interfaces.start_live`, and closed by the callbacks those push on the daemon's exit stack,
so shutdown undoes start-up in reverse order.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
from typing import TYPE_CHECKING

from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.params import describe, to_dict
from racecar_hw.base.topics import CLOCK_TOPIC
from racecar_hw.config import FOXGLOVE_INPUT, Config, cmd_vel_input_topic, listeners, network_topics
from racecar_hw.control.path import ControlPath
from racecar_hw.net import zenoh_logins
from racecar_hw.net.control import CarControl
from racecar_hw.net.dds_bridge import DdsBridge
from racecar_hw.net.dds_config import cyclone_available
from racecar_hw.net.inbox import Inbox
from racecar_hw.net.parameters import ParameterService
from racecar_hw.net.ports import port_taken, taken_message
from racecar_hw.net.rosout import RosoutHandler, logger_name
from racecar_hw.net.topics import Direction, Topic
from racecar_hw.net.zenoh_bridge import ZenohBridge
from racecar_hw.runtime.extras import missing_extra
from racecar_hw.runtime.refusals import Refusals
from racecar_hw.runtime.teardown import quietly, quietly_sync
from racecar_hw.sources.cmd_vel import CmdVelConverter, CmdVelParams
from vesc.driver import TOPIC_ODOM, TOPIC_TF

if TYPE_CHECKING:  # imported where foxglove.enabled: the SDK comes with the foxglove extra
    from racecar_hw.net.foxglove_server import FoxgloveServer
    from racecar_hw.net.web import WebServer  # where web.enabled: aiohttp is a fifth of a second

log = logging.getLogger(__name__)


class Interfaces:
    """The network and live interfaces the config switches on (None: off)."""

    def __init__(self, config: Config, bus: Bus, control: ControlPath, car: CarControl,
                 refusals: Refusals) -> None:
        self.config, self.bus, self.refusals = config, bus, refusals
        z, d, mux = config.zenoh, config.dds, config.mux
        #: the topics the live interfaces (Foxglove, Zenoh, DDS) serve, named by ``zenoh.profile``
        #: and ``zenoh.remap``; the simulator adds its own before the daemon runs
        self.live_topics: list[Topic] = network_topics(config)
        #: the daemon's log on /rosout (the topic table's row; every network interface carries it)
        self.rosout = (RosoutHandler(bus, config.rosout, logger_name(z.namespace, z.node_name))
                       if config.rosout.enabled else None)
        #: the read-only parameter services' answers: the effective configuration
        self.parameters = ParameterService(to_dict(config), {name: doc for name, _, doc in describe(Config)})
        teleop = next((i.topic for i in mux.inputs if i.name == FOXGLOVE_INPUT), None)
        self.foxglove: FoxgloveServer | None = None
        absent = missing_extra("foxglove", "the Foxglove live view") if config.foxglove.enabled else None
        if absent is not None:  # on by default: a car whose config predates the extra still drives
            log.warning("foxglove: the live view is off: %s; or set foxglove.enabled: false", absent)
        elif config.foxglove.enabled:
            from racecar_hw.net.foxglove_server import FoxgloveServer  # noqa: PLC0415 - needs the extra

            self.foxglove = FoxgloveServer(bus, config.foxglove, car, self.live_topics,
                                           parameters=to_dict(config), teleop_input=teleop,
                                           wheelbase_m=config.vesc.wheelbase_m,
                                           max_steering_rad=config.vesc.steering_max_rad, refusals=refusals)
        self.web: WebServer | None = None
        if config.web.enabled:
            from racecar_hw.net.web import WebServer  # noqa: PLC0415 - aiohttp, only for the page

            self.web = WebServer(bus, config.web, car, scan_topic=config.safety.scan_topic, refusals=refusals)
        self.cmd_vel: CmdVelConverter | None = None
        self.inbox: Inbox | None = None
        self.zenoh: ZenohBridge | None = None
        self.dds: DdsBridge | None = None
        dds_on = d.enabled and cyclone_available()
        if d.enabled and not dds_on:
            log.warning("dds: the DDS interface is off: the cyclonedds package is not installed "
                        "(pip install cyclonedds; docs/dds.md), or set dds.enabled: false")
        if not z.enabled and not dds_on:
            return
        remote = control.remote_inputs
        remote.update({i.topic: i.name for i in mux.inputs})
        twist_input = cmd_vel_input_topic(config)
        if z.cmd_vel and twist_input:
            self.cmd_vel = CmdVelConverter(bus, CmdVelParams(
                z.cmd_vel_topic, twist_input, config.vesc.wheelbase_m, config.vesc.steering_max_rad))
            remote[z.cmd_vel_topic] = remote[twist_input]
        # sent at once, not in the next batch: remote code waits for them; /clock (the simulator's,
        # when it has one) so that a node on simulation time is not a batch behind the stamps
        urgent = {config.safety.scan_topic, TOPIC_ODOM, TOPIC_TF, CLOCK_TOPIC}
        self.inbox = Inbox([t.bus for t in self.live_topics if t.direction is Direction.IN],
                           control.take_input, period_s=1.0 / mux.rate_hz, estop_topic=mux.estop_topic,
                           release_topic=mux.estop_release_topic, on_estop=control.network_estop,
                           refusals=refusals)
        if z.enabled:
            self.zenoh = ZenohBridge(bus, z, self.live_topics, urgent=urgent,
                                     early={config.safety.scan_topic}, inbox=self.inbox,
                                     refusals=refusals, parameters=self.parameters)
            # the scan is queued by the control path right after its motor write
            control.early.append(functools.partial(self.zenoh.send_early, config.safety.scan_topic))
            logins = zenoh_logins.installed()  # the command counts failed Zenoh logins: into our refusals
            if logins is not None:
                logins.attach(refusals)
        if dds_on:
            self.dds = DdsBridge(bus, d, self.live_topics, namespace=z.namespace, node_name=z.node_name,
                                 urgent=urgent, refusals=refusals, inbox=self.inbox,
                                 period_s=1.0 / mux.rate_hz, early={config.safety.scan_topic})
            control.early.append(functools.partial(self.dds.send_early, config.safety.scan_topic))
        control.idle.extend(s.control_idle for s in (self.zenoh, self.dds) if s is not None)

    async def open(self, loop: asyncio.AbstractEventLoop, stack: contextlib.AsyncExitStack) -> None:
        """Refuse a taken port (a one-line ConfigError naming the key), then open the network:
        the inbox in ``loop``, the Zenoh and DDS sessions (in a worker thread: they block)."""
        self._refuse_taken_ports()
        if self.rosout is not None:
            self.rosout.install()
            stack.callback(self._uninstall_rosout)
        if self.inbox is not None:
            self.inbox.bind(loop)
            stack.callback(self.inbox.close)
        bridges = [b for b in (self.zenoh, self.dds) if b is not None]
        for bridge in bridges:  # closed also when its open fails half-way
            stack.push_async_callback(quietly, loop.run_in_executor, None, bridge.close)
        # side by side: each mostly waits in its library (sockets, discovery), and a lockstep
        # run's virtual time stands still until both are open
        opened = await asyncio.gather(*(loop.run_in_executor(None, b.open, loop) for b in bridges),
                                      return_exceptions=True)
        failed = next((r for r in opened if isinstance(r, BaseException)), None)
        if failed is not None:  # both have ended: the first bridge's error, as one after the other gave
            raise failed

    def _refuse_taken_ports(self) -> None:
        """The rule for every interface (docs/live-view.md, "Ports"); Zenoh's own open refuses a
        taken listen port the same way, naming ``zenoh.listen[i]``."""
        for item in listeners(self.config):
            if not item.key.startswith("zenoh.") and port_taken(item.host, item.port, item.kind):
                raise ConfigError(item.key, taken_message(item))

    def _uninstall_rosout(self) -> None:
        rosout = self.rosout
        if rosout is not None:
            rosout.uninstall()
            if rosout.dropped:
                log.info("rosout: %d log records published, %d dropped (over rosout.max_rate_hz or "
                         "before the loop ran)", rosout.published, rosout.dropped)

    async def start_live(self, control: ControlPath, stack: contextlib.AsyncExitStack) -> dict[str, str]:
        """Start the Foxglove server and the status page (one that cannot start is left off, as
        it says in the log); returns where they listen (:meth:`urls`)."""
        if self.foxglove is not None and not self.foxglove.start():
            self.foxglove = None
        if self.web is not None and not await self.web.start():
            self.web = None
        if self.foxglove is not None:
            foxglove = self.foxglove
            stack.callback(quietly_sync, foxglove.stop)
            self.bus.subscribe(self.config.mux.output_topic, lambda msg: foxglove.on_output())
        if self.web is not None:
            stack.push_async_callback(quietly, self.web.stop)
        control.idle.extend(s.control_idle for s in (self.foxglove, self.web) if s is not None)
        return self.urls()

    def urls(self) -> dict[str, str]:
        """Where the live interfaces that run listen: ``foxglove`` (ws://) and ``web`` (http://)."""
        urls: dict[str, str] = {}
        if self.foxglove is not None and self.foxglove.port is not None:
            urls["foxglove"] = f"ws://{self.config.foxglove.host}:{self.foxglove.port}"
        if self.web is not None and self.web.port:
            urls["web"] = f"http://{self.config.web.host}:{self.web.port}/"
        return urls

