"""Sample-clock recovery: each sample's time on the sensor's steady clock, in one place.

Every source's samples get their times here. The model is one line (``model.py``): sample
``k`` is taken at ``t_k = offset + k·period`` on the host's monotonic clock, the period the
sensor's real one (its oscillator is 0.5–2 % off nominal and drifts with temperature), and a
gap in the samples is a whole number of periods (:func:`whole_periods`). What differs is
what the host observes of that line, so there is one fit for each kind of observation:

=======================  =====================================================  =====================================
fit                      what the host sees                                     used by
=======================  =====================================================  =====================================
:class:`SampleClock`     a stamp per sample or block, late by a jittery          polling boards, the autopilot's IMU
(``stamped.py``)         latency, sometimes bursty, samples lost unseen         (``stamp_indexed``), ``estimators.run``
                         (or counted, ``stamp_indexed``); :func:`recover_times`  and offline evaluation
                         is the batch form
:class:`SensorClock`     the index of each sample (a FIFO counts them) and       the FIFO boards, through
(``bounded.py``)         two-sided bounds from each FIFO level read: the         ``drivers/fifo.py``'s ``FifoTimeline``
                         newest sample existed at the latch, the next did not
:class:`SensorClockMap`  the node's own timestamp of each sample (index and     the DroneCAN source
(``remote.py``)          period known): only the two clocks' offset is left
=======================  =====================================================  =====================================

All three are causal (a sample's time depends only on observations up to it), so the live
service and offline evaluation share them; replay never recovers again (it uses the times
stored in the log). Model, methods and measured limits: ``docs/timing.md``.
"""

from ahrs_service.core.sample_clock.bounded import SensorClock
from ahrs_service.core.sample_clock.model import whole_periods
from ahrs_service.core.sample_clock.remote import SensorClockMap
from ahrs_service.core.sample_clock.stamped import ClockTuning, SampleClock, recover_times

__all__ = ["ClockTuning", "SampleClock", "SensorClock", "SensorClockMap", "recover_times", "whole_periods"]
