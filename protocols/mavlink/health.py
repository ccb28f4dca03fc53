"""SYS_STATUS (message 1) and STATUSTEXT (message 253) encoders, and the heartbeat's MAV_STATE.

SYS_STATUS reports the gyroscope, accelerometer and magnetometer as
MAV_SYS_STATUS_SENSOR_3D_GYRO/ACCEL/MAG present/enabled/health bits, and the estimator as
MAV_SYS_STATUS_AHRS. The magnetometer counts as enabled only when the estimator uses it (not in
reduced mode). ``load`` is the estimator loop load in d% (0..1000). Battery fields carry
MAVLink's "not sent" values. errors_comm = sensor bus errors, errors_count1 = loop overruns,
errors_count2 = rejected samples, errors_count3 = IMU samples lost (every cause: FIFO
overflow, bus error, gap, host stall; by cause in STATUSTEXT and the log's /loop) (all
saturate at 65535).

STATUSTEXT text is at most 50 bytes of UTF-8. Longer texts are split into chunks that share a
non-zero ``id`` and count ``chunk_seq`` from 0, as MAVLink 2 defines; the final chunk is
shorter than 50 bytes (its NUL marks the end), so a text that fills whole chunks exactly gets
an empty final chunk. Chunks break between characters, never inside a UTF-8 sequence.
"""

from __future__ import annotations

from ahrs_service.protocols.mavlink.dialect import mavlink
from ahrs_service.protocols.mavlink.telemetry import SensorStatus, Telemetry

STATUSTEXT_LEN = 50
MAX_CHUNKS = 256  # chunk_seq is a uint8

_GYRO = mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
_ACCEL = mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
_MAG = mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
_AHRS = mavlink.MAV_SYS_STATUS_AHRS


def _u16(n: int) -> int:
    return max(0, min(0xFFFF, int(n)))


def sensor_bits(t: Telemetry) -> tuple[int, int, int]:
    """(present, enabled, health) MAV_SYS_STATUS_SENSOR bitmaps of ``t``."""
    present = enabled = health = 0
    mag = SensorStatus(t.mag_status.present, t.mag_status.enabled and not t.reduced_mode, t.mag_status.healthy)
    for bit, status in ((_GYRO, t.gyro), (_ACCEL, t.accel), (_MAG, mag)):
        if status.present:
            present |= bit
            if status.enabled:
                enabled |= bit
            if status.healthy:
                health |= bit
    present |= _AHRS
    enabled |= _AHRS
    if t.ahrs_healthy:
        health |= _AHRS
    return present, enabled, health


def encode_sys_status(t: Telemetry) -> "mavlink.MAVLink_sys_status_message":
    """SYS_STATUS: sensor bits, load (d%), error counters; battery fields "not sent"."""
    present, enabled, health = sensor_bits(t)
    load = max(0, min(1000, round(float(t.load_percent) * 10.0)))
    return mavlink.MAVLink_sys_status_message(
        present, enabled, health, load,
        0xFFFF, -1, -1,  # voltage, current, remaining: not measured
        0, _u16(t.comm_errors), _u16(t.overruns), _u16(t.sensor_faults), _u16(t.lost_samples), 0,
    )


def system_state(t: Telemetry | None) -> int:
    """MAV_STATE for the heartbeat: BOOT before the first estimate, CRITICAL when the gyroscope,
    accelerometer or estimator is unhealthy, else ACTIVE."""
    if t is None:
        return mavlink.MAV_STATE_BOOT
    if not (t.gyro.healthy and t.accel.healthy and t.ahrs_healthy):
        return mavlink.MAV_STATE_CRITICAL
    return mavlink.MAV_STATE_ACTIVE


def split_statustext(text: str) -> list[bytes]:
    """UTF-8 chunks of ``text``, each ≤ 50 bytes, split between characters.

    A text of one chunk is returned as one chunk of < 50 bytes or exactly 50 bytes; a longer
    one ends with a chunk shorter than 50 bytes (possibly empty) so receivers see its end.
    """
    data = text.encode("utf-8")
    if len(data) <= STATUSTEXT_LEN:
        return [data]
    chunks: list[bytes] = []
    start = 0
    while start < len(data) and len(chunks) < MAX_CHUNKS - 1:
        end = min(start + STATUSTEXT_LEN, len(data))
        # step back over UTF-8 continuation bytes (10xxxxxx) so no character is cut
        while end < len(data) and end > start and (data[end] & 0xC0) == 0x80:
            end -= 1
        chunks.append(data[start:end])
        start = end
    if len(chunks[-1]) == STATUSTEXT_LEN:
        chunks.append(b"")
    return chunks


def encode_statustext(severity: int, text: str, chunk_id: int) -> list["mavlink.MAVLink_statustext_message"]:
    """STATUSTEXT messages for ``text`` at MAV_SEVERITY ``severity``.

    ``chunk_id`` (1..65535) is used only when the text needs several chunks; a single chunk
    goes out with id 0 ("the only chunk"). Texts beyond 255 chunks are cut.
    """
    if not 0 <= int(severity) <= 7:
        raise ValueError(f"MAV_SEVERITY must be 0..7, got {severity}")
    chunks = split_statustext(text)
    if len(chunks) == 1:
        return [mavlink.MAVLink_statustext_message(int(severity), chunks[0], 0, 0)]
    return [mavlink.MAVLink_statustext_message(int(severity), c, int(chunk_id), i) for i, c in enumerate(chunks)]
