"""MJCF/URDF import through MuJoCo's compiler (jaxbody/io/mujoco.py).

Structure round trips against the compiled ``mujoco.MjModel`` on the shared menagerie models
and on seeded random trees; the import warning and ``strict=True``; errors naming the element.
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb
from jaxbody.io.mujoco import unsupported_features

mujoco = pytest.importorskip("mujoco")

from _support.mjcf_random import random_mjcf, random_state

MENAGERIE = ("panda", "ur5e", "anymal_c")
RANDOM_SEEDS = tuple(range(12))


def _load_quiet(source, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return jb.from_mjcf(source, **kw)


def _random_xml(seed, **kw):
    kw.setdefault("n_body", 3 + seed % 10)
    return random_mjcf(seed, **kw)


@pytest.fixture(params=[f"menagerie:{n}" for n in MENAGERIE] + [f"random:{s}" for s in RANDOM_SEEDS])
def case(request, models_dir):
    """(jaxbody model, mujoco model) for a menagerie file or a random tree."""
    kind, name = request.param.split(":")
    if kind == "menagerie":
        path = models_dir / f"{name}.xml"
        return _load_quiet(path), mujoco.MjModel.from_xml_path(str(path))
    xml = _random_xml(int(name))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # rigid_only random trees import without a warning
        model = jb.from_mjcf(xml)
    return model, mujoco.MjModel.from_xml_string(xml)


# ----------------------------------------------------------------------------- structure
def test_structure_matches_mujoco(case):
    model, m = case
    nb = m.nbody - 1
    assert model.n_body == nb
    assert model.nq == m.nq and model.nv == m.nv and model.n_joint == m.njnt
    np.testing.assert_array_equal(model.tree.parent_array, m.body_parentid[1:] - 1)
    for k in range(nb):
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, k + 1)
        if name:
            assert model.body_names[k] == name
    for j in range(m.njnt):
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
        if name:
            assert model.joint_names[j] == name
    assert model.joints.type == tuple(int(t) for t in m.jnt_type)
    assert model.joints.body == tuple(int(b) - 1 for b in m.jnt_bodyid)
    assert model.joints.qposadr == tuple(int(a) for a in m.jnt_qposadr)
    assert model.joints.dofadr == tuple(int(a) for a in m.jnt_dofadr)
    assert model.joints.dof_joint == tuple(int(j) for j in m.dof_jntid)
    assert model.joints.dof_body == tuple(int(b) - 1 for b in m.dof_bodyid)
    assert model.joints.body_joint_count == tuple(int(n) for n in m.body_jntnum[1:])


def test_parameters_match_mujoco(case):
    model, m = case
    close = lambda a, b: np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-14, atol=1e-14)
    close(model.body_mass, m.body_mass[1:])
    close(model.body_com, m.body_ipos[1:])
    close(model.body_pos, m.body_pos[1:])
    close(model.body_quat, m.body_quat[1:])
    close(model.joint_pos, m.jnt_pos)
    close(model.joint_axis, m.jnt_axis)
    close(model.joint_stiffness, m.jnt_stiffness)
    close(model.dof_armature, m.dof_armature)
    close(model.dof_damping, m.dof_damping)
    close(model.qpos0, m.qpos0)
    close(model.qpos_spring, m.qpos_spring)
    close(model.gravity, m.opt.gravity)
    assert model.body_mass.dtype == jnp.float64


def test_inertia_and_com_in_world_frame(case):
    """Our body-axes tensor, rotated by xmat, equals MuJoCo's ximat·diag·ximatᵀ (at qpos0 and
    at a random pose); our CoM lands on xipos."""
    model, m = case
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    for q in (m.qpos0, random_state(m, rng)[0]):
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        for k in range(model.n_body):
            R = d.xmat[k + 1].reshape(3, 3)
            Ri = d.ximat[k + 1].reshape(3, 3)
            ours = R @ np.asarray(model.body_inertia[k]) @ R.T
            ref = Ri @ np.diag(m.body_inertia[k + 1]) @ Ri.T
            scale = max(np.abs(ref).max(), 1e-300)
            assert np.abs(ours - ref).max() <= 1e-13 * scale, (k, ours, ref)
            com = d.xpos[k + 1] + R @ np.asarray(model.body_com[k])
            np.testing.assert_allclose(com, d.xipos[k + 1], rtol=0, atol=1e-13)


def test_keyframes(models_dir):
    for name in ("panda", "ur5e"):
        model = _load_quiet(models_dir / f"{name}.xml")
        m = mujoco.MjModel.from_xml_path(str(models_dir / f"{name}.xml"))
        assert model.keyframe_names == ("home",)
        q, v = model.keyframe("home")
        np.testing.assert_array_equal(np.asarray(q), m.key_qpos[0])
        np.testing.assert_array_equal(np.asarray(v), m.key_qvel[0])
    anymal = _load_quiet(models_dir / "anymal_c.xml")
    assert anymal.keyframe_names == () and anymal.keyframe_qpos.shape == (0, anymal.nq)
    with pytest.raises(KeyError, match="no keyframe named 'home'"):
        anymal.keyframe("home")
    xml = _random_xml(3, n_key=3)
    model = jb.from_mjcf(xml)
    m = mujoco.MjModel.from_xml_string(xml)
    assert model.keyframe_names == ("key0", "key1", "key2")
    np.testing.assert_array_equal(np.asarray(model.keyframe_qpos), m.key_qpos)
    np.testing.assert_array_equal(np.asarray(model.keyframe_qvel), m.key_qvel)


def test_free_body_keeps_its_pose_as_qpos0(models_dir):
    model = _load_quiet(models_dir / "anymal_c.xml")
    assert model.joints.type[0] == jb.FREE and model.joint_names[0] == "base_free0"
    np.testing.assert_array_equal(np.asarray(model.qpos0[:3]), np.asarray(model.body_pos[0]))
    np.testing.assert_array_equal(np.asarray(model.qpos0[3:7]), np.asarray(model.body_quat[0]))


def test_from_mujoco_equals_from_mjcf(models_dir):
    for name in MENAGERIE:
        path = models_dir / f"{name}.xml"
        a = _load_quiet(path)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            b = jb.from_mujoco(mujoco.MjModel.from_xml_path(str(path)))
        _assert_models_equal(a, b)
    xml = _random_xml(5)
    _assert_models_equal(jb.from_mjcf(xml), jb.from_mujoco(mujoco.MjModel.from_xml_string(xml)))


def test_path_forms(models_dir, tmp_path):
    path = models_dir / "panda.xml"
    a = _load_quiet(path)
    _assert_models_equal(a, _load_quiet(str(path)))
    _assert_models_equal(a, _load_quiet(path.read_text()))


def test_jit_twice_with_equal_models(models_dir):
    """Two separately loaded, equal models hit the same jit cache entry."""
    traces = []

    def total_mass(mdl):
        traces.append(1)  # runs once per trace, not per call
        return mdl.body_mass.sum()

    f = jax.jit(total_mass)
    a = _load_quiet(models_dir / "anymal_c.xml")
    b = _load_quiet(models_dir / "anymal_c.xml")
    assert a.tree == b.tree and a.joints == b.joints and hash(a.joints) == hash(b.joints)
    ra, rb = f(a), f(b)
    assert float(ra) == float(rb) == pytest.approx(float(np.sum(np.asarray(a.body_mass))))
    # the second, equal model reuses the first trace (the C++ cache size is not used: other
    # tests in the same pytest worker can switch jit to its Python path)
    assert len(traces) == 1


def test_dtype_float32(models_dir):
    model = _load_quiet(models_dir / "panda.xml", dtype=jnp.float32)
    assert model.body_inertia.dtype == jnp.float32 and model.qpos0.dtype == jnp.float32


def test_unnamed_elements_get_names():
    xml = """<mujoco><worldbody>
      <body><freejoint/><geom size="0.1" contype="0" conaffinity="0"/>
        <body pos="0 0 1"><joint type="ball"/><joint type="slide"/><geom size="0.1" contype="0" conaffinity="0"/></body>
      </body></worldbody></mujoco>"""
    model = jb.from_mjcf(xml)
    assert model.name == "MuJoCo Model"  # MuJoCo's default model name
    assert model.body_names == ("body0", "body1")
    assert model.joint_names == ("body0_free0", "body1_ball0", "body1_slide1")


# ----------------------------------------------------------------------------- option flags
def test_disable_flags_gravity_spring_damper():
    body = """<compiler angle="radian"/><worldbody><body><joint name="h" stiffness="3" damping="2" springref="0.5"/>
      <inertial pos="0 0 -1" mass="1" diaginertia="1 1 1"/></body></worldbody>"""
    on = jb.from_mjcf(f"<mujoco><option gravity='0 0 -5'/>{body}</mujoco>")
    assert float(on.joint_stiffness[0]) == 3 and float(on.dof_damping[0]) == 2
    np.testing.assert_array_equal(np.asarray(on.gravity), [0, 0, -5])
    off = jb.from_mjcf(
        "<mujoco><option gravity='0 0 -5'><flag gravity='disable' spring='disable' "
        f"damper='disable'/></option>{body}</mujoco>"
    )
    assert float(off.joint_stiffness[0]) == 0 and float(off.dof_damping[0]) == 0
    np.testing.assert_array_equal(np.asarray(off.gravity), [0, 0, 0])
    np.testing.assert_array_equal(np.asarray(off.qpos_spring), [0.5])


def test_actuator_armature_and_damping_fold_into_the_joint():
    """MuJoCo 4 adds gear²·armature (damping) of a joint actuator to the joint's DoF."""
    xml = """<mujoco><worldbody><body><joint name="j" armature="0.1" damping="0.2"/>
      <inertial pos="0 0 -1" mass="1" diaginertia="1 1 1"/></body></worldbody>
      <actuator><motor name="m" joint="j" gear="-2" armature="0.5" damping="0.7"/></actuator></mujoco>"""
    with pytest.warns(UserWarning, match=r"actuators .*: 1 actuators \('m'\)"):
        model = jb.from_mjcf(xml)
    np.testing.assert_allclose(np.asarray(model.dof_armature), [0.1 + 4 * 0.5], rtol=1e-15)
    np.testing.assert_allclose(np.asarray(model.dof_damping), [0.2 + 4 * 0.7], rtol=1e-15)
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qvel[:] = 1.0
    mujoco.mj_forward(m, d)
    M = np.zeros((1, 1))
    mujoco.mj_fullM(m, d, M)
    rigid = 1.0  # I_zz: the CoM lies on the hinge axis (z)
    np.testing.assert_allclose(M[0, 0] - rigid, float(model.dof_armature[0]), rtol=1e-12)
    np.testing.assert_allclose(-d.qfrc_passive[0], float(model.dof_damping[0]), rtol=1e-12)


# ----------------------------------------------------------------------------- warnings
def _one_warning(fn, *args, **kw):
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        model = fn(*args, **kw)
    user = [w for w in rec if issubclass(w.category, UserWarning)]
    assert len(user) == 1, [str(w.message) for w in user]
    return model, str(user[0].message)


def test_warning_anymal_contacts(models_dir):
    _, msg = _one_warning(jb.from_mjcf, models_dir / "anymal_c.xml")
    assert msg.startswith(
        "from_mjcf: MuJoCo model 'anymal_c' has features jaxbody does not model; they are ignored:"
    )
    assert "contacts (collision geoms are ignored" in msg
    assert "44 collision geoms on 13 bodies ('base', 'LF_HIP'," in msg
    assert "actuators (" in msg and "12 actuators ('LF_HAA'," in msg
    assert "joint limits (ignored): 12 limited joints ('LF_HAA'," in msg
    assert "joint friction loss (ignored): 12 joints" in msg
    assert "... and 4 more" in msg
    assert "tendons" not in msg and "equality" not in msg


def test_warning_panda_actuators_and_limits(models_dir):
    _, msg = _one_warning(jb.from_mjcf, models_dir / "panda.xml")
    lines = msg.splitlines()
    assert lines[0] == (
        "from_mjcf: MuJoCo model 'panda nohand' has features jaxbody does not model; "
        "they are ignored:"
    )
    assert lines[1].startswith("  - actuators (actuator forces, gains, biases, activation dynamics")
    assert lines[1].endswith(
        "7 actuators ('actuator1', 'actuator2', 'actuator3', 'actuator4', 'actuator5', "
        "'actuator6', 'actuator7')"
    )
    assert lines[2] == (
        "  - joint limits (ignored): 7 limited joints ('joint1', 'joint2', 'joint3', 'joint4', "
        "'joint5', 'joint6', 'joint7')"
    )
    assert len(lines) == 3  # panda has no geoms: no contacts line


def test_warning_ur5e_contacts(models_dir):
    _, msg = _one_warning(jb.from_mjcf, models_dir / "ur5e.xml")
    assert "9 collision geoms on 6 bodies ('shoulder_link'," in msg


@pytest.mark.parametrize("name", MENAGERIE)
def test_strict_raises(models_dir, name):
    with pytest.raises(ValueError, match=r"has features jaxbody does not model \(strict=True\):\n  - "):
        jb.from_mjcf(models_dir / f"{name}.xml", strict=True)
    with pytest.raises(ValueError, match=r"joint limits \(ignored\)"):
        jb.from_mjcf(models_dir / f"{name}.xml", strict=True)


def test_strict_passes_on_rigid_models():
    for seed in RANDOM_SEEDS[:4]:
        jb.from_mjcf(_random_xml(seed), strict=True)


def test_random_unsupported_features_listed():
    xml = _random_xml(7, rigid_only=False, n_body=8)
    m = mujoco.MjModel.from_xml_string(xml)
    model, msg = _one_warning(jb.from_mjcf, xml)
    assert "tendons (their stiffness, damping, limits, friction loss and actuation are ignored): 1 tendons ('t0')" in msg
    assert "actuators (" in msg and "1 actuators ('m0')" in msg
    assert m.neq == 1
    if int(m.eq_type[0]) == int(mujoco.mjtEq.mjEQ_CONNECT):  # imported as the model's loop closure
        assert [spec.label for spec in model.loops] == ["e0"] and "'e0'" not in msg
    else:
        assert "equality constraints other than active <connect> loops (ignored): 1 constraints ('e0')" in msg
    if m.jnt_limited.any():
        assert "joint limits (ignored)" in msg
    with pytest.raises(ValueError, match=r"tendons"):
        jb.from_mjcf(xml, strict=True)


def test_disabled_features_are_not_reported():
    """Limits, contacts, equality, friction loss, actuation switched off by <flag>: no warning."""
    xml = _random_xml(7, rigid_only=False, n_body=8)
    flags = '<option><flag contact="disable" limit="disable" equality="disable" frictionloss="disable" actuation="disable"/></option>'
    xml = xml.replace('<compiler angle="radian" autolimits="true"/>', '<compiler angle="radian" autolimits="true"/>' + flags, 1)
    m = mujoco.MjModel.from_xml_string(xml)
    assert unsupported_features(m) == [
        "tendons (their stiffness, damping, limits, friction loss and actuation are ignored): "
        "1 tendons ('t0')"
    ]


def test_other_unsupported_features():
    xml = """<mujoco><option density="1.2" viscosity="0.01"/><worldbody>
      <body name="mc" mocap="true"/>
      <body name="g" gravcomp="0.5"><joint name="h" frictionloss="1"/>
        <inertial pos="0 0 -1" mass="1" diaginertia="1 1 1"/></body></worldbody></mujoco>"""
    _, msg = _one_warning(jb.from_mjcf, xml)
    assert "fluid forces (option density=1.2, viscosity=0.01; ignored)" in msg
    assert "gravity compensation (body gravcomp, ignored): 1 bodies ('g')" in msg
    assert "mocap bodies (treated as welded to the world at their model pose" in msg
    assert "1 bodies ('mc')" in msg
    assert "joint friction loss (ignored): 1 joints ('h')" in msg


def test_pairs_transmissions_and_nonlinear_springs_listed():
    xml = """<mujoco><worldbody><geom name="floor" type="plane" size="1 1 1"/>
      <body name="b"><joint name="ba" type="ball"/><joint name="h" type="slide"/><geom name="s" size="0.1"/></body></worldbody>
      <contact><pair name="p0" geom1="floor" geom2="s"/></contact>
      <actuator><motor name="bm" joint="ba" armature="0.3"/><motor name="sm" joint="h" damping="0.3"/></actuator></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    m.jnt_stiffnesspoly[1] = [1.0, 0.0]
    m.jnt_springyield[0] = 1.0
    m.dof_dampingpoly[0] = [0.0, 2.0]
    assert unsupported_features(m) == [
        "contacts (collision geoms are ignored; their mass, if any, is already in the body "
        "inertias): 2 collision geoms on 2 bodies ('world', 'b')",
        "explicit contact pairs (ignored): 1 pairs ('p0')",
        "actuators (actuator forces, gains, biases, activation dynamics and control ranges are "
        "ignored; pass joint forces instead): 2 actuators ('bm', 'sm')",
        "actuator armature/damping on transmissions other than a hinge or slide joint "
        "(ignored): 1 actuators ('bm')",
        "nonlinear or plastic joint springs (only the linear stiffness is kept): 2 joints ('ba', 'h')",
        "nonlinear joint damping (only the linear damping is kept): 1 joints ('ba')",
    ]
    with pytest.warns(UserWarning, match=r"explicit contact pairs"):
        model = jb.from_mujoco(m)
    # the slide actuator's damping is folded into the slide DoF (index 3); the ball's is not
    np.testing.assert_array_equal(np.asarray(model.dof_damping), [0, 0, 0, 0.3])
    np.testing.assert_array_equal(np.asarray(model.dof_armature), [0, 0, 0, 0])


def test_unsupported_features_empty_for_rigid_models():
    for seed in RANDOM_SEEDS:
        assert unsupported_features(mujoco.MjModel.from_xml_string(_random_xml(seed))) == []


# ----------------------------------------------------------------------------- errors
def _inline(body, extra=""):
    return f"<mujoco>{extra}<worldbody>{body}</worldbody></mujoco>"


def test_negative_mass_named():
    xml = _inline('<body name="b"><joint name="h"/><inertial pos="0 0 0" mass="-1" diaginertia="1 1 1"/></body>')
    with pytest.raises(
        ValueError,
        match=r"from_mjcf: MuJoCo's compiler rejected the MJCF string: body 'b' moves \(it carries "
        r"a joint\) but its mass or inertia is not positive \[MuJoCo: mass and inertia of moving "
        r"bodies must be larger than mjMINVAL; element 'b', id 1, line 1\]",
    ):
        jb.from_mjcf(xml)


def test_free_joint_below_root_named():
    xml = _inline(
        '<body name="a"><joint name="h"/><geom size=".1"/>'
        '<body name="b"><freejoint name="fj"/><geom size=".1"/></body></body>'
    )
    with pytest.raises(ValueError, match=r"body 'b' has a free joint but is not attached to the world"):
        jb.from_mjcf(xml)


def test_triangle_inequality_named():
    xml = _inline('<body name="b"><joint name="h"/><inertial pos="0 0 0" mass="1" diaginertia="1 1 3"/></body>')
    with pytest.raises(ValueError, match=r"body 'b': the principal moments of inertia violate the triangle inequality"):
        jb.from_mjcf(xml)
    xml = _inline('<body name="b"><joint name="h"/><inertial pos="0 0 0" mass="1" fullinertia="1 1 1 2 0 0"/></body>')
    with pytest.raises(ValueError, match=r"body 'b': the inertia tensor is not positive definite"):
        jb.from_mjcf(xml)


def test_nan_position_named(tmp_path, monkeypatch):
    # MuJoCo compiles a NaN body position (with a printed warning); our validation names it.
    monkeypatch.chdir(tmp_path)  # MuJoCo appends its warning to ./MUJOCO_LOG.TXT
    xml = _inline('<body name="b" pos="nan 0 0"><joint name="h"/><inertial pos="0 0 0" mass="1" diaginertia="1 1 1"/></body>')
    with pytest.raises(ValueError, match=r"body 0 \('b'\): body_pos is not finite"):
        jb.from_mjcf(xml)


def test_negative_armature_named():
    # MuJoCo accepts a negative armature (here M stays positive: 1 - 0.5); jaxbody does not.
    xml = _inline('<body name="b"><joint name="h" armature="-0.5"/><inertial pos="0 0 0" mass="1" diaginertia="1 1 1"/></body>')
    with pytest.raises(ValueError, match=r"MuJoCo model 'MuJoCo Model': joint 0 \('h'\): dof_armature is negative \(-0.5\)"):
        jb.from_mjcf(xml)


def test_edited_mujoco_arrays_are_validated():
    xml = _inline(
        '<body name="a"><joint name="h1"/><inertial pos="0 0 -1" mass="1" diaginertia="1 1 1"/>'
        '<body name="b"><joint name="h2"/><inertial pos="0 0 -1" mass="1" diaginertia="1 1 1"/></body></body>'
    )
    m = mujoco.MjModel.from_xml_string(xml)
    m.body_mass[1] = 0.0
    with pytest.raises(
        ValueError,
        match=r"from_mujoco: MuJoCo model 'MuJoCo Model': body 0 \('a'\) moves \(has joints\) but its "
        r"body_mass is 0.0: MuJoCo requires positive mass on every moving body",
    ):
        jb.from_mujoco(m)
    m.body_mass[1] = -2.0
    with pytest.raises(ValueError, match=r"body 0 \('a'\): body_mass is negative \(-2.0\)"):
        jb.from_mujoco(m)
    m = mujoco.MjModel.from_xml_string(xml)
    m.body_inertia[2] = [1.0, 1.0, 3.0]
    with pytest.raises(ValueError, match=r"body 1 \('b'\): body_inertia violates the triangle inequality"):
        jb.from_mujoco(m)
    m = mujoco.MjModel.from_xml_string(xml)
    m.jnt_axis[0] = 0.0
    with pytest.raises(ValueError, match=r"joint 0 \('h1'\): joint_axis is zero"):
        jb.from_mujoco(m)


def test_edited_joint_types_are_named():
    xml = _inline(
        '<body name="a"><joint name="h1"/><inertial pos="0 0 -1" mass="1" diaginertia="1 1 1"/>'
        '<body name="b"><joint name="h2"/><inertial pos="0 0 -1" mass="1" diaginertia="1 1 1"/></body></body>'
    )
    m = mujoco.MjModel.from_xml_string(xml)
    m.jnt_type[1] = 7
    with pytest.raises(ValueError, match=r"joint 1 \('h2'\) of body 'b' has MuJoCo joint type 7, which jaxbody does not know"):
        jb.from_mujoco(m)
    m.jnt_type[1] = mujoco.mjtJoint.mjJNT_FREE
    with pytest.raises(ValueError, match=r"joint 1 \('h2'\) is a free joint on body 1 \('b'\), which is not a root body"):
        jb.from_mujoco(m)


def test_compiler_error_passes_mujoco_message():
    with pytest.raises(ValueError, match=r"from_mjcf: MuJoCo's compiler rejected the MJCF string: .*unrecognized"):
        jb.from_mjcf("<mujoco><worldbody><bodyy/></worldbody></mujoco>")


def test_world_only_model():
    with pytest.raises(ValueError, match=r"MuJoCo model 'empty' has no bodies besides the world body"):
        jb.from_mjcf('<mujoco model="empty"><worldbody/></mujoco>')


def test_bad_arguments(tmp_path):
    missing = tmp_path / "missing.xml"
    with pytest.raises(FileNotFoundError, match=r"from_mjcf: MJCF file not found: .*missing.xml"):
        jb.from_mjcf(missing)
    with pytest.raises(FileNotFoundError, match=r"from_urdf: URDF file not found"):
        jb.from_urdf(str(missing))
    with pytest.raises(TypeError, match=r"from_mjcf: expected a file path or an XML string, got int"):
        jb.from_mjcf(123)
    with pytest.raises(TypeError, match=r"from_mujoco: expected a mujoco.MjModel, got str"):
        jb.from_mujoco("<mujoco/>")


# ----------------------------------------------------------------------------- URDF
URDF = """<robot name="arm2">
  <link name="base"/>
  <link name="l1">
    <inertial><origin xyz="0 0 0.1" rpy="0.1 0.2 0.3"/><mass value="1.5"/>
      <inertia ixx="0.01" iyy="0.02" izz="0.015" ixy="0.001" ixz="0" iyz="0"/></inertial>
  </link>
  <link name="l2">
    <inertial><origin xyz="0.2 0 0" rpy="0 0 0"/><mass value="0.5"/>
      <inertia ixx="0.002" iyy="0.003" izz="0.004" ixy="0" ixz="0" iyz="0"/></inertial>
  </link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0.5" rpy="0 0 0.3"/><axis xyz="0 1 0"/>
    <limit lower="-1" upper="1" effort="10" velocity="1"/></joint>
  <joint name="j2" type="continuous"><parent link="l1"/><child link="l2"/>
    <origin xyz="0 0 0.3" rpy="0.2 0 0"/><axis xyz="1 0 0"/></joint>
</robot>
"""


def test_from_urdf(tmp_path):
    path = tmp_path / "arm2.urdf"
    path.write_text(URDF)
    model, msg = _one_warning(jb.from_urdf, path)
    assert "joint limits (ignored): 1 limited joints ('j1')" in msg
    assert model.name == "arm2"
    assert model.body_names == ("l1", "l2") and model.joint_names == ("j1", "j2")
    assert model.joints.type == (jb.HINGE, jb.HINGE)
    np.testing.assert_allclose(np.asarray(model.body_mass), [1.5, 0.5])
    # URDF inertia (about the CoM, in the rotated inertial frame) back in body axes
    R = _rpy(0.1, 0.2, 0.3)
    I_urdf = np.array([[0.01, 0.001, 0], [0.001, 0.02, 0], [0, 0, 0.015]])
    np.testing.assert_allclose(np.asarray(model.body_inertia[0]), R @ I_urdf @ R.T, atol=1e-12)
    np.testing.assert_allclose(np.asarray(model.body_com[0]), [0, 0, 0.1], atol=1e-15)
    same, _ = _one_warning(jb.from_urdf, URDF)
    _assert_models_equal(model, same)


def _rpy(r, p, y):
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


# ----------------------------------------------------------------------------- random MJCF
def test_random_mjcf_is_seeded_and_covers_the_joint_kinds():
    assert random_mjcf(11) == random_mjcf(11)
    assert random_mjcf(11) != random_mjcf(12)
    kinds, multi, ratio = set(), 0, 0.0
    for seed in range(40):
        m = mujoco.MjModel.from_xml_string(random_mjcf(seed, n_body=10))
        kinds |= set(int(t) for t in m.jnt_type)
        multi += int((m.body_jntnum > 1).sum())
        ratio = max(ratio, m.body_mass[1:].max() / m.body_mass[1:].min())
        for j in np.nonzero(m.jnt_type == mujoco.mjtJoint.mjJNT_FREE)[0]:
            assert m.body_parentid[m.jnt_bodyid[j]] == 0
        assert m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
        assert m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
        assert not m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_SPRING
    assert kinds == {0, 1, 2, 3}
    assert multi > 20
    assert ratio == pytest.approx(1e4)


# ----------------------------------------------------------------------------- helpers
def _assert_models_equal(a, b):
    assert a.tree == b.tree and a.joints == b.joints
    assert a.keyframe_names == b.keyframe_names and a.name == b.name
    la, ta = jax.tree.flatten(a)
    lb, tb = jax.tree.flatten(b)
    assert ta == tb
    for x, y in zip(la, lb):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_a_model_without_a_degree_of_freedom_is_a_clear_error():
    xml = """<mujoco><worldbody><body name="plate">
      <inertial pos="0 0 0" mass="1" diaginertia="1 1 1"/></body></worldbody></mujoco>"""
    with pytest.raises(ValueError, match=r"from_mjcf: .*model has no degree of freedom: no body has a joint "
                                         r"\(1 body welded to the world\); add a joint to a body"):
        jb.from_mjcf(xml)


URDF_WITH_EXTRAS = """<robot name="r">
  <link name="base"><inertial><mass value="1"/><inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="l1"><inertial><mass value="1"/><inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="j1" type="continuous"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/></joint>
  <transmission name="t1"><type>transmission_interface/SimpleTransmission</type></transmission>
  <gazebo reference="l1"><material>Gazebo/Grey</material></gazebo>
  <gazebo><plugin name="p" filename="libp.so"/></gazebo>
</robot>"""


def test_urdf_elements_mujoco_skips_are_named_in_the_one_warning(tmp_path):
    """MuJoCo's URDF reader skips <gazebo> and <transmission> without a word: the importer's one
    warning names them with their counts (strict=True refuses them); MJCF has no such silence
    (MuJoCo's compiler rejects an unknown element, naming it)."""
    path = tmp_path / "r.urdf"
    path.write_text(URDF_WITH_EXTRAS)
    for source in (URDF_WITH_EXTRAS, path):
        with warnings.catch_warnings(record=True) as rec:
            warnings.simplefilter("always")
            model = jb.from_urdf(source)
        assert model.nv == 1
        (w,) = rec
        assert "URDF elements MuJoCo's URDF reader skips (ignored): 3 elements (2 <gazebo>, 1 <transmission>)" in str(w.message)
    with pytest.raises(ValueError, match=r"(?s)strict=True.*2 <gazebo>, 1 <transmission>"):
        jb.from_urdf(URDF_WITH_EXTRAS, strict=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a URDF MuJoCo reads fully: no warning
        jb.from_urdf(URDF_WITH_EXTRAS.replace("<transmission", "<!--").replace("</transmission>", "-->")
                     .replace('<gazebo reference="l1"><material>Gazebo/Grey</material></gazebo>', "")
                     .replace('<gazebo><plugin name="p" filename="libp.so"/></gazebo>', ""))
    with pytest.raises(ValueError, match=r"unrecognized element.*'gazebo'"):
        jb.from_mjcf("<mujoco><gazebo/><worldbody><body><joint/><geom size='.1'/></body></worldbody></mujoco>")
