"""Spatial equations against the reference tables of spec §12 (T-8, T-9a–d)."""

import jax.numpy as jnp
import numpy as np

import jaxbody as jb
from jaxbody import spatial
from jaxbody.augmented import augmented_inertia, static_moment, subtree_mass

RTOL = 1e-10


def close(x, ref, rtol=RTOL, atol=0.0):
    """Table values carry 6–12 significant digits: compare to their printed precision."""
    np.testing.assert_allclose(np.asarray(x), np.asarray(ref, dtype=float), rtol=rtol, atol=atol)


# ----------------------------------------------------------------------------- T-9 data
T9_MASS = np.array([2.0, 1.5, 1.0])
T9_R = np.array([[0.05, 0.02, -0.25], [0.0, 0.04, -0.2], [0.03, -0.02, -0.15]])
T9_LINK = np.array([[0.0, 0.0, 0.0], [0.02, -0.03, -0.5], [0.01, 0.0, -0.4]])
T9_IC = np.array(
    [
        [[0.050, 0.002, -0.001], [0.002, 0.045, 0.003], [-0.001, 0.003, 0.010]],
        [[0.030, -0.001, 0.0], [-0.001, 0.028, 0.002], [0.0, 0.002, 0.006]],
        [[0.012, 0.0, 0.001], [0.0, 0.011, -0.001], [0.001, -0.001, 0.004]],
    ]
)
T9_W = np.array([[0.5, -0.3, 0.8], [-0.7, 0.4, 1.1], [0.9, 1.2, -0.6]])
G = np.array([0.0, 0.0, -9.81])
CHAIN3 = jb.BodyTree([-1, 0, 1])


def t9_augmented():
    m = subtree_mass(CHAIN3, T9_MASS)
    mbar = static_moment(CHAIN3, T9_MASS, T9_R, T9_LINK)
    I = augmented_inertia(CHAIN3, T9_MASS, T9_IC, T9_R, T9_LINK)
    return m, mbar, I


def test_t9a_augmented_quantities():
    m, mbar, I = t9_augmented()
    close(m, [4.5, 2.5, 1.0])
    close(mbar, [[0.15, -0.035, -1.75], [0.01, 0.06, -0.7], [0.03, -0.02, -0.15]], atol=1e-15)
    ref = {
        0: ([0.80305, 0.0015, 0.049], [0.801, -0.0245, 0.01905]),
        1: ([0.2524, -0.001, 0.004], [0.2481, 0.014, 0.0085]),
        2: ([0.0349, 0.0006, 0.0055], [0.0344, -0.004, 0.0053]),
    }
    for k, (row, rest) in ref.items():
        Ik = np.asarray(I[k])
        close([Ik[0, 0], Ik[0, 1], Ik[0, 2]], row, atol=1e-15)
        close([Ik[1, 1], Ik[1, 2], Ik[2, 2]], rest, atol=1e-15)


def test_t9b_absolute_mass_matrix_blocks():
    _, mbar, I = t9_augmented()
    D = np.asarray(spatial.absolute_mass_matrix(CHAIN3, mbar, I, jnp.asarray(T9_LINK)))
    blk = lambda k, i: D[3 * k : 3 * k + 3, 3 * i : 3 * i + 3]
    close(blk(1, 0), [[0.3482, -0.0012, 0.014], [0.0003, 0.3502, -0.021], [0.005, 0.03, -0.0016]], atol=1e-14)
    close(blk(2, 0), [[0.0756, 0.0004, 0.003], [0.0009, 0.0756, -0.0045], [0.015, -0.01, 0.0012]], atol=1e-14)
    close(blk(2, 1), [[0.06, 0.0002, 0.0015], [0.0, 0.0603, 0.0], [0.012, -0.008, 0.0003]], atol=1e-14)
    np.testing.assert_allclose(D, D.T, atol=1e-15)
    for k in range(3):
        close(blk(k, k), I[k], atol=1e-15)
    assert np.all(np.linalg.eigvalsh(D) > 0)


T9_TORQUE = np.array([[1.0, -2.0, 0.3], [0.4, 0.6, -0.2], [-0.1, 0.2, 0.05]])


def test_t9c_forward_dynamics_absolute_form():
    _, mbar, I = t9_augmented()
    b = spatial.absolute_bias(CHAIN3, mbar, I, jnp.asarray(T9_LINK), jnp.asarray(T9_W), jnp.asarray(G))
    close(
        b,
        [[-0.298939, -1.415963, 0.0129445], [0.643808, -0.139842, 0.004015], [-0.187319, -0.334626, 0.005833]],
        rtol=2e-6,
        atol=1e-6,
    )
    tau = T9_TORQUE - np.concatenate([T9_TORQUE[1:], np.zeros((1, 3))])  # τ_k = M_k − M_{k+1}
    D = spatial.absolute_mass_matrix(CHAIN3, mbar, I, jnp.asarray(T9_LINK))
    eps = np.linalg.solve(np.asarray(D), (tau - np.asarray(b)).reshape(-1)).reshape(3, 3)
    close(
        eps,
        [
            [0.531934985668, -5.795309651, 32.4724471166],
            [-4.77231675783, 11.353146888, -21.58886869],
            [3.3252671698, 15.5770856146, 26.0107456593],
        ],
        rtol=1e-10,
    )


T9_EPS = np.array([[1.0, -2.0, 0.5], [-0.5, 1.5, 2.0], [2.5, -1.0, -1.5]])
T9D_M = [[1.48195, -3.423631, 0.1103175], [0.954389, -0.921218, 0.021348], [-0.059319, -0.423626, 0.033833]]
T9D_F = [[2.17715, 2.00465, 45.8178], [1.47615, 1.38525, 25.7574], [0.6246, 0.7887, 10.5582]]


def test_t9d_statement1_inverse_dynamics():
    m, mbar, I = t9_augmented()
    z = jnp.zeros((3, 3))
    f = spatial.relative_force_factors(
        CHAIN3, m, mbar, I, jnp.asarray(T9_LINK), jnp.asarray(T9_W), jnp.asarray(T9_EPS), z, z, z, jnp.asarray(G)
    )
    close(f.moment, T9D_M, rtol=5e-6, atol=1e-6)
    close(f.force, T9D_F, rtol=5e-6, atol=1e-5)
    # Cor. 4 matrix form gives the same torques: D ε + b = τ, M_k = sum over the subsystem
    D = spatial.absolute_mass_matrix(CHAIN3, mbar, I, jnp.asarray(T9_LINK))
    b = spatial.absolute_bias(CHAIN3, mbar, I, jnp.asarray(T9_LINK), jnp.asarray(T9_W), jnp.asarray(G))
    tau = (np.asarray(D) @ T9_EPS.reshape(-1)).reshape(3, 3) + np.asarray(b)
    np.testing.assert_allclose(np.cumsum(tau[::-1], axis=0)[::-1], np.asarray(f.moment), rtol=1e-12, atol=1e-13)


def t9_model():
    """The T-9 chain as a jaxbody Model with ball joints, at identity orientations."""
    b = jb.ModelBuilder(gravity=G)
    base = np.cumsum(T9_LINK, axis=0)
    for k in range(3):
        b.add_body(
            f"b{k}",
            None if k == 0 else f"b{k - 1}",
            pos=T9_LINK[k],
            mass=T9_MASS[k],
            com=T9_R[k],
            inertia=T9_IC[k],
            joints=[jb.Ball()],
        )
    return b.build(), base


def test_t9d_through_the_joint_space_pipeline():
    """Joint space (ball joints, MuJoCo conventions) reproduces T-9d from absolute rates."""
    model, _ = t9_model()
    q = jnp.asarray(np.tile([1.0, 0.0, 0.0, 0.0], 3))
    w, e = T9_W, T9_EPS
    # at identity orientations the ball rates are relative angular velocities in world axes;
    # ε_k = ε_{k-1} + a_k + ω_{k-1} × v_k (derivative of the rotating joint axes)
    v = np.concatenate([w[0], w[1] - w[0], w[2] - w[1]])
    a = np.concatenate(
        [e[0], e[1] - e[0] - np.cross(w[0], w[1] - w[0]), e[2] - e[1] - np.cross(w[1], w[2] - w[1])]
    )
    tau = jb.inverse_dynamics(model, q, jnp.asarray(v), jnp.asarray(a))
    close(np.asarray(tau).reshape(3, 3), T9D_M, rtol=5e-6, atol=1e-6)
    F, M = jb.joint_reactions(model, q, jnp.asarray(v), jnp.asarray(a))
    close(F, T9D_F, rtol=5e-6, atol=1e-5)
    close(M, T9D_M, rtol=5e-6, atol=1e-6)
    aug = jb.augmented_bodies(model, q)
    _, mbar, I = t9_augmented()
    close(aug.static_moment, mbar, atol=1e-15)
    close(aug.augmented_inertia, I, atol=1e-15)
    # M = Aᵀ D A with A the map from ball rates to absolute angular velocities (identity pose)
    D = np.asarray(spatial.absolute_mass_matrix(CHAIN3, mbar, I, jnp.asarray(T9_LINK)))
    A = np.kron(np.tril(np.ones((3, 3))), np.eye(3))
    np.testing.assert_allclose(np.asarray(jb.mass_matrix(model, q)), A.T @ D @ A, rtol=1e-12, atol=1e-14)


def test_t8_statement1_with_a_slider():
    tree = jb.BodyTree([-1, 0])
    mass = np.array([2.0, 1.0])
    r = np.array([[0.05, 0.0, -0.3], [0.02, 0.0, -0.35]])
    link = np.array([[0.0, 0.0, 0.0], [0.0, 0.1, -0.6]])
    Ic = np.array([np.diag([0.06, 0.05, 0.01]), [[0.02, 0.001, 0.0], [0.001, 0.02, 0.0], [0.0, 0.0, 0.004]]])
    w = np.array([[0.3, -0.2, 0.5], [0.6, 0.1, -0.4]])
    e = np.array([[0.5, 1.0, -0.3], [-1.2, 0.4, 0.8]])
    Vr = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -0.4]])
    Wr = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.3]])
    m = subtree_mass(tree, mass)
    mbar = static_moment(tree, mass, r, link)
    I = augmented_inertia(tree, mass, Ic, r, link)
    f = spatial.relative_force_factors(
        tree, m, mbar, I, jnp.asarray(link), jnp.asarray(w), jnp.asarray(e), jnp.asarray(Vr), jnp.asarray(Wr),
        jnp.zeros((2, 3)), jnp.asarray(G),
    )
    close(f.base_point_acceleration, [[0, 0, 0], [-0.666, 0.326, 0.118]], atol=1e-12)
    close(f.inertial_force, [[-1.4244, 0.7412, 0.5277], [-0.0394, 0.0912, 0.4167]], atol=1e-12)
    close(f.force, [[-1.4244, 0.7412, 29.9577], [-0.7054, 0.4172, 10.3447]], atol=1e-12)
    close(f.moment, [[1.53929, -0.241294, 0.096234], [0.1233, 0.042916, 0.011894]], atol=1e-12)


def test_translating_base_matrix_is_symmetric_and_is_the_kinetic_energy():
    """Cor. 1 rows: ½ xᵀ D x equals the kinetic energy of the bodies for x = (V, ω)."""
    _, mbar, I = t9_augmented()
    M = float(T9_MASS.sum())
    D = np.asarray(spatial.absolute_mass_matrix(CHAIN3, mbar, I, jnp.asarray(T9_LINK), total_mass=jnp.asarray(M)))
    np.testing.assert_allclose(D, D.T, atol=1e-15)
    rng = np.random.default_rng(3)
    V, w = rng.standard_normal(3), rng.standard_normal((3, 3))
    base = np.cumsum(T9_LINK, axis=0)
    # velocities of the base points: O_01 moves with V, then ω_i × R_c along the chain
    vb = [V, V + np.cross(w[0], T9_LINK[1]), V + np.cross(w[0], T9_LINK[1]) + np.cross(w[1], T9_LINK[2])]
    T = 0.0
    for k in range(3):
        vc = vb[k] + np.cross(w[k], T9_R[k])
        T += 0.5 * T9_MASS[k] * vc @ vc + 0.5 * w[k] @ T9_IC[k] @ w[k]
    x = np.concatenate([V, w.reshape(-1)])
    np.testing.assert_allclose(0.5 * x @ D @ x, T, rtol=1e-13)
    del base
