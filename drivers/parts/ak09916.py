"""AKM AK09916 magnetometer (inside the ICM-20948, behind its auxiliary I2C master), and its twin.

Register map used (AKM AK09916 datasheet, register map; 7-bit address 0x0C on the aux bus):

=====  ===========  ===========================================================
0x01   WIA2         0x09 (device ID; WIA1 0x00 = 0x48, the company ID)
0x10   ST1          bit 0 DRDY, bit 1 DOR
0x11…  HXL…HZH      X, Y, Z little-endian two's complement, 0.15 µT/LSB
0x18   ST2          bit 3 HOFL (overflow); reading ST2 ends the read and clears DRDY
0x31   CNTL2        MODE 4:0: 0x00 power-down, 0x02 10 Hz, 0x04 20 Hz, 0x06 50 Hz, 0x08 100 Hz
0x32   CNTL3        bit 0 SRST
=====  ===========  ===========================================================

The ICM-20948 reads ST1 … ST2 (9 bytes, 0x10 … 0x18) each sample with its I2C slave 0 and
puts them in EXT_SLV_SENS_DATA_00 … 08 and, with SLV_0_FIFO_EN, into each FIFO packet.
Field range ±32752 counts (±4912 µT). Die axes against the ICM-20948 accelerometer: X, −Y, −Z
(PX4: accelerometer "+x forward, +y left, +z up", AK09916 "+X forward, +Y right, +Z down").

Verified against (2026-12-02; read, not copied): PX4-Autopilot
``src/drivers/imu/invensense/icm20948/AKM_AK09916_registers.hpp`` (25ed6b67: address 0x0C,
WIA1 0x48, WIA2 0x09, ST1 DRDY/DOR, HXL…HZH, ST2 HOFL, CNTL2 modes 0x02/0x04/0x06/0x08,
CNTL3 SRST) and ``ICM20948_AK09916.cpp`` (542f41f2: 0.15 µT/LSB, little-endian HXL/HXH, the
axes); Linux ``drivers/iio/magnetometer/ak8975.c`` (AK09916: WIA2 0x09, the AK09912 register
layout, range 32752, 0.15 µT scale). "Reading ST2 ends the read and clears DRDY" is the AKM
data-protection rule both drivers rely on by always reading through ST2; DOR's exact set
condition (a measurement skipped unread) is not spelled out by either. The section number
formerly cited here (§9) could not be confirmed and was dropped.
"""

from __future__ import annotations

ADDRESS = 0x0C
WIA2, WIA2_VALUE, ST1, HXL, ST2, CNTL2, CNTL3 = 0x01, 0x09, 0x10, 0x11, 0x18, 0x31, 0x32
DRDY, DOR, HOFL, SRST = 0x01, 0x02, 0x08, 0x01
MODES_HZ = {0x02: 10.0, 0x04: 20.0, 0x06: 50.0, 0x08: 100.0}
UT_PER_LSB = 0.15
FULL_SCALE = 32752  # ±4912 µT
