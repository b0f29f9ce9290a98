"""The Zenoh bridge's service servers: the node's read-only parameter services on rmw_zenoh.

One Zenoh queryable per service, on rmw_zenoh's service key (``<domain>/<node>/<service>/<srv DDS
type>/<hash>``), declared complete, as ``rmw_service_data.cpp`` does. A query carries the CDR
request and the client's 33-byte attachment; the answer, computed in Zenoh's thread (a pure
function of an immutable configuration, cached per request bytes,
:class:`~racecar_hw.net.parameters.CdrAnswers`) goes back as a reply on the same key with an
attachment of the request's sequence number, a fresh timestamp and the client's GID, which is how
rmw_zenoh's client matches it to its request. See :mod:`racecar_hw.net.zenoh_bridge`.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from racecar_hw.base.clock import wall_ns
from racecar_hw.net import rmw
from racecar_hw.net.parameters import (
    PARAMETER_SERVICES,
    SERVICE_QOS,
    CdrAnswers,
    ParameterService,
    RequestRefused,
    ServiceSpec,
    service_name,
)
from racecar_hw.net.zenoh_node import ZenohNode

log = logging.getLogger(__name__)


class ZenohServices:
    """The parameter services of one node. ``stats`` (``service_calls``, ``service_errors``,
    ``set_calls``) is written under ``lock``."""

    def __init__(self, parameters: ParameterService, stats: Any, lock: threading.Lock) -> None:
        self.answers = CdrAnswers(parameters)
        self.stats = stats
        self.lock = lock
        self.declared = 0

    def declare(self, node: ZenohNode) -> None:
        """Declare every parameter service of ``node``, its answers computed ahead."""
        self.answers.warm()
        for spec in PARAMETER_SERVICES:
            name = service_name(node.names.namespace, node.names.name, spec.name)
            key = node.names.key(name, spec.srv_type)
            node.service(name, spec.srv_type, SERVICE_QOS, self._answerer(spec, name, key))
            self.declared += 1

    def _answerer(self, spec: ServiceSpec, name: str, key: str) -> Callable[[Any], None]:
        stats, lock, answers = self.stats, self.lock, self.answers

        def refuse(why: str) -> None:
            with lock:
                stats.service_errors += 1
                n = stats.service_errors
            if n in (1, 10, 100) or n % 1000 == 0:
                log.warning("zenoh: refused a call of %s: %s (%d so far)", name, why, n)

        def answer(query: Any) -> None:
            attachment, payload = query.attachment, query.payload
            if attachment is None or payload is None:
                refuse("no rmw_zenoh attachment" if attachment is None else "no request")
                return
            try:
                request = rmw.Attachment.decode(attachment.to_bytes())
                reply = answers.answer(spec.name, payload.to_bytes())
            except RequestRefused as err:
                refuse(str(err))
                return
            except Exception as err:  # noqa: BLE001 - hostile bytes: whatever the decoder raises
                refuse(f"malformed request ({type(err).__name__})")
                return
            if spec.name.startswith("set_"):
                with lock:
                    stats.set_calls += 1
                    n = stats.set_calls
                if n in (1, 10, 100) or n % 1000 == 0:
                    log.info("zenoh: a client called %s: refused, the parameters are read-only "
                             "(%d so far)", name, n)
            try:
                query.reply(key, reply, attachment=rmw.encode_attachment(
                    request.sequence_number, wall_ns(), request.gid))
            except Exception as err:  # noqa: BLE001 - the client went away: nothing to answer
                refuse(f"reply failed ({err!r})")
                return
            with lock:
                stats.service_calls += 1

        return answer
