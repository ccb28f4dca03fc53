"""MAVLink AHRS companion service: the package root. Layers and layout: docs/design.md."""

from ahrs_service import _moved

_moved.install()
