"""Lost samples by cause: how they add up and where they are reported (SYS_STATUS, text)."""

from __future__ import annotations

from ahrs_service.core.samples import LossCounts, SampleBlock, SourceDiagnostics
from ahrs_service.protocols.mavlink import Telemetry
from ahrs_service.protocols.mavlink.health import encode_sys_status


def test_loss_counts_add_up_by_cause():
    total = LossCounts()
    total.add(LossCounts(fifo_overflow=58))
    total.add(LossCounts(bus_error=3, gap=2, host_stall=1))
    assert total.as_dict() == {"fifo_overflow": 58, "bus_error": 3, "gap": 2, "host_stall": 1, "total": 64}
    d = SourceDiagnostics()
    d.lost.add(total)
    assert d.as_dict()["lost"]["total"] == 64
    assert len(SampleBlock.empty(LossCounts(gap=4))) == 0


def test_sys_status_errors_count3_is_the_lost_samples():
    t = Telemetry.from_quaternion(0, (1.0, 0.0, 0.0, 0.0), lost_samples=70_000)
    msg = encode_sys_status(t)
    assert msg.errors_count3 == 65535  # saturates
    assert encode_sys_status(Telemetry.from_quaternion(0, (1.0, 0.0, 0.0, 0.0), lost_samples=12)).errors_count3 == 12
