"""`ssp-rehab drives`: bring up the twelve CiA 402 drives, home them, run a short profile, report.

On `--bus virtual --simulate 12` the drives are simulated on python-can's virtual bus; on a real
interface (`--bus socketcan --channel can0 --simulate 0`) the same sequence drives real hardware.
Millimetres at this edge; the HAL speaks metres.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from server.hal.canopen.master import CanopenHal

import typer

from core.errors import InvalidValueError
from server.cli.output import console, emit, fail, progress_bar
from server.cli.robot_option import ROBOT_OPTION, twin_from_option

FEEDBACK_TIMEOUT_S = 1.0


def grouped_transitions(hal: CanopenHal) -> list[dict[str, Any]]:
    """State changes the master saw, one entry per (cycle, from, to) with the axes that made it."""
    from server.hal.base import AXIS_COUNT, HardwareInterface

    groups: dict[tuple[int, str, str], list[str]] = {}
    for cycle, axis, source, target in hal.transition_log:
        groups.setdefault((cycle, source.name, target.name), []).append(HardwareInterface.axis_name(axis))
    return [
        {"cycle": cycle, "from": source, "to": target, "axes": "all" if len(axes) == AXIS_COUNT else axes}
        for (cycle, source, target), axes in groups.items()
    ]


def run_profile(hal: CanopenHal, amplitude_m: float, duration_s: float, advance: Any) -> dict[str, float]:
    """Every axis out by `amplitude_m` and back (raised cosine), paced at the control period.

    The drive reports, at SYNC k, the position it reached following the target of SYNC k − 1, so the
    following error compares each reading with the previous command. The demo runs lock-step: the
    next SYNC waits for every TPDO of the last one, so each reading belongs to its own cycle; a cycle
    whose answers took longer than the control period is counted as late.
    """
    import numpy as np

    from server.hal.base import HalCommand, HalError, HalReading

    reading, command = HalReading(), HalCommand()
    hal.read(reading)
    start = reading.positions_m.copy()
    outward = hal.scaling.direction
    cycles = max(2, round(duration_s / hal.control_period_s))
    previous = start.copy()
    max_error_m = 0.0
    late_cycles = 0
    cycle_times: list[float] = []
    next_tick = time.perf_counter()
    for k in range(1, cycles + 1):
        began = time.perf_counter()
        phase = 2.0 * math.pi * k / cycles
        command.positions_m[:] = start + outward * amplitude_m * (1.0 - math.cos(phase)) / 2.0
        hal.write(command)
        if not hal.wait_for_feedback(FEEDBACK_TIMEOUT_S):
            raise HalError(f"no answer from every drive within {FEEDBACK_TIMEOUT_S} s at cycle {k}")
        late_cycles += time.perf_counter() - began > hal.control_period_s
        hal.read(reading)
        max_error_m = max(max_error_m, float(np.max(np.abs(previous - reading.positions_m))))
        previous[:] = command.positions_m
        cycle_times.append(time.perf_counter() - began)
        advance(1)
        next_tick += hal.control_period_s
        time.sleep(max(0.0, next_tick - time.perf_counter()))
    return {
        "profile_cycles": cycles,
        "cycles_over_period": late_cycles,
        "max_following_error_mm": max_error_m * 1e3,
        "mean_cycle_ms": float(np.mean(cycle_times)) * 1e3,
    }


def register(app: typer.Typer) -> None:
    @app.command()
    def drives(
        bus: str = typer.Option("virtual", "--bus", help="python-can interface: virtual, socketcan, pcan…"),
        channel: str | None = typer.Option(None, "--channel", help="Bus channel (default: a fresh virtual one)."),
        simulate: int = typer.Option(0, "--simulate", help="Simulated drives on the bus (0–12; 12 = whole robot)."),
        period_ms: float = typer.Option(1.0, "--period-ms", help="Control period: SYNC and CSP cycle (ms)."),
        homing_method: int | None = typer.Option(None, "--homing-method", help="Override 0x6098 for every drive."),
        drives_file: Path | None = typer.Option(None, "--drives", help="Drive configuration TOML (default: built-in)."),
        bitrate: int | None = typer.Option(None, "--bitrate", help="Real bus bitrate (bit/s): checks the bus load."),
        amplitude_mm: float = typer.Option(20.0, "--amplitude-mm", help="Profile excursion outwards from home (mm)."),
        duration_s: float = typer.Option(1.0, "--duration-s", help="Profile duration (s)."),
        as_json: bool = typer.Option(False, "--json", help="Print the report as JSON."),
        robot_file: Path | None = ROBOT_OPTION,
    ) -> None:
        """Enable all axes, home them, move them through a short profile and print the state transitions."""
        from server.hal.base import AXIS_COUNT, DriveState, HalError, HalReading, HardwareInterface
        from server.hal.canopen.master import create_canopen_hal
        from server.hal.canopen.units import load_drive_configuration

        if not 0.0 < amplitude_mm <= 100.0:
            raise fail(f"amplitude_mm = {amplitude_mm}: must be in (0, 100] mm", as_json=as_json)
        if not 0.1 <= duration_s <= 60.0:
            raise fail(f"duration_s = {duration_s}: must be in [0.1, 60] s", as_json=as_json)
        try:
            twin = twin_from_option(robot_file)
            configuration = load_drive_configuration(drives_file)
            if homing_method is not None:
                configuration = configuration.with_homing_method(homing_method)
            channel_name = channel or f"ssp-drives-{os.getpid()}"
            hal = create_canopen_hal(
                twin,
                period_ms / 1e3,
                bus,
                channel_name,
                configuration=configuration,
                simulate=simulate,
                bitrate=bitrate,
            )
        except (InvalidValueError, HalError, ValueError) as error:
            raise fail(str(error), as_json=as_json) from error
        started = time.perf_counter()
        try:
            hal.configure()
            hal.home()
            hal.activate()
            with progress_bar("profile", round(duration_s * 1e3 / period_ms), enabled=not as_json) as advance:
                figures = run_profile(hal, amplitude_mm / 1e3, duration_s, advance)
            hal.deactivate()
            reading = HalReading()
            hal.read(reading)
        except (HalError, ValueError) as error:
            events = [e["message"] for e in hal.drain_events()]
            hal.shutdown()
            raise fail(f"{error}" + (f" (events: {'; '.join(events)})" if events else ""), as_json=as_json) from error
        hal.shutdown()
        data: dict[str, Any] = {
            "bus": {"interface": bus, "channel": channel_name},
            "simulated_drives": simulate,
            "control_period_ms": period_ms,
            "homing_methods": sorted({a.drive_type.homing_method for a in configuration.axes}),
            "axes": [
                {
                    "axis": HardwareInterface.axis_name(axis),
                    "node_id": hal.node_ids[axis],
                    "final_state": DriveState(int(reading.drive_states[axis])).name,
                    "homed": bool(reading.homed[axis]),
                    "position_mm": float(reading.positions_m[axis]) * 1e3,
                }
                for axis in range(AXIS_COUNT)
            ],
            "transitions": grouped_transitions(hal),
            "cycles": hal.sync_count,
            **figures,
            "wall_time_s": time.perf_counter() - started,
            "events": [{"kind": e["kind"], "message": e["message"]} for e in hal.drain_events()],
        }
        emit(data, as_json=as_json, human=_print_report)


def _print_report(data: dict[str, Any]) -> None:
    console.print("[bold]state transitions[/]")
    for group in data["transitions"]:
        axes = group["axes"] if group["axes"] == "all" else ", ".join(group["axes"])
        console.print(f"  cycle {group['cycle']:5d}: {group['from']} → {group['to']}  ({axes})")
    console.print("[bold]axes[/]")
    for axis in data["axes"]:
        homed = "homed" if axis["homed"] else "NOT homed"
        console.print(
            f"  {axis['axis']:15s} node {axis['node_id']:3d}  {axis['final_state']:20s} {homed:9s} "
            f"{axis['position_mm']:9.2f} mm"
        )
    console.print(
        f"cycles: {data['cycles']}  profile: {data['profile_cycles']} cycles, "
        f"mean {data['mean_cycle_ms']:.3f} ms/cycle ({data['cycles_over_period']} longer than the period)  "
        f"max following error: {data['max_following_error_mm']:.4f} mm"
    )
