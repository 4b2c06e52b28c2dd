"""Joint-space dynamics against MuJoCo on the same MJCF (the references are code we did not
write).

Models: the shared menagerie copies (panda, ur5e, anymal_c) and seeded random trees from
``tests/_support/mjcf_random.py`` (every joint kind, several joints per body, off-axis joints, rotated
frames and inertias, mass ratios up to 1e4). States are random with unit quaternions.

MuJoCo references, float64, relative to the norm of the reference quantity, ≤ ``RTOL``:

==========================  =========================================================
jaxbody                     MuJoCo
==========================  =========================================================
``mass_matrix``             ``mj_fullM`` (armature included)
``bias_forces``             ``qfrc_bias``
``inverse_dynamics``        ``mj_inverse`` → ``qfrc_inverse`` with springs and dampers
                            disabled (``mjDSBL_SPRING | mjDSBL_DAMPER``)
``forward_dynamics``        ``qacc`` of ``mj_forward`` with ``qfrc_applied = tau`` and
                            passive forces, constraints and actuation disabled
``joint_reactions``         ``cfrc_int`` after ``mj_rnePostConstraint`` (with ``qacc = a``),
                            moved from the root's subtree CoM to the body's joint point
``passive_forces``          ``qfrc_passive`` (springs and dampers as in the model)
``kinetic_energy``          ``mj_energyVel`` (½ vᵀ M v, armature included)
``potential_energy``        ``mj_energyPos`` (gravity + joint springs)
==========================  =========================================================

Every case is compiled once (one jitted, vmapped function computing all quantities at all
states of the case) because XLA compile time dominates; the random trees beyond the first
few run with ``-m slow``.

At the end: external body loads against ``xfrc_applied``, and a 60-link chain.
"""

import copy
import zlib
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb

mujoco = pytest.importorskip("mujoco")

from _support.mjcf_random import random_mjcf, random_state

RTOL = 1e-10
N_STATES = 3
MENAGERIE = ("panda", "ur5e", "anymal_c")
RANDOM_FAST = (0, 1, 2, 3)
RANDOM_SLOW = (4, 5, 6, 7, 8, 9)
FOREST_SEED = 100  # one larger forest: 3 trees, 30 bodies

D = mujoco.mjtDisableBit
RIGID_FLAGS = (
    D.mjDSBL_CONSTRAINT | D.mjDSBL_CONTACT | D.mjDSBL_EQUALITY | D.mjDSBL_LIMIT
    | D.mjDSBL_FRICTIONLOSS | D.mjDSBL_ACTUATION
)
PASSIVE_FLAGS = D.mjDSBL_SPRING | D.mjDSBL_DAMPER

CASES = (
    [pytest.param(("menagerie", n), id=n) for n in MENAGERIE]
    + [pytest.param(("random", s), id=f"random{s}") for s in RANDOM_FAST]
    + [pytest.param(("forest", FOREST_SEED), id=f"forest{FOREST_SEED}", marks=pytest.mark.slow)]
    + [pytest.param(("random", s), id=f"random{s}", marks=pytest.mark.slow) for s in RANDOM_SLOW]
)


# ----------------------------------------------------------------------------- references
def _source(kind, key, models_dir):
    if kind == "menagerie":
        return str(models_dir / f"{key}.xml")
    if kind == "forest":
        return random_mjcf(key, n_body=30, n_root=3, free_root=True)
    return random_mjcf(key, n_body=3 + key % 10)


def _mj_model(src):
    if src.lstrip().startswith("<"):
        return mujoco.MjModel.from_xml_string(src)
    return mujoco.MjModel.from_xml_path(src)


def _joint_point(m, d, i):
    """World position of body i's joint point O_0k: first joint's anchor, or the body origin."""
    if m.body_jntnum[i] > 0 and m.jnt_type[m.body_jntadr[i]] != mujoco.mjtJoint.mjJNT_FREE:
        return d.xanchor[m.body_jntadr[i]].copy()
    return d.xpos[i].copy()


def mujoco_reference(m0, q, v, a, tau):
    """MuJoCo's quantities at one state (see the module docstring)."""
    out = {}
    m = copy.copy(m0)
    base = int(m0.opt.disableflags)
    m.opt.disableflags = base | RIGID_FLAGS | PASSIVE_FLAGS
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.qfrc_applied[:] = q, v, tau
    mujoco.mj_forward(m, d)
    M = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M)
    out["M"], out["bias"], out["qacc"] = M, d.qfrc_bias.copy(), d.qacc.copy()
    d.qacc[:] = a
    mujoco.mj_inverse(m, d)
    out["inverse"] = d.qfrc_inverse.copy()
    # reactions: cfrc_int = (torque, force) at the subtree CoM of the body's root, world axes
    d.qfrc_applied[:] = 0.0
    mujoco.mj_forward(m, d)
    d.qacc[:] = a
    mujoco.mj_rnePostConstraint(m, d)
    nb = m.nbody - 1
    force, moment = np.zeros((nb, 3)), np.zeros((nb, 3))
    for k in range(nb):
        i = k + 1
        c = d.subtree_com[m.body_rootid[i]]
        P = _joint_point(m, d, i)
        force[k] = d.cfrc_int[i, 3:]
        moment[k] = d.cfrc_int[i, :3] + np.cross(c - P, d.cfrc_int[i, 3:])
    out["force"], out["moment"] = force, moment
    # passive forces and energies with springs and dampers as in the model
    m.opt.disableflags = base | RIGID_FLAGS
    m.opt.enableflags = int(m0.opt.enableflags) | mujoco.mjtEnableBit.mjENBL_ENERGY
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = q, v
    mujoco.mj_forward(m, d)
    mujoco.mj_energyPos(m, d)
    mujoco.mj_energyVel(m, d)
    out["passive"] = d.qfrc_passive.copy()
    out["potential"], out["kinetic"] = float(d.energy[0]), float(d.energy[1])
    # a natural scale for the potential energy (it may be near zero by cancellation)
    g = np.linalg.norm(m.opt.gravity)
    out["potential_scale"] = float(
        np.sum(m.body_mass[1:] * g * np.linalg.norm(d.xipos[1:], axis=1))
    ) + abs(out["potential"])
    return out


def _jaxbody_all(model, q, v, a, tau):
    f, mo = jb.joint_reactions(model, q, v, a)
    return dict(
        M=jb.mass_matrix(model, q),
        bias=jb.bias_forces(model, q, v),
        inverse=jb.inverse_dynamics(model, q, v, a),
        force=f,
        moment=mo,
        passive=jb.passive_forces(model, q, v),
        kinetic=jb.kinetic_energy(model, q, v),
        potential=jb.potential_energy(model, q),
    )


def _jaxbody_forward(model, q, v, a, tau):
    return dict(qacc=jb.forward_dynamics(model, q, v, tau))


_CACHE = {}


def _case(param, models_dir):
    """(ours, refs): per quantity, arrays stacked over N_STATES states. Compiled once."""
    if param in _CACHE:
        return _CACHE[param]
    kind, key = param
    src = _source(kind, key, models_dir)
    m = _mj_model(src)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # menagerie: contacts, limits, actuators
        model = jb.from_mjcf(src)
    rng = np.random.default_rng(zlib.crc32(repr(param).encode()))
    states = [random_state(m, rng) for _ in range(N_STATES)]
    Q, V, A = (np.stack(x) for x in zip(*states))
    TAU = rng.normal(size=A.shape) * 10.0
    refs = [mujoco_reference(m, Q[i], V[i], A[i], TAU[i]) for i in range(N_STATES)]
    refs = {k: np.stack([r[k] for r in refs]) for k in refs[0]}
    ours = {}
    for fn, keys in ((_jaxbody_all, _ALL_KEYS), (_jaxbody_forward, ("qacc",))):
        try:
            out = jax.jit(jax.vmap(fn, in_axes=(None, 0, 0, 0, 0)))(model, Q, V, A, TAU)
            ours.update({k: np.asarray(x) for k, x in out.items()})
        except Exception as e:  # re-raised by the tests that need these quantities
            ours.update({k: e for k in keys})
    _CACHE[param] = (ours, refs)
    return ours, refs


_ALL_KEYS = ("M", "bias", "inverse", "force", "moment", "passive", "kinetic", "potential")


def _get(ours, key):
    x = ours[key]
    if isinstance(x, Exception):
        raise x
    return x


def _rel(x, ref):
    """Relative error per state: ‖x − ref‖ / ‖ref‖ (Frobenius over everything but the state)."""
    x, ref = np.asarray(x), np.asarray(ref)
    n = x.shape[0]
    num = np.linalg.norm((x - ref).reshape(n, -1), axis=1)
    den = np.linalg.norm(ref.reshape(n, -1), axis=1)
    return num / np.where(den > 0, den, 1.0)


def _check(name, x, ref):
    err = _rel(x, ref)
    assert np.all(err <= RTOL), f"{name}: relative error per state {err.tolist()} > {RTOL}"


# ----------------------------------------------------------------------------- tests
def _energies(ours, refs):
    _check("kinetic_energy vs mj_energyVel", _get(ours, "kinetic"), refs["kinetic"])
    err = np.abs(_get(ours, "potential") - refs["potential"]) / refs["potential_scale"]
    assert np.all(err <= RTOL), f"potential_energy vs mj_energyPos: {err.tolist()}"


CHECKS = {
    "mass_matrix": lambda o, r: _check("mass_matrix vs mj_fullM", _get(o, "M"), r["M"]),
    "bias_forces": lambda o, r: _check("bias_forces vs qfrc_bias", _get(o, "bias"), r["bias"]),
    "inverse_dynamics": lambda o, r: _check("inverse_dynamics vs mj_inverse", _get(o, "inverse"), r["inverse"]),
    "forward_dynamics": lambda o, r: _check("forward_dynamics vs mj_forward qacc", _get(o, "qacc"), r["qacc"]),
    "joint_reactions": lambda o, r: (
        _check("joint_reactions force vs cfrc_int", _get(o, "force"), r["force"]),
        _check("joint_reactions moment vs cfrc_int at O_0k", _get(o, "moment"), r["moment"]),
    ),
    "passive_forces": lambda o, r: _check("passive_forces vs qfrc_passive", _get(o, "passive"), r["passive"]),
    "energies": _energies,
}


@pytest.mark.parametrize("param", CASES)
def test_agrees_with_mujoco(param, models_dir):
    """Every quantity of one model against MuJoCo, from one compilation (one test per model,
    so that parallel workers do not compile the same model several times). All failures are
    reported together, each naming the quantity."""
    ours, refs = _case(param, models_dir)
    failures = []
    for name, check in CHECKS.items():
        try:
            check(ours, refs)
        except Exception as err:  # noqa: BLE001 - collected and reported below
            failures.append(f"{name}: {type(err).__name__}: {err}")
    assert not failures, "\n".join(failures)


def test_reference_sign_convention_on_a_hanging_pendulum():
    """cfrc_int is what the parent exerts on the body: a pendulum at rest is held up."""
    xml = """<mujoco><option gravity="0 0 -10"/><worldbody>
      <body name="p" pos="0 0 1"><joint name="h" axis="0 1 0"/>
        <inertial pos="0 0 -0.5" mass="2" diaginertia="0.1 0.1 0.1"/></body></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    ref = mujoco_reference(m, np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1))
    np.testing.assert_allclose(ref["force"][0], [0, 0, 20], atol=1e-12)
    np.testing.assert_allclose(ref["moment"][0], [0, 0, 0], atol=1e-12)
    # hinge angle -90° about y: CoM at (0.5, 0, 1); held static (a = 0) the parent also
    # supplies the torque against gravity: r × F_g = (0.5, 0, 0) × (0, 0, -20) = (0, 10, 0)
    ref = mujoco_reference(m, np.array([-np.pi / 2]), np.zeros(1), np.zeros(1), np.zeros(1))
    np.testing.assert_allclose(ref["force"][0], [0, 0, 20], atol=1e-12)
    np.testing.assert_allclose(ref["moment"][0], [0, -10, 0], atol=1e-12)


# ----------------------------------------------------------------------------- external loads, deep chains
# MuJoCo's ``xfrc_applied`` body loads, and a 60-link chain (deep recursion).
RIGID = (
    mujoco.mjtDisableBit.mjDSBL_SPRING
    | mujoco.mjtDisableBit.mjDSBL_DAMPER
    | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    | mujoco.mjtDisableBit.mjDSBL_CONTACT
    | mujoco.mjtDisableBit.mjDSBL_ACTUATION
)


def rel(x, ref):
    ref = np.asarray(ref)
    return float(np.abs(np.asarray(x) - ref).max() / max(np.abs(ref).max(), 1e-300))


def mujoco_pair(xml):
    m = mujoco.MjModel.from_xml_string(xml)
    m.opt.disableflags |= RIGID
    return m, mujoco.MjData(m), jb.from_mujoco(m)


@pytest.mark.parametrize("seed", [3, 4])
def test_external_loads_match_xfrc_applied(seed):
    m, d, model = mujoco_pair(random_mjcf(seed, n_body=6, rigid_only=True))
    rng = np.random.default_rng(seed)
    q = np.asarray(jb.normalize_qpos(model, jnp.asarray(m.qpos0 + 0.4 * rng.standard_normal(m.nq))))
    v, tau = rng.standard_normal(m.nv), rng.standard_normal(m.nv)
    xfrc = rng.standard_normal((m.nbody - 1, 6))
    d.qpos[:], d.qvel[:], d.qfrc_applied[:] = q, v, tau
    d.xfrc_applied[1:] = xfrc
    mujoco.mj_forward(m, d)
    fwd = jax.jit(lambda m, q, v, t, e: jb.forward_dynamics(m, q, v, t, external=e))
    assert rel(fwd(model, q, v, tau, jnp.asarray(xfrc)), d.qacc) < 1e-9
    a = d.qacc.copy()
    d.qacc[:] = a
    mujoco.mj_inverse(m, d)  # qfrc_inverse = M a + bias = qfrc_applied + Jᵀ xfrc (passive off)
    inv = jax.jit(lambda m, q, v, a, e=None: jb.inverse_dynamics(m, q, v, a, external=e))
    assert rel(inv(model, q, v, jnp.asarray(a)), d.qfrc_inverse) < 1e-10
    assert rel(inv(model, q, v, jnp.asarray(a), jnp.asarray(xfrc)), tau) < 1e-9


def chain_mjcf(n):
    body = ""
    for k in range(n):
        body += (
            f'<body name="l{k}" pos="0 0 {-0.3 if k else 0}">'
            f'<joint type="hinge" axis="{"0 1 0" if k % 2 else "1 0 0"}"/>'
            f'<inertial pos="0.01 0.005 -0.15" mass="{1 + 0.01 * k}" diaginertia="0.01 0.011 0.002"/>'
        )
    body += "</body>" * n
    return f"<mujoco><worldbody>{body}</worldbody></mujoco>"


def test_deep_chain_matches_mujoco():
    """60 links: deep recursion handled by pointer jumping and dense sums, still exact."""
    m, d, model = mujoco_pair(chain_mjcf(60))
    rng = np.random.default_rng(0)
    q, v = 0.3 * rng.standard_normal(m.nv), rng.standard_normal(m.nv)
    d.qpos[:], d.qvel[:] = q, v
    mujoco.mj_forward(m, d)
    M = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M)
    assert rel(jax.jit(jb.mass_matrix)(model, q), M) < 1e-10
    assert rel(jax.jit(jb.bias_forces)(model, q, v), d.qfrc_bias) < 1e-10
    assert rel(jax.jit(jb.forward_dynamics)(model, q, v), d.qacc) < 1e-8
