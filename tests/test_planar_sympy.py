"""Independent Lagrange derivation in sympy vs ``jaxbody.planar`` (spec §9.2–9.4).

For each shape the CM positions are written from the **joint** (relative) coordinates,
``T`` and ``V`` formed, and Euler–Lagrange's equations ``M_q(q) q̈ + b(q, q̇) = Q`` derived
symbolically with every parameter a symbol (masses, off-axis CMs, hinge offsets, inertias,
gravity vector, base mass). No ``simplify``: derivatives of the raw expressions, lambdified with
common-subexpression elimination. The code works in absolute angles, so the comparison goes
through ``α = T q`` with ``T`` built here from the parent array.
"""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy as sp

from jaxbody import planar

# name: (parent, translating base, angle_origin)
SHAPES = {
    "chain2": ((-1, 0), False, -0.5 * math.pi),
    "chain3": ((-1, 0, 1), False, -0.5 * math.pi),
    "chain4": ((-1, 0, 1, 2), False, -0.5 * math.pi),
    "tree_ground": ((-1, 0, 0, 1), False, 0.0),
    "tree_on_base": ((-1, 0, 0, -1), True, 0.0),
}
N_STATES = 4


@functools.lru_cache(maxsize=None)
def derive(name):
    """Lambdified ``M_q(Q, params)`` and ``b(Q, U, params)`` of Euler–Lagrange's equations."""
    parent, base, origin = SHAPES[name]
    n = len(parent)
    q = sp.symbols(f"q0:{n}")
    u = sp.symbols(f"u0:{n}")
    xy, uxy = sp.symbols("x y"), sp.symbols("ux uy")
    Q = (list(xy) if base else []) + list(q)
    U = (list(uxy) if base else []) + list(u)
    m = sp.symbols(f"m0:{n}")
    cx, cy = sp.symbols(f"cx0:{n}"), sp.symbols(f"cy0:{n}")
    px, py = sp.symbols(f"px0:{n}"), sp.symbols(f"py0:{n}")
    inertia = sp.symbols(f"I0:{n}")
    gx, gy, mb = sp.symbols("gx gy mb")
    params = [*m, *cx, *cy, *px, *py, *inertia, gx, gy, mb]
    zero_angle = sp.nsimplify(origin / math.pi) * sp.pi

    def rot(t, v):
        return sp.Matrix([sp.cos(t) * v[0] - sp.sin(t) * v[1], sp.sin(t) * v[0] + sp.cos(t) * v[1]])

    base_pos = sp.Matrix(xy) if base else sp.zeros(2, 1)
    theta, O, C = [], [], []
    for k, p in enumerate(parent):
        th = (zero_angle if p < 0 else theta[p]) + q[k]  # joint coordinates: relative angles
        o = base_pos + sp.Matrix([px[k], py[k]]) if p < 0 else O[p] + rot(theta[p], (px[k], py[k]))
        theta.append(th)
        O.append(o)
        C.append(o + rot(th, (cx[k], cy[k])))

    def rate(expr):
        return sum(sp.diff(expr, Qi) * Ui for Qi, Ui in zip(Q, U))

    T = sp.Rational(1, 2) * mb * (uxy[0] ** 2 + uxy[1] ** 2) if base else sp.Integer(0)
    V = -mb * (gx * xy[0] + gy * xy[1]) if base else sp.Integer(0)
    for k in range(n):
        vx, vy = rate(C[k][0]), rate(C[k][1])
        T += sp.Rational(1, 2) * m[k] * (vx**2 + vy**2) + sp.Rational(1, 2) * inertia[k] * rate(theta[k]) ** 2
        V += -m[k] * (gx * C[k][0] + gy * C[k][1])
    p_mom = [sp.diff(T, Ui) for Ui in U]
    Mq = sp.Matrix([[sp.diff(pi, Uj) for Uj in U] for pi in p_mom])
    b = sp.Matrix([rate(pi) - sp.diff(T, Qi) + sp.diff(V, Qi) for pi, Qi in zip(p_mom, Q)])
    M_fn = sp.lambdify((Q, params), Mq, modules="numpy", cse=True)
    b_fn = sp.lambdify((Q, U, params), b, modules="numpy", cse=True)
    return M_fn, b_fn


def path_matrix(parent, base):
    n = len(parent)
    T = np.zeros((n, n))
    for k in range(n):
        i = k
        while i >= 0:
            T[k, i] = 1.0
            i = parent[i]
    nb = 2 if base else 0
    full = np.eye(n + nb)
    full[nb:, nb:] = T
    return full


@jax.jit
def library(s, q, v, tau):
    def one(qq, vv, tt):
        acc = planar.forward_dynamics(s, qq, vv, tt)
        return dict(
            M=planar.mass_matrix(s, qq),
            h=planar.bias_forces(s, qq, vv),
            joint_M=planar.joint_mass_matrix(s, qq),
            joint_h=planar.joint_bias_forces(s, qq, vv),
            acc=acc,
            tau_back=planar.inverse_dynamics(s, qq, vv, acc),
        )

    return jax.vmap(one)(q, v, tau)


@pytest.mark.parametrize("name", list(SHAPES))
def test_planar_equations_match_sympy_lagrange(name):
    parent, base, origin = SHAPES[name]
    n = len(parent)
    M_fn, b_fn = derive(name)
    rng = np.random.default_rng(100 + list(SHAPES).index(name))
    mass = rng.uniform(0.3, 2.0, n)
    com = rng.normal(0.0, 0.3, (n, 2))
    hinge = rng.normal(0.0, 0.5, (n, 2))
    inertia = rng.uniform(0.01, 0.2, n)
    gravity = np.array([rng.normal(0.0, 1.0), -9.81])
    base_mass = rng.uniform(0.5, 3.0) if base else 0.0
    s = planar.from_parents(parent, mass, com, hinge, inertia, gravity=gravity,
                    base_mass=base_mass if base else None, angle_origin=origin)
    params = [*mass, *com[:, 0], *com[:, 1], *hinge[:, 0], *hinge[:, 1], *inertia, *gravity, base_mass]

    nq = s.nq
    T = path_matrix(parent, base)
    q_rel = rng.uniform(-math.pi, math.pi, (N_STATES, nq))
    u_rel = rng.normal(0.0, 1.5, (N_STATES, nq))
    tau = rng.normal(0.0, 2.0, (N_STATES, nq))  # joint torques M_k (and base force)
    out = library(s, jnp.asarray(q_rel @ T.T), jnp.asarray(u_rel @ T.T), jnp.asarray(tau))
    Tinv = np.linalg.inv(T)
    for i in range(N_STATES):
        Mq = np.asarray(M_fn(q_rel[i], params), dtype=np.float64)
        bq = np.asarray(b_fn(q_rel[i], u_rel[i], params), dtype=np.float64).reshape(-1)
        scale_M = np.abs(Mq).max()
        scale_b = np.abs(bq).max()
        # joint space: TᵀℳT and Tᵀh are Lagrange's M_q and b
        np.testing.assert_allclose(out["joint_M"][i], Mq, rtol=0, atol=1e-10 * scale_M)
        np.testing.assert_allclose(out["joint_h"][i], bq, rtol=0, atol=1e-10 * scale_b)
        # absolute angles: ℳ = T⁻ᵀ M_q T⁻¹, h = T⁻ᵀ b (spec §9.4)
        np.testing.assert_allclose(out["M"][i], Tinv.T @ Mq @ Tinv, rtol=0, atol=1e-10 * scale_M)
        np.testing.assert_allclose(out["h"][i], Tinv.T @ bq, rtol=0, atol=1e-10 * scale_b)
        # forward dynamics: α̈ = T q̈ with q̈ from Lagrange's equations
        qdd = np.linalg.solve(Mq, tau[i] - bq)
        acc_ref = T @ qdd
        np.testing.assert_allclose(out["acc"][i], acc_ref, rtol=0, atol=1e-10 * (1 + np.abs(acc_ref).max()))
        np.testing.assert_allclose(out["tau_back"][i], tau[i], rtol=0, atol=1e-9)


def test_chain_builder_matches_sympy_chain():
    """``planar.chain`` (links on the body x-axis) is the sympy chain with ``c_y = p_y = 0``."""
    M_fn, b_fn = derive("chain3")
    mass, a, L, inertia = [2.0, 1.5, 0.8], [0.35, 0.25, 0.15], [0.7, 0.5], [0.09, 0.04, 0.01]
    s = planar.chain(mass, a, L, inertia)
    params = [*mass, *a, 0, 0, 0, 0, L[0], L[1], 0, 0, 0, *inertia, 0.0, -9.81, 0.0]
    T = path_matrix((-1, 0, 1), False)
    q_abs = np.array([0.3, -0.5, 1.1])  # the T-2 state
    v_abs = np.array([0.8, -1.2, 2.0])
    q_rel, u_rel = np.linalg.solve(T, q_abs), np.linalg.solve(T, v_abs)
    out = library(s, jnp.asarray(q_abs[None]), jnp.asarray(v_abs[None]), jnp.asarray([[3.0, -1.0, 0.5]]))
    Mq = np.asarray(M_fn(q_rel, params), dtype=np.float64)
    bq = np.asarray(b_fn(q_rel, u_rel, params), dtype=np.float64).reshape(-1)
    np.testing.assert_allclose(out["joint_M"][0], Mq, rtol=1e-12)
    np.testing.assert_allclose(out["joint_h"][0], bq, rtol=1e-12)
    # and both reproduce table T-2's accelerations
    acc = T @ np.linalg.solve(Mq, np.array([3.0, -1.0, 0.5]) - bq)
    np.testing.assert_allclose(acc, [-5.0619699013, 13.5580578134, -12.6450247619], rtol=1e-10)
    np.testing.assert_allclose(out["acc"][0], acc, rtol=1e-12)
