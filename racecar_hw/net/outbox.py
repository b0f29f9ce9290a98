"""Moved to :mod:`racecar_hw.runtime.outbox` (the recorder shares it); kept for imports from before."""

from racecar_hw.runtime.outbox import BATCH_S, SENDER_NICE, WAKE_AT, Outbox

__all__ = ["BATCH_S", "SENDER_NICE", "WAKE_AT", "Outbox"]
