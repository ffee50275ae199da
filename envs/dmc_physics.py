"""The dm_control ``Physics`` of the path-following task: a house model with a kinematic agent.

:class:`HousePhysics` is a :class:`dm_control.mujoco.Physics` of a house model
(:func:`~envs.house_mesh.house_mjcf`) with a kinematic agent added: a body with two
slide joints and a hinge, so ``qpos`` = (x m, y m, heading rad) is the agent's pose
and part of ``physics.get_state()``; the house's ``"eye"`` camera rides on it, so
``physics.render(camera_id="eye")`` shows the agent's view. Nothing collides and
there is no gravity: ``physics.step()`` leaves the pose as the task set it. Models
are compiled once per process (:data:`MODEL_CACHE_SIZE` houses kept). Used by
:mod:`envs.dmc`, which imports dm_control only after choosing the GL back-end.
"""
from __future__ import annotations

import functools
import logging
from collections.abc import Sequence

import mujoco
import numpy as np
from dm_control.mujoco import Physics
from dm_control.mujoco.wrapper import MjModel

from envs.house_mesh import house_mjcf
from envs.render import FirstPersonView
from envs.scenes import House, build_house

logger = logging.getLogger(__name__)

#: The agent's body, its joints (x metres, y metres, heading radians) and its camera.
AGENT_BODY = "agent"
AGENT_JOINTS = ("agent_x", "agent_y", "agent_heading")
EYE_CAMERA = "eye"
#: Camera axes in the agent's frame (x: right = -y, y: up = +z): it looks along the agent's +x.
EYE_XYAXES = (0.0, -1.0, 0.0, 0.0, 0.0, 1.0)
#: Mass (kg) and diagonal inertia (kg m^2) of the agent: MuJoCo needs them for a body with
#: joints; they never matter (no forces act on the agent and its velocity stays zero).
AGENT_MASS_KG = 1.0
AGENT_INERTIA_KG_M2 = 0.1
#: Compiled house-with-agent models kept per process (about 3.4 MB each).
MODEL_CACHE_SIZE = 128
@functools.lru_cache(maxsize=MODEL_CACHE_SIZE)
def agent_house_model(house_seed: int) -> mujoco.MjModel:
    """The model of house ``house_seed`` with the kinematic agent carrying the ``"eye"`` camera.

    Built from :func:`~envs.house_mesh.house_mjcf`: the house's fixed camera is moved
    onto an ``"agent"`` body with joints ``agent_x``, ``agent_y`` (slides, metres)
    and ``agent_heading`` (hinge about z, radians); gravity is off. Cached per
    process and shared by every :class:`HousePhysics` of that house: treat it as
    read-only.

    Examples:
        >>> model = agent_house_model(0)
        >>> model.nq, model.ncam
        (3, 1)
    """
    house = build_house(house_seed)
    xml, assets = house_mjcf(house)
    spec = mujoco.MjSpec.from_string(xml, assets=assets)
    house_camera = spec.camera(EYE_CAMERA)
    fovy_deg = house_camera.fovy
    spec.delete(house_camera)
    spec.option.gravity = [0.0, 0.0, 0.0]
    agent = spec.worldbody.add_body(
        name=AGENT_BODY, mass=AGENT_MASS_KG, inertia=[AGENT_INERTIA_KG_M2] * 3, explicitinertial=True
    )
    for name, kind, axis in zip(
        AGENT_JOINTS,
        (mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_HINGE),
        ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    ):
        agent.add_joint(name=name, type=kind, axis=list(axis))
    eye = agent.add_camera(name=EYE_CAMERA, pos=[0.0, 0.0, house.eye_height_m], fovy=fovy_deg)
    eye.alt.type = mujoco.mjtOrientation.mjORIENTATION_XYAXES
    eye.alt.xyaxes = list(EYE_XYAXES)
    return spec.compile()


class HousePhysics(Physics):
    """A :class:`dm_control.mujoco.Physics` of one house with a kinematic agent.

    The agent's pose is ``qpos`` = (x metres, y metres, heading radians), so it
    is part of ``get_state()``/``set_state()``; see :func:`agent_house_model`.
    Build one with :meth:`from_house`; :meth:`load_house` switches houses.

    Examples:
        >>> physics = HousePhysics.from_house(build_house(0))
        >>> physics.set_agent_pose([2.5, 1.5, 0.0])
        >>> physics.forward()
        >>> physics.named.data.cam_xpos["eye"].tolist()
        [2.5, 1.5, 0.9]
        >>> physics.render(32, 32, camera_id="eye").shape
        (32, 32, 3)
    """

    _house: House | None = None

    @classmethod
    def from_house(cls, house: House) -> HousePhysics:
        """A physics of ``house`` (a :func:`~envs.scenes.build_house` house), agent at the origin."""
        physics = cls.from_model(MjModel(agent_house_model(house.seed)))
        physics._house = house
        return physics

    @property
    def house(self) -> House:
        """The house whose model this physics simulates."""
        return self._house

    def load_house(self, house: House) -> None:
        """Reload this physics with ``house``'s model (a no-op for the current house).

        As with dm_control's ``reload_from_*`` methods, the state is that of a new
        physics afterwards, and rendering contexts of ``physics.render`` are freed.
        """
        if self._house is not None and self._house.seed == house.seed:
            return
        logger.debug("HousePhysics: loading house %d", house.seed)
        self._reload_from_model(MjModel(agent_house_model(house.seed)))
        self._house = house

    @property
    def first_person_view(self) -> FirstPersonView:
        """This physics' model as :class:`~envs.render.FirstPersonRenderer` draws it (from any pose)."""
        return FirstPersonView(self.model.ptr, self._house.eye_height_m)

    def agent_pose(self) -> np.ndarray:
        """A copy of the agent's pose (x metres, y metres, heading radians)."""
        return np.array(self.data.qpos[:3])

    def set_agent_pose(self, pose: Sequence[float] | np.ndarray) -> None:
        """Place the agent at ``pose`` = (x metres, y metres, heading radians), at rest.

        Derived quantities (camera placement) follow at the next ``forward()`` or ``step()``.
        """
        self.data.qpos[:3] = pose
        self.data.qvel[:3] = 0.0

    def copy(self, share_model: bool = False) -> HousePhysics:
        """A copy of this physics (see :meth:`dm_control.mujoco.Physics.copy`), house included."""
        new = super().copy(share_model=share_model)
        new._house = self._house
        return new
