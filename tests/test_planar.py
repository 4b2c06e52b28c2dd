"""Planar systems in absolute angles (spec §9–§10): identities on random trees, gradients,
float32, trace size, decoupling (Cor. 8) and input validation.

References are computed here, independently of ``jaxbody.planar``: forward kinematics written
with a Python loop and 2×2 rotation matrices, velocities and accelerations by ``jax.jvp``,
Kane's method on that kinematics, virtual work for loads (Lagrange's equations derived
symbolically are in ``test_planar_sympy.py``).
Every check on a random tree goes through one jitted bundle per topology (compile once).
"""

import math

import jax
import jax.test_util
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxbody as jb
from jaxbody import planar

HYP = settings(
    max_examples=8,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)


# ------------------------------------------------------------------------ random trees
def _random_parent(rng, n, n_roots_max=2):
    parent = [-1]
    for k in range(1, n):
        root = rng.random() < 0.25 and sum(p < 0 for p in parent) < n_roots_max
        parent.append(-1 if root else int(rng.integers(0, k)))
    return tuple(parent)


_rng = np.random.default_rng(3)
# (parent, translating base, angle_origin): two random topologies plus an edge case; a tuple,
# so no test can change what the others draw from
TOPOLOGIES = (
    (_random_parent(_rng, 5), False, 0.0),
    (_random_parent(_rng, 4), True, -0.5 * math.pi),
    ((-1,), True, 0.0),  # one body on a translating base: no carrier pairs
)


def random_system(topology, seed, dtype=np.float64):
    """Random parameters from ``seed`` on ``topology`` = (parent, translating base, angle_origin)."""
    parent, base, origin = topology
    rng = np.random.default_rng(seed)
    n = len(parent)
    return planar.from_parents(
        parent,
        rng.uniform(0.3, 2.0, n).astype(dtype),
        rng.normal(0.0, 0.3, (n, 2)).astype(dtype),
        rng.normal(0.0, 0.5, (n, 2)).astype(dtype),
        rng.uniform(0.01, 0.2, n).astype(dtype),
        gravity=np.array([rng.normal(0.0, 1.0), -9.81 + rng.normal()], dtype),
        base_mass=dtype(rng.uniform(0.5, 3.0)) if base else None,
        angle_origin=origin,
    )


def random_state(s, seed, dtype=np.float64):
    rng = np.random.default_rng(seed + 1)
    n = s.n_body
    f = lambda *x: jnp.asarray(np.asarray(x[0], dtype))  # noqa: E731
    return dict(
        q=f(rng.uniform(-math.pi, math.pi, s.nq)),
        v=f(rng.normal(0.0, 1.5, s.nv)),
        tau=f(rng.normal(0.0, 2.0, s.nv)),
        force=f(rng.normal(0.0, 3.0, (n, 2))),
        moment=f(rng.normal(0.0, 1.0, n)),
        onehot=jnp.asarray(np.eye(n, dtype=dtype)[int(rng.integers(0, n))]),
        point=f(rng.normal(0.0, 0.4, 2)),
        point_force=f(rng.normal(0.0, 3.0, 2)),
    )


# ------------------------------------------------------------------------ references
def _rotmat(t):
    c, s = jnp.cos(t), jnp.sin(t)
    return jnp.array([[c, -s], [s, c]])


def ref_points(s, q):
    """Hinges ``O_k``, CMs ``C_k``, absolute angles, base position: plain forward kinematics."""
    nb = 2 if s.translating_base else 0
    base = q[:2] if nb else jnp.zeros(2, q.dtype)
    theta = q[nb:] + s.angle_origin
    O, C = [], []
    for k, p in enumerate(s.tree.parent):
        o = base + s.hinge_pos[k] if p < 0 else O[p] + _rotmat(theta[p]) @ s.hinge_pos[k]
        O.append(o)
        C.append(o + _rotmat(theta[k]) @ s.body_com[k])
    return jnp.stack(O), jnp.stack(C), theta, base


def ref_kinetic(s, q, v):
    _, Cdot = jax.jvp(lambda qq: ref_points(s, qq)[1], (q,), (v,))
    _, thdot = jax.jvp(lambda qq: ref_points(s, qq)[2], (q,), (v,))
    T = 0.5 * jnp.sum(s.body_mass * jnp.sum(Cdot**2, axis=1)) + 0.5 * jnp.sum(s.body_inertia * thdot**2)
    if s.translating_base:
        T = T + 0.5 * s.base_mass * jnp.sum(v[:2] ** 2)
    return T


def ref_potential(s, q):
    _, C, _, base = ref_points(s, q)
    V = -jnp.sum(s.body_mass * (C @ s.gravity))
    if s.translating_base:
        V = V - s.base_mass * jnp.dot(base, s.gravity)
    return V


def ref_dynamics(s, q, v):
    """Mass matrix and ``h`` by Kane's method on the reference kinematics.

    ``ℳ = Σ m_k J_Ckᵀ J_Ck + I_k J_θkᵀ J_θk (+ m_base J_bᵀ J_b)`` and
    ``h = Σ m_k J_Ckᵀ (J̇_Ck v − g) (− m_base J_bᵀ g)`` with the Jacobians from ``jax.jacfwd``
    and ``J̇ v`` from a second ``jvp`` of the reference positions.
    """
    JO, JC, Jth, Jb = jax.jacfwd(lambda qq: ref_points(s, qq))(q)
    quad = jax.jvp(lambda qq: jax.jvp(lambda x: ref_points(s, x)[1], (qq,), (v,))[1], (q,), (v,))[1]
    m, inertia = s.body_mass, s.body_inertia
    M = jnp.einsum("k,kai,kaj->ij", m, JC, JC) + jnp.einsum("k,ki,kj->ij", inertia, Jth, Jth)
    h = jnp.einsum("k,kai,ka->i", m, JC, quad - s.gravity)
    if s.translating_base:
        M = M + s.base_mass * Jb.T @ Jb
        h = h - s.base_mass * Jb.T @ s.gravity
    del JO
    return M, h


def ref_power(s, q, v, tau, force, moment):
    """Drives: ``Σ M_k (θ̇_k − θ̇_p(k)) + F·v_base``; loads: ``F_rk·v_Ok + M_rk θ̇_k``."""
    nb = 2 if s.translating_base else 0
    _, (Odot, _, thdot, _) = jax.jvp(lambda qq: ref_points(s, qq), (q,), (v,))
    rel = jnp.stack([thdot[k] - (thdot[p] if p >= 0 else 0.0) for k, p in enumerate(s.tree.parent)])
    P = jnp.dot(tau[nb:], rel) + jnp.sum(force * Odot) + jnp.dot(moment, thdot)
    if nb:
        P = P + jnp.dot(tau[:2], v[:2])
    return P


def ref_com_acceleration(s, q, v, a):
    C = lambda qq: ref_points(s, qq)[1]  # noqa: E731
    quad = jax.jvp(lambda qq: jax.jvp(C, (qq,), (v,))[1], (q,), (v,))[1]
    return quad + jax.jvp(C, (q,), (a,))[1]


def subtree_sets(parent):
    n = len(parent)
    sets = [{k} for k in range(n)]
    for k in reversed(range(n)):
        if parent[k] >= 0:
            sets[parent[k]] |= sets[k]
    return sets


def _point_load_refs(s, q, body_onehot, point, force):
    """Generalized force of a point load: library vs virtual work ``J_pᵀ f`` (reference FK)."""
    body = jnp.argmax(body_onehot)

    def pos(qq):
        O, _, theta, _ = ref_points(s, qq)
        return O[body] + _rotmat(theta[body]) @ point

    Q_ref = jax.jacfwd(pos)(q).T @ force
    # library loads: F_r on the body, M_r = arm × f about its hinge (the body index is traced
    # here, so the one-hot selector replaces planar.point_load, which is checked separately)
    arm = _rotmat(planar.absolute_angles(s, q)[body]) @ point
    F = body_onehot[:, None] * force
    Mr = body_onehot * (arm[0] * force[1] - arm[1] * force[0])
    return Q_ref, planar.generalized_forces(s, q, None, external_force=F, external_moment=Mr), pos(q)


@jax.jit
def bundle(s, st_):
    q, v, tau, F, Mr = st_["q"], st_["v"], st_["tau"], st_["force"], st_["moment"]
    M = planar.mass_matrix(s, q)
    h = planar.bias_forces(s, q, v)
    acc = planar.forward_dynamics(s, q, v, tau, external_force=F, external_moment=Mr)
    M_ref, h_ref = ref_dynamics(s, q, v)
    Q_ref, Q_load, point_ref = _point_load_refs(s, q, st_["onehot"], st_["point"], st_["point_force"])
    out = dict(
        M=M,
        h=h,
        M_ref=M_ref,
        h_ref=h_ref,
        T=planar.kinetic_energy(s, q, v),
        T_quad=0.5 * v @ M @ v,
        T_ref=ref_kinetic(s, q, v),
        V=planar.potential_energy(s, q),
        V_ref=ref_potential(s, q),
        acc=acc,
        acc_protocol=s.acceleration(0.0, q, v, tau),
        acc_drives=planar.forward_dynamics(s, q, v, tau),
        tau_back=planar.inverse_dynamics(s, q, v, acc, external_force=F, external_moment=Mr),
        dE=jax.jvp(lambda qq, vv: planar.total_energy(s, qq, vv), (q, v), (v, acc))[1],
        P=planar.power(s, q, v, tau, external_force=F, external_moment=Mr),
        P_protocol=s.power(0.0, q, v, tau),
        P_ref=ref_power(s, q, v, tau, F, Mr),
        P_ref_drives=ref_power(s, q, v, tau, 0.0 * F, 0.0 * Mr),
        joint_reactions=planar.joint_reactions(s, q, v, acc, external_force=F)[0],
        root_force=planar.root_force(s, q, v, acc, external_force=F),
        com_acc=ref_com_acceleration(s, q, v, acc),
        hinges=planar.body_positions(s, q),
        points=ref_points(s, q),
        joint_M=planar.joint_mass_matrix(s, q),
        joint_h=planar.joint_bias_forces(s, q, v),
        rel=planar.absolute_to_relative(s, q),
        back=planar.relative_to_absolute(s, planar.absolute_to_relative(s, q)),
        Q_load=Q_load,
        Q_load_ref=Q_ref,
        point_ref=point_ref,
    )
    return out


def _close(a, b, rtol=1e-10, atol=1e-10):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=rtol, atol=atol)


topology = st.sampled_from(TOPOLOGIES)
seed = st.integers(0, 2**31 - 1)


# ------------------------------------------------------------------------ identities
def check_identities(s, sd):
    st_ = random_state(s, sd)
    out = bundle(s, st_)
    M = np.asarray(out["M"])
    scale = 1.0 + np.abs(M).max()
    # symmetric positive definite
    np.testing.assert_array_equal(M, M.T)
    assert np.linalg.eigvalsh(M).min() > 0
    # ½ vᵀℳv = kinetic energy from CM velocities (reference FK + jvp); library T the same
    _close(out["T_quad"], out["T_ref"], atol=1e-10 * scale)
    _close(out["T"], out["T_ref"], atol=1e-10 * scale)
    _close(out["V"], out["V_ref"], atol=1e-9)
    # mass matrix and h agree with Kane's method on the reference kinematics
    _close(M, out["M_ref"], atol=1e-10 * scale)
    _close(out["h"], out["h_ref"], atol=1e-9 * (1 + np.abs(np.asarray(out["h_ref"])).max()))
    # forward then inverse dynamics is the identity (drives and external loads)
    _close(out["tau_back"], st_["tau"], atol=1e-9)
    _close(out["acc_protocol"], out["acc_drives"], rtol=1e-12, atol=1e-12)
    # dE/dt = power of drives and external loads; power = independent virtual-power sum
    _close(out["P"], out["P_ref"], atol=1e-9)
    _close(out["P_protocol"], out["P_ref_drives"], atol=1e-9)
    _close(out["dE"], out["P"], atol=1e-8)


def check_reactions_kinematics_and_joint_space(s, sd):
    st_ = random_state(s, sd)
    out = bundle(s, st_)
    parent = s.tree.parent
    mass, g = np.asarray(s.body_mass), np.asarray(s.gravity)
    a_c, F = np.asarray(out["com_acc"]), np.asarray(st_["force"])
    # eq. (1): force from the base body on subsystem k = Σ m a_C − m g − Σ F_r over S(k)
    for k, sub in enumerate(subtree_sets(parent)):
        idx = sorted(sub)
        ref = (mass[idx, None] * a_c[idx]).sum(0) - mass[idx].sum() * g - F[idx].sum(0)
        _close(out["joint_reactions"][k], ref, atol=1e-8)
    roots = [k for k, p in enumerate(parent) if p < 0]
    _close(out["root_force"], np.asarray(out["joint_reactions"])[roots].sum(0), atol=1e-12)
    # hinge and CM positions
    _close(out["hinges"][0], out["points"][0], atol=1e-12)
    _close(out["hinges"][1], out["points"][1], atol=1e-12)
    # joint space: α = T q with the dense path matrix; TᵀℳT and Tᵀh
    nb = s.n_base
    T = np.eye(s.nq)
    T[nb:, nb:] = s.tree.path_matrix
    q = np.asarray(st_["q"])
    _close(T @ np.asarray(out["rel"]), q, atol=1e-12)
    _close(out["back"], q, atol=1e-12)
    _close(out["joint_M"], T.T @ np.asarray(out["M"]) @ T, atol=1e-12)
    _close(out["joint_h"], T.T @ np.asarray(out["h"]), atol=1e-10)


def check_point_load_is_virtual_work(s, sd):
    out = bundle(s, random_state(s, sd))
    _close(out["Q_load"], out["Q_load_ref"], atol=1e-10)


@HYP
@given(topology, seed)
def test_random_tree_identities(topo, sd):
    check_identities(random_system(topo, sd), sd)


@HYP
@given(topology, seed)
def test_random_tree_reactions_kinematics_and_joint_space(topo, sd):
    check_reactions_kinematics_and_joint_space(random_system(topo, sd), sd)


@HYP
@given(topology, seed)
def test_random_tree_point_load_is_virtual_work(topo, sd):
    check_point_load_is_virtual_work(random_system(topo, sd), sd)


def test_point_load_helpers():
    s = random_system(TOPOLOGIES[1], 3)
    st_ = random_state(s, 3)
    body = int(np.argmax(np.asarray(st_["onehot"])))
    out = bundle(s, st_)

    @jax.jit
    def helpers(s_, q, point, force):
        F, Mr = planar.point_load(s_, q, body, point, force)
        return planar.generalized_forces(s_, q, None, external_force=F, external_moment=Mr), planar.point_position(s_, q, body, point)

    Q, pos = helpers(s, st_["q"], st_["point"], st_["point_force"])
    _close(Q, out["Q_load_ref"], atol=1e-10)
    _close(pos, out["point_ref"], atol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("n_body, base, tree_seed", [(2, False, 1), (6, True, 2), (7, False, 3), (8, True, 4)])
def test_more_random_topologies(n_body, base, tree_seed):
    """Slow: fresh random topologies (one compilation each) through the same identities."""
    rng = np.random.default_rng(tree_seed)
    topo = (_random_parent(rng, n_body, n_roots_max=3), base, float(rng.choice([0.0, -0.5 * math.pi])))
    for sd in range(3):
        s = random_system(topo, sd)
        check_identities(s, sd)
        check_reactions_kinematics_and_joint_space(s, sd)
        check_point_load_is_virtual_work(s, sd)


# ------------------------------------------------------------------------ trajectory: dE/dt = P
def _rk4_energy_balance(s, q0, v0, tau, dt, steps):
    def f(y):
        q, v, _ = y
        return (v, s.acceleration(0.0, q, v, tau), s.power(0.0, q, v, tau))

    def step(y, _):
        add = lambda y_, k, c: jax.tree.map(lambda a_, b_: a_ + c * b_, y_, k)  # noqa: E731
        k1 = f(y)
        k2 = f(add(y, k1, 0.5 * dt))
        k3 = f(add(y, k2, 0.5 * dt))
        k4 = f(add(y, k3, dt))
        inc = jax.tree.map(lambda a1, a2, a3, a4: (a1 + 2 * a2 + 2 * a3 + a4) / 6.0, k1, k2, k3, k4)
        y = add(y, inc, dt)
        return y, s.total_energy(y[0], y[1]) - y[2]

    y0 = (q0, v0, jnp.zeros((), q0.dtype))
    _, balance = jax.lax.scan(step, y0, None, length=steps)
    return balance - s.total_energy(q0, v0)


@pytest.mark.parametrize("topo", [1])
def test_trajectory_energy_change_equals_work_of_drives(topo):
    s = random_system(TOPOLOGIES[topo], 11)
    st_ = random_state(s, 11)
    drift = jax.jit(_rk4_energy_balance, static_argnums=(4, 5))(
        s, st_["q"], 0.3 * st_["v"], st_["tau"], 1e-3, 400
    )
    # E(t) − E(0) − ∫ P dt stays at the RK4 truncation level while E changes by O(1)
    assert float(jnp.max(jnp.abs(drift))) < 1e-7


# ------------------------------------------------------------------------ gradients
def test_gradients_match_finite_differences():
    parent, base, origin = TOPOLOGIES[1]
    s0 = random_system(TOPOLOGIES[1], 5)
    st_ = random_state(s0, 5)
    params = dict(mass=s0.body_mass, com=s0.body_com, hinge_pos=s0.hinge_pos, inertia=s0.body_inertia,
                  base_mass=s0.base_mass, gravity=s0.gravity)

    @jax.jit
    def f(p):
        s = planar.from_parents(parent, p["mass"], p["com"], p["hinge_pos"], p["inertia"], gravity=p["gravity"],
                        base_mass=p["base_mass"], angle_origin=origin)
        M = planar.mass_matrix(s, st_["q"])
        acc = planar.forward_dynamics(s, st_["q"], st_["v"], st_["tau"])
        return jnp.concatenate([M.ravel(), acc])

    jax.test_util.check_grads(f, (params,), order=1, modes=("rev",), eps=1e-6, atol=1e-6, rtol=1e-6)

    # the chain builder is differentiable in its own arguments too (central differences)
    q, v = jnp.array([0.3, -0.5, 1.1]), jnp.array([0.8, -1.2, 2.0])

    def g(length):
        s = planar.chain(jnp.array([2.0, 1.5, 0.8]), jnp.array([0.35, 0.25, 0.15]), length,
                         jnp.array([0.09, 0.04, 0.01]))
        return planar.forward_dynamics(s, q, v)[2]

    value_and_grad = jax.jit(jax.value_and_grad(g))
    L = jnp.array([0.7, 0.5])
    _, grad = value_and_grad(L)
    h = 1e-6
    fd = jnp.stack([(value_and_grad(L + h * e)[0] - value_and_grad(L - h * e)[0]) / (2 * h) for e in jnp.eye(2)])
    _close(grad, fd, rtol=1e-6, atol=1e-8)


# ------------------------------------------------------------------------ float32
@jax.jit
def _lite(s, q, v, tau):
    return planar.mass_matrix(s, q), planar.forward_dynamics(s, q, v, tau), planar.total_energy(s, q, v)


@pytest.mark.parametrize("topo", [1])
def test_float32_matches_float64(topo):
    sd = 7
    s64, s32 = random_system(TOPOLOGIES[topo], sd), random_system(TOPOLOGIES[topo], sd, np.float32)
    st64, st32 = random_state(s64, sd), random_state(s32, sd, np.float32)
    assert s32.body_mass.dtype == jnp.float32
    out64 = _lite(s64, st64["q"], 0.5 * st64["v"], st64["tau"])
    out32 = _lite(s32, st32["q"], 0.5 * st32["v"], st32["tau"])
    for x32, x64 in zip(out32, out64):
        assert x32.dtype == jnp.float32
        err = np.abs(np.asarray(x32, np.float64) - np.asarray(x64)).max() / np.abs(np.asarray(x64)).max()
        assert err < 2e-5


# ------------------------------------------------------------------------ trace size
def _count_eqns(jaxpr):
    count = 0
    for eqn in jaxpr.eqns:
        count += 1
        for val in eqn.params.values():
            vals = val if isinstance(val, (tuple, list)) else (val,)
            for sub in vals:
                if isinstance(sub, jax.extend.core.ClosedJaxpr):
                    count += _count_eqns(sub.jaxpr)
                elif isinstance(sub, jax.extend.core.Jaxpr):
                    count += _count_eqns(sub)
    return count


def _sized_tree(n, base, seed=0):
    rng = np.random.default_rng(seed)
    parent = [-1] + [int(rng.integers(max(0, k - 3), k)) for k in range(1, n)]
    return planar.from_parents(
        parent, rng.uniform(0.5, 1.5, n), rng.normal(0, 0.2, (n, 2)), rng.normal(0, 0.5, (n, 2)),
        rng.uniform(0.01, 0.1, n), base_mass=1.0 if base else None,
    )


@pytest.mark.parametrize("kind", ["chain", "tree", "tree_on_base"])
def test_trace_size_does_not_grow_with_bodies(kind):
    def systems(n):
        if kind == "chain":
            return planar.chain(np.ones(n), 0.3 * np.ones(n), 0.5 * np.ones(n - 1), 0.01 * np.ones(n))
        return _sized_tree(n, kind == "tree_on_base")

    fns = {
        "mass_matrix": lambda s, q, v: planar.mass_matrix(s, q),
        "bias_forces": lambda s, q, v: planar.bias_forces(s, q, v),
        "forward_dynamics": lambda s, q, v: planar.forward_dynamics(s, q, v, v),
        "inverse_dynamics": lambda s, q, v: planar.inverse_dynamics(s, q, v, v),
        "joint_mass_matrix": lambda s, q, v: planar.joint_mass_matrix(s, q),
        "kinetic_energy": lambda s, q, v: planar.kinetic_energy(s, q, v),
        "joint_reactions": lambda s, q, v: planar.joint_reactions(s, q, v, v)[0],
    }
    counts = {}
    for n in (4, 64):
        s = systems(n)
        q = jnp.zeros(s.nq)
        for name, fn in fns.items():
            counts.setdefault(name, []).append(_count_eqns(jax.make_jaxpr(fn)(s, q, q).jaxpr))
    for name, (c4, c64) in counts.items():
        if name != "forward_dynamics":
            assert c4 == c64, f"{name}: {c4} equations for 4 bodies, {c64} for 64"
    # the solve unrolls for small systems (n <= AUTO_UNROLLED_MAX_N, bounded trace) and loops
    # above: compare two sizes on the loop path
    from jaxbody.linalg import AUTO_UNROLLED_MAX_N

    n_small = AUTO_UNROLLED_MAX_N + 4
    fd = [
        _count_eqns(jax.make_jaxpr(fns["forward_dynamics"])(s, jnp.zeros(s.nq), jnp.zeros(s.nq)).jaxpr)
        for s in (systems(n_small), systems(64))
    ]
    assert fd[0] == fd[1], f"forward_dynamics: {fd[0]} equations for {n_small} bodies, {fd[1]} for 64"


def test_trace_size_augmented_functions():
    counts = {}
    for n in (4, 64):
        rng = np.random.default_rng(n)
        tr = jb.BodyTree([-1] + [int(rng.integers(max(0, k - 3), k)) for k in range(1, n)])
        m = jnp.asarray(rng.uniform(0.5, 1.5, n))
        r2, l2 = jnp.asarray(rng.normal(size=(n, 2))), jnp.asarray(rng.normal(size=(n, 2)))
        r3, l3 = jnp.asarray(rng.normal(size=(n, 3))), jnp.asarray(rng.normal(size=(n, 3)))
        i1, i3 = jnp.asarray(rng.uniform(0.1, 1, n)), jnp.broadcast_to(jnp.eye(3), (n, 3, 3))
        fns = {
            "subtree_mass": lambda m_: jb.subtree_mass(tr, m_),
            "static_moment_2d": lambda m_: jb.static_moment(tr, m_, r2, l2),
            "static_moment_3d": lambda m_: jb.static_moment(tr, m_, r3, l3),
            "augmented_inertia": lambda m_: jb.augmented_inertia(tr, m_, i3, r3, l3),
            "augmented_moment_of_inertia": lambda m_: jb.augmented_moment_of_inertia(tr, m_, i1, r2, l2),
        }
        for name, fn in fns.items():
            counts.setdefault(name, []).append(_count_eqns(jax.make_jaxpr(fn)(m).jaxpr))
    for name, (c4, c64) in counts.items():
        assert c4 == c64, f"{name}: {c4} equations for 4 bodies, {c64} for 64"


# ------------------------------------------------------------------------ conventions
def test_chain_angle_convention():
    s = planar.chain([1.0, 0.6], [0.4, 0.3], [0.8], [0.05, 0.02])

    @jax.jit
    def probe(s_, q):
        return dict(
            positions=planar.body_positions(s_, q),
            theta=planar.absolute_angles(s_, q),
            h_rest=planar.bias_forces(s_, q, jnp.zeros(2)),
            rel=planar.absolute_to_relative(s_, q),
            back=planar.relative_to_absolute(s_, q),
        )

    # q = 0: both links hang straight down from the origin
    hinge, com = probe(s, jnp.zeros(2))["positions"]
    _close(hinge, [[0.0, 0.0], [0.0, -0.8]], atol=1e-15)
    _close(com, [[0.0, -0.4], [0.0, -1.1]], atol=1e-15)
    # q_1 = π/2: counter-clockwise from the downward vertical, link 1 points along +i
    hinge, com = probe(s, jnp.array([0.5 * math.pi, 0.0]))["positions"]
    _close(hinge[1], [0.8, 0.0], atol=1e-15)
    _close(com[1], [0.8, -0.3], atol=1e-15)
    out = probe(s, jnp.array([0.3, -0.5]))
    _close(out["theta"], [0.3 - 0.5 * math.pi, -0.5 - 0.5 * math.pi])
    _close(planar.vertical_to_horizontal(0.3), 0.3 - 0.5 * math.pi)
    _close(planar.horizontal_to_vertical(planar.vertical_to_horizontal(0.3)), 0.3, atol=1e-15)
    # gravity torque (md)_k g sin α_k in eq. (14): h at rest
    _close(out["h_rest"], [0.88 * 9.81 * math.sin(0.3), 0.18 * 9.81 * math.sin(-0.5)], rtol=1e-13)
    # relative angles of the chain: q_rel = (α_1, α_2 − α_1); back: α = (q_1, q_1 + q_2)
    _close(out["rel"], [0.3, -0.8], rtol=1e-15)
    _close(out["back"], [0.3, -0.2], rtol=1e-15)


def test_inverse_dynamics_returns_hinge_torques_of_t1():
    s = planar.chain([1.0, 0.6], [0.4, 0.3], [0.8], [0.05, 0.02])
    q, v = jnp.array([0.3, -0.5]), jnp.array([0.8, -1.2])
    tau = planar.inverse_dynamics(s, q, v, jnp.array([-6.03982668881, 17.8193431534]))
    _close(tau, [0.7, -0.2], rtol=1e-9)


def test_ground_force_of_a_pendulum_at_rest_is_its_weight():
    s = planar.chain([1.0, 0.6], [0.4, 0.3], [0.8], [0.05, 0.02])
    z = jnp.zeros(2)
    _close(planar.root_force(s, jnp.array([0.4, -0.2]), z, z), [0.0, 1.6 * 9.81], atol=1e-13)


# ------------------------------------------------------------------------ Corollary 8
def _three_link(a2, a3, base_mass=None, a1=0.3):
    # link masses 1, 2, 1; L_2 = 0.5: (md)_3 = a_3, (md)_2 = 2 a_2 + 0.5, (md)_1 = a_1 + 3 L_1
    com = [[a1, 0.0], [a2, 0.0], [a3, 0.0]]
    hinge = [[0.0, 0.0], [0.6, 0.0], [0.5, 0.0]]
    return planar.from_parents([-1, 0, 1], [1.0, 2.0, 1.0], com, hinge, [0.02, 0.03, 0.01], base_mass=base_mass)


def test_decoupling_balanced_chain_has_diagonal_mass_matrix():
    s = _three_link(a2=-0.25, a3=0.0)  # (md)_2 = (md)_3 = 0 exactly; (md)_1 ≠ 0
    rep = jb.design.decoupling_report(s, n_samples=16, seed=1)
    _close(rep.static_moment_magnitude, [1.0 * 0.3 + 3.0 * 0.6, 0.0, 0.0], atol=1e-15)
    assert rep.must_vanish.tolist() == [False, True, True]
    assert rep.decoupled and rep.offending == ()
    assert rep.residual == 0.0  # exactly diagonal at all sampled configurations
    assert rep.configurations.shape == (16, 3)
    # decoupled equations J_k α̈_k = M_k − Σ_{A(k)} M_j (+ gravity of the grounded body only)
    q, v, tau = jnp.array([0.4, -1.0, 2.0]), jnp.array([1.0, -2.0, 0.5]), jnp.array([0.5, -0.3, 0.2])

    @jax.jit
    def probe(s_, q_, v_, tau_):
        return (planar.augmented_bodies_in_body_axes(s_).augmented_inertia, planar.forward_dynamics(s_, q_, v_, tau_),
                planar.joint_mass_matrix(s_, q_))

    J, acc, Mq = (np.asarray(x) for x in probe(s, q, v, tau))
    t_abs = np.array([0.5 + 0.3, -0.3 - 0.2, 0.2])
    grav = np.array([2.1 * 9.81 * math.cos(0.4), 0.0, 0.0])  # −m̄_1 × g with θ from i
    _close(acc, (t_abs - grav) / J, rtol=1e-12)
    # but not in joint angles (spec §10)
    assert np.abs(Mq - np.diag(np.diag(Mq))).max() > 1e-3


def test_decoupling_unbalanced_chain_is_coupled():
    s = _three_link(a2=0.2, a3=0.1)
    rep = jb.design.decoupling_report(s, n_samples=8)
    assert not rep.decoupled and rep.offending == (1, 2)
    assert rep.residual > 0.1
    # only body 3 unbalanced: still coupled, and only body 3 reported
    rep = jb.design.decoupling_report(_three_link(a2=-0.25, a3=0.1), configurations=np.zeros((1, 3)))
    assert rep.offending == (2,) and rep.residual > 0.01


def test_decoupling_on_a_translating_base_needs_every_body_balanced():
    balanced = planar.from_parents([-1, 0], [1.0, 1.0], [[-0.5, 0.0], [0.0, 0.0]], [[0.0, 0.0], [0.5, 0.0]],
                           [0.1, 0.02], base_mass=2.0)
    rep = jb.design.decoupling_report(balanced)
    assert rep.must_vanish.tolist() == [True, True] and rep.decoupled and rep.residual == 0.0
    # body 1 unbalanced on the base: (md)_1 ≠ 0 couples body 1 with the base
    s = planar.from_parents([-1, 0], [1.0, 1.0], [[0.3, 0.0], [0.0, 0.0]], [[0.0, 0.0], [0.5, 0.0]],
                    [0.1, 0.02], base_mass=2.0)
    rep = jb.design.decoupling_report(s)
    assert rep.offending == (0,) and not rep.decoupled and rep.residual > 0.1


# ------------------------------------------------------------------------ bad input
GOOD = dict(parent=[-1, 0, 0], mass=[1.0, 0.5, 0.5], com=[[0.1, 0.0]] * 3, hinge_pos=[[0.0, 0.0], [0.5, 0.0], [0.4, 0.1]],
            inertia=[0.01, 0.02, 0.03])


def _build(**kw):
    args = {**GOOD, **kw}
    names = kw.pop("names", ("arm", "left", "right"))
    return planar.from_parents(args["parent"], args["mass"], args["com"], args["hinge_pos"], args["inertia"],
                       gravity=args.get("gravity", (0.0, -9.81)), base_mass=args.get("base_mass"), names=names)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(mass=[1.0, -0.5, 0.5]), r"planar body 1 \('left'\): body_mass is negative \(-0.5\)"),
        (dict(mass=[1.0, 0.5, 0.0]), r"planar body 2 \('right'\): body_mass of its subsystem is zero"),
        (dict(inertia=[0.01, -0.02, 0.03]), r"planar body 1 \('left'\): body_inertia is negative"),
        (dict(mass=[1.0, float("nan"), 0.5]), r"planar body 1 \('left'\): body_mass is not finite"),
        (dict(com=[[0.1, 0.0], [0.1, 0.0], [float("nan"), 0.0]]), r"planar body 2 \('right'\): body_com is not finite"),
        (dict(hinge_pos=[[0.0, 0.0], [float("inf"), 0.0], [0.4, 0.1]]), r"planar body 1 \('left'\): hinge_pos is not finite"),
        (dict(inertia=[0.01, 0.02, float("nan")]), r"planar body 2 \('right'\): body_inertia is not finite"),
        (dict(gravity=(0.0, float("nan"))), r"planar system: gravity is not finite"),
        (dict(base_mass=-1.0), r"planar system: base_mass is negative"),
        (dict(base_mass=float("nan")), r"planar system: base_mass is not finite"),
        (dict(com=[[0.1, 0.0, 0.0]] * 3), r"com \(body_com\) has shape \(3, 3\), expected \(3, 2\)"),
        (dict(mass=[1.0, 0.5]), r"mass \(body_mass\) has shape \(2,\), expected \(3,\)"),
        (dict(inertia=[0.01, 0.02]), r"inertia \(body_inertia\) has shape \(2,\), expected \(3,\)"),
        (dict(hinge_pos=[[0.0, 0.0]] * 4), r"hinge_pos has shape \(4, 2\), expected \(3, 2\)"),
        (dict(gravity=(0.0, -9.81, 0.0)), r"gravity has shape \(3,\), expected \(2,\)"),
        (dict(mass=["a", "b", "c"]), r"mass \(body_mass\) must be numeric"),
        (dict(parent=[-1, 2, 0]), r"body 1 \('left'\) has parent 2"),
    ],
)
def test_bad_parameters_raise(kw, match):
    with pytest.raises(ValueError, match=match):
        _build(**kw)


def test_zero_augmented_inertia_raises():
    with pytest.raises(ValueError, match=r"planar body 0 \('bob'\): body_inertia gives a zero augmented moment"):
        planar.from_parents([-1], [1.0], [[0.0, 0.0]], [[0.0, 0.0]], [0.0], names=("bob",))


def test_bad_chain_arguments_raise():
    with pytest.raises(ValueError, match=r"planar chain: length has shape \(3,\), expected \(1,\)"):
        planar.chain([1.0, 0.6], [0.4, 0.3], [0.8, 0.8, 0.8], [0.05, 0.02])
    with pytest.raises(ValueError, match=r"planar chain: mass must be a 1-D array"):
        planar.chain([[1.0, 0.6]], [0.4, 0.3], [0.8], [0.05, 0.02])
    with pytest.raises(ValueError, match=r"com_distance has shape \(3,\), expected \(2,\)"):
        planar.chain([1.0, 0.6], [0.4, 0.3, 0.1], [0.8], [0.05, 0.02])
    with pytest.raises(ValueError, match=r"planar body 1 \('body1'\): body_mass is negative"):
        planar.chain([1.0, -0.6], [0.4, 0.3], [0.8], [0.05, 0.02])


def test_bad_state_shapes_raise():
    s = _build(base_mass=1.0)
    q, v = jnp.zeros(5), jnp.zeros(5)
    with pytest.raises(ValueError, match=r"planar system: q has shape \(3,\), expected \(5,\)"):
        planar.mass_matrix(s, jnp.zeros(3))
    with pytest.raises(ValueError, match=r"planar system: v has shape \(4,\), expected \(5,\)"):
        planar.bias_forces(s, q, jnp.zeros(4))
    with pytest.raises(ValueError, match=r"planar system: tau has shape \(3,\), expected \(5,\)"):
        planar.forward_dynamics(s, q, v, jnp.zeros(3))
    with pytest.raises(ValueError, match=r"planar system: tau has shape \(3,\), expected \(5,\)"):
        s.acceleration(0.0, q, v, jnp.zeros(3))
    with pytest.raises(ValueError, match=r"planar system: a has shape \(2,\), expected \(5,\)"):
        planar.inverse_dynamics(s, q, v, jnp.zeros(2))
    with pytest.raises(ValueError, match=r"external_force has shape \(2, 2\), expected \(3, 2\)"):
        planar.generalized_forces(s, q, None, external_force=jnp.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"external_moment has shape \(2,\), expected \(3,\)"):
        planar.generalized_forces(s, q, None, external_moment=jnp.zeros(2))
    with pytest.raises(ValueError, match=r"decoupling_report: configurations has shape \(2, 3\)"):
        jb.design.decoupling_report(s, configurations=np.zeros((2, 3)))


def test_validate_and_system_in_jit():
    s = _build()
    planar.validate(s)
    bad = jax.tree.map(lambda x: x, s)
    bad = eqx_replace(bad, body_mass=jnp.array([1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match=r"planar body 1 \('left'\): body_mass is negative"):
        planar.validate(bad)
    # systems are pytrees with static topology: equal topologies share one compilation
    f = jax.jit(planar.mass_matrix)
    f(s, jnp.zeros(3))
    f(_build(mass=[2.0, 0.5, 0.5]), jnp.zeros(3))
    assert f._cache_size() == 1


def eqx_replace(module, **kw):
    import equinox as eqx

    names = list(kw)
    return eqx.tree_at(lambda m: [getattr(m, k) for k in names], module, [kw[k] for k in names])
