"""MuJoCo as an independent cross-check of the clearance model (issue 13 §1): with contacts on, the old
interleaved layout's rods touch in the physics too, and the default layout's do not."""

from __future__ import annotations

import mujoco
import numpy as np

from core.robot import TwinRobot, named_twin
from server.hal.sim.mjcf import SimModelOptions
from server.hal.sim.model import TwinSimModel


def touching_pairs(twin: TwinRobot, steps: int) -> set[tuple[str, str]]:
    """Geom pairs in contact while the twin holds its neutral pose for `steps` physics steps."""
    model = TwinSimModel(twin, SimModelOptions(contacts=True))
    data = model.make_data()
    found: set[tuple[str, str]] = set()
    for _ in range(steps):
        mujoco.mj_step(model.model, data)
        for contact in data.contact[: data.ncon]:
            names = sorted(
                mujoco.mj_id2name(model.model, mujoco.mjtObj.mjOBJ_GEOM, geom)
                for geom in (contact.geom1, contact.geom2)
            )
            found.add((names[0], names[1]))
    return found


def test_the_old_layout_rods_touch_in_mujoco_where_the_clearance_model_says() -> None:
    pairs = touching_pairs(named_twin("legacy-interleaved"), 5)
    assert ("left_rod3", "right_rod3") in pairs and ("left_rod4", "right_rod4") in pairs


def test_the_default_layout_has_no_contact_in_mujoco(twin: TwinRobot) -> None:
    assert touching_pairs(twin, 5) == set()


def test_contacts_are_off_unless_asked_for(twin: TwinRobot) -> None:
    model = TwinSimModel(named_twin("legacy-interleaved"))
    data = model.make_data()
    mujoco.mj_step(model.model, data)
    assert data.ncon == 0 and np.all(np.isfinite(data.qpos))
