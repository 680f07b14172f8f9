"""The `kinematic` HAL backend: ideal drives that reach every set-point exactly, at the write.

It is a real backend, not a test hack (ros2_control's mock hardware): commands go through the base
class's validation, every axis reports its CiA 402 `DriveState`, and like a real drive it stops by
itself when set-points stop arriving (communication-loss stop: no write for `communication_timeout_s`
while enabled → quick stop, FAULT). With a patient attached (`attach_patient`), the simulated patient
(core.patient) stands on the platforms and produces the force-plate and harness readings; otherwise
those read zero. Drive forces are the command's force feed-forward: an ideal drive delivers exactly
the force the inverse dynamics predicted.
"""

from __future__ import annotations

import time

import numpy as np

from core.patient import SimulatedPatient
from core.robot import TwinRobot
from core.twin_kernels import TwinKernels
from server.hal.base import AXIS_COUNT, DriveState, HalCommand, HalReading, HalState, HardwareInterface, PatientLike
from server.hal.canopen.cia402 import DriveStateMachines


class KinematicHal(HardwareInterface):
    simulates_patient = True
    measures_patient_loads = True  # the simulated patient's plates and harness

    def __init__(self, twin: TwinRobot, control_period_s: float, *, communication_timeout_s: float = 0.05) -> None:
        super().__init__(twin, control_period_s)
        self.communication_timeout_ns = int(communication_timeout_s * 1e9)
        self._kernels = TwinKernels(twin, control_period_s)
        self._positions = self._kernels.neutral_sliders()
        self._velocities = np.zeros(AXIS_COUNT)
        self._forces = np.zeros(AXIS_COUNT)
        self._drives: DriveStateMachines | None = None  # the drives boot at configure()
        self._homed = np.zeros(AXIS_COUNT, dtype=bool)
        self.last_write_ns: int | None = None
        self.writes = 0
        self._ticks = 0
        self._patient: SimulatedPatient | None = None
        self._stance = np.zeros(6)
        self._stance_velocity = np.zeros(6)
        self._stance_scratch = np.zeros(6)
        self._support_acceleration = np.zeros(3)

    def attach_patient(self, patient: PatientLike | None) -> None:
        """Put a simulated patient on the platforms (None takes them off)."""
        if patient is None:
            self._patient = None
            return
        self._patient = SimulatedPatient(patient.parameters, self.control_period_s, patient.seed)
        self._kernels.measured_stance_pose(self._positions[:6], self._stance)
        self._stance_velocity[:] = 0.0

    # --- lifecycle hooks ---------------------------------------------------------------------------

    @property
    def drive_states(self) -> np.ndarray:
        """Every axis's CiA 402 state now (a copy), without a read()."""
        return self._drive_machines().states.copy()

    def _drive_machines(self) -> DriveStateMachines:
        assert self._drives is not None, "read() and the lifecycle hooks run only once configured"
        return self._drives

    def _on_configure(self) -> None:
        self._drives = DriveStateMachines(AXIS_COUNT)

    def _on_home(self) -> None:
        self._homed[:] = True

    def _on_activate(self) -> None:
        self._drive_machines().command(DriveState.OPERATION_ENABLED)
        self.last_write_ns = time.perf_counter_ns()

    def _on_deactivate(self) -> None:
        self._velocities[:] = 0.0
        self._drive_machines().disable()

    def _on_quick_stop(self) -> None:
        self._velocities[:] = 0.0  # ideal drives stop at once, where they are
        self._drive_machines().quick_stop()

    def _on_disable(self) -> None:
        self._forces[:] = 0.0
        self._drive_machines().disable()

    def _on_reset_fault(self) -> None:
        self._drive_machines().command(DriveState.SWITCH_ON_DISABLED, reset_faults=True)

    def _on_shutdown(self) -> None:
        self._drives = None

    # --- cyclic hooks ------------------------------------------------------------------------------

    def _communication_lost(self) -> bool:
        """A drive's heartbeat consumer: set-points must keep coming while enabled."""
        if self.state is not HalState.ACTIVE or self.last_write_ns is None:
            return False
        silent_ns = time.perf_counter_ns() - self.last_write_ns
        if silent_ns <= self.communication_timeout_ns:
            return False
        self.fault(f"communication lost: no set-point for {silent_ns * 1e-6:.1f} ms")
        drives = self._drive_machines()
        drives.fault()  # each drive's own reaction; an ideal drive is at standstill at once
        drives.internal(DriveState.FAULT_REACTION_ACTIVE, DriveState.FAULT)
        return True

    def _on_write(self, command: HalCommand) -> None:
        if self._communication_lost():
            return
        np.subtract(command.positions_m, self._positions, out=self._velocities)
        self._velocities /= self.control_period_s
        self._positions[:] = command.positions_m
        self._forces[:] = command.force_feedforward_n
        self.last_write_ns = time.perf_counter_ns()
        self.writes += 1

    def _on_read(self, out: HalReading) -> None:
        self._communication_lost()
        self._ticks += 1
        out.positions_m[:] = self._positions
        out.velocities_m_s[:] = self._velocities if self.state is HalState.ACTIVE else 0.0
        out.drive_forces_n[:] = self._forces
        out.drive_states[:] = self._drive_machines().states
        out.homed[:] = self._homed
        self._step_patient(out)
        out.monotonic_ns = time.perf_counter_ns()
        out.hardware_time_s = self._ticks * self.control_period_s

    def _step_patient(self, out: HalReading) -> None:
        if self._patient is None:
            out.plate_force_z_n[:] = 0.0
            out.plate_cop_m[:] = 0.0
            out.harness_load_n = 0.0
            return
        # Support motion from the platforms' actual pose (FK), differentiated over one period.
        self._stance_scratch[:] = self._stance
        self._kernels.measured_stance_pose(self._positions[:6], self._stance)
        previous_velocity = self._support_acceleration  # reuse as scratch before overwriting
        previous_velocity[:] = self._stance_velocity[:3]
        np.subtract(self._stance, self._stance_scratch, out=self._stance_velocity)
        self._stance_velocity /= self.control_period_s
        np.subtract(self._stance_velocity[:3], previous_velocity, out=self._support_acceleration)
        self._support_acceleration /= self.control_period_s
        sample = self._patient.step(self._support_acceleration, self._stance[3:5], self._stance_velocity[3:])
        out.plate_force_z_n[:] = sample.plate_force_z_n
        out.plate_cop_m[:] = sample.plate_cop_m
        out.harness_load_n = sample.harness_load_n

    def _measured_positions(self) -> np.ndarray:
        return self._positions
