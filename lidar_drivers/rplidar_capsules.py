"""The newer RPLIDAR measurement capsules: ultra (answer type 0x84) and dense (0x85), both ways.

Pure numpy, no state: the stream decoder in :mod:`lidar_drivers.rplidar_codec` cuts the byte
stream into capsules and calls :func:`decode_ultra` / :func:`decode_dense`; the fake lidar builds
its stream with :func:`encode_ultra` / :func:`encode_dense`. Layouts and decoding rules as
Slamtec's SDK defines them (``sl_lidar_cmd.h``, ``handler_capsules.cpp``; reference
``lidars.md`` section 2), written here from that description:

* Both start like the legacy express capsule: ``0xA0|cs_lo``, ``0x50|cs_hi`` with ``cs`` the XOR of
  every byte after these two, then a u16 start angle in q6 degrees (bit 15: the first capsule
  after the scan request). A capsule's samples are spread evenly from its own start angle to the
  next capsule's, so a capsule is decoded only when the next one has arrived.
* **Ultra** (132 bytes): 32 u32 cabins of three samples: bits 0-11 the first distance in a
  variable bit scale (1 mm steps below 512 mm, then 2, 4, 8 and 16 mm), bits 12-21 and 22-31 two
  signed 10-bit predictions: the second sample relative to this cabin's first, the third relative
  to the *next* cabin's first, both in this scale's steps (511 and -512 mean "no return"). The
  device's angles are the rotor's; each sample's beam is ``7.5..8`` degrees behind it, by a
  distance-dependent amount (:func:`ultra_angle_offset_q16`), which the decoder subtracts.
* **Dense** (84 bytes): 40 u16 distances in mm, no angle correction.

Angles are device degrees, clockwise, in [0, 360); distances mm, 0 = no return.
"""

from __future__ import annotations

import numpy as np

ULTRA_LEN = 132
ULTRA_SAMPLES = 96
DENSE_LEN = 84
DENSE_SAMPLES = 40
FULL_TURN_Q6 = 360 * 64
FULL_TURN_Q16 = 360 << 16

ULTRA_DTYPE = np.dtype([("sync_cs_lo", "u1"), ("sync_cs_hi", "u1"), ("start", "<u2"),
                        ("cabins", "<u4", (32,))])
DENSE_DTYPE = np.dtype([("sync_cs_lo", "u1"), ("sync_cs_hi", "u1"), ("start", "<u2"),
                        ("cabins", "<u2", (DENSE_SAMPLES,))])

#: Variable bit scale, by level (the step is 2**level mm): first scaled value, first distance mm.
_VBS_SCALED = np.array([0, 512, 1280, 1792, 3328], dtype=np.int64)
_VBS_MM = np.array([0, 512, 2048, 4096, 16384], dtype=np.int64)
#: Largest distance the 12-bit scaled value can carry (mm).
ULTRA_MAX_MM = 16384 + ((4095 - 3328) << 4)
#: The mean beam lag of an ultra sample with no usable distance, and the base of the
#: distance-dependent one, in q16 radians (the SDK's constants, truncated as it truncates them).
_OFFSET_FAR_Q16 = int(8 * 3.1415926535 * 65536 / 180)
_OFFSET_NEAR_Q16 = int(7.5 * 3.1415926535 * 65536 / 180)


def varbitscale_decode(scaled: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """12-bit scaled values -> (distance mm, scale level 0..4), elementwise."""
    s = np.asarray(scaled, dtype=np.int64)
    level = np.searchsorted(_VBS_SCALED, s, side="right") - 1
    return _VBS_MM[level] + ((s - _VBS_SCALED[level]) << level), level


def varbitscale_encode(mm: np.ndarray) -> np.ndarray:
    """Distances (mm, >= 0) -> the nearest 12-bit scaled values (clipped at :data:`ULTRA_MAX_MM`)."""
    d = np.clip(np.rint(np.asarray(mm, dtype=np.float64)), 0, ULTRA_MAX_MM).astype(np.int64)
    level = np.searchsorted(_VBS_MM, d, side="right") - 1
    half = (1 << level) >> 1
    return np.minimum(_VBS_SCALED[level] + ((d - _VBS_MM[level] + half) >> level), 4095)


def ultra_angle_offset_q16(dist_q2: np.ndarray) -> np.ndarray:
    """How far (q16 degrees) an ultra sample's beam lags its rotor angle, by distance (q2 mm)."""
    dq2 = np.asarray(dist_q2, dtype=np.int64)
    near = dq2 < 200  # below 50 mm (and no return): the mean lag
    k2 = 98361 // np.where(near, 200, dq2)
    rad_q16 = np.where(near, _OFFSET_NEAR_Q16, _OFFSET_FAR_Q16 - (k2 << 6) - (k2 ** 3) // 98304)
    return (rad_q16 * 180 / 3.14159265).astype(np.int64)  # truncated, as in the SDK


def _sign10(v: np.ndarray) -> np.ndarray:
    return v - ((v & 0x200) << 1)


def _start_q8(rec: np.ndarray) -> np.ndarray:
    return (rec["start"].astype(np.int64) & 0x7FFF) << 2


def _spans_q8(start_q8: np.ndarray) -> np.ndarray:
    """Angle from each capsule's start to the next one's (q8 degrees, wrapping at 360)."""
    diff = start_q8[1:] - start_q8[:-1]
    return diff + (diff < 0) * (360 << 8)


def _sweep(start_q8: np.ndarray, inc_q16: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Raw q16 angles of ``n`` samples per capsule, and where a revolution starts."""
    raw = (start_q8[:-1] << 8)[:, None] + inc_q16[:, None] * np.arange(n, dtype=np.int64)[None, :]
    start = ((raw + inc_q16[:, None]) % FULL_TURN_Q16) < inc_q16[:, None]
    return raw, start


def decode_ultra(caps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples of every capsule but the last of ``caps`` (K consecutive valid ones, K x 132 bytes).

    Returns (angle_deg, distance_mm, revolution start), 96 samples per capsule, in time order.
    """
    rec = np.ascontiguousarray(caps, dtype=np.uint8).view(ULTRA_DTYPE).reshape(-1)
    k = len(rec) - 1
    start_q8 = _start_q8(rec)
    inc_q16 = (_spans_q8(start_q8) << 3) // 3
    cab = rec["cabins"].astype(np.int64)
    major, level = varbitscale_decode(cab & 0xFFF)
    n = k * 32
    m1, l1 = major.ravel()[:n], level.ravel()[:n]
    m2, l2 = major.ravel()[1:n + 1], level.ravel()[1:n + 1]  # the next cabin's, across capsules
    borrow = (m1 == 0) & (m2 != 0)
    base1, lvl1 = np.where(borrow, m2, m1), np.where(borrow, l2, l1)
    p1 = _sign10((cab[:k] >> 12) & 0x3FF).ravel()
    p2 = _sign10((cab[:k] >> 22) & 0x3FF).ravel()
    d1 = np.where((p1 == 511) | (p1 == -512), 0, (p1 << lvl1) + base1)  # 511, -512: no return
    d2 = np.where((p2 == 511) | (p2 == -512), 0, (p2 << l2) + m2)
    dist = np.maximum(np.stack([m1, d1, d2], axis=1).reshape(k, ULTRA_SAMPLES), 0)
    raw, start = _sweep(start_q8, inc_q16, ULTRA_SAMPLES)
    angle_q6 = ((raw - ultra_angle_offset_q16(dist << 2)) >> 10) % FULL_TURN_Q6
    return angle_q6.ravel() * (1 / 64), dist.ravel().astype(np.float64), start.ravel()


def decode_dense(caps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples of every capsule but the last of ``caps`` (K consecutive valid ones, K x 84 bytes).

    Returns (angle_deg, distance_mm, revolution start), 40 samples per capsule, in time order.
    """
    rec = np.ascontiguousarray(caps, dtype=np.uint8).view(DENSE_DTYPE).reshape(-1)
    start_q8 = _start_q8(rec)
    inc_q16 = (_spans_q8(start_q8) << 8) // DENSE_SAMPLES
    raw, _ = _sweep(start_q8, inc_q16, DENSE_SAMPLES)
    # the SDK's rule for dense capsules: a wrap within two increments, the first of such a pair
    # (its increment is truncated, so a wrap exactly at a capsule start shows one sample late)
    near = (((raw + inc_q16[:, None]) % FULL_TURN_Q16) < (inc_q16[:, None] << 1)).ravel()
    start = near & ~np.concatenate([[False], near[:-1]])
    angle_q6 = (raw >> 10) % FULL_TURN_Q6
    dist = rec["cabins"][:-1].astype(np.float64)
    return angle_q6.ravel() * (1 / 64), dist.ravel(), start


def capsules_valid(arr: np.ndarray) -> np.ndarray:
    """Per capsule (rows of ``arr``): sync nibbles, checksum and start angle are right."""
    cs = np.bitwise_xor.reduce(arr[:, 2:], axis=1)
    sync = ((arr[:, 0] & 0xF0) == 0xA0) & ((arr[:, 1] & 0xF0) == 0x50)
    declared = (arr[:, 0] & 0x0F) | ((arr[:, 1] & 0x0F) << 4)
    start_q6 = (arr[:, 2].astype(np.int32) | (arr[:, 3].astype(np.int32) << 8)) & 0x7FFF
    return sync & (declared == cs) & (start_q6 < FULL_TURN_Q6)


def _finish(out: np.ndarray, start_angle_deg: np.ndarray, first: bool) -> bytes:
    """Start angles, the first-capsule flag and the checksum into capsules ``out`` (K x len)."""
    starts = np.round(np.mod(np.asarray(start_angle_deg, dtype=np.float64), 360.0) * 64)
    sa = starts.astype(np.int64) % FULL_TURN_Q6
    if first and len(sa):
        sa[0] |= 0x8000
    out[:, 2], out[:, 3] = sa & 0xFF, sa >> 8
    cs = np.bitwise_xor.reduce(out[:, 2:], axis=1)
    out[:, 0] = 0xA0 | (cs & 0x0F)
    out[:, 1] = 0x50 | (cs >> 4)
    return out.tobytes()


def encode_dense(start_angle_deg: np.ndarray, distance_mm: np.ndarray, first: bool = False) -> bytes:
    """Dense capsules: one start angle (degrees clockwise) and 40 distances (mm) per capsule."""
    k = len(start_angle_deg)
    out = np.zeros((k, DENSE_LEN), dtype=np.uint8)
    d = np.clip(np.rint(np.asarray(distance_mm, dtype=np.float64)), 0, 0xFFFF).astype("<u2")
    out[:, 4:] = d.reshape(k, DENSE_SAMPLES).view(np.uint8).reshape(k, DENSE_SAMPLES * 2)
    return _finish(out, start_angle_deg, first)


def encode_ultra(start_angle_deg: np.ndarray, distance_mm: np.ndarray, next_mm: float,
                 first: bool = False) -> bytes:
    """Ultra capsules: one start angle (degrees clockwise) and 96 distances (mm) per capsule.

    ``next_mm`` is the first distance of the capsule that will follow (the last cabin's third
    sample is predicted from it). A sample whose prediction does not fit 10 bits (a jump of more
    than 510 steps from its base, e.g. a return next to a no-return base) goes out as "no
    return": the format cannot carry it, and a missing beam is safer than a wrong one. Distances
    beyond :data:`ULTRA_MAX_MM` read as :data:`ULTRA_MAX_MM`.
    """
    k = len(start_angle_deg)
    d = np.asarray(distance_mm, dtype=np.float64).reshape(k * 32, 3)
    scaled = varbitscale_encode(np.append(d[:, 0], next_mm))
    major, level = varbitscale_decode(scaled)
    m1, l1, m2, l2 = major[:-1], level[:-1], major[1:], level[1:]
    borrow = (m1 == 0) & (m2 != 0)
    base1, lvl1 = np.where(borrow, m2, m1), np.where(borrow, l2, l1)

    def predict(target: np.ndarray, base: np.ndarray, lvl: np.ndarray) -> np.ndarray:
        p = np.rint((target - base) / (1 << lvl)).astype(np.int64)
        return np.where((target > 0) & (p >= -511) & (p <= 510), p, 511) & 0x3FF

    word = (scaled[:-1] | (predict(d[:, 1], base1, lvl1) << 12)
            | (predict(d[:, 2], m2, l2) << 22)).astype("<u4")
    out = np.zeros((k, ULTRA_LEN), dtype=np.uint8)
    out[:, 4:] = word.reshape(k, 32).view(np.uint8).reshape(k, 128)
    return _finish(out, start_angle_deg, first)


def ultra_beam_lag_deg(distance_mm: np.ndarray) -> np.ndarray:
    """How far (degrees) behind its rotor angle an ultra sample at ``distance_mm`` is measured."""
    dq2 = np.rint(np.asarray(distance_mm, dtype=np.float64) * 4).astype(np.int64)
    return ultra_angle_offset_q16(dq2) / 65536.0

