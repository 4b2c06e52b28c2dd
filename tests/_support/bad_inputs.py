"""The table of malformed inputs: each case a call that must fail with a message naming the input.

Shared by ``tests/test_bad_inputs.py`` (which pins every message) and
``scripts/bad_input_survey.py`` (which classifies today's behaviour of each case as clear,
misleading, silent or crash and prints the counts).

A case is ``(id, call, pattern)``: ``call()`` must raise, and ``pattern`` (a regular expression)
must be found on the FIRST line of the error's text — the line a user reads. Command-line cases
run ``jaxbody.cli.main(argv)`` in process; a non-zero exit status becomes :class:`CommandFailed`
whose text is what the command wrote on stderr. One tiny model family serves every case, so the
few cases that really integrate share compiled programs.
"""

import contextlib
import dataclasses
import functools
import io
import os
import pathlib
import tempfile
from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxbody as jb
from jaxbody import constraints as jc
from jaxbody import maggi


@dataclasses.dataclass(frozen=True)
class Case:
    id: str
    call: Callable
    pattern: str
    # a case whose message may be pinned anywhere in the error's text, not on its first line
    # (none is today: inside jax.jit a check's status carries its message on the first line)
    first_line: bool = True


class CommandFailed(Exception):
    """A ``jaxbody`` command that exited with a non-zero status; the text is its stderr."""

    def __init__(self, status, stderr):
        super().__init__(stderr.strip() or f"(exit status {status}, nothing on stderr)")
        self.status = status


def cli(*argv):
    """Run ``jaxbody ARGV`` in process; raise :class:`CommandFailed` unless it exits with 0."""
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            status = _main(list(argv))
        except SystemExit as e:  # argparse exits on usage errors
            status = e.code if isinstance(e.code, int) else 2
    if status:
        raise CommandFailed(status, err.getvalue())
    return status


def _main(argv):
    from jaxbody.cli import main

    return main(argv)


# ------------------------------------------------------------------------------ tiny models
@functools.lru_cache
def pendulum():
    """One hinge about y, hanging along -z."""
    b = jb.ModelBuilder()
    b.add_body("arm", mass=1.0, com=(0, 0, -0.2), inertia=(0.01, 0.01, 0.002),
               joints=[jb.Hinge(axis=(0, 1, 0), name="shoulder")])
    return b.build()


@functools.lru_cache
def chain():
    """Two hinges: 'upper' (joint 'shoulder') and 'lower' (joint 'elbow')."""
    b = jb.ModelBuilder()
    b.add_body("upper", mass=1.0, com=(0, 0, -0.2), inertia=(0.01, 0.01, 0.002),
               joints=[jb.Hinge(axis=(0, 1, 0), name="shoulder", damping=0.1)])
    b.add_body("lower", "upper", pos=(0, 0, -0.4), mass=0.5, com=(0, 0, -0.2), inertia=(0.01, 0.01, 0.002),
               joints=[jb.Hinge(axis=(0, 1, 0), name="elbow", damping=0.1)])
    return b.build()


@functools.lru_cache
def ball():
    """A body on a ball joint 'socket' (nq = 4, nv = 3) with a hinge 'wrist' below it."""
    b = jb.ModelBuilder()
    b.add_body("head", mass=1.0, com=(0, 0, -0.2), inertia=(0.02, 0.02, 0.01), joints=[jb.Ball(name="socket")])
    b.add_body("hand", "head", pos=(0, 0, -0.4), mass=0.5, com=(0, 0, -0.1), inertia=(0.01, 0.01, 0.002),
               joints=[jb.Hinge(axis=(0, 1, 0), name="wrist")])
    return b.build()


FOUR_BAR = (1.0, 0.4, 1.0, 0.7)  # ground, crank, coupler, rocker lengths


def _four_bar_angles(crank):
    import scipy.optimize

    d, l1, l2, l3 = FOUR_BAR

    def closure(z):
        return [l1 * np.cos(crank) + l2 * np.cos(z[0]) - d - l3 * np.cos(z[1]),
                l1 * np.sin(crank) + l2 * np.sin(z[0]) - l3 * np.sin(z[1])]

    z = scipy.optimize.fsolve(closure, [0.3, 1.6], xtol=1e-14)
    return np.array([crank, z[0], z[1]])


@functools.lru_cache
def four_bar_parts():
    """``(model, loop, q_closed)``: a planar four-bar as a tree and its closing constraint; the
    angles ``q_closed`` close the loop."""
    d, l1, l2, l3 = FOUR_BAR
    b = jb.ModelBuilder(gravity=(0, 0, -9.81))
    for name, parent, pos, m, ln in (("crank", None, (0, 0, 0), 0.5, l1), ("coupler", "crank", (l1, 0, 0), 1.2, l2),
                                     ("rocker", None, (d, 0, 0), 0.9, l3)):
        inertia = m * ln**2 / 12
        b.add_body(name, parent=parent, pos=pos, mass=m, com=(ln / 2, 0, 0),
                   inertia=(inertia / 10, inertia, inertia), joints=[jb.Hinge(axis=(0, -1, 0))])
    model = b.build()
    loop = jc.LoopClosure(model, "coupler", (l2, 0, 0), "rocker", (l3, 0, 0), axes=[(1, 0, 0), (0, 0, 1)])
    th = _four_bar_angles(0.6)
    return model, loop, jnp.array([th[0], th[1] - th[0], th[2]])


@functools.lru_cache
def four_bar_scene():
    model, loop, q = four_bar_parts()
    return jb.scene(model, constraints=maggi.constrain(model, [loop], q_ref=q))


def z(n):
    return jnp.zeros((n,))


def q1():
    return jnp.array([0.3])


def with_field(model, field, value):
    """``model`` with one parameter replaced after building (the user's ``eqx.tree_at``)."""
    return eqx.tree_at(lambda m: getattr(m, field), model, jnp.asarray(value, getattr(model, field).dtype))


def sim(system, q0=None, v0=None, t1=0.1, **kw):
    q0 = jnp.zeros((system.nq,)) + (0.3 if system.nq < 3 else 0.0) if q0 is None else q0
    return jb.simulate(system, q0, z(system.nv) if v0 is None else v0, t1, **kw)


class Law(eqx.Module):
    """A control law ``−k √(q − c)`` whose gain and offset are parameters: one compiled solve
    serves every case that integrates (``c = −10``: a benign law; ``c = 0.25``: NaN once the
    pendulum swings below 0.25)."""

    k: jax.Array
    c: jax.Array

    def __call__(self, t, q, v):
        return -self.k * jnp.sqrt(q - self.c)


def law_solve(t1=0.1, c=-10.0, k=0.0, q0=0.3):
    """The pendulum under :class:`Law` from ``q0`` at rest; every such solve shares one program
    (a budget of 64 steps, plenty for 0.1 s)."""
    return jb.simulate(pendulum(), jnp.array([q0]), z(1), t1, tau=Law(jnp.array(k), jnp.array(c)), max_steps=64)


def nan_law_solve():
    """A control law that returns NaN once the pendulum swings below q = 0.25."""
    return law_solve(1.0, c=0.25, k=1.0)


@functools.lru_cache
def _jitted_solve():
    model = pendulum()  # built outside the trace: the cases are about the solve's inputs

    def solve(q0, ts, mass):
        return law_solve_at(q0, ts, eqx.tree_at(lambda m: m.body_mass, model, mass)).q

    return jax.jit(jax.vmap(solve, in_axes=(0, None, 0)))


def law_solve_at(q0, ts, model=None):
    model = pendulum() if model is None else model
    return jb.simulate(model, q0, z(1), 0.1, tau=Law(jnp.array(0.0), jnp.array(-10.0)), max_steps=64, saveat=ts)


def jit_solve(q0=((0.3,), (0.2,)), ts=(0.05, 0.1), mass=((1.0,), (1.0,))):
    """:func:`law_solve_at` of a batch of two pendulums (initial angles ``q0``, masses ``mass``)
    under ``jax.jit`` (one compilation for every case)."""
    return _jitted_solve()(jnp.asarray(q0, float), jnp.asarray(ts, float), jnp.asarray(mass, float))


def jit_mass_matrix(model):
    """``jb.mass_matrix`` of ``model`` (built outside the trace) under ``jax.jit``."""
    return jax.jit(lambda q: jb.mass_matrix(model, q))


def builder(**kwargs):
    """A pendulum whose second body gets ``kwargs`` (the builder's checks)."""
    b = jb.ModelBuilder()
    b.add_body("base", mass=1.0, inertia=(0.1, 0.1, 0.1), joints=[jb.Hinge(axis=(0, 0, 1))])
    args = dict(pos=(0, 0, -0.5), mass=1.0, inertia=(0.1, 0.1, 0.1), joints=[jb.Hinge(axis=(0, 1, 0), name="knee")])
    args.update(kwargs)
    b.add_body("link", "base", **args)
    return b.build()


def _welded_only():
    b = jb.ModelBuilder()
    b.add_body("block", mass=1.0, inertia=(0.1, 0.1, 0.1))
    return b.build()


def _no_bodies():
    return jb.ModelBuilder().build()


@functools.lru_cache
def solved():
    """A short successful solve of the pendulum (the program of :func:`law_solve`)."""
    return law_solve()


@functools.lru_cache
def batch_solution():
    """A vmapped solve of three pendulums, the middle one given NaN (``throw=False``)."""
    q0s = jnp.array([[0.3], [jnp.nan], [0.2]])
    return jax.vmap(lambda q: sim(pendulum(), q, z(1), 0.1, throw=False))(q0s)


@functools.lru_cache
def dense_solution():
    return sim(pendulum(), q1(), z(1), 0.1, dense=True)


def tmpfile(name, text=None, data=None):
    d = pathlib.Path(tempfile.mkdtemp(prefix="jaxbody_bad_"))
    p = d / name
    if text is not None:
        p.write_text(text)
    if data is not None:
        p.write_bytes(data)
    return p


MJCF_HEAD = '<mujoco><worldbody><body name="b"><joint name="j" type="hinge" axis="0 1 0"/>'
MJCF_TAIL = "</body></worldbody></mujoco>"


def mjcf(body):
    return MJCF_HEAD + body + MJCF_TAIL


def _dynamics_cases():
    p, c, bl = pendulum, chain, ball
    nanq = jnp.array([jnp.nan])
    zero_quat = jnp.array([0.0, 0.0, 0.0, 0.0, 0.1])
    return [
        Case("mass_matrix q wrong shape", lambda: jb.mass_matrix(c(), z(3)), r"\bq\b.*shape"),
        Case("mass_matrix q 2-D", lambda: jb.mass_matrix(c(), jnp.zeros((2, 2))), r"\bq\b.*shape"),
        Case("mass_matrix q NaN", lambda: jb.mass_matrix(p(), nanq), r"\bq contains NaN or inf"),
        Case("mass_matrix zero quaternion", lambda: jb.mass_matrix(bl(), zero_quat), r"joint 0 \('socket'\).*quaternion.*zero"),
        Case("forward_dynamics zero quaternion", lambda: jb.forward_dynamics(bl(), zero_quat, z(4)), r"'socket'.*quaternion.*zero"),
        Case("forward_dynamics tau wrong shape", lambda: jb.forward_dynamics(c(), z(2), z(2), z(3)), r"\btau\b.*shape"),
        Case("forward_dynamics tau NaN", lambda: jb.forward_dynamics(p(), q1(), z(1), nanq), r"\btau contains NaN or inf"),
        Case("forward_dynamics v inf", lambda: jb.forward_dynamics(p(), q1(), jnp.array([jnp.inf])), r"\bv contains NaN or inf"),
        Case("inverse_dynamics a wrong shape", lambda: jb.inverse_dynamics(c(), z(2), z(2), z(5)), r"\ba\b.*shape"),
        Case("inverse_dynamics a NaN", lambda: jb.inverse_dynamics(p(), q1(), z(1), nanq), r"\ba contains NaN or inf"),
        Case("inverse_dynamics external wrong shape",
             lambda: jb.inverse_dynamics(c(), z(2), z(2), z(2), external=jnp.zeros((2, 3))), r"external.*shape"),
        Case("inverse_dynamics external NaN",
             lambda: jb.inverse_dynamics(p(), q1(), z(1), z(1), external=jnp.full((1, 6), jnp.nan)), r"external contains NaN"),
        Case("bias_forces v wrong shape", lambda: jb.bias_forces(c(), z(2), z(1)), r"\bv\b.*shape"),
        Case("kinetic_energy v NaN", lambda: jb.kinetic_energy(p(), q1(), nanq), r"\bv contains NaN or inf"),
        Case("potential_energy q NaN", lambda: jb.potential_energy(p(), nanq), r"\bq contains NaN or inf"),
        Case("passive_forces v NaN", lambda: jb.passive_forces(p(), q1(), nanq), r"\bv contains NaN or inf"),
        Case("joint_reactions q wrong shape", lambda: jb.joint_reactions(c(), z(1), z(2), z(2)), r"\bq\b.*shape"),
        # parameters changed after building, read by a dynamics function
        Case("mass_matrix negative mass (tree_at)",
             lambda: jb.mass_matrix(with_field(p(), "body_mass", [-1.0]), q1()), r"body 0 \('arm'\): body_mass is negative"),
        Case("mass_matrix NaN inertia (tree_at)",
             lambda: jb.mass_matrix(with_field(p(), "body_inertia", jnp.full((1, 3, 3), jnp.nan)), q1()),
             r"body 0 \('arm'\): body_inertia is not finite"),
        Case("forward_dynamics negative armature (tree_at)",
             lambda: jb.forward_dynamics(with_field(p(), "dof_armature", [-0.1]), q1(), z(1)),
             r"joint 0 \('shoulder'\): dof_armature is negative"),
        Case("forward_dynamics zero joint axis (tree_at)",
             lambda: jb.forward_dynamics(with_field(p(), "joint_axis", jnp.zeros((1, 3))), q1(), z(1)),
             r"joint 0 \('shoulder'\): joint_axis is zero"),
        Case("mass_matrix zero joint axis (tree_at)",
             lambda: jb.mass_matrix(with_field(c(), "joint_axis", jnp.array([[0, 1.0, 0], [0, 0, 0]])), z(2)),
             r"joint 1 \('elbow'\): joint_axis is zero"),
        Case("check_inputs planar external", lambda: jb.check_inputs(jb.examples.double_pendulum(), external=jnp.zeros((2, 6))),
             r"planar system: external loads"),
    ]


def _builder_cases():
    return [
        Case("builder negative mass", lambda: builder(mass=-1.0), r"body 1 \('link'\): body_mass is negative"),
        Case("builder NaN mass", lambda: builder(mass=float("nan")), r"body 'link' mass is not finite"),
        Case("builder inf pos", lambda: builder(pos=(0, float("inf"), 0)), r"body 'link' pos is not finite"),
        Case("builder NaN quat", lambda: builder(quat=(1, float("nan"), 0, 0)), r"body 'link' quat is not finite"),
        Case("builder zero quat", lambda: builder(quat=(0, 0, 0, 0)), r"body 'link'.*quat.*zero"),
        Case("builder triangle inequality", lambda: builder(inertia=(1.0, 0.1, 0.1)),
             r"body 1 \('link'\): body_inertia violates the triangle inequality"),
        Case("builder negative principal moment", lambda: builder(inertia=(-0.1, 0.1, 0.1)),
             r"body 1 \('link'\): body_inertia has a negative principal moment"),
        Case("builder unsymmetric inertia", lambda: builder(inertia=[[0.1, 0.05, 0], [0, 0.1, 0], [0, 0, 0.1]]),
             r"body 1 \('link'\): body_inertia is not symmetric"),
        Case("builder inertia wrong size", lambda: builder(inertia=(0.1, 0.1)), r"body 'link': inertia must have 3, 6 or 3x3"),
        Case("builder massless moving leaf", lambda: builder(mass=0.0, inertia=(0, 0, 0)),
             r"body 1 \('link'\) moves \(has joints\) but its subtree mass is 0"),
        Case("builder zero principal moment", lambda: builder(inertia=(0.1, 0.1, 0.0)),
             r"body 1 \('link'\) moves .*principal moment"),
        Case("builder zero hinge axis", lambda: builder(joints=[jb.Hinge(axis=(0, 0, 0), name="knee")]),
             r"joint 'knee' of body 'link': axis is zero"),
        Case("builder zero slide axis", lambda: builder(joints=[jb.Slide(axis=(0, 0, 0), name="rail")]),
             r"joint 'rail' of body 'link': axis is zero"),
        Case("builder NaN axis", lambda: builder(joints=[jb.Hinge(axis=(0, float("nan"), 0))]), r"body 'link' axis is not finite"),
        Case("builder free joint not at root", lambda: builder(joints=[jb.Free(name="float")]),
             r"joint 1 \('float'\) is a free joint on body 1 \('link'\), which is not a root"),
        Case("builder negative damping", lambda: builder(joints=[jb.Hinge(name="knee", damping=-1.0)]),
             r"joint 1 \('knee'\): dof_damping is negative"),
        Case("builder negative stiffness", lambda: builder(joints=[jb.Hinge(name="knee", stiffness=-1.0)]),
             r"joint 1 \('knee'\): joint_stiffness is negative"),
        Case("builder negative armature", lambda: builder(joints=[jb.Hinge(name="knee", armature=-1.0)]),
             r"joint 1 \('knee'\): dof_armature is negative"),
        Case("builder joints not joint specs", lambda: builder(joints=["hinge"]), r"body 'link': joints must be Hinge/Slide/Ball/Free"),
        Case("builder duplicate body", lambda: (lambda b: (b.add_body("a"), b.add_body("a")))(jb.ModelBuilder()),
             r"body 'a' is defined twice"),
        Case("builder unknown parent name", lambda: jb.ModelBuilder().add_body("a", "ghost"), r"body 'a': unknown parent body 'ghost'"),
        Case("builder unknown parent index", lambda: jb.ModelBuilder().add_body("a", 3), r"body 'a': unknown parent index 3"),
        Case("builder NaN gravity", lambda: jb.ModelBuilder(gravity=(0, 0, float("nan"))), r"gravity is not finite"),
        Case("builder no bodies", _no_bodies, r"model has no bodies"),
        Case("builder no degree of freedom", _welded_only, r"no (joint|degree of freedom)"),
    ]


def _tree_at_simulate_cases():
    p, c = pendulum, chain
    return [
        Case("simulate triangle inequality (tree_at)",
             lambda: sim(with_field(p(), "body_inertia", jnp.diag(jnp.array([1.0, 0.1, 0.1]))[None])),
             r"body 0 \('arm'\): body_inertia violates the triangle inequality"),
        Case("simulate negative principal moment (tree_at)",
             lambda: sim(with_field(p(), "body_inertia", jnp.diag(jnp.array([-0.1, 0.1, 0.1]))[None])),
             r"body 0 \('arm'\): body_inertia has a negative principal moment"),
        Case("simulate unsymmetric inertia (tree_at)",
             lambda: sim(with_field(p(), "body_inertia", jnp.array([[[0.1, 0.05, 0], [0, 0.1, 0], [0, 0, 0.1]]]))),
             r"body 0 \('arm'\): body_inertia is not symmetric"),
        Case("simulate negative mass (tree_at)", lambda: sim(with_field(p(), "body_mass", [-1.0])),
             r"body 0? ?\(?'arm'\)?:? .*(body_mass is negative|negative mass)"),
        Case("simulate zero mass (tree_at)", lambda: sim(with_field(c(), "body_mass", [1.0, 0.0])),
             r"body 1 \('lower'\) moves .*mass"),
        Case("simulate zero joint axis (tree_at)", lambda: sim(with_field(p(), "joint_axis", jnp.zeros((1, 3)))),
             r"joint 0 \('shoulder'\): joint_axis is zero"),
        Case("simulate negative model damping (tree_at)", lambda: sim(with_field(c(), "dof_damping", [0.1, -1.0])),
             r"joint 1 \('elbow'\): dof_damping is negative"),
        Case("simulate negative stiffness (tree_at)", lambda: sim(with_field(c(), "joint_stiffness", [-5.0, 0.0])),
             r"joint 0 \('shoulder'\): joint_stiffness is negative"),
        Case("simulate NaN com (tree_at)", lambda: sim(with_field(p(), "body_com", jnp.full((1, 3), jnp.nan))),
             r"body_com.*(NaN|not finite)"),
        Case("simulate zero body quaternion (tree_at)", lambda: sim(with_field(p(), "body_quat", jnp.zeros((1, 4)))),
             r"body 0 \('arm'\): body_quat is zero"),
        Case("scene triangle inequality (tree_at)",
             lambda: jb.scene(with_field(p(), "body_inertia", jnp.diag(jnp.array([1.0, 0.1, 0.1]))[None])),
             r"body 0 \('arm'\): body_inertia violates the triangle inequality"),
        Case("scene zero joint axis (tree_at)", lambda: jb.scene(with_field(p(), "joint_axis", jnp.zeros((1, 3)))),
             r"joint 0 \('shoulder'\): joint_axis is zero"),
        Case("scene negative model damping (tree_at)", lambda: jb.scene(with_field(c(), "dof_damping", [0.1, -1.0])),
             r"joint 1 \('elbow'\): dof_damping is negative"),
        Case("scene negative damping array", lambda: jb.scene(c(), dampers=jnp.array([0.1, -1.0])),
             r"dampers: .*joint 1 \('elbow'\).*negative"),
        Case("scene negative spring array", lambda: jb.scene(c(), springs=jnp.array([-2.0, 0.0])),
             r"springs: .*joint 0 \('shoulder'\).*negative"),
        Case("simulate negative damping set on the scene (tree_at)",
             lambda: sim(eqx.tree_at(lambda s: s.effects[-1].damping, jb.scene(c()), jnp.array([0.1, -1.0]))),
             r"dampers: .*joint 1 \('elbow'\).*negative"),
        Case("scene NaN damping array", lambda: jb.scene(c(), dampers=jnp.array([0.1, jnp.nan])), r"dampers: .*(NaN|not finite)"),
        Case("scene dampers wrong shape", lambda: jb.scene(c(), dampers=jnp.array([0.1])), r"dampers: damping has shape"),
        Case("scene springs wrong shape", lambda: jb.scene(c(), springs=jnp.array([1.0, 2.0, 3.0])), r"springs: stiffness has shape"),
        Case("scene gravity wrong shape", lambda: jb.scene(c(), gravity=jnp.array([0.0, -9.81])), r"gravity"),
        Case("scene unknown kernel", lambda: jb.scene(c(), kernel="warp"), r"kernel.*'warp'"),
        Case("scene actuation not callable", lambda: jb.scene(c(), actuation=3.0), r"actuation"),
        Case("scene loads not callable", lambda: jb.scene(c(), loads="heavy"), r"loads"),
        Case("scene constraints of a wrong kind", lambda: jb.scene(c(), constraints=42), r"constraints"),
    ]


def _simulate_cases():
    p, c, bl = pendulum, chain, ball
    return [
        Case("simulate q0 wrong shape", lambda: sim(c(), z(3)), r"q0 must have shape \(2,\)"),
        Case("simulate v0 wrong shape", lambda: sim(c(), z(2), z(5)), r"v0 \(2,\)"),
        Case("simulate q0 NaN", lambda: sim(p(), jnp.array([jnp.nan])), r"q0 contains NaN or inf"),
        Case("simulate v0 inf", lambda: sim(p(), q1(), jnp.array([jnp.inf])), r"v0 contains NaN or inf"),
        Case("simulate t1 before t0", lambda: sim(p(), t1=-1.0), r"t1 \(-1.0\) must be after t0"),
        Case("simulate t1 equal to t0", lambda: sim(p(), t1=0.0), r"t1 \(0.0\) must be after t0"),
        Case("simulate negative rtol", lambda: sim(p(), rtol=-1e-6), r"rtol must be a positive finite number"),
        Case("simulate zero atol", lambda: sim(p(), atol=0.0), r"atol must be a positive finite number"),
        Case("simulate NaN rtol", lambda: sim(p(), rtol=float("nan")), r"rtol must be a positive finite number"),
        Case("simulate negative dt0", lambda: sim(p(), solver="rk4", dt0=-0.01), r"dt0 must be a positive finite number"),
        Case("simulate zero max_steps", lambda: sim(p(), max_steps=0), r"max_steps must be a positive"),
        Case("simulate fractional max_steps", lambda: sim(p(), max_steps=2.5), r"max_steps must be a positive integer"),
        Case("simulate unknown solver", lambda: sim(p(), solver="rk45"), r"solver.*'rk45'"),
        Case("simulate fixed step without dt0", lambda: sim(p(), solver="rk4"), r"dt0"),
        Case("simulate saveat 2-D", lambda: sim(p(), saveat=jnp.zeros((2, 2))), r"saveat must be 1-D"),
        Case("simulate saveat before t0", lambda: sim(p(), saveat=jnp.array([-0.5, 0.05])),
             r"saveat.*-0.5.*outside \[t0, t1\]"),
        Case("simulate saveat after t1", lambda: sim(p(), saveat=jnp.array([0.05, 2.0])),
             r"saveat.*2.*outside \[t0, t1\]"),
        Case("simulate saveat decreasing", lambda: sim(p(), saveat=jnp.array([0.08, 0.02])), r"saveat.*(increasing|order)"),
        Case("simulate saveat and n_save", lambda: sim(p(), saveat=jnp.array([0.05]), n_save=3), r"give saveat or n_save, not both"),
        Case("simulate n_save 1", lambda: sim(p(), n_save=1), r"n_save must be at least 2"),
        Case("simulate SaveAt dense", lambda: sim(p(), saveat=diffrax.SaveAt(dense=True)), r"pass dense=True"),
        Case("simulate tau wrong shape", lambda: sim(c(), tau=jnp.zeros(3)), r"tau must have shape \(2,\)"),
        Case("simulate tau NaN", lambda: sim(c(), tau=jnp.array([0.0, jnp.nan])), r"(tau|actuation).*(NaN|not finite)"),
        Case("simulate tau law of a wrong shape", lambda: sim(c(), tau=lambda t, q, v: jnp.zeros(3)), r"(tau|actuation).*shape"),
        Case("simulate event not callable", lambda: sim(p(), event=3), r"event must be a jaxbody.Event or a callable"),
        Case("simulate not a system", lambda: jb.simulate(object(), z(1), z(1), 1.0), r"object lacks nq, nv, qdot, acceleration"),
        Case("simulate zero quaternion in q0", lambda: sim(bl(), jnp.array([0.0, 0.0, 0.0, 0.0, 0.1]), z(4)),
             r"q0: joint 0 \('socket'\).*quaternion.*zero"),
        Case("simulate phases with tau", lambda: jb.simulate(jb.Phases((jb.scene(p()),), ()), q1(), z(1), 1.0, tau=z(1)),
             r"tau cannot be given with jaxbody.Phases"),
        # failed solves: the reason, not "increase max_steps"
        Case("simulate NaN from the control law", lambda: nan_law_solve(),
             r"solve failed at t = .*(actuation|control law|tau).*NaN"),
        Case("simulate genuinely too few steps", lambda: law_solve(t1=20.0), r"solve failed at t = .*max_steps"),
    ]


def _constraint_cases():
    return [
        Case("constrain q_ref off the loop",
             lambda: maggi.constrain(four_bar_parts()[0], [four_bar_parts()[1]], q_ref=four_bar_parts()[2] + 0.3),
             r"q_ref.*(violates|off).*loop"),
        Case("constrain redundant rows",
             lambda: maggi.constrain(four_bar_parts()[0], [four_bar_parts()[1]] * 2, q_ref=four_bar_parts()[2]),
             r"constraints are redundant|redundant"),
        Case("constrain partition tolerance", lambda: maggi.constrain(four_bar_parts()[0], [four_bar_parts()[1]],
                                                                       q_ref=four_bar_parts()[2], partition_tolerance=2.0),
             r"partition_tolerance must lie in \(0, 1\)"),
        Case("constrain not a constraint", lambda: maggi.constrain(four_bar_parts()[0], ["loop"], q_ref=four_bar_parts()[2]),
             r"constraints must be jaxbody.maggi.Constraint instances"),
        Case("four-bar started off its loop closure",
             lambda: sim(four_bar_scene(), four_bar_parts()[2] + jnp.array([0.6, 0.0, 0.0]), z(3), 0.1),
             r"q0: .*(positions|coordinates) violate the constraints"),
        Case("four-bar velocities off the loop", lambda: sim(four_bar_scene(), four_bar_parts()[2], jnp.array([1.0, 0.0, 0.0]), 0.1),
             r"v0: .*velocities violate the constraints"),
    ]


def _traced_cases():
    p = pendulum
    two = jnp.array([[0.3], [jnp.nan]])
    return [
        Case("vmap simulate q0 NaN in member 1",
             lambda: jax.vmap(lambda q: sim(p(), q, z(1), 0.1).q)(two), r"q0 contains NaN or inf.*batch member 1"),
        Case("vmap mass_matrix q NaN in member 1",
             lambda: jax.vmap(lambda q: jb.mass_matrix(p(), q))(two), r"\bq contains NaN or inf.*batch member 1"),
        # inside jax.jit the check fails the program with INVALID_ARGUMENT and jaxbody's message
        Case("jit vmap simulate q0 NaN in member 1", lambda: jit_solve(q0=((0.3,), (np.nan,))),
             r"^INVALID_ARGUMENT: simulate: q0 contains NaN or inf \(batch member 1 of 2\)$"),
        Case("jit mass_matrix q NaN", lambda: jit_mass_matrix(p())(jnp.array([jnp.nan])),
             r"^INVALID_ARGUMENT: q contains NaN or inf$"),
        Case("jit simulate saveat outside [t0, t1]", lambda: jit_solve(ts=(0.05, 2.0)),
             r"^INVALID_ARGUMENT: simulate: saveat: a time lies outside \[t0, t1\]"),
        Case("jit simulate saveat decreasing", lambda: jit_solve(ts=(0.08, 0.02)),
             r"^INVALID_ARGUMENT: simulate: saveat times must be increasing"),
        Case("jit vmap simulate negative mass in member 1", lambda: jit_solve(mass=((1.0,), (-1.0,))),
             r"^INVALID_ARGUMENT: simulate: body 0 \('arm'\): body_mass is negative \(batch member 1 of 2\)$"),
        Case("jit vmap mass_matrix q NaN in member 2", lambda: jax.jit(jax.vmap(lambda q: jb.mass_matrix(p(), q)))(
             jnp.array([[0.1], [0.2], [jnp.inf]])), r"^INVALID_ARGUMENT: q contains NaN or inf \(batch member 2 of 3\)$"),
        Case("jit builder given a traced mass", lambda: jax.jit(lambda m: builder(mass=m))(1.0),
             r"^body 'link' mass is a traced value .*build the model outside the traced function"),
        Case("jit builder given a traced joint damping",
             lambda: jax.jit(lambda d: builder(joints=[jb.Hinge(axis=(0, 1, 0), name="knee", damping=d)]))(0.1),
             r"^joint 'knee' damping is a traced value"),
        Case("jit validate_parameters of a traced model",
             lambda: jax.jit(lambda m: jb.validate_parameters(with_field(pendulum(), "body_mass", m)))(jnp.ones(1)),
             r"^validate_parameters: model field body_mass is a traced value"),
        Case("simulate_batch q0s 1-D", lambda: jb.simulate_batch(p(), z(1), z(1), 0.1), r"q0s and v0s must be \(batch, nq\)"),
        Case("simulate_batch chunk_size 0", lambda: jb.simulate_batch(p(), jnp.zeros((2, 1)), jnp.zeros((2, 1)), 0.1, chunk_size=0),
             r"chunk_size must be a positive integer"),
    ]


def _solution_cases():
    def csv_roundtrip_bad_header():
        path = tmpfile("bad.csv", text="time,x\n0,1\n")
        return jb.load_solution(path)

    def not_a_solution():
        path = tmpfile("other.npz")
        with open(path, "wb") as fh:
            np.savez(fh, a=np.zeros(3))
        return jb.load_solution(path)

    return [
        Case("Solution.evaluate without dense", lambda: solved().evaluate(0.05), r"evaluate needs simulate\(..., dense=True\)"),
        Case("Solution.evaluate past t1", lambda: dense_solution().evaluate(0.5), r"t = 0.5 .*outside \[t0, t_final\]"),
        Case("Solution.evaluate before t0", lambda: dense_solution().evaluate(-0.1), r"t = -0.1 .*outside \[t0, t_final\]"),
        Case("Solution index of an unbatched solve", lambda: solved()[0], r"not batched"),
        Case("Solution index out of range", lambda: batch_solution()[5], r"batch member 5.*3 members"),
        Case("Solution.result index of an unbatched solve", lambda: solved().result[0],
             r"single solve's result has no members"),
        Case("Solution.result index out of range", lambda: batch_solution().result[3], r"result: no batch member 3.*3 members"),
        Case("Solution.to_csv of a batch", lambda: batch_solution().to_csv(tmpfile("b.csv")), r"batch.*sol\[i\]"),
        Case("load_solution missing file", lambda: jb.load_solution("/nonexistent/run.npz"), r"/nonexistent/run.npz"),
        Case("load_solution CSV of other columns", csv_roundtrip_bad_header, r"bad.csv.*column"),
        Case("load_solution npz of other arrays", not_a_solution, r"other.npz.*not a (jaxbody )?solution"),
    ]


def _import_cases():
    return [
        Case("from_mjcf missing file", lambda: jb.from_mjcf("/nonexistent/robot.xml"), r"/nonexistent/robot.xml"),
        Case("from_mjcf malformed XML", lambda: jb.from_mjcf("<mujoco><worldbody>"), r"(XML|xml|parse|Error)"),
        Case("from_mjcf unknown joint type", lambda: jb.from_mjcf(MJCF_HEAD.replace("hinge", "twist") + MJCF_TAIL), r"twist|type"),
        Case("from_mjcf no degree of freedom",
             lambda: jb.from_mjcf('<mujoco><worldbody><body name="b"><geom size=".1"/></body></worldbody></mujoco>'),
             r"no (joint|degree of freedom)"),
        Case("from_urdf missing file", lambda: jb.from_urdf("/nonexistent/robot.urdf"), r"/nonexistent/robot.urdf"),
        Case("Model.keyframe unknown", lambda: pendulum().keyframe("home"), r"no keyframe named 'home'"),
        Case("Model.body_index unknown", lambda: pendulum().body_index("leg"), r"no body named 'leg'"),
        Case("Model.joint_index unknown", lambda: pendulum().joint_index("hip"), r"no joint named 'hip'"),
    ]


def _cli_cases():
    return [
        Case("cli simulate unknown source", lambda: cli("simulate", "no_such_robot"), r"no_such_robot"),
        Case("cli simulate negative t1", lambda: cli("simulate", "double_pendulum", "--t1", "-1"), r"--t1"),
        Case("cli simulate zero rtol", lambda: cli("simulate", "double_pendulum", "--rtol", "0"), r"--rtol"),
        Case("cli simulate q0 count", lambda: cli("simulate", "double_pendulum", "--q0", "1,2,3"), r"--q0 has 3 values but .* nq = 2"),
        Case("cli simulate q0 not numbers", lambda: cli("simulate", "double_pendulum", "--q0", "a,b"), r"--q0"),
        Case("cli simulate q0 NaN", lambda: cli("simulate", "double_pendulum", "--q0", "nan,0"), r"q0.*(NaN|finite)"),
        Case("cli simulate v0 count", lambda: cli("simulate", "double_pendulum", "--v0", "1"), r"--v0 has 1 value"),
        Case("cli simulate unknown solver", lambda: cli("simulate", "double_pendulum", "--solver", "rk45"), r"rk45"),
        Case("cli simulate keyframe of an example", lambda: cli("simulate", "double_pendulum", "--keyframe", "home"), r"keyframe"),
        Case("cli simulate negative damping", lambda: cli("simulate", "double_pendulum", "--damping", "-1"), r"--damping"),
        Case("cli simulate zero saves", lambda: cli("simulate", "double_pendulum", "--saves", "1"), r"--saves"),
        Case("cli simulate missing file", lambda: cli("simulate", "/nonexistent/robot.xml"), r"/nonexistent/robot.xml"),
        Case("cli simulate gravity of two values", lambda: cli("simulate", "double_pendulum", "--gravity", "0,1"), r"--gravity"),
        Case("cli info unknown source", lambda: cli("info", "no_such_robot"), r"no_such_robot"),
        Case("cli info missing file", lambda: cli("info", "/nonexistent/robot.xml"), r"/nonexistent/robot.xml"),
        Case("cli balance unknown target", lambda: cli("balance", "no_such_robot"), r"no_such_robot"),
        Case("cli balance negative radius", lambda: cli("balance", "double_pendulum", "--radius", "-1"), r"radius"),
        Case("cli simulate zero quaternion",
             lambda: cli("simulate", str(_ball_file()), "--q0", "0,0,0,0,0.1", "--t1", "0.01", "--no-progress"),
             r"q0: joint 0 \('socket'\).*quaternion.*zero"),
    ]


@functools.lru_cache
def _ball_file():
    return tmpfile("ball.xml", text=(
        '<mujoco><worldbody><body name="head"><joint name="socket" type="ball"/>'
        '<geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.05" mass="1"/>'
        '<body name="hand" pos="0 0 -0.4"><joint name="wrist" type="hinge" axis="0 1 0"/>'
        '<geom type="sphere" size="0.05" mass="0.5"/></body></body></worldbody></mujoco>'))


def all_cases():
    cases = (_builder_cases() + _dynamics_cases() + _tree_at_simulate_cases() + _simulate_cases() + _constraint_cases()
             + _traced_cases() + _solution_cases() + _import_cases() + _cli_cases())
    ids = [c.id for c in cases]
    assert len(ids) == len(set(ids)), "case ids must be unique"
    return cases


def first_line(err: BaseException) -> str:
    """The line a user reads first: the first line of the error's text (for a command, its
    ``error:`` line; notes printed before it are not the error)."""
    text = str(err).strip()
    if isinstance(err, CommandFailed):
        errors = [line for line in text.splitlines() if ": error:" in line]
        if errors:
            return errors[0]
    return text.splitlines()[0] if text else type(err).__name__


def classify(case: Case) -> tuple[str, str]:
    """``(verdict, text)``: ``clear`` (raises; the pattern is on the first line), ``misleading``
    (raises from jaxbody's own checks, or the pattern is further down the text), ``silent`` (no
    error) or ``crash`` (an error from deep inside JAX, NumPy or equinox)."""
    import re
    import traceback

    try:
        jax.block_until_ready(case.call())  # an error of a running program is raised when its result is read
    except Exception as err:  # noqa: BLE001 (every failure is classified)
        text = str(err)
        if re.search(case.pattern, first_line(err)):
            return "clear", first_line(err)
        if re.search(case.pattern, text, flags=re.S):
            return "misleading", first_line(err)
        if isinstance(err, CommandFailed):
            internal = re.search(r"\b(IndexError|AttributeError|JaxRuntimeError|XlaRuntimeError|EquinoxRuntimeError|"
                                 r"TypeError|KeyError|ZeroDivisionError)\b", text)
            return ("crash" if internal else "misleading"), first_line(err)
        frames = traceback.extract_tb(err.__traceback__)
        last = frames[-1].filename if frames else ""
        own = f"{os.sep}jaxbody{os.sep}" in last and "site-packages" not in last
        return ("misleading" if own else "crash"), f"{type(err).__name__}: {first_line(err)}"
    return "silent", ""
