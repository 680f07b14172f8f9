"""The MuJoCo twin (server/hal/sim): generated MJCF, inverse dynamics against core.dynamics, sensors."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest

from core.dynamics import PayloadModel, StanceTrajectory, TwinInverseDynamics, paper_step_trajectory
from core.physics import GRAVITY_M_S2
from core.robot import TwinRobot
from server.hal.sim.mjcf import SimModelOptions, twin_mjcf
from server.hal.sim.model import TwinSimModel, rms_relative_error

PATIENT = PayloadModel.from_body(75.0, 1.75)


@pytest.fixture(scope="module")
def sim_model(twin: TwinRobot) -> TwinSimModel:
    return TwinSimModel(twin, SimModelOptions(payload=PATIENT))


def _sparse(trajectory: StanceTrajectory, stride: int) -> StanceTrajectory:
    return StanceTrajectory(*(getattr(trajectory, f.name)[::stride] for f in dataclasses.fields(trajectory)))


def test_mjcf_is_generated_from_the_geometry(twin: TwinRobot) -> None:
    longer = dataclasses.replace(twin, robot=dataclasses.replace(twin.robot, rod_length_m=1.1))
    assert twin_mjcf(twin) != twin_mjcf(longer)
    model = mujoco.MjModel.from_xml_string(twin_mjcf(twin))
    assert (model.nu, model.neq, model.ntendon) == (12, 12, 1)
    assert model.nv == 2 * (6 + 6 * 3 + 6)  # sliders, rod ball joints, free platform per robot


def test_reference_configuration_closes_every_loop(sim_model: TwinSimModel) -> None:
    data = sim_model.make_data()
    assert np.max(np.abs(data.efc_pos)) < 1e-9


@pytest.mark.parametrize("axis", ["z", "y"])
def test_inverse_dynamics_matches_mujoco_on_paper_scenarios(
    twin: TwinRobot, sim_model: TwinSimModel, axis: str
) -> None:
    trajectory = _sparse(paper_step_trajectory(axis, 0.3, 0.001), 10)
    dynamics = TwinInverseDynamics(twin, PATIENT)
    mujoco_forces = sim_model.inverse_slider_forces(dynamics, trajectory)
    ours = dynamics.slider_forces(trajectory.poses, trajectory.velocities, trajectory.accelerations)
    assert mujoco_forces.max_residual < 1e-8
    assert rms_relative_error(ours, mujoco_forces.slider_forces_n) < 0.05
    assert rms_relative_error(ours, mujoco_forces.slider_forces_n) < 1e-6  # in fact to rounding


def test_inverse_dynamics_matches_mujoco_with_rotation(twin: TwinRobot, sim_model: TwinSimModel) -> None:
    """All six stance coordinates moving at once: gyroscopic and Coriolis terms included."""
    times = np.linspace(0.0, 1.0, 21)
    amplitude = np.array([0.04, 0.03, 0.03, 0.08, 0.06, 0.1])
    omega = np.array([4.0, 5.0, 6.0, 3.0, 4.0, 5.0])
    phase = omega * times[:, None]
    trajectory = StanceTrajectory(
        times, amplitude * np.sin(phase), amplitude * omega * np.cos(phase), -amplitude * omega**2 * np.sin(phase)
    )
    dynamics = TwinInverseDynamics(twin, PATIENT)
    mujoco_forces = sim_model.inverse_slider_forces(dynamics, trajectory)
    ours = dynamics.slider_forces(trajectory.poses, trajectory.velocities, trajectory.accelerations)
    assert rms_relative_error(ours, mujoco_forces.slider_forces_n) < 1e-6


def test_forward_simulation_follows_under_the_inverse_dynamics_forces(twin: TwinRobot, sim_model: TwinSimModel) -> None:
    """Open loop: MuJoCo driven only by our forces stays on the planned sliders (massless-rod forces do not)."""
    trajectory = paper_step_trajectory("y", 0.3, sim_model.model.opt.timestep)

    def final_error(include_rods: bool) -> float:
        dynamics = TwinInverseDynamics(twin, PATIENT, include_rods=include_rods)
        forces = dynamics.slider_forces(trajectory.poses, trajectory.velocities, trajectory.accelerations)
        motions = TwinInverseDynamics(twin, PATIENT).platform_motion(
            trajectory.poses, trajectory.velocities, trajectory.accelerations
        )
        data = mujoco.MjData(sim_model.model)
        sim_model.set_state(data, motions, 0)
        for sample in range(len(trajectory.times_s) - 1):
            data.ctrl[:] = forces[sample]
            mujoco.mj_step(sim_model.model, data)
        planned = np.concatenate([motions[side][1].slider_positions_m[-1] for side in twin.sides])
        return float(np.max(np.abs(data.qpos[sim_model.slider_qpos] - planned)))

    assert final_error(include_rods=True) < 2e-3
    assert final_error(include_rods=False) > 10e-3


def _static_data(twin: TwinRobot, model: TwinSimModel, payload: PayloadModel, stance: np.ndarray) -> mujoco.MjData:
    """The twin held still at `stance` by the inverse-dynamics forces, sensors evaluated."""
    still = np.zeros((1, 6))
    dynamics = TwinInverseDynamics(twin, payload)
    data = mujoco.MjData(model.model)
    model.set_state(data, dynamics.platform_motion(stance[None], still, still), 0)
    data.ctrl[:] = dynamics.slider_forces(stance, still[0], still[0])[0]
    mujoco.mj_forward(model.model, data)
    return data


def test_force_plates_read_the_patient_weight_and_centre_of_pressure(twin: TwinRobot) -> None:
    payload = PayloadModel(70.0, (0.04, -0.02, 0.95), (11.0, 12.0, 1.4))
    model = TwinSimModel(twin, SimModelOptions(payload=payload))
    data = _static_data(twin, model, payload, np.zeros(6))
    assert np.max(np.abs(data.qacc)) < 0.02  # static but for the loops' 0.01 % constraint softness
    force_z, cop = np.zeros(2), np.zeros((2, 2))
    model.plate_readings(data, force_z, cop)
    np.testing.assert_allclose(force_z, [35.0 * GRAVITY_M_S2] * 2, rtol=1e-3)
    np.testing.assert_allclose(cop, [[0.04, -0.02], [0.04, -0.02]], atol=1e-3)


def test_harness_load_cell_reads_only_a_taut_rope(twin: TwinRobot, sim_model: TwinSimModel) -> None:
    standing = _static_data(twin, sim_model, PATIENT, np.zeros(6))
    assert sim_model.harness_load_n(standing) == 0.0
    harness = sim_model.options.harness
    lowered = _static_data(twin, sim_model, PATIENT, np.array([0.0, 0.0, -0.1, 0.0, 0.0, 0.0]))
    stretch = 0.1 - harness.slack_m
    assert sim_model.harness_load_n(lowered) == pytest.approx(harness.stiffness_n_m * stretch, rel=0.02)


@pytest.mark.parametrize("scenario", ["paper-z", "paper-y"])
def test_dynamics_cli_reproduces_the_paper_force_band(scenario: str, tmp_path) -> None:  # type: ignore[no-untyped-def]
    import json

    from typer.testing import CliRunner

    from server.cli.main import app

    result = CliRunner().invoke(app, ["dynamics", "--scenario", scenario, "--json", "--plot", str(tmp_path)])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["setting"] == "rated-load"
    assert data["mujoco_rms_rel_error"] < 0.05
    # Paper §3.2: each linear joint needs between 500 N and 3000 N (friction neglected).
    assert 500.0 <= data["min_abs_force_n"] <= data["max_abs_force_n"] <= 3000.0
    assert data["in_paper_band"] is True
    assert data["mass_assumptions"]["payload"]["mass_kg"] == 250.0
    assert (tmp_path / f"dynamics_{scenario}.png").stat().st_size > 10_000


def test_dynamics_cli_patient_setting_and_refusals() -> None:
    import json

    from typer.testing import CliRunner

    from server.cli.main import app

    result = CliRunner().invoke(app, ["dynamics", "--scenario", "paper-y", "--setting", "patient", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["mass_assumptions"]["patient"]["mass_kg"] == 75.0
    assert data["in_paper_band"] == (data["min_abs_force_n"] >= 500.0 and data["max_abs_force_n"] <= 3000.0)
    refused = CliRunner().invoke(app, ["dynamics", "--scenario", "paper-x", "--json"])
    assert refused.exit_code == 2 and "paper-x" in refused.stdout
    refused = CliRunner().invoke(app, ["dynamics", "--scenario", "paper-y", "--setting", "heavy", "--json"])
    assert refused.exit_code == 2 and "setting" in refused.stdout
