"""Model import: MJCF and URDF through MuJoCo's compiler (:mod:`jaxbody.io.mujoco`)."""

from .mujoco import from_mjcf as from_mjcf, from_mujoco as from_mujoco, from_urdf as from_urdf
