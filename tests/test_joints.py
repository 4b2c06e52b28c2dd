"""Joint layout (joints.py): qpos and dof addresses follow MuJoCo's conventions."""

import numpy as np

import jaxbody as jb



def test_layout_addresses_follow_mujoco():
    b = jb.ModelBuilder()
    b.add_body("f", mass=1.0, inertia=(0.1, 0.1, 0.1), joints=[jb.Free()])
    b.add_body("u", "f", mass=1.0, inertia=(0.1, 0.1, 0.1), joints=[jb.Hinge(), jb.Hinge(axis=(1, 0, 0))])
    b.add_body("s", "u", mass=1.0, inertia=(0.1, 0.1, 0.1), joints=[jb.Ball()])
    m = b.build()
    assert (m.nq, m.nv) == (7 + 2 + 4, 6 + 2 + 3)
    assert m.joints.qposadr == (0, 7, 8, 9) and m.joints.dofadr == (0, 6, 7, 8)
    assert m.joints.dof_body == (0,) * 6 + (1, 1) + (2,) * 3
    np.testing.assert_allclose(m.qpos0[3:7], [1, 0, 0, 0])
