"""C++ code generation of the native kernel: the programs of every mode from the traced tree.

The templates (``common.h``, ``kernel.cc``, ``access.h``, ``hermite.h``, ``run_block.cc``,
``run_vjp_block.cc``, ``handler.cc``) are package data next to this module; the generated
lines of one tree fill their ``@…@`` slots.
"""

from importlib import resources

import numpy as np

from .. import scalar
from .symbolic import declared_scalars, Emitter, input_scalars, stop_derivative, Sym, sym_sqrt, SymbolicModel, with_derivative
from .rk4 import fourier_torque, joint_force, qdot_scalars, rk4_scalars, spring_potential, torque_size, work_count
from .differentiate import active_values, adjoint_program, inverse_dynamics_block, tangent_program

def _template(name: str) -> str:
    """The C++ template ``name``, shipped as package data next to this module."""
    return resources.files(__package__).joinpath(name).read_text(encoding="utf-8")


# the operands of every generated function, in order: the state and the model, then (for the
# derivatives) the tangents of (q, v, f) or the cotangent of the acceleration. The RK4 step's
# programs take the step h and the joint springs and dampers after the model, then the tangents
# or the seven cotangents.
_SLOTS = {"q": 0, "v": 1, "f": 2, "p": 3, "g": 4, "ext": 5, "dq": 6, "dv": 7, "df": 8, "ct": 6}
_STEP_SLOTS = {"q": 0, "v": 1, "f": 2, "p": 3, "g": 4, "ext": 5, "h": 6, "k": 7, "r": 8, "d": 9, "dq": 10, "dv": 11, "df": 12, "ct": 10}
# the whole-solve program (generate_run): the state, the model, springs and dampers, the work
# reached so far and the schedule. The whole-solve and adaptive programs take no body loads: the
# loads' slot ("ext") holds the coefficient row of a Fourier-series joint torque where they
# have one (rk4.torque_size)
_RUN_SLOTS = {"q": 0, "v": 1, "f": 2, "p": 3, "g": 4, "ext": 5, "k": 6, "r": 7, "d": 8, "w": 9, "s": 10}
# the RK4 step with a Fourier-series joint torque ("rk4" only: its derivatives come from the step
# written in JAX): the torque's coefficient row and the step's times (t0, t1) after the dampers
_STEP_TORQUE_SLOTS = {"tq": 10, "tm": 11}
# the energy program: the state, the model, gravity and the joint springs
_ENERGY_SLOTS = {"q": 0, "v": 1, "p": 2, "g": 3, "k": 4, "r": 5}

#: Programs: forward dynamics and one RK4 step, each with its forward- and reverse-mode
#: derivative, and the energies of a state (no derivative programs: their tangents are rare).
MODES = ("fd", "jvp", "vjp", "rk4", "rk4_jvp", "rk4_vjp", "energy", "rk4_run", "rk4_run_vjp",
         *(f"{kind}:{method}" for kind in ("adaptive", "adaptive_vjp") for method in ("tsit5", "dopri5", "dopri8")))


def result_widths(joints, mode: str, harmonics=None) -> tuple:
    """Row widths of a program's results (``harmonics``: of a whole solve's Fourier-series joint
    torque, whose work is a second one)."""
    nq, nv, nw = joints.nq, joints.nv, work_count(harmonics)
    if mode.startswith("adaptive_vjp:"):
        return (nq, nv, nw)
    if mode.startswith("adaptive:"):
        return (nq, nv, nw, 6)  # then the saved states and the checkpoints, sized per call
    return {
        "fd": (nv,),
        "jvp": (nv,),
        "vjp": (nq, nv, nv),
        "rk4": (nq, nv, nq, nv, nq, nv, 3 * nw),
        "rk4_jvp": (nq, nv, nq, nv, nq, nv, 3),
        "rk4_vjp": (nq, nv, nv),
        "energy": (3,),
        "rk4_run": (nq, nv, nw, 6),  # then the saved states and the checkpoints, sized per call
        "rk4_run_vjp": (nq, nv, nw),
    }[mode]


def residual_count(mode: str) -> int:
    """Operands a program takes before its tangents: (q, v, f, p, g, ext), then for a step h and
    the springs and dampers (stiffness, reference, damping)."""
    return 10 if mode.startswith("rk4") else 6


# ----------------------------------------------------------------------------- code generation
# Two translation units: the per-tree kernel (plain C++, quick to compile) and, once per dtype,
# the XLA FFI handler (XLA's FFI headers take longer to parse than a small tree takes to
# optimise). The handler receives the kernel's registry key as a call attribute.
#: The declarations both translation units share (``@T@``: the scalar type).
COMMON_TEMPLATE = _template("common.h")
_KERNEL = _template("kernel.cc")

# how a block reads its operands (ld), writes its results (st) and takes sines and cosines (sc)
_ACCESS = _template("access.h")

# A whole fixed-step RK4 solve per block of states (:func:`generate_run`): the state stays in
# registers (or on the stack) from the first step to the last; each lane keeps its own time,
# step count and failure flag, and the block ends when every lane is done. Step times, the
# clip to t1, the quaternion renormalisation after each step and the hold of a trajectory at
# its first non-finite step are those of jaxbody.simulation's fixed-step solve (diffrax's
# ConstantStepSize): t_k = t0 + (t1 - t0) * (k / N), t_N = t1, a time within 100 ulp below t1
# rounded to t1. Operands: q, v, f, p, g, ext, k, r, d, the work w0, the schedule (t0, t1, N,
# t1 - 100 ulp, the step budget, dt0, frozen, steps per checkpoint, number of save times) and the
# save times; results: q, v, w, the status (jaxbody.backends.native.solve.STATUS: t reached,
# steps, accepted, rejected, result code, saves), the saved states (each from the dense output of
# the step that covers its time, _HERMITE) and, when asked for, the checkpoints of the reverse
# sweep (_RUN_VJP_BLOCK). A frozen lane (an input that failed simulate's checks) takes its steps
# without moving.
_RUN_BLOCK = _template("run_block.cc")

# The dense output of an RK4 step (diffrax's cubic Hermite interpolant) and its derivatives,
# which the whole solve and its reverse sweep share
_HERMITE = _template("hermite.h")

# The reverse sweep of a whole solve (reverse mode with respect to the initial state): for each
# segment of `every` steps, last first, the steps are recomputed from the segment's checkpoint
# (the forward program, so the same states) and kept; then the reverse-mode program of one step
# carries the cotangents of (q, v) back through them, the work's cotangent held (w1 = w0 + Δw);
# the cotangents of the states saved in a step enter its reverse-mode program through the dense
# output (its stage increments and its end state before renormalisation). A lane's own steps are
# those it took (a frozen lane: none; its saves pass their cotangents to its state). Operands:
# those of _RUN_BLOCK but the save times, then the checkpoints, the forward's status, the
# cotangents of the final q, v and w, the save times and the cotangents of the saved states;
# results: the cotangents of the initial q, v and w.
_RUN_VJP_BLOCK = _template("run_vjp_block.cc")

#: The XLA FFI handler, one per dtype: a thread pool that runs a program over a batch.
HANDLER_TEMPLATE = _template("handler.cc")

#: The C++ scalar and XLA FFI data type of each dtype the programs are built for.
SCALAR_TYPES = {np.dtype(np.float64): ("double", "XLA_FFI_DataType_F64"), np.dtype(np.float32): ("float", "XLA_FFI_DataType_F32")}


def _acceleration(em, model, joints, q, v, f, g, ext, derivative):
    """Forward dynamics' acceleration on symbolic scalars; for ``derivative="vjp"`` written so
    that its reverse mode goes through inverse dynamics (below)."""
    M, bias, lam = scalar.bias_and_mass(model, q, v, g, ext)
    L, inv_d = scalar.ltdl_factor(M, lam)
    a = scalar.ltdl_substitute(L, inv_d, lam, [fi - b for fi, b in zip(f, bias)])
    if derivative != "vjp":
        return a
    # The reverse-mode programs differentiate a = a₀ + M⁻¹ (f − τ(q, v, a₀)), a₀ and the factor
    # of M held constant: equal to a up to rounding, its derivative is forward dynamics'
    # (implicit function theorem on τ(q, v, a) = f): M⁻¹ (∂f − ∂τ/∂q ∂q − ∂τ/∂v ∂v). The
    # derivative passes go through inverse dynamics (Newton–Euler), not through the
    # composite inertias and the factorisation (forward mode stays on the direct program,
    # whose tangent is shorter than the tangent of inverse dynamics).
    a0 = [stop_derivative(x) for x in a]
    L0 = {k: stop_derivative(x) for k, x in L.items()}
    inv_d0 = [stop_derivative(x) for x in inv_d]
    tau = scalar.inverse_dynamics(model, q, v, a0, g, ext)
    if ext is None and scalar.adjoint_applies(joints):
        tau = inverse_dynamics_block(em, model, q, v, a0, g, tau)
    correction = scalar.ltdl_substitute(L0, inv_d0, lam, [fi - t for fi, t in zip(f, tau)])
    # the value is a₀ itself (the correction is zero up to rounding): the stages that follow
    # do not wait on inverse dynamics and a second substitution, which only the reverse pass reads
    return [with_derivative(x, x + c) for x, c in zip(a0, correction)]


def generate(tree, joints, with_external: bool, dtype, mode: str = "fd", harmonics=None) -> str:
    """C++ source of forward dynamics, or of one RK4 step, for this tree (parameters, gravity,
    loads as inputs).

    ``mode``: ``"fd"`` the acceleration; ``"jvp"`` its directional derivative along tangents
    ``(dq, dv, df)`` of the state and force (forward mode on the generated program);
    ``"vjp"`` the cotangents of ``(q, v, f)`` for a cotangent of the acceleration (reverse mode).
    ``"rk4"``, ``"rk4_jvp"``, ``"rk4_vjp"``: the same for one RK4 step of length ``h`` (an extra
    input) with the force held over the step (:func:`rk4_scalars`: six results). ``harmonics``
    (``"rk4"`` only): a Fourier-series joint torque evaluated at the stages' times, its work a
    second one (the last result: ``(Δw, k1w, k4w)`` of each work, work by work within each).
    """
    step = mode.startswith("rk4")
    if mode == "energy":
        return _generate_energy(tree, joints, dtype)
    slots = _STEP_SLOTS if step else _SLOTS
    em = Emitter()
    model = SymbolicModel(tree, joints, em, slots["p"])
    q = input_scalars(em, "q", joints.nq, slots["q"])
    v = input_scalars(em, "v", joints.nv, slots["v"])
    f = input_scalars(em, "f", joints.nv, slots["f"])
    g = tuple(input_scalars(em, "g", 3, slots["g"]))
    ext = None
    if with_external:
        flat = input_scalars(em, "ext", 6 * tree.n_body, slots["ext"])
        ext = [tuple(flat[6 * b : 6 * b + 6]) for b in range(tree.n_body)]

    derivative = mode.split("_")[-1] if mode not in ("fd", "rk4") else None

    def acceleration(q, v, f):
        return _acceleration(em, model, joints, q, v, f, g, ext, derivative)

    if step:
        h = input_scalars(em, "h", 1, slots["h"])[0]
        stiffness = input_scalars(em, "k", joints.n_joint, slots["k"])
        reference = input_scalars(em, "r", joints.nq, slots["r"])
        damping = input_scalars(em, "d", joints.nv, slots["d"])

        def field(q, v, t):
            total, power = joint_force(joints, q, v, f, stiffness, reference, damping)
            return acceleration(q, v, total), power

        times = (None, None)
        if harmonics is not None:
            torque = (input_scalars(em, "tq", torque_size(joints.nv, harmonics), _STEP_TORQUE_SLOTS["tq"]), harmonics)
            times = tuple(input_scalars(em, "tm", 2, _STEP_TORQUE_SLOTS["tm"]))
            operands = (model, f, g, stiffness, reference, damping, torque)

            def field(q, v, t):  # noqa: F811 (the torque's field)
                return _stage_field(em, joints, operands, q, v, t, derivative, ext)

        outputs = list(rk4_scalars(field, joints, q, v, h, *times))
        if harmonics is not None:
            outputs[-1] = [x for part in outputs[-1] for x in part]
    else:
        outputs = [acceleration(q, v, f)]
    primal = list(em.ops)
    if derivative is None:
        results = outputs
    elif derivative == "jvp":
        seeds = {}
        for x, name in ((q, "dq"), (v, "dv"), (f, "df")):
            for xi, di in zip(x, input_scalars(em, name, len(x), slots[name])):
                seeds[xi.name] = di
        tan = tangent_program(primal, seeds)
        results = [[tan.get(o.name, 0.0) if isinstance(o, Sym) else 0.0 for o in out] for out in outputs]
    elif derivative == "vjp":
        pairs = []
        for j, out in enumerate(outputs):
            cts = input_scalars(em, f"ct{j}", len(out), slots["ct"] + j)
            pairs += [(o, c) for o, c in zip(out, cts)]
        active = active_values(primal, {"q", "v", "f"})
        adj = adjoint_program(primal, active, pairs)
        results = [[adj.get(xi.name, 0.0) for xi in x] for x in (q, v, f)]
    else:
        raise ValueError(f"unknown mode {mode!r}")

    return _source(em, results, dtype)


def _generate_energy(tree, joints, dtype) -> str:
    """C++ source of the energies of a state: ``(kinetic, gravity potential, spring potential)``
    (:func:`jaxbody.scalar.energies`, :func:`spring_potential`)."""
    slots = _ENERGY_SLOTS
    em = Emitter()
    model = SymbolicModel(tree, joints, em, slots["p"])
    q = input_scalars(em, "q", joints.nq, slots["q"])
    v = input_scalars(em, "v", joints.nv, slots["v"])
    g = tuple(input_scalars(em, "g", 3, slots["g"]))
    stiffness = input_scalars(em, "k", joints.n_joint, slots["k"])
    reference = input_scalars(em, "r", joints.nq, slots["r"])
    kinetic, potential = scalar.energies(model, q, v, g)
    return _source(em, [[kinetic, potential, spring_potential(joints, q, stiffness, reference)]], dtype)


def _source(em: Emitter, results: list, dtype) -> str:
    """The kernel's C++ source: the emitted lines, then every result stored."""

    body = ["  " + line for line in em.lines]
    body += [f"  st({j}, {i}, {_symbol_value(x)});" for j, xs in enumerate(results) for i, x in enumerate(xs)]
    return _KERNEL.replace("@ACCESS@", _ACCESS).replace("@COMMON@", COMMON_TEMPLATE.replace("@T@", SCALAR_TYPES[np.dtype(dtype)][0])).replace(
        "@BODY@", "\n".join(body))


def _carried(em: Emitter, name: str, n: int, array: str) -> list:
    """``n`` scalars read from the local array ``array`` (a loop's carried state)."""
    return declared_scalars(em, name, n, lambda i: f"{array}[{i}]")


def _quaternion_coordinates(joints) -> list:
    """The ``q`` coordinates of every ball and free joint's quaternion, four at a time."""
    out = []
    for kind, _, qadr, _ in joints.kind_groups():
        if kind.quaternion is not None:
            out += [[int(a) + kind.quaternion + c for c in range(4)] for a in qadr]
    return out


def _run_operands(em: Emitter, tree, joints, harmonics=None):
    """The operands a whole solve holds over its steps (:data:`_RUN_SLOTS`), loaded first:
    ``(model, force, gravity, stiffness, reference, damping, torque)``, ``torque`` the
    coefficient row of a Fourier-series joint torque of ``harmonics`` harmonics (``None``: none)."""
    slots = _RUN_SLOTS
    model = SymbolicModel(tree, joints, em, slots["p"])
    f = input_scalars(em, "f", joints.nv, slots["f"])
    g = tuple(input_scalars(em, "g", 3, slots["g"]))
    stiffness = input_scalars(em, "k", joints.n_joint, slots["k"])
    reference = input_scalars(em, "r", joints.nq, slots["r"])
    damping = input_scalars(em, "d", joints.nv, slots["d"])
    torque = None
    if harmonics is not None:
        torque = (input_scalars(em, "tq", torque_size(joints.nv, harmonics), slots["ext"]), harmonics)
    return model, f, g, stiffness, reference, damping, torque


def _stage_field(em: Emitter, joints, operands, q: list, v: list, t, derivative=None, ext=None) -> tuple:
    """``(a, P)`` at one stage: the held force plus the torque at time ``t``, the springs and
    dampers, through forward dynamics; ``P`` the list of works' powers (:func:`.rk4.work_count`):
    the dampers', then the torque's ``τ·v``."""
    model, f, g, stiffness, reference, damping, torque = operands
    powers = []
    if torque is not None:
        tau = fourier_torque(torque[0], joints.nv, torque[1], t)
        f = [fi + ti for fi, ti in zip(f, tau)]
        power = 0.0
        for ti, vi in zip(tau, v):
            power = power + ti * vi
        powers.append(power)
    total, power = joint_force(joints, q, v, f, stiffness, reference, damping)
    return _acceleration(em, model, joints, q, v, total, g, ext, derivative), [power] + powers


def _run_step(em: Emitter, joints, operands, q: list, v: list, h, derivative=None, t0=None, t1=None) -> tuple:
    """One step of a whole solve on symbolic scalars from ``t0`` to ``t1``: the RK4 step of
    :func:`rk4_scalars`, then the quaternions of ball and free joints renormalised (``q /
    sqrt(|q|²)``, as :func:`jaxbody.kinematics.normalize_qpos`). Returns ``(q1, v1, Δw, dense)``,
    ``Δw`` the list of works' increments and ``dense`` what the step's dense output reads:
    ``(k1, k4, q1 before renormalisation)``, ``k1`` and ``k4`` the first and last stage increments
    of the whole state ``(q, v, w)`` (diffrax interpolates a step's unrenormalised end state)."""

    def field(q, v, t):
        return _stage_field(em, joints, operands, q, v, t, derivative)

    q1, v1, k1q, k1v, k4q, k4v, work = rk4_scalars(field, joints, q, v, h, t0, t1)
    dense = (list(k1q) + list(k1v) + list(work[1]), list(k4q) + list(k4v) + list(work[2]), list(q1))
    q1 = list(q1)
    for block in _quaternion_coordinates(joints):
        squares = [q1[i] * q1[i] for i in block]
        inverse = 1.0 / sym_sqrt(squares[0] + squares[1] + squares[2] + squares[3])
        for i in block:
            q1[i] = q1[i] * inverse
    return q1, list(v1), work[0], dense


def _symbol_value(x) -> str:
    return x.name if isinstance(x, Sym) else f"U{{}} + T({float(x)!r})"


def _hoisted(lines: list) -> list:
    """``lines`` without operand loads (:func:`_run_operands` puts them before the loop)."""
    return [line for line in lines if " = ld(" not in line]


def _run_program(tree, joints, derivative=None, harmonics=None) -> tuple:
    """One step of a whole solve on the carried state ``qc``, ``vc`` from ``tprev`` to ``tnext``
    (:func:`_run_step`): ``(emitter, operand loads, step lines, (q, v), (q1, v1, Δw), dense)``, the
    step lines ending in the stores of ``q1``, ``v1`` to ``qn``, ``vn``; ``dense``: the symbols
    of :func:`_run_step`'s dense output."""
    em = Emitter()
    operands = _run_operands(em, tree, joints, harmonics)
    invariant = len(em.lines)
    q = _carried(em, "q", joints.nq, "qc")
    v = _carried(em, "v", joints.nv, "vc")
    # the step's times enter only a field that depends on time (the torque's)
    times = (Sym("tprev", em), Sym("tnext", em)) if harmonics is not None else (None, None)
    q1, v1, dw, dense = _run_step(em, joints, operands, q, v, Sym("h", em), derivative, *times)
    step = em.lines[invariant:]
    step += [f"qn[{i}] = {_symbol_value(x)};" for i, x in enumerate(q1)]
    step += [f"vn[{i}] = {_symbol_value(x)};" for i, x in enumerate(v1)]
    return em, em.lines[:invariant], step, (q, v), (q1, v1, dw), dense


def generate_run(tree, joints, dtype, harmonics=None) -> str:
    """C++ source of a whole fixed-step RK4 solve (``"rk4_run"``, :data:`_RUN_BLOCK`): the
    step of :func:`_run_step` on the carried state, the operands loaded before the loop, and
    what the step's dense output reads stored in ``k1``, ``k4`` (first and last stage increments
    of ``(q, v, w)``) and ``qu`` (``q1`` before renormalisation) for the saves inside the step;
    ``harmonics``: that of a Fourier-series joint torque (``None``: none)."""
    _, invariant, step, _, (_, _, dw), (k1, k4, qu) = _run_program(tree, joints, harmonics=harmonics)
    body = step + [f"dw[{j}] = {_symbol_value(x)};" for j, x in enumerate(dw)]
    # stored only by a solve that saves at requested times (n_ts > 0): a solve that keeps its end
    # state alone stores nothing more than it did without them
    dense = [f"  {name}[{i}] = {_symbol_value(x)};" for name, xs in (("k1", k1), ("k4", k4), ("qu", qu))
             for i, x in enumerate(xs)]
    body += ["if (n_ts > 0) {"] + dense + ["}"]
    return _run_source(_RUN_BLOCK, invariant, {"BODY": body}, joints, dtype, harmonics)


def generate_run_vjp(tree, joints, dtype, harmonics=None) -> str:
    """C++ source of the reverse sweep of a whole solve (``"rk4_run_vjp"``, :data:`_RUN_VJP_BLOCK`):
    the same steps recomputed from the checkpoints, and the reverse-mode program of
    :func:`_run_step` on a kept state (``bq``, ``bv``) and its times: the cotangents of ``(q, v)``
    for those of ``q1`` (``sq``), ``v1`` (``sv``), ``Δw`` (``sw``) and of the step's dense output
    (``sk1``, ``sk4``: its stage increments, ``squ``: ``q1`` before renormalisation)."""
    _, invariant, step, _, _, _ = _run_program(tree, joints, harmonics=harmonics)
    rev, _, _, (q, v), (q1, v1, dw), (k1, k4, qu) = _run_program(tree, joints, derivative="vjp", harmonics=harmonics)
    primal = list(rev.ops)
    pairs = []
    for name, xs in (("sq", q1), ("sv", v1), ("sw", dw), ("sk1", k1), ("sk4", k4), ("squ", qu)):
        cts = _carried(rev, name, len(xs), name)
        pairs += [(x, c) for x, c in zip(xs, cts) if isinstance(x, Sym)]
    adj = adjoint_program(primal, active_values(primal, {"q", "v"}), pairs)
    # the kept state's reads, then the step's operations and their adjoints
    body = [f"const U q_{i} = bq[{i}];" for i in range(joints.nq)] + [f"const U v_{i} = bv[{i}];" for i in range(joints.nv)]
    body += _hoisted(rev.lines[len(invariant) + joints.nq + joints.nv :])
    body += [f"rq[{i}] = {_symbol_value(adj.get(x.name, 0.0))};" for i, x in enumerate(q)]
    body += [f"rv[{i}] = {_symbol_value(adj.get(x.name, 0.0))};" for i, x in enumerate(v)]
    return _run_source(_RUN_VJP_BLOCK, invariant, {"STEP": step, "BODY": body}, joints, dtype, harmonics)


def _run_source(block: str, invariant: list, parts: dict, joints, dtype, harmonics=None) -> str:
    text = block.replace("@HERMITE@", _HERMITE).replace("@ACCESS@", _ACCESS)
    text = text.replace("@INVARIANT@", "\n".join("  " + line for line in invariant))
    for key, lines in parts.items():
        text = text.replace(f"@{key}@", "\n".join("      " + line for line in lines))
    text = text.replace("@NQ@", str(joints.nq)).replace("@NV@", str(joints.nv)).replace("@NW@", str(work_count(harmonics)))
    prelude = _KERNEL.split("// the generated function of the states")[0]
    return prelude.replace("@COMMON@", COMMON_TEMPLATE.replace("@T@", SCALAR_TYPES[np.dtype(dtype)][0])) + text


# ----------------------------------------------------------------------------- adaptive solves
# A whole adaptive solve by an embedded Runge–Kutta pair (:mod:`.tableaux`) per block of states:
# the stages loop over the tableau's coefficients and call the field, generated once; the
# controller is diffrax's PIDController (the step of _ADAPTIVE_ATTEMPT, shared by the solve and
# its reverse sweep's replay so that both take the same steps). Operands: q, v, f, p, g, ext,
# k, r, d, the work w0, the schedule (jaxbody.backends.native.adaptive) and the save times;
# results: q, v, w, the status (t reached, steps, accepted, rejected, result code, saves), the
# saved states and, when asked for, the checkpoints of the reverse sweep.
_ADAPTIVE_ATTEMPT = _template("adaptive_attempt.cc")
_ADAPTIVE_BLOCK = _template("adaptive_block.cc")
# Its reverse sweep: operands those of the solve (the save times' slot unused), then the
# checkpoints, the solve's status and the cotangents of the final q, v and w; results: the
# cotangents of the initial q, v and w.
_ADAPTIVE_VJP_BLOCK = _template("adaptive_vjp_block.cc")


def _field_program(tree, joints, derivative=None, harmonics=None) -> tuple:
    """The field ``(q̇, a, P)`` at a state read from ``sq``, ``sv`` at time ``t`` on symbolic
    scalars (springs, dampers, gravity, the force held and a Fourier-series torque of
    ``harmonics`` harmonics): ``(emitter, operand loads, field lines, (q, v), outputs)``."""
    em = Emitter()
    operands = _run_operands(em, tree, joints, harmonics)
    invariant = len(em.lines)
    q = _carried(em, "q", joints.nq, "sq")
    v = _carried(em, "v", joints.nv, "sv")
    a, powers = _stage_field(em, joints, operands, q, v, Sym("t", em), derivative)
    outputs = list(qdot_scalars(joints, q, v)) + list(a) + powers
    return em, em.lines[:invariant], em.lines[invariant:], (q, v), outputs


def _c_array(values) -> str:
    """A C++ brace initialiser of (nested) numbers."""
    if isinstance(values, (list, tuple)):
        return "{" + ", ".join(_c_array(x) for x in values) + "}"
    return f"T({float(values)!r})"


def _projection(joints) -> tuple[list, list]:
    """C++ lines renormalising the quaternions of ``x`` in place (as :func:`_run_step`:
    ``q / sqrt(|q|²)``), and of the reverse of that on the cotangent ``lam`` at ``x``."""
    forward, reverse = [], []
    for block in _quaternion_coordinates(joints):
        sq = " + ".join(f"x[{i}] * x[{i}]" for i in block)
        forward.append("{ const U inverse = T(1) / vsqrt(" + sq + "); "
                       + " ".join(f"x[{i}] = x[{i}] * inverse;" for i in block) + " }")
        # n = x/|x|: λₓ = (λₙ − n (n·λₙ)) / |x|
        reverse.append("{ const U inverse = T(1) / vsqrt(" + sq + "); "
                       + " ".join(f"const U n{c} = x[{i}] * inverse;" for c, i in enumerate(block))
                       + " const U dot = " + " + ".join(f"n{c} * lam[{i}]" for c, i in enumerate(block)) + "; "
                       + " ".join(f"lam[{i}] = (lam[{i}] - n{c} * dot) * inverse;" for c, i in enumerate(block)) + " }")
    return forward, reverse


def _adaptive_source(template: str, invariant: list, parts: dict, joints, dtype, tab, harmonics=None) -> str:
    helpers, attempt = _ADAPTIVE_ATTEMPT.split("//@@ATTEMPT\n")
    text = template.replace("@HELPERS@", helpers).replace("@ATTEMPT@", attempt)
    dense = np.array(tab.dense)
    S = tab.stages
    A = [list(row) + [0.0] * (S - len(row)) for row in tab.a]
    forward, reverse = _projection(joints)
    parts = {**parts, "PROJECT": forward, "PROJECT_VJP": reverse}
    text = (text.replace("@S@", str(S)).replace("@D@", str(dense.shape[1])).replace("@A@", _c_array(A))
            .replace("@E@", _c_array(tab.e)).replace("@P@", _c_array(dense.tolist())).replace("@C@", _c_array(list(tab.c))))
    return _run_source(text, invariant, parts, joints, dtype, harmonics)


def generate_adaptive(tree, joints, dtype, tab, harmonics=None) -> str:
    """C++ source of a whole adaptive solve by the pair ``tab`` (:data:`_ADAPTIVE_BLOCK`);
    ``harmonics``: that of a Fourier-series joint torque (``None``: none)."""
    em, invariant, lines, _, outputs = _field_program(tree, joints, harmonics=harmonics)
    field = lines + [f"f[{i}] = {_symbol_value(x)};" for i, x in enumerate(outputs)]
    return _adaptive_source(_ADAPTIVE_BLOCK, invariant, {"FIELD": field}, joints, dtype, tab, harmonics)


def generate_adaptive_vjp(tree, joints, dtype, tab, harmonics=None) -> str:
    """C++ source of the reverse sweep of :func:`generate_adaptive` (:data:`_ADAPTIVE_VJP_BLOCK`):
    the field and the reverse-mode program of the field (cotangents ``lf`` of ``(q̇, a, P)`` to
    those of ``(q, v)`` in ``r``)."""
    em, invariant, lines, _, outputs = _field_program(tree, joints, harmonics=harmonics)
    field = lines + [f"f[{i}] = {_symbol_value(x)};" for i, x in enumerate(outputs)]
    rev, _, rev_lines, (q, v), rev_outputs = _field_program(tree, joints, derivative="vjp", harmonics=harmonics)
    primal = list(rev.ops)
    cts = _carried(rev, "lf", len(rev_outputs), "lf")
    pairs = [(o, c) for o, c in zip(rev_outputs, cts) if isinstance(o, Sym)]
    adj = adjoint_program(primal, active_values(primal, {"q", "v"}), pairs)
    body = _hoisted(rev.lines[len(invariant):])
    body += [f"r[{i}] = {_symbol_value(adj.get(x.name, 0.0))};" for i, x in enumerate(list(q) + list(v))]
    return _adaptive_source(_ADAPTIVE_VJP_BLOCK, invariant, {"FIELD": field, "FIELD_VJP": body}, joints, dtype, tab,
                            harmonics)
