"""The `sim` HAL backend: the MuJoCo twin (this package) stepped once per control period.

The emulated drives (`server.hal.sim.drives`) run a position loop with velocity and force limits, their own
quick stop and holding brake, and report CiA 402 states per axis. Each drive watches the set-points like a
heartbeat consumer: when no write() arrives for `communication_timeout_s` of drive (simulation) time while
enabled, every drive quick-stops by itself and faults, and the HAL enters FAULT. Homing is immediate (the
sliders' encoders are absolute in the simulator). Force plates and harness come from the MuJoCo sensors
with the rigid payload, or from the simulated patient once one is attached (`attach_patient`).

Time: read() advances the physics by one control period under the set-points written last, then reports;
`hardware_time_s` is the simulation clock.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from core.dynamics import PayloadModel
from core.robot import TwinRobot
from server.hal.base import (
    AXIS_COUNT,
    DriveState,
    HalCommand,
    HalError,
    HalReading,
    HalState,
    HardwareInterface,
    PatientLike,
)
from server.hal.sim.drives import ServoParameters
from server.hal.sim.mjcf import SimModelOptions
from server.hal.sim.simulator import SimulatorOptions, TwinSimulator


class SimHal(HardwareInterface):
    simulates_patient = True
    measures_patient_loads = True  # the simulated patient's plates and harness

    def __init__(
        self,
        twin: TwinRobot,
        control_period_s: float,
        *,
        communication_timeout_s: float = 0.05,
        servo: ServoParameters | None = None,
        payload: PayloadModel | None = None,
        physics_substeps: int = 1,
    ) -> None:
        super().__init__(twin, control_period_s)
        if not communication_timeout_s >= 2.0 * control_period_s:
            raise ValueError(
                f"communication_timeout_s = {communication_timeout_s}: must be >= two control periods "
                f"({2.0 * control_period_s} s)"
            )
        limits = twin.robot.limits
        servo = servo or ServoParameters(
            velocity_limit_m_s=limits.slider_velocity_max_m_s, force_limit_n=limits.drive_force_max_n
        )
        payload = payload if payload is not None else PayloadModel.from_body(75.0, 1.75)
        self.communication_timeout_s = communication_timeout_s
        self._options = SimulatorOptions(
            control_period_s=control_period_s,
            physics_substeps=physics_substeps,
            model=SimModelOptions(payload=payload),
            servo=servo,
        )
        self.simulator: TwinSimulator | None = None
        self._homed = np.zeros(AXIS_COUNT, dtype=bool)
        self._last_write_s = 0.0

    @property
    def drive_targets_m(self) -> np.ndarray:
        """The set-points the drives hold now (what reached them), a copy."""
        return self._sim().drives.target_m.copy()

    def attach_patient(self, patient: PatientLike | None) -> None:
        """Put a simulated patient on the platforms (None: back to the rigid payload). Not while ACTIVE."""
        if self.state is HalState.ACTIVE:
            raise HalError("attach_patient: deactivate the HAL first")
        parameters = None if patient is None else patient.parameters
        seed = 0 if patient is None else patient.seed
        self._options = replace(self._options, patient=parameters, patient_seed=seed)
        if self.simulator is not None:
            self._build()

    def _sim(self) -> TwinSimulator:
        if self.simulator is None:
            raise HalError("the sim backend is not configured")
        return self.simulator

    def _build(self) -> None:
        self.simulator = TwinSimulator(self.twin, self._options)  # its drives boot into SWITCH ON DISABLED

    # --- lifecycle hooks ---------------------------------------------------------------------------

    def _on_configure(self) -> None:
        self._build()

    def _on_activate(self) -> None:
        simulator = self._sim()
        simulator.drives.enable(simulator.positions_m)
        self._last_write_s = simulator.time_s

    def _on_deactivate(self) -> None:
        simulator = self._sim()
        simulator.drives.disable(simulator.positions_m)

    def _on_quick_stop(self) -> None:
        simulator = self._sim()
        simulator.drives.quick_stop(simulator.positions_m, simulator.velocities_m_s)

    def _on_disable(self) -> None:
        simulator = self._sim()
        simulator.drives.disable(simulator.positions_m)

    def _on_reset_fault(self) -> None:
        simulator = self._sim()
        simulator.drives.reset_fault(simulator.positions_m)

    def _on_home(self) -> None:
        self._homed[:] = True

    def _on_shutdown(self) -> None:
        self.simulator = None
        self._homed[:] = False

    # --- cyclic hooks ------------------------------------------------------------------------------

    def _on_write(self, command: HalCommand) -> None:
        simulator = self._sim()
        simulator.drives.set_command(command.positions_m, command.velocity_feedforward_m_s, command.force_feedforward_n)
        self._last_write_s = simulator.time_s

    def _on_read(self, out: HalReading) -> None:
        simulator = self._sim()
        simulator.advance()
        self._watch_heartbeat(simulator)
        out.positions_m[:] = simulator.positions_m
        out.velocities_m_s[:] = simulator.velocities_m_s
        out.drive_forces_n[:] = simulator.drives.forces_n
        out.drive_states[:] = simulator.drives.states
        out.homed[:] = self._homed
        out.plate_force_z_n[:] = simulator.plate_force_z_n
        out.plate_cop_m[:] = simulator.plate_cop_m
        out.harness_load_n = simulator.harness_load_n
        out.monotonic_ns = time.perf_counter_ns()
        out.hardware_time_s = simulator.time_s

    def _watch_heartbeat(self, simulator: TwinSimulator) -> None:
        """The drives' own reaction to silence: quick stop, then FAULT; the HAL follows into FAULT."""
        drives = simulator.drives
        if self.state is HalState.ACTIVE:
            silent_s = simulator.time_s - self._last_write_s
            if silent_s > self.communication_timeout_s:
                drives.quick_stop(simulator.positions_m, simulator.velocities_m_s, fault=True)
                self.fault(f"communication lost: no set-point for {silent_s * 1e3:.1f} ms; drives quick-stopped")
        if self.state is not HalState.FAULT and np.any(drives.states == DriveState.FAULT):
            axis = int(np.argmax(drives.states == DriveState.FAULT))
            self.fault(f"{self.axis_name(axis)}: drive fault")

    def _measured_positions(self) -> np.ndarray:
        return self._sim().positions_m
