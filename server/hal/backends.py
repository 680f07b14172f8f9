"""The HAL backends by name: `kinematic` (ideal), `sim` (MuJoCo physics), `canopen` (CiA 402 drives)."""

from __future__ import annotations

from typing import Any

from core.robot import TwinRobot
from server.hal.base import HardwareInterface

BACKENDS = ("sim", "kinematic", "canopen")


def make_hal(backend: str, twin: TwinRobot, control_period_s: float, **options: Any) -> HardwareInterface:
    """Construct a backend; imports are deferred so a clinic without MuJoCo or a CAN adapter needs neither.

    `canopen` options: `interface` and `channel` (python-can), optional `configuration` (drives TOML),
    `simulate` (number of simulated drives on the same bus) and `bitrate`.
    """
    if backend == "kinematic":
        from server.hal.kinematic import KinematicHal

        return KinematicHal(twin, control_period_s, **options)
    if backend == "sim":
        from server.hal.sim.backend import SimHal

        return SimHal(twin, control_period_s, **options)
    if backend == "canopen":
        from server.hal.canopen.master import create_canopen_hal

        interface, channel = options.pop("interface", "socketcan"), options.pop("channel", "can0")
        return create_canopen_hal(twin, control_period_s, interface, channel, **options)
    raise ValueError(f"backend = {backend!r}: must be one of {list(BACKENDS)}")
