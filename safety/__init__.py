"""The safety-stop controller: never let the car hit what the lidar sees.

``SafetyController`` (pure logic), ``SafetyNode`` (its bus adapter, inserted by the daemon after
the mux), ``ConeSafety`` (the seeds' simple stop on the mux safety input) and ``SafetyParams``.
"""

from safety.controller import Obstacle, SafetyController, SafetyState
from safety.node import ConeSafety, SafetyNode
from safety.params import SafetyParams

__all__ = ["ConeSafety", "Obstacle", "SafetyController", "SafetyNode", "SafetyParams", "SafetyState"]
