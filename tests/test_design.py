"""Balancing synthesis: static moments to zero, decoupling verified on the engine."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxbody as jb
from jaxbody import design
from jaxbody.cli.balance import cli_balance


def _arm(gravity=9.81):
    return jb.examples.three_link_manipulator(gravity=gravity)


def _offdiag_ratio(M):
    d = np.sqrt(np.abs(np.diagonal(M, axis1=-2, axis2=-1)))
    R = np.abs(M) / (d[..., :, None] * d[..., None, :])
    n = M.shape[-1]
    return R[..., ~np.eye(n, dtype=bool)].max()


def _configs(n, nq, seed=3):
    return np.random.default_rng(seed).uniform(-np.pi, np.pi, size=(n, nq))


def test_static_moments_follow_the_chain_formula():
    # spec eq. (14) data: (md)_k = m_0k a_k + m_{k+1} L_k along the link
    s = _arm()
    m, a, L = np.array([2.0, 1.5, 0.8]), np.array([0.35, 0.25, 0.15]), np.array([0.7, 0.5, 0.0])
    sub = np.array([m.sum(), m[1:].sum(), m[2]])
    md = m * a + np.append(sub[1:], 0.0) * L
    np.testing.assert_allclose(np.asarray(design.static_moments(s)), np.stack([md, np.zeros(3)], 1), atol=1e-14)
    assert design.required_bodies(s) == (1, 2)
    assert design.required_bodies(jb.examples.cart_pendulum().system) == (0,)


@pytest.fixture(scope="module")
def balanced_arm():
    return design.balance(_arm(), penalty={"mass": 1.0, "inertia": 0.0})


def test_balance_decouples_the_three_link_arm(balanced_arm):
    s, rep = balanced_arm
    assert rep.bodies == (1, 2)
    Ms = np.asarray(eqx.filter_jit(jax.vmap(jb.planar.mass_matrix, in_axes=(None, 0)))(s, jnp.asarray(_configs(64, 3))))
    assert _offdiag_ratio(Ms) <= 1e-10
    assert rep.residual_coupling <= 1e-10 and rep.coupling_before > 0.1
    r = design.decoupling_report(s)
    assert r.decoupled and r.offending == ()
    # body 1 (on the ground) keeps its static moment: not required
    assert np.linalg.norm(rep.static_moment_after[0]) > 1.0
    # with only the mass penalised, the optimum puts each counterweight as far away as the
    # default box allows, opposite its static moment: the closed form mirroring the links
    np.testing.assert_allclose(rep.added_mass, rep.closed_form_added_mass, rtol=1e-6)
    jb.planar.validate(s)


def test_balanced_arm_torque_on_root_leaves_other_bodies_at_rest(balanced_arm):
    s, _ = balanced_arm
    q0 = jnp.array([0.3, 1.0, -0.5])
    tau = jnp.array([2.0, 0.0, 0.0])
    sol = jb.simulate(s, q0, jnp.zeros(3), 1.0, tau=tau, rtol=1e-11, atol=1e-11, n_save=21)
    q = np.asarray(sol.q)
    assert np.abs(q[:, 0] - 0.3).max() > 0.1  # the root body turns (and swings under gravity)
    assert np.abs(q[:, 1:] - np.asarray(q0[1:])).max() < 1e-10
    # a torque in the elbow turns only the two bodies it connects
    sol = jb.simulate(s, q0, jnp.zeros(3), 1.0, tau=jnp.array([0.0, 0.0, 0.3]), rtol=1e-11, atol=1e-11, n_save=21)
    assert np.abs(np.asarray(sol.q)[:, 2] - (-0.5)).max() > 0.1
    # the unbalanced arm couples
    sol = jb.simulate(_arm(), q0, jnp.zeros(3), 1.0, tau=tau, rtol=1e-11, atol=1e-11, n_save=21)
    assert np.abs(np.asarray(sol.q)[:, 1:] - np.asarray(q0[1:])).max() > 1e-2


def test_partial_decoupling_of_one_body():
    s, rep = design.balance(_arm(), bodies=["hand"])
    assert rep.bodies == (2,)
    Ms = np.asarray(eqx.filter_jit(jax.vmap(jb.planar.mass_matrix, in_axes=(None, 0)))(s, jnp.asarray(_configs(16, 3))))
    scale = np.abs(Ms).max()
    assert np.abs(Ms[:, 2, :2]).max() <= 1e-10 * scale
    assert np.abs(Ms[:, 1, 0]).max() > 1e-2 * scale


def test_static_balance_all_bodies_removes_gravity():
    s, rep = design.static_balance(_arm(), bodies="all")
    assert rep.bodies == (0, 1, 2)
    for q in _configs(5, 3):
        g = np.asarray(jb.planar.bias_forces(s, jnp.asarray(q), jnp.zeros(3)))
        assert np.abs(g).max() < 1e-12


def test_translating_base_needs_every_static_moment_zero():
    cart = jb.examples.cart_pendulum().system
    s, rep = design.balance(cart)
    assert rep.bodies == (0,)
    Ms = np.asarray(eqx.filter_jit(jax.vmap(jb.planar.mass_matrix, in_axes=(None, 0)))(
        s, jnp.asarray(np.concatenate([np.zeros((16, 2)), _configs(16, 1)], axis=1))))
    assert _offdiag_ratio(Ms) <= 1e-10


def _ball_tree():
    b = jb.ModelBuilder(gravity=(0.0, 0.0, -9.81), name="ball tree")
    b.add_body("torso", mass=3.0, com=(0.0, 0.05, 0.2), inertia=(0.05, 0.06, 0.03), joints=[jb.Ball()])
    b.add_body("left", parent="torso", pos=(0.15, 0.0, 0.4), mass=1.0, com=(0.1, 0.02, -0.15),
               inertia=(0.01, 0.012, 0.004), joints=[jb.Ball()])
    b.add_body("right", parent="torso", pos=(-0.15, 0.0, 0.4), mass=1.2, com=(-0.05, 0.0, -0.2),
               inertia=(0.012, 0.012, 0.004), joints=[jb.Ball()])
    b.add_body("hand", parent="left", pos=(0.05, 0.0, -0.3), mass=0.4, com=(0.0, 0.03, -0.08),
               inertia=(0.002, 0.002, 0.001), joints=[jb.Ball()])
    return b.build()


@pytest.mark.slow  # about 45 s; the planar and hinge-tree design tests cover the default job
def test_spatial_ball_tree_block_matrix_becomes_block_diagonal():
    model = _ball_tree()
    assert design.required_bodies(model) == (1, 2, 3)
    out, rep = design.balance(model, steps=50, outer=10)
    q, _, _ = jb.identify.random_states(model, 16, seed=4)
    batched = jax.jit(jax.vmap(design.coupling_measure.absolute_mass_matrix, in_axes=(None, 0)))

    def worst(m):
        blocks = np.asarray(batched(m, jnp.asarray(q))).reshape(-1, 4, 3, 4, 3).transpose(0, 1, 3, 2, 4)
        norms = np.abs(blocks).max(axis=(-2, -1))  # (n, 4, 4)
        off = np.where(np.eye(4, dtype=bool), 0.0, norms).max(axis=(1, 2))
        diag = np.diagonal(norms, axis1=1, axis2=2).max(axis=1)
        return (off / diag).max()

    worst_before, worst_after = worst(model), worst(out)
    assert worst_before > 1e-2
    assert worst_after <= 1e-10
    assert rep.residual_coupling <= 1e-10
    jb.validate_parameters(out)
    # the joint-space dynamics of the folded model stay consistent
    M = np.asarray(jb.mass_matrix(out, jnp.asarray(q[0])))
    assert np.all(np.linalg.eigvalsh(M) > 0)


def test_tradeoff_curve_trades_mass_for_coupling():
    w, mass, coup, res = design.tradeoff_curve(_arm(), [1e-2, 1e0, 1e2, 1e4], steps=100, outer=2)
    assert np.all(np.diff(mass) > 0)
    assert np.all(np.diff(coup) < 0)
    assert coup[-1] < 1e-2 < coup[0]


def test_fold_counterweights_preserves_moments_and_differentiates():
    s = _arm()
    mu, p = jnp.array([0.5]), jnp.array([[-0.2, 0.1]])
    f = design.fold_counterweights(s, [1], mu, p)
    # first and second moments about the hinge add up
    h0, h1 = s.body_mass[1] * s.body_com[1], f.body_mass[1] * f.body_com[1]
    np.testing.assert_allclose(np.asarray(h1 - h0), np.asarray(mu[0] * p[0]), atol=1e-14)
    J = lambda x: x.body_inertia[1] + x.body_mass[1] * jnp.sum(x.body_com[1] ** 2)
    np.testing.assert_allclose(float(J(f) - J(s)), float(mu[0] * jnp.sum(p[0] ** 2)), atol=1e-14)
    g = lambda mu, p: jnp.sum(design.static_moments(design.fold_counterweights(s, [1, 2], mu, p)) ** 2)
    check_grads(g, (jnp.array([0.5, 0.2]), jnp.array([[-0.2, 0.1], [-0.1, 0.0]])), order=1, modes=("rev",))


def test_balance_errors():
    s = _arm()
    with pytest.raises(ValueError, match="bodies: no body named 'elbow'"):
        design.balance(s, bodies=["elbow"])
    with pytest.raises(ValueError, match=r"penalty: unknown keys \['size'\]"):
        design.balance(s, penalty={"size": 1.0})
    with pytest.raises(ValueError, match=r"bounds: unknown keys \['radius'\]"):
        design.balance(s, bounds={"radius": 1.0})
    with pytest.raises(ValueError, match=r"body 2 \('hand'\) must be balanced but carries no counterweight"):
        design.balance(s, counterweights=[1])
    with pytest.raises(TypeError, match="balancing needs a planar system"):
        design.balance(object())


def test_cli_balance(capsys):
    assert cli_balance(["three_link_manipulator"]) == 0
    out = capsys.readouterr().out
    assert "augmented static moments" in out and "proposed design" in out and "forearm" in out
    assert cli_balance(["no_such_model"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("jaxbody balance: error: 'no_such_model' is neither")
    assert cli_balance(["double_pendulum", "--radius", "-1"]) == 2
    assert capsys.readouterr().err.startswith("jaxbody balance: error: --radius must be positive")
    assert cli_balance([]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_closed_form_decouples_panda_and_cli_reads_mjcf(models_dir, capsys):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        panda = jb.from_mjcf(models_dir / "panda.xml")
    out, rep = design.static_balance(panda)
    assert rep.bodies == (2, 3, 4, 5, 6, 7)  # link1 turns about the fixed ground: not required
    assert rep.coupling_before > 0.1 and rep.residual_coupling <= 1e-10
    jb.validate_parameters(out)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert cli_balance([str(models_dir / "panda.xml")]) == 0
    text = capsys.readouterr().out
    assert "link4" in text and "proposed design" in text and "nan" not in text
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert cli_balance(["panda"]) == 0  # the shipped model by name, as `jaxbody simulate panda`
    assert capsys.readouterr().out == text


# ------------------------------------------------------------------ link extensions
# 3-link arm data (spec eq. 14): hand m̄_3 = 0.8 · 0.15 = 0.12 along the link; the forearm's
# reach is L_2 = 0.5, the hand's 0.15; carriers of the hand at distances 0.5 (forearm) and 0.7.
def test_extensions_put_counterweights_beyond_the_links_reach():
    s = _arm()
    L = np.array([0.5, 0.15])
    out, rep = design.balance(s, penalty={"mass": 1.0, "inertia": 0.0}, extensions={"length": (0.0, 2.0 * L)})
    # massless extensions, mass penalised only: each extension runs to its bound, counterweight at
    # its end, backwards along the link; by hand, leaves first: μ_3 = 0.12 / 0.3 = 0.4 and
    # μ_2 = (1.5 · 0.25 + (0.8 + 0.4) · 0.5) / 1.0 = 0.975
    np.testing.assert_allclose(rep.extension_length, 2.0 * L, rtol=1e-9)
    np.testing.assert_allclose(rep.counterweight_mass, [0.975, 0.4], rtol=1e-9)
    np.testing.assert_allclose(rep.counterweight_position, [[-1.0, 0.0], [-0.3, 0.0]], atol=1e-9)
    np.testing.assert_allclose(rep.added_mass, 1.375, rtol=1e-9)
    # the same decoupling as without extensions, for less than half the added mass
    assert rep.added_mass < 0.5 * rep.closed_form_added_mass  # 3.15: counterweights mirroring the links
    Ms = np.asarray(eqx.filter_jit(jax.vmap(jb.planar.mass_matrix, in_axes=(None, 0)))(out, jnp.asarray(_configs(64, 3))))
    assert _offdiag_ratio(Ms) <= 1e-10
    # the mechanism's joints are untouched
    np.testing.assert_array_equal(np.asarray(out.hinge_pos), np.asarray(s.hinge_pos))
    jb.planar.validate(out)


def test_extension_rod_mass_gives_an_interior_optimum_and_bounds_hold():
    s = _arm()
    m3 = 0.12
    lam = 0.5  # kg/m: the extension's own mass counts
    # counterweight μ at the end of a rod of length e: μ e + λ e²/2 = m̄ and the added mass
    # μ + λ e = m̄/e + λ e/2 is least at e* = sqrt(2 m̄/λ), where the rod alone balances (μ = 0)
    out, rep = design.balance(s, bodies=["hand"], penalty={"mass": 1.0, "inertia": 0.0},
                              extensions={"length": (0.0, 2.0), "density": lam})
    e_star = np.sqrt(2.0 * m3 / lam)
    np.testing.assert_allclose(rep.extension_length, [e_star], rtol=1e-6)
    np.testing.assert_allclose(rep.added_mass, np.sqrt(2.0 * m3 * lam), rtol=1e-6)
    assert rep.counterweight_mass[0] < 1e-6
    assert np.linalg.norm(design.static_moments(out)[2]) < 1e-12
    # a shorter bound is respected: e = 0.4 and μ = m̄/e − λe/2 = 0.2
    out, rep = design.balance(s, bodies=["hand"], penalty={"mass": 1.0, "inertia": 0.0},
                              extensions={"length": (0.0, 0.4), "density": lam})
    np.testing.assert_allclose(rep.extension_length, [0.4], rtol=1e-9)
    np.testing.assert_allclose(rep.counterweight_mass, [0.2], rtol=1e-9)
    np.testing.assert_allclose(rep.added_mass, 0.4, rtol=1e-9)
    # the rod's inertia λe³/3 and the counterweight's μe² about the hand's joint
    J = lambda x: float(x.body_inertia[2] + x.body_mass[2] * np.sum(np.asarray(x.body_com[2]) ** 2))
    np.testing.assert_allclose(J(out) - J(s), lam * 0.4**3 / 3 + 0.2 * 0.4**2, rtol=1e-9)
    Ms = np.asarray(eqx.filter_jit(jax.vmap(jb.planar.mass_matrix, in_axes=(None, 0)))(out, jnp.asarray(_configs(16, 3))))
    assert np.abs(Ms[:, 2, :2]).max() <= 1e-10 * np.abs(Ms).max()
    with pytest.raises(ValueError, match="'position' cannot be combined with extensions"):
        design.balance(s, bounds={"position": (-1.0, 1.0)}, extensions=True)
    with pytest.raises(ValueError, match=r"extensions: unknown keys \['width'\]"):
        design.balance(s, extensions={"width": 1.0})


# ------------------------------------------------------------------ options
def test_explicit_bounds_are_respected():
    # box |x| <= 0.3, |y| <= 0.1 and masses up to 4: the counterweights go to x = -0.3, and
    # leaves first μ_3 = 0.12 / 0.3 = 0.4, μ_2 = (0.375 + 1.2 · 0.5) / 0.3 = 3.25
    lo, hi = np.array([-0.3, -0.1]), np.array([0.3, 0.1])
    out, rep = design.balance(_arm(), bounds={"mass": (0.0, 4.0), "position": (lo, hi)},
                              penalty={"mass": 1.0, "inertia": 0.0})
    p = rep.counterweight_position
    assert np.all(p >= lo - 1e-12) and np.all(p <= hi + 1e-12) and np.all(rep.counterweight_mass <= 4.0)
    np.testing.assert_allclose(p, [[-0.3, 0.0], [-0.3, 0.0]], atol=1e-9)
    np.testing.assert_allclose(rep.counterweight_mass, [3.25, 0.4], rtol=1e-9)
    assert rep.residual_coupling <= 1e-10


def test_inertia_penalty_pulls_the_counterweight_in():
    # hand only, wide box: added inertia m̄ρ (hand) + (m̄/ρ)(0.5² + 0.7²) (its carriers) is least
    # at ρ = sqrt(0.74); the mass penalty alone drives ρ to the box edge (2)
    s, box = _arm(), {"position": ([-2.0, -2.0], [2.0, 2.0])}
    _, rep_i = design.balance(s, bodies=["hand"], bounds=box, penalty={"mass": 0.0, "inertia": 1.0})
    _, rep_m = design.balance(s, bodies=["hand"], bounds=box, penalty={"mass": 1.0, "inertia": 0.0})
    np.testing.assert_allclose(rep_i.counterweight_position, [[-np.sqrt(0.74), 0.0]], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(rep_m.counterweight_position, [[-2.0, 0.0]], atol=1e-9)
    np.testing.assert_allclose(rep_i.added_inertia, 2.0 * 0.12 * np.sqrt(0.74), rtol=1e-6)
    assert rep_i.added_inertia < rep_m.added_inertia and rep_i.added_mass > rep_m.added_mass


def test_balance_with_adam():
    s = _arm()
    # the optimiser alone (no closed-form polish) drives the hand's m̄ to ~1e-9 ...
    _, rep = design.balance(s, bodies=["hand"], optimizer="adam", learning_rate=0.05, polish=False)
    assert not rep.polished and rep.residual_static_moment < 1e-6
    # ... at more added mass than the optimum on the default box (0.12 / 0.15 = 0.8): Adam
    # stalls on the constraint surface short of the box edge
    assert 0.8 - 1e-9 <= rep.added_mass < 2.0
    out, rep = design.balance(s, bodies=["hand"], optimizer="adam", learning_rate=0.05)
    assert rep.polished
    Ms = np.asarray(eqx.filter_jit(jax.vmap(jb.planar.mass_matrix, in_axes=(None, 0)))(out, jnp.asarray(_configs(16, 3))))
    assert np.abs(Ms[:, 2, :2]).max() <= 1e-10 * np.abs(Ms).max()
    with pytest.raises(ValueError, match="optimizer"):
        design.balance(s, optimizer="sgd")


def test_required_bodies_with_a_free_floating_root():
    b = jb.ModelBuilder(gravity=(0.0, 0.0, -9.81), name="floating")
    b.add_body("torso", mass=3.0, com=(0.0, 0.05, 0.2), inertia=(0.05, 0.06, 0.03), joints=[jb.Free()])
    b.add_body("left", parent="torso", pos=(0.15, 0.0, 0.4), mass=1.0, com=(0.1, 0.02, -0.15),
               inertia=(0.01, 0.012, 0.004), joints=[jb.Ball()])
    b.add_body("welded", parent="torso", pos=(-0.15, 0.0, 0.4), mass=1.2, com=(-0.05, 0.0, -0.2),
               inertia=(0.012, 0.012, 0.004))
    b.add_body("hand", parent="left", pos=(0.05, 0.0, -0.3), mass=0.4, com=(0.0, 0.03, -0.08),
               inertia=(0.002, 0.002, 0.001), joints=[jb.Hinge(axis=(0.0, 1.0, 0.0))])
    model = b.build()
    # on a moving base every jointed body must be balanced, the floating root included; a body
    # welded to its parent has no angle of its own
    assert design.required_bodies(model) == (0, 1, 3)
    # the same tree on a fixed ball joint: the root turns about the fixed ground, not required
    assert design.required_bodies(_ball_tree()) == (1, 2, 3)


def test_cli_balance_optimise(capsys):
    from jaxbody.cli import main

    assert main(["balance", "three_link_manipulator", "--optimise", "--penalty-inertia", "0"]) == 0
    out = capsys.readouterr().out
    assert "proposed design (closed form" in out and "optimised design (optax" in out
    opt = out.split("optimised design")[1]
    # mass penalised only on the default box: the optimum is the closed form (3.15)
    assert "added mass 3.15," in opt and "coupling 7.747e-01 ->" in opt
    coupling_after = float(opt.split("-> ")[1].split()[0])
    assert coupling_after <= 1e-10


def test_extension_along_the_link_cannot_cancel_an_off_axis_static_moment():
    # forearm CM 0.1 off the link's line: the extension (backwards along the line to the
    # hand's joint) cancels only m̄'s component along it; balance says so instead of
    # returning a silently coupled design
    s = _arm()
    s = eqx.tree_at(lambda x: x.body_com, s, s.body_com.at[1, 1].set(0.1))
    with pytest.warns(RuntimeWarning, match="cancels only the static moment along its direction"):
        _, rep = design.balance(s, penalty={"mass": 1.0, "inertia": 0.0}, extensions=True, steps=50, outer=3)
    assert rep.residual_static_moment > 1e-3
    # an extension opposite the forearm's m̄ = 1.5 · (0.25, 0.1) + 0.8 · (0.5, 0) (the hand's mass
    # at its joint) balances it exactly
    d1 = -np.array([1.5 * 0.25 + 0.8 * 0.5, 1.5 * 0.1])
    _, rep = design.balance(s, bodies=["forearm"], penalty={"mass": 1.0, "inertia": 0.0},
                            extensions={"direction": d1})
    assert rep.residual_static_moment < 1e-12


@pytest.mark.slow  # about 60 s on 2 busy cores (compiling the spatial synthesis)
def test_spatial_extension_balances_the_ball_tree_hand():
    model = _ball_tree()
    hand = model.tree.names.index("hand")
    lam = 0.2
    out, rep = design.balance(model, bodies=["hand"], penalty={"mass": 1.0, "inertia": 0.0},
                              extensions={"length": (0.0, 1.0), "density": lam})
    # the hand's CM is its reach: the extension runs opposite it; leaf optimum as in the plane,
    # e* = sqrt(2 |m̄| / λ) with |m̄| = 0.4 · |(0, 0.03, -0.08)|
    md = 0.4 * np.hypot(0.03, 0.08)
    # (the added mass is flat at e*, so e is pinned less tightly than the added mass)
    np.testing.assert_allclose(rep.extension_length, [np.sqrt(2 * md / lam)], rtol=1e-4)
    np.testing.assert_allclose(rep.added_mass, np.sqrt(2 * md * lam), rtol=1e-7)
    assert np.linalg.norm(np.asarray(design.static_moments(out))[hand]) < 1e-12
    jb.validate_parameters(out)
