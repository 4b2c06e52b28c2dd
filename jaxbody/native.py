"""The native kernel: forward dynamics of a tree compiled to machine code, called from XLA.

XLA's CPU backend runs a traced program as a sequence of fused loops, each writing its
outputs to memory; for multibody dynamics — thousands of scalar operations along short
chains of bodies — that is dominated by memory traffic and per-loop overhead, not by
arithmetic (docs/performance.md). The native kernel removes both: the same algorithm as
the unrolled kernel (:mod:`jaxbody.unrolled`: kinematics root to leaves, composite
(augmented) inertias and subtree forces leaves to root, the tree-sparse ``LᵀDL``
factorisation), written out at build time for the model's static tree, is emitted as C++
and compiled once per tree with the system's C++ compiler. Every intermediate stays in
registers; one call evaluates a whole batch of states, split over the CPU cores.

How it plugs into JAX:

* **Code generation.** :func:`jaxbody.unrolled._bias_and_mass` and ``_ltdl_solve`` run on
  *symbolic* scalars (:class:`_Sym`) instead of arrays; every operation appends one line
  of C++. Structural zeros and ones are folded as in the unrolled kernel and repeated
  expressions are shared. The model's parameters (offsets, axes, masses, centres of mass,
  inertias, armature, ``qpos0``) are *inputs* of the compiled function, not constants, so
  one compilation serves every parameter value, batches over parameters and gradients
  with respect to them.
* **XLA FFI.** The compiled function is registered as an XLA foreign-function target
  (:func:`jax.ffi.ffi_call`); XLA calls it inside jitted programs and solver loops.
* **Batches.** A :func:`jax.custom_batching.custom_vmap` rule turns ``vmap`` (nested or
  not) into one call over the stacked states; inputs that are not batched (the model under
  a ``vmap`` over states) are passed once and read with stride zero.
* **Derivatives.** The generated program is differentiated at build time too (on first
  use): a forward-mode pass emits the tangent of every operation along ``(dq, dv, dτ)``
  (:func:`_tangent_program`), a reverse-mode pass the adjoint of every value that depends on
  the state, last operation first (:func:`_adjoint_program`); each is compiled like the
  forward program. The reverse-mode program differentiates forward dynamics implicitly: with
  ``a₀`` the computed acceleration and ``M = LᵀDL`` its factor held constant, it reverses
  ``a₀ + M⁻¹ (τ − ID(q, v, a₀))`` (``ID``: inverse dynamics by the Newton–Euler passes), whose
  derivative is that of ``a``, so its reverse sweep goes through the Newton–Euler passes once
  and one solve with the factor, not through the composite inertias and the factorisation.
  For trees of hinges and slides without body loads, the adjoint of those passes is emitted
  in closed form (:func:`jaxbody.unrolled._inverse_dynamics_vjp`, about half the operations
  of their operation-by-operation reverse). A :func:`jax.custom_jvp` rule takes the value from the native call and the
  tangent along the state and force from a primitive that is linear in the tangents, runs
  the forward-mode program, and transposes to the reverse-mode one (so ``jvp``/``jacfwd``
  and ``grad``/``vjp``/``jacrev``, under ``vmap`` too, are native calls). Tangents of the
  model's parameters, gravity and body loads come from the vectorised JAX kernel
  (:mod:`jaxbody.kernels`), which computes the same function, as do the tangents of trees
  above :data:`MAX_DERIVATIVE_DOFS`; second derivatives differentiate the same linear map
  written in JAX on the unrolled kernel (:mod:`jaxbody.unrolled`).

* **Whole solves.** A fixed-step RK4 solve is one program too (:func:`rk4_rollout`, mode
  ``"rk4_run"``): each block of states is loaded once and carried in registers through every
  step (each lane with its own times, step count and failure flag), with diffrax's step times,
  the quaternions renormalised after each step. Its reverse sweep (:func:`rk4_rollout_vjp`,
  ``"rk4_run_vjp"``) recomputes the steps between checkpoints that the forward call wrote and
  runs the reverse-mode program of each step, last first: the gradient with respect to the
  initial state. :func:`jaxbody.simulate` takes both where a solve keeps only its end state.

It needs a C++17 compiler (``g++``, or ``$CXX``) when a tree is first used; compiled
kernels are cached in ``$JAXBODY_CACHE_DIR`` (default ``~/.cache/jaxbody``) under a hash of
their source. :func:`available` says whether the kernel can be used here; with
``kernel="auto"`` jaxbody falls back to the vectorised kernel where it cannot.
"""

import contextlib
import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

try:  # POSIX: builders of the same library in several processes take turns (_build)
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

from . import unrolled
from ._types import Array, ArrayLike, Float
from .model import Model

__all__ = ["MAX_DOFS", "applies", "available", "checkpoint_layout", "energies", "forward_dynamics", "parameter_vector",
           "rk4_rollout", "rk4_rollout_checkpointed", "rk4_rollout_vjp", "rk4_step", "threads"]

#: Largest number of DoFs ``kernel="auto"`` gives the native kernel. The generated code grows
#: with the mass-matrix entries on each DoF's ancestor chain and their factorisation (for a
#: chain, quadratically and cubically): the 7-DoF Panda arm compiles in about 4 s, a 20-link
#: chain in about 25 s (once; cached on disk). Above this the vectorised kernel (whose program
#: does not grow with the tree) serves.
MAX_DOFS = 24

_lock = threading.RLock()


# ----------------------------------------------------------------------------- symbolic scalars
class _Emitter:
    """Collects the lines of one generated function and shares repeated expressions.

    Besides the C++ lines it records the program as operations ``(outputs, kind, args)`` in
    order, so that its derivatives can be generated from it (:func:`_tangent_program`,
    :func:`_adjoint_program`).
    """

    def __init__(self):
        self.lines: list[str] = []
        self.memo: dict[str, "_Sym"] = {}
        self.ops: list[tuple] = []
        # value name -> (group, index) of the outputs of a hand-differentiated block
        # (:func:`_inverse_dynamics_block`): the reverse pass emits the block's adjoint rule
        # instead of reversing the operations inside it
        self.blocks: dict[str, tuple[dict, int]] = {}

    def emit(self, expr: str, kind: str = "", args: tuple = ()) -> "_Sym":
        sym = self.memo.get(expr)
        if sym is None:
            name = f"t{len(self.lines)}"
            self.lines.append(f"const U {name} = {expr};")
            sym = self.memo[expr] = _Sym(name, self)
            self.ops.append((sym, kind, args))
        return sym

    def sincos(self, x):
        key = f"sincos({x.name})"
        pair = self.memo.get(key)
        if pair is None:
            n = len(self.lines)
            self.lines.append(f"U s{n}, c{n}; sc({x.name}, s{n}, c{n});")
            pair = self.memo[key] = (_Sym(f"s{n}", self), _Sym(f"c{n}", self))
            self.ops.append((pair, "sincos", (x,)))
        return pair


def _lit(x) -> str:
    if isinstance(x, _Sym):
        return x.name
    return f"T({float(x)!r})"


def _value(x) -> str:
    """``x`` as a vector expression (a constant broadcast to every lane)."""
    return x.name if isinstance(x, _Sym) else f"(U{{}} + T({float(x)!r}))"


class _Sym:
    """A scalar of the generated program: a C++ name; arithmetic emits code.

    Python floats mixed in are constants known at generation time (the unrolled kernel's
    structural ``0.0``/``1.0``); they fold as in :func:`jaxbody.unrolled._add` and friends.
    """

    symbolic = True
    __slots__ = ("name", "em")

    def __init__(self, name: str, em: _Emitter):
        self.name, self.em = name, em

    def _bin(self, op: str, a, b, commutative: bool):
        x, y = _lit(a), _lit(b)
        if commutative and y < x:
            x, y = y, x
        return self.em.emit(f"{x} {op} {y}", op, (a, b))

    def __add__(self, o):
        if isinstance(o, float | int) and o == 0:
            return self
        return self._bin("+", self, o, True)

    __radd__ = __add__

    def __sub__(self, o):
        if isinstance(o, float | int) and o == 0:
            return self
        return self._bin("-", self, o, False)

    def __rsub__(self, o):
        if isinstance(o, float | int) and o == 0:
            return -self
        return self._bin("-", o, self, False)

    def __mul__(self, o):
        if isinstance(o, float | int):
            if o == 0:
                return 0.0
            if o == 1:
                return self
        return self._bin("*", self, o, True)

    __rmul__ = __mul__

    def __truediv__(self, o):
        if isinstance(o, float | int) and o == 1:
            return self
        return self._bin("/", self, o, False)

    def __rtruediv__(self, o):
        return self._bin("/", o, self, False)

    def __neg__(self):
        return self.em.emit(f"-{self.name}", "neg", (self,))

    def cos(self):
        return self.em.sincos(self)[1]

    def sqrt(self):
        return self.em.emit(f"vsqrt({self.name})", "sqrt", (self,))

    def atan2(self, x):
        """``atan2(self, x)``."""
        return self.em.emit(f"vatan2({self.name}, {_lit(x)})", "atan2", (self, x))

    def where_negative(self, a, b):
        """``a`` where ``self < 0``, else ``b`` (lane by lane)."""
        return self.em.emit(f"({self.name} < T(0)) ? {_value(a)} : {_value(b)}", "select", (self, a, b))

    def sin(self):
        return self.em.sincos(self)[0]

    def stop(self):
        """The same value with no derivative (the derivative programs treat it as a constant)."""
        return self.em.emit(f"{self.name} /* constant */", "stop", (self,))


def _with_derivative(value, derivative):
    """``value``, whose derivative the derivative programs take to be ``derivative``'s: the
    computation of ``derivative``'s own value is left to the compiler to drop where nothing else
    reads it."""
    if not isinstance(derivative, _Sym):
        return value
    return derivative.em.emit(f"{_value(value)} /* derivative: {derivative.name} */", "attach", (value, derivative))


def _stop(x):
    return x.stop() if isinstance(x, _Sym) else x


class _SymbolicModel:
    """What the unrolled passes read of a model, with every parameter a symbol ``p[i]``."""

    FIELDS = ("body_pos", "body_quat", "body_mass", "body_com", "body_inertia", "joint_pos", "joint_axis", "dof_armature", "qpos0")

    def __init__(self, tree, joints, em: _Emitter, slot: int = 3):
        n = sum(int(np.prod(shape)) for shape in _field_shapes(tree, joints))
        p = np.empty(n, dtype=object)
        p[:] = _inputs(em, "p", n, slot)
        _unflatten_parameters(self, tree, joints, p, np.reshape)


def _unflatten_parameters(target, tree, joints, flat, reshape) -> None:
    """Set the fields the unrolled passes read on ``target``, sliced from the flat parameter
    vector ``flat`` (order of :func:`parameter_vector`) with ``reshape``."""
    target.tree, target.joints = tree, joints
    target.n_body, target.nv, target.nq = tree.n_body, joints.nv, joints.nq
    offset = 0
    for name, shape in zip(_SymbolicModel.FIELDS, _field_shapes(tree, joints)):
        size = int(np.prod(shape))
        setattr(target, name, reshape(flat[offset : offset + size], shape))
        offset += size


# the operands of every generated function, in order: the state and the model, then (for the
# derivatives) the tangents of (q, v, f) or the cotangent of the acceleration. The RK4 step's
# programs take the step h and the joint springs and dampers after the model, then the tangents
# or the seven cotangents.
_SLOTS = {"q": 0, "v": 1, "f": 2, "p": 3, "g": 4, "ext": 5, "dq": 6, "dv": 7, "df": 8, "ct": 6}
_STEP_SLOTS = {"q": 0, "v": 1, "f": 2, "p": 3, "g": 4, "ext": 5, "h": 6, "k": 7, "r": 8, "d": 9, "dq": 10, "dv": 11, "df": 12, "ct": 10}
# the whole-solve program (_generate_run): the state, the model, springs and dampers, the work
# reached so far and the schedule
_RUN_SLOTS = {"q": 0, "v": 1, "f": 2, "p": 3, "g": 4, "ext": 5, "k": 6, "r": 7, "d": 8, "w": 9, "s": 10}
# the energy program: the state, the model, gravity and the joint springs
_ENERGY_SLOTS = {"q": 0, "v": 1, "p": 2, "g": 3, "k": 4, "r": 5}

#: Programs: forward dynamics and one RK4 step, each with its forward- and reverse-mode
#: derivative, and the energies of a state (no derivative programs: their tangents are rare).
MODES = ("fd", "jvp", "vjp", "rk4", "rk4_jvp", "rk4_vjp", "energy", "rk4_run", "rk4_run_vjp")


def _widths(joints, mode: str) -> tuple:
    """Row widths of a program's results."""
    nq, nv = joints.nq, joints.nv
    return {
        "fd": (nv,),
        "jvp": (nv,),
        "vjp": (nq, nv, nv),
        "rk4": (nq, nv, nq, nv, nq, nv, 3),
        "rk4_jvp": (nq, nv, nq, nv, nq, nv, 3),
        "rk4_vjp": (nq, nv, nv),
        "energy": (3,),
        "rk4_run": (nq, nv, 1, 3),
        "rk4_run_vjp": (nq, nv),
    }[mode]


def _residual_count(mode: str) -> int:
    """Operands a program takes before its tangents: (q, v, f, p, g, ext), then for a step h and
    the springs and dampers (stiffness, reference, damping)."""
    return 10 if mode.startswith("rk4") else 6


def _qdot_scalars(joints, q: list, v: list) -> list:
    """``q̇`` for joint rates ``v`` on lists of scalars (quaternions: ``q̇ = ½ q ⊗ (0, ω)``), as
    :func:`jaxbody.kinematics.qpos_rate`; works on symbols and on JAX scalars alike."""
    qd = [0.0] * joints.nq
    for kind, _, qa, da in joints.kind_groups():
        for qi, di in zip(qa.tolist(), da.tolist()):
            if kind.quaternion is None:
                qd[qi] = v[di]
                continue
            n = kind.translation
            for k in range(n):
                qd[qi + k] = v[di + k]
            i = qi + kind.quaternion
            aw, ax, ay, az = q[i], q[i + 1], q[i + 2], q[i + 3]
            wx, wy, wz = v[di + n], v[di + n + 1], v[di + n + 2]
            qd[i] = 0.5 * (-(ax * wx) - ay * wy - az * wz)
            qd[i + 1] = 0.5 * (aw * wx + ay * wz - az * wy)
            qd[i + 2] = 0.5 * (aw * wy - ax * wz + az * wx)
            qd[i + 3] = 0.5 * (aw * wz + ax * wy - ay * wx)
    return qd


def _where_negative(c, a, b):
    """``a`` where ``c < 0``, else ``b``: on symbols, JAX scalars or constants."""
    if isinstance(c, _Sym):
        if not isinstance(a, _Sym) and not isinstance(b, _Sym) and a == b:
            return a
        return c.where_negative(a, b)
    if isinstance(c, float | int):
        return a if c < 0 else b
    return jnp.where(c < 0, a, b)


def _sqrt(x):
    return x.sqrt() if isinstance(x, _Sym) else jnp.sqrt(x)


def _atan2(y, x):
    return y.atan2(x) if isinstance(y, _Sym) else jnp.arctan2(y, x)


def _quat_spring_displacement(q: list, r: list) -> list:
    """Rotation vector of ``r⁻¹ ⊗ q/|q|`` on scalars, the short way round, as
    :func:`jaxbody.kernels._quat_log_diff` (MuJoCo's ``mju_subQuat``; the same safe branches)."""
    n = _sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    aw, ax, ay, az = (x / n for x in q)
    bw, bx, by, bz = r[0], -r[1], -r[2], -r[3]
    d = [
        bw * aw - bx * ax - by * ay - bz * az,
        bw * ax + bx * aw + by * az - bz * ay,
        bw * ay - bx * az + by * aw + bz * ax,
        bw * az + bx * ay - by * ax + bz * aw,
    ]
    sign = _where_negative(d[0], -1.0, 1.0)
    d = [x * sign for x in d]
    s2 = d[1] * d[1] + d[2] * d[2] + d[3] * d[3]
    s = _sqrt(_where_negative(-s2, s2, 1.0))  # s2 > 0, else 1: no infinite derivative at zero
    scale = _where_negative(1e-30 - s2, 2.0 * _atan2(s, d[0]) / s, 2.0)
    return [d[1] * scale, d[2] * scale, d[3] * scale]


def _spring_displacements(joints, q: list, reference: list) -> list:
    """``(joint, DoF, q ⊖ q_ref)`` of every DoF on scalars: a coordinate's difference, or for the
    rotation of a ball or free joint a component of the rotation vector of ``q_ref⁻¹ ⊗ q``."""
    out = []
    for kind, js, qa, da in joints.kind_groups():
        for j, qi, di in zip(js.tolist(), qa.tolist(), da.tolist()):
            if kind.quaternion is None:
                out.append((j, di, q[qi] - reference[qi]))
                continue
            n = kind.translation
            for k in range(n):
                out.append((j, di + k, q[qi + k] - reference[qi + k]))
            i = qi + kind.quaternion
            disp = _quat_spring_displacement(q[i : i + 4], reference[i : i + 4])
            for k in range(3):
                out.append((j, di + n + k, disp[k]))
    return out


def _spring_potential(joints, q: list, stiffness: list, reference: list):
    """``½ Σ_j k_j |q_j ⊖ q_ref,j|²`` on scalars, as the potential of :class:`jaxbody.JointSprings`."""
    total = 0.0
    for j, _, disp in _spring_displacements(joints, q, reference):
        total = total + stiffness[j] * (disp * disp)
    return 0.5 * total


def _joint_force(joints, q: list, v: list, force: list, stiffness: list, reference: list, damping: list) -> tuple:
    """``force`` plus joint springs ``−k (q ⊖ q_ref)`` (quaternion joints: rotation-vector
    difference) and dampers ``−c v`` on lists of scalars, and the dampers' power ``(−c v)·v``;
    as :class:`jaxbody.JointSprings` and :class:`jaxbody.JointDampers`."""
    total = list(force)
    for j, d, disp in _spring_displacements(joints, q, reference):
        total[d] = total[d] - stiffness[j] * disp
    power = 0.0
    for i in range(len(v)):
        damper = -(damping[i] * v[i])
        total[i] = total[i] + damper
        power = power + damper * v[i]
    return total, power


def _rk4_scalars(field, joints, q: list, v: list, h) -> tuple:
    """One classical RK4 step of ``(q̇, v̇, ẇ) = (q̇(q, v), a, P)`` on lists of scalars, where
    ``field(q, v) = (a, P)`` (``P``: the dampers' power, integrated as work). Returns ``(q1, v1,
    k1q, k1v, k4q, k4v, (Δw, k1w, k4w))``, the stage increments ``k = h·f`` being those of the
    first and last stage (the dense output's end slopes). The same arithmetic, in the same
    order, as :class:`jaxbody.simulation.RK4Stages`."""

    def increment(q, v):
        a, power = field(q, v)
        return [h * x for x in _qdot_scalars(joints, q, v)], [h * x for x in a], h * power

    def ahead(k, c):
        return [y + c * d for y, d in zip(q, k[0])], [y + c * d for y, d in zip(v, k[1])]

    k1 = increment(q, v)
    k2 = increment(*ahead(k1, 0.5))
    k3 = increment(*ahead(k2, 0.5))
    k4 = increment(*ahead(k3, 1.0))
    y1 = [[y + (a + 2 * b + 2 * c + d) / 6 for y, a, b, c, d in zip(y0, *ks)] for y0, *ks in zip((q, v), k1, k2, k3, k4)]
    work = (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2]) / 6
    return y1[0], y1[1], k1[0], k1[1], k4[0], k4[1], [work, k1[2], k4[2]]


def _declared(em: _Emitter, name: str, n: int, source) -> list:
    """``n`` input scalars ``name_i`` of the program, declared as ``source(i)`` (a C++ expression)."""
    out = []
    for i in range(n):
        em.lines.append(f"const U {name}_{i} = {source(i)};")
        sym = _Sym(f"{name}_{i}", em)
        em.ops.append((sym, "input", (name,)))
        out.append(sym)
    return out


def _inputs(em: _Emitter, name: str, n: int, slot: int) -> list:
    """``n`` scalars of operand ``slot``, loaded (one lane per state) where they are emitted."""
    return _declared(em, name, n, lambda i: f"ld({slot}, {i})")


def _field_shapes(tree, joints):
    nb, nj = tree.n_body, joints.n_joint
    return ((nb, 3), (nb, 4), (nb,), (nb, 3), (nb, 3, 3), (nj, 3), (nj, 3), (joints.nv,), (joints.nq,))


def parameter_vector(model: Model) -> Float[Array, " n_param"]:
    """The model's parameters flattened in the order the native kernel reads them."""
    return jnp.concatenate([jnp.ravel(getattr(model, name)) for name in _SymbolicModel.FIELDS])


# ----------------------------------------------------------------------------- code generation
# Two translation units: the per-tree kernel (plain C++, quick to compile) and, once per dtype,
# the XLA FFI handler (XLA's FFI headers take longer to parse than a small tree takes to
# optimise). The handler receives the kernel's address as a call attribute.
_COMMON = r"""
#include <cstdint>
using T = @T@;
constexpr int MAX_IN = 24, MAX_OUT = 8;
// operand k of state b: x[k] + b * s[k] (rows of a (batch, n) array; s = 0: shared by all
// states); result j of state b: y[j] + b * n[j]
struct Inputs {
  const T* x[MAX_IN];
  int64_t s[MAX_IN];
  T* y[MAX_OUT];
  int64_t n[MAX_OUT];
};
typedef void (*Range)(const Inputs*, int64_t, int64_t);
"""

_KERNEL = r"""
#include <cmath>
#include <type_traits>
@COMMON@
// states per block: one vector register of lanes, VECTOR_BYTES wide (jaxbody.native.BUILDS):
// scalar code for a single state (a vector build would carry every value in a whole register,
// and the long derivative programs keep most of them on the stack), 256-bit lanes for small
// batches, 512-bit lanes (with AVX-512) for larger ones
#define JB_VECTOR_BYTES @VECTOR_BYTES@
constexpr int VECTOR_BYTES = JB_VECTOR_BYTES == 0 ? int(sizeof(T)) : JB_VECTOR_BYTES;
constexpr int W = VECTOR_BYTES / sizeof(T);
typedef T V __attribute__((vector_size(sizeof(T) * W)));
typedef std::conditional<sizeof(T) == 8, int64_t, int32_t>::type IntT;
typedef IntT I __attribute__((vector_size(sizeof(T) * W)));

// 512-bit blocks read a batched operand and write a result with one gather or scatter
// instruction per scalar (lane l: row b0 + l of a row-major (batch, n) array): per-lane loads
// and stores would cost the same per state in either precision, a larger share of float32's
// shorter time per state
#if JB_VECTOR_BYTES == 64 && defined(__AVX512F__)
#include <immintrin.h>
#define JB_GATHER 1
static inline V gather_rows(const float* base, int64_t stride, int n) {
  const __m512i lane = _mm512_min_epi32(_mm512_set_epi32(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0),
                                        _mm512_set1_epi32(n - 1));
  return (V)_mm512_i32gather_ps(_mm512_mullo_epi32(lane, _mm512_set1_epi32(int(stride))), base, 4);
}
static inline V gather_rows(const double* base, int64_t stride, int n) {
  const __m256i lane = _mm256_min_epi32(_mm256_set_epi32(7, 6, 5, 4, 3, 2, 1, 0), _mm256_set1_epi32(n - 1));
  return (V)_mm512_i32gather_pd(_mm256_mullo_epi32(lane, _mm256_set1_epi32(int(stride))), base, 8);
}
static inline void scatter_rows(float* base, int64_t stride, int n, V x) {
  const __m512i row = _mm512_mullo_epi32(_mm512_set_epi32(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0),
                                         _mm512_set1_epi32(int(stride)));
  _mm512_mask_i32scatter_ps(base, __mmask16((1u << n) - 1u), row, (__m512)x, 4);
}
static inline void scatter_rows(double* base, int64_t stride, int n, V x) {
  const __m256i row = _mm256_mullo_epi32(_mm256_set_epi32(7, 6, 5, 4, 3, 2, 1, 0), _mm256_set1_epi32(int(stride)));
  _mm512_mask_i32scatter_pd(base, __mmask8((1u << n) - 1u), row, (__m512d)x, 8);
}
#else
#define JB_GATHER 0
#endif

// sine and cosine of every lane: Cody-Waite reduction by pi/2 (two-part constant, fused
// multiply-adds) and Cephes' minimax polynomials on [-pi/4, pi/4] (six terms in double, three in
// single precision), about 1 ulp for the angles
// of joints (|x| < 1e5); larger angles (and NaN) go lane by lane through libm
static inline void sincos_(double x, double* s, double* c) { sincos(x, s, c); }
static inline void sincos_(float x, float* s, float* c) { sincosf(x, s, c); }

static inline void sincos_lanes(V x, V& s, V& c, int n) {
  T sl = 0, cl = 0;
  for (int l = 0; l < W; ++l) {
    if (l < n) {
      sincos_(x[l], &sl, &cl);
    }
    s[l] = sl;
    c[l] = cl;
  }
}

static inline void vsincos(V x, V& s, V& c, int n) {
  {
    bool small = true;
    for (int l = 0; l < W; ++l) small &= std::fabs(x[l]) < T(1e5);  // false for NaN: libm's NaN
    if (small) {
      // 1.5 * 2^(mantissa bits): adding it rounds to an integer, held in the low bits
      const T magic = sizeof(T) == 8 ? T(6755399441055744.0) : T(12582912.0f);
      const T pio2_hi = sizeof(T) == 8 ? T(1.5707963267948966) : T(1.57079637f);
      const T pio2_lo = sizeof(T) == 8 ? T(6.123233995736766e-17) : T(-4.37113883e-8f);
      const V shifted = x * T(0.63661977236758134308) + magic;
      const V k = shifted - magic;
      I quadrant;
      __builtin_memcpy(&quadrant, &shifted, sizeof(V));
      quadrant &= 3;
      V r = x - k * pio2_hi;  // contracted to a fused multiply-add
      r = r - k * pio2_lo;
      const V z = r * r;
      V ps, pc;
      if constexpr (sizeof(T) == 4) {
        // Cephes' single-precision polynomials (sinf, cosf): three terms each suffice
        ps = V{} + T(-1.9515295891e-4f);
        ps = ps * z + T(8.3321608736e-3f);
        ps = ps * z + T(-1.6666654611e-1f);
        pc = V{} + T(2.443315711809948e-5f);
        pc = pc * z + T(-1.388731625493765e-3f);
        pc = pc * z + T(4.166664568298827e-2f);
      } else {
        ps = V{} + T(1.58962301576546568060e-10);
        ps = ps * z + T(-2.50507477628578072866e-8);
        ps = ps * z + T(2.75573136213857245213e-6);
        ps = ps * z + T(-1.98412698295895385996e-4);
        ps = ps * z + T(8.33333333332211858878e-3);
        ps = ps * z + T(-1.66666666666666307295e-1);
        pc = V{} + T(-1.13585365213876817300e-11);
        pc = pc * z + T(2.08757008419747316778e-9);
        pc = pc * z + T(-2.75573141792967388112e-7);
        pc = pc * z + T(2.48015872888517045348e-5);
        pc = pc * z + T(-1.38888888888730564116e-3);
        pc = pc * z + T(4.16666666666665929218e-2);
      }
      const V sr = r + r * z * ps;
      const V cr = T(1.0) - T(0.5) * z + z * z * pc;
      const I swap = (quadrant & 1) != 0;
      const V s0 = swap ? cr : sr, c0 = swap ? sr : cr;
      s = ((quadrant & 2) != 0) ? -s0 : s0;
      c = (((quadrant + 1) & 2) != 0) ? -c0 : c0;
      return;
    }
  }
  sincos_lanes(x, s, c, n);
}

// square root and two-argument arc tangent of every lane (the springs of quaternion joints)
static inline V vsqrt(V x) {
  V r;
  for (int l = 0; l < W; ++l) r[l] = std::sqrt(x[l]);
  return r;
}
static inline V vatan2(V y, V x) {
  V r;
  for (int l = 0; l < W; ++l) r[l] = std::atan2(y[l], x[l]);
  return r;
}

// the generated function of the states b0 .. b0 + n - 1 (n <= W); lane l is state b0 + min(l, n - 1)
static void fd_block(const Inputs& in, int64_t b0, int n) {
@ACCESS@
@BODY@
}

extern "C" void jaxbody_range(const Inputs* in, int64_t b0, int64_t b1) {
  for (int64_t b = b0; b < b1; b += W) fd_block(*in, b, b1 - b < W ? int(b1 - b) : W);
}
"""

# how a block reads its operands (ld), writes its results (st) and takes sines and cosines (sc)
_ACCESS = r"""  typedef V U;
  int64_t idx[W];
  for (int l = 0; l < W; ++l) idx[l] = b0 + (l < n ? l : n - 1);
  auto ld = [&](int k, int i) {
    const T* x = in.x[k];
    const int64_t s = in.s[k];
    // an operand shared by all states (the model under a vmap over states), or a block of
    // one state: one load broadcast to every lane; else one load per lane
    if (s == 0) return U{} + x[i];
    if (n == 1) return U{} + x[b0 * s + i];
#if JB_GATHER
    return gather_rows(x + b0 * s + i, s, n);
#else
    U r;
    for (int l = 0; l < W; ++l) r[l] = x[idx[l] * s + i];
    return r;
#endif
  };
  auto st = [&](int j, int i, U x) {
#if JB_GATHER
    scatter_rows(in.y[j] + b0 * in.n[j] + i, in.n[j], n, x);
#else
    for (int l = 0; l < n; ++l) in.y[j][(b0 + l) * in.n[j] + i] = x[l];
#endif
  };
  auto sc = [n](U x, U& s, U& c) { vsincos(x, s, c, n); };"""

# A whole fixed-step RK4 solve per block of states (:func:`_generate_run`): the state stays in
# registers (or on the stack) from the first step to the last; each lane keeps its own time,
# step count and failure flag, and the block ends when every lane is done. Step times, the
# clip to t1, the quaternion renormalisation after each step and the hold of a trajectory at
# its first non-finite step are those of jaxbody.simulation's fixed-step solve (diffrax's
# ConstantStepSize): t_k = t0 + (t1 - t0) * (k / N), t_N = t1, a time within 100 ulp below t1
# rounded to t1. Operands: q, v, f, p, g, ext, k, r, d, the work w0 and the schedule (t0, t1, N,
# t1 - 100 ulp, the step budget, dt0, frozen, steps per checkpoint); results: q, v, w, (t reached,
# steps, failed) and, when asked for, the checkpoints of the reverse sweep (_RUN_VJP_BLOCK). A
# frozen lane (an input that failed simulate's checks) takes its steps without moving.
_RUN_BLOCK = r"""
static void run_block(const Inputs& in, int64_t b0, int n) {
@ACCESS@
@INVARIANT@
  U qc[@NQ@], vc[@NV@], qn[@NQ@], vn[@NV@];
  for (int i = 0; i < @NQ@; ++i) qc[i] = ld(0, i);
  for (int i = 0; i < @NV@; ++i) vc[i] = ld(1, i);
  U wc = ld(9, 0);
  const U t0 = ld(10, 0), t1 = ld(10, 1), steps = ld(10, 2), t1_floor = ld(10, 3), limit = ld(10, 4), dt0 = ld(10, 5);
  const I frozen = ld(10, 6) != T(0);
  U tprev = t0, tnext = t0 + dt0;
  tnext = tnext < t1 ? tnext : t1;
  U count = U{};
  I failed = I{};
  // checkpoints (a fifth result): every `every` steps
  const bool store = in.y[4] != nullptr;
  const int64_t every = store ? int64_t(ld(10, 7)[0]) : 1;
  int64_t it = 0;
  for (;;) {
    const I active = (tprev < t1) & (count < limit) & (failed == 0);
    bool any = false;
    for (int l = 0; l < W; ++l) any |= active[l] != 0;
    if (!any) break;
    if (store && it % every == 0) {
      // a checkpoint: the state at the start of this step and its times (the reverse sweep
      // recomputes the steps from here); active lanes all have taken `it` steps
      const int64_t at = (it / every) * (@NQ@ + @NV@ + 2);
      for (int i = 0; i < @NQ@; ++i) st(4, at + i, qc[i]);
      for (int i = 0; i < @NV@; ++i) st(4, at + @NQ@ + i, vc[i]);
      st(4, at + @NQ@ + @NV@, tprev);
      st(4, at + @NQ@ + @NV@ + 1, tnext);
    }
    ++it;
    const U h = tnext - tprev;
    U dw;
    {
@BODY@
    }
    const U wn = wc + dw;
    I finite = (wn - wn) == T(0);  // false for inf and NaN
    for (int i = 0; i < @NQ@; ++i) finite &= (qn[i] - qn[i]) == T(0);
    for (int i = 0; i < @NV@; ++i) finite &= (vn[i] - vn[i]) == T(0);
    finite |= frozen;
    // a lane that is done keeps its state, and so does a frozen one (its time runs on)
    const I moving = active & (frozen == 0);
    for (int i = 0; i < @NQ@; ++i) qc[i] = moving ? qn[i] : qc[i];
    for (int i = 0; i < @NV@; ++i) vc[i] = moving ? vn[i] : vc[i];
    wc = moving ? wn : wc;
    count = active ? count + T(1) : count;
    failed |= active & (finite == 0);
    const U next = count + T(1);
    U tn = t0 + (t1 - t0) * (next / steps);
    tn = next == steps ? t1 : tn;
    tn = tn > t1_floor ? t1 : tn;
    const U tp = tnext < t1 ? tnext : t1;
    tprev = active ? tp : tprev;
    tnext = active ? tn : tnext;
  }
  for (int i = 0; i < @NQ@; ++i) st(0, i, qc[i]);
  for (int i = 0; i < @NV@; ++i) st(1, i, vc[i]);
  st(2, 0, wc);
  st(3, 0, tprev);
  st(3, 1, count);
  st(3, 2, failed != 0 ? U{} + T(1) : U{});
}

extern "C" void jaxbody_range(const Inputs* in, int64_t b0, int64_t b1) {
  for (int64_t b = b0; b < b1; b += W) run_block(*in, b, b1 - b < W ? int(b1 - b) : W);
}
"""

# The reverse sweep of a whole solve (reverse mode with respect to the initial state): for each
# segment of `every` steps, last first, the steps are recomputed from the segment's checkpoint
# (the forward program, so the same states) and kept; then the reverse-mode program of one step
# carries the cotangents of (q, v) back through them, the work's cotangent held (w1 = w0 + Δw).
# A lane's own steps are those it took (a frozen lane: none). Operands: those of _RUN_BLOCK, then
# the checkpoints, the forward's status, and the cotangents of the final q, v and w; results:
# the cotangents of the initial q and v.
_RUN_VJP_BLOCK = r"""
#include <memory>
static void vjp_block(const Inputs& in, int64_t b0, int n) {
@ACCESS@
@INVARIANT@
  constexpr int NS = @NQ@ + @NV@;
  U qc[@NQ@], vc[@NV@], qn[@NQ@], vn[@NV@], aq[@NQ@], av[@NV@], rq[@NQ@], rv[@NV@];
  const U t0 = ld(10, 0), t1 = ld(10, 1), steps = ld(10, 2), t1_floor = ld(10, 3);
  const I frozen = ld(10, 6) != T(0);
  const int64_t every = int64_t(ld(10, 7)[0]);
  const U taken = ld(12, 1);
  for (int i = 0; i < @NQ@; ++i) aq[i] = ld(13, i);
  for (int i = 0; i < @NV@; ++i) av[i] = ld(14, i);
  const U aw = ld(15, 0);
  int64_t total = 0;
  for (int l = 0; l < n; ++l) total = int64_t(taken[l]) > total ? int64_t(taken[l]) : total;
  std::unique_ptr<V[]> kept(new V[every * (NS + 1)]);  // a segment's states and step lengths
  for (int64_t seg = (total - 1) / every; seg >= 0 && total > 0; --seg) {
    const int64_t first = seg * every, end = first + every < total ? first + every : total;
    const int64_t at = seg * (NS + 2);
    for (int i = 0; i < @NQ@; ++i) qc[i] = ld(11, at + i);
    for (int i = 0; i < @NV@; ++i) vc[i] = ld(11, at + @NQ@ + i);
    U tprev = ld(11, at + NS), tnext = ld(11, at + NS + 1);
    for (int64_t r = first; r < end; ++r) {
      V* row = &kept[(r - first) * (NS + 1)];
      const U h = tnext - tprev;
      for (int i = 0; i < @NQ@; ++i) row[i] = qc[i];
      for (int i = 0; i < @NV@; ++i) row[@NQ@ + i] = vc[i];
      row[NS] = h;
      if (r + 1 == end) break;
      {
@STEP@
      }
      for (int i = 0; i < @NQ@; ++i) qc[i] = qn[i];
      for (int i = 0; i < @NV@; ++i) vc[i] = vn[i];
      // the times of the next step, as the forward loop takes them (after r + 1 steps)
      const U next = U{} + T(r + 2);
      U tn = t0 + (t1 - t0) * (next / steps);
      tn = next == steps ? t1 : tn;
      tn = tn > t1_floor ? t1 : tn;
      tprev = tnext < t1 ? tnext : t1;
      tnext = tn;
    }
    for (int64_t r = end - 1; r >= first; --r) {
      const V* row = &kept[(r - first) * (NS + 1)];
      const I active = ((U{} + T(r)) < taken) & (frozen == 0);
      {
        const V* bq = row;
        const V* bv = row + @NQ@;
        const U h = row[NS];
@BODY@
      }
      for (int i = 0; i < @NQ@; ++i) aq[i] = active ? rq[i] : aq[i];
      for (int i = 0; i < @NV@; ++i) av[i] = active ? rv[i] : av[i];
    }
  }
  for (int i = 0; i < @NQ@; ++i) st(0, i, aq[i]);
  for (int i = 0; i < @NV@; ++i) st(1, i, av[i]);
}

extern "C" void jaxbody_range(const Inputs* in, int64_t b0, int64_t b1) {
  for (int64_t b = b0; b < b1; b += W) vjp_block(*in, b, b1 - b < W ? int(b1 - b) : W);
}
"""

_HANDLER = r"""
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <mutex>
#include <thread>
#include <vector>
#include "xla/ffi/api/ffi.h"
@COMMON@
namespace ffi = xla::ffi;
constexpr ffi::DataType DT = @DT@;

// A persistent pool: a batch is cut into as many slices as threads; the calling thread runs
// the first, the workers the others (starting threads on every call would cost as much as a
// few hundred states). Between calls the workers spin (yielding the core to any other
// runnable thread) for up to SPIN_NS before they sleep on a condition variable, and so does the
// caller waiting for them: the next call of a simulation comes a few tens of microseconds after
// the last (the integrator's own work on the batch), and waking a sleeping thread costs as much
// on a virtual machine. Every worker acknowledges every call, so a call's fields stay valid
// until all of them have read them.
class Pool {
 public:
  void run(Range range, const Inputs* in, int64_t batch, int64_t threads) {
    std::lock_guard<std::mutex> call(call_);  // one batch at a time (XLA may call from several devices)
    grow(threads - 1);
    const int64_t chunk = (batch + threads - 1) / threads;
    range_ = range, in_ = in, batch_ = batch, chunk_ = chunk, slices_ = threads;
    pending_.store(int64_t(workers_.size()), std::memory_order_relaxed);
    {
      std::lock_guard<std::mutex> lock(m_);
      generation_.fetch_add(1, std::memory_order_release);  // publishes the fields above
    }
    cv_.notify_all();  // no system call when every worker is spinning
    range(in, 0, chunk < batch ? chunk : batch);
    if (!spin([&] { return pending_.load(std::memory_order_acquire) == 0; })) {
      std::unique_lock<std::mutex> lock(m_);
      done_.wait(lock, [&] { return pending_.load(std::memory_order_acquire) == 0; });
    }
  }

 private:
  static constexpr int64_t SPIN_NS = @SPIN_NS@;
  template <class Ready>
  static bool spin(Ready ready) {
    if (ready()) return true;
    const auto until = std::chrono::steady_clock::now() + std::chrono::nanoseconds(SPIN_NS);
    for (;;) {
      for (int k = 0; k < 16; ++k) {
        if (ready()) return true;
#if defined(__x86_64__) || defined(__i386__)
        __builtin_ia32_pause();
#endif
      }
      if (std::chrono::steady_clock::now() > until) return ready();
      std::this_thread::yield();  // a core shared with other work gets it back at once
    }
  }
  void grow(int64_t n) {
    while (int64_t(workers_.size()) < n) {
      const int64_t slot = int64_t(workers_.size()) + 1;
      // a new worker starts at the calls made so far: the next one is its first
      const uint64_t seen = generation_.load(std::memory_order_relaxed);
      workers_.emplace_back([this, slot, seen] { work(slot, seen); });
      workers_.back().detach();
    }
  }
  void work(int64_t slot, uint64_t seen) {
    for (;;) {
      auto fresh = [&] { return generation_.load(std::memory_order_acquire) != seen; };
      if (!spin(fresh)) {
        std::unique_lock<std::mutex> lock(m_);
        cv_.wait(lock, fresh);
      }
      seen = generation_.load(std::memory_order_acquire);
      if (slot < slices_) {
        const int64_t b0 = slot * chunk_, b1 = b0 + chunk_ < batch_ ? b0 + chunk_ : batch_;
        if (b0 < b1) range_(in_, b0, b1);
      }
      if (pending_.fetch_sub(1, std::memory_order_acq_rel) == 1) {
        std::lock_guard<std::mutex> lock(m_);  // the caller checks pending_ under m_ before it sleeps
        done_.notify_one();
      }
    }
  }
  std::mutex call_, m_;
  std::condition_variable cv_, done_;
  std::vector<std::thread> workers_;
  Range range_ = nullptr;
  const Inputs* in_ = nullptr;
  int64_t batch_ = 0, chunk_ = 0, slices_ = 0;
  std::atomic<int64_t> pending_{0};
  std::atomic<uint64_t> generation_{0};
};

static Pool* pool() {
  static Pool* p = new Pool();  // never destroyed: workers outlive static destruction
  return p;
}

static ffi::Error fd_impl(ffi::RemainingArgs args, ffi::RemainingRets rets, int64_t kernel, int64_t threads) {
  const Range range = reinterpret_cast<Range>(kernel);
  if (args.size() > MAX_IN || rets.size() > MAX_OUT || rets.size() == 0)
    return ffi::Error(ffi::ErrorCode::kInvalidArgument, "jaxbody native kernel: too many operands");
  Inputs in{};
  for (size_t k = 0; k < args.size(); ++k) {
    auto x = args.get<ffi::AnyBuffer>(k);
    if (x.has_error()) return x.error();
    if (x->element_type() != DT || x->dimensions().size() != 2)
      return ffi::Error(ffi::ErrorCode::kInvalidArgument, "jaxbody native kernel: operands are 2-D, of the kernel's dtype");
    in.x[k] = static_cast<const T*>(x->untyped_data());
    in.s[k] = x->dimensions()[0] == 1 ? 0 : x->dimensions()[1];
  }
  int64_t batch = 0;
  for (size_t j = 0; j < rets.size(); ++j) {
    auto y = rets.get<ffi::AnyBuffer>(j);
    if (y.has_error()) return y.error();
    in.y[j] = static_cast<T*>((*y)->untyped_data());
    batch = (*y)->dimensions()[0];
    in.n[j] = (*y)->dimensions()[1];
  }
  // one slice per thread for batches worth it (at least 64 states a slice)
  int64_t n = threads < batch / 64 ? threads : batch / 64;
  if (n <= 1) range(&in, 0, batch);
  else pool()->run(range, &in, batch, n);
  return ffi::Error::Success();
}

XLA_FFI_DEFINE_HANDLER_SYMBOL(jaxbody_fd, fd_impl,
                              ffi::Ffi::Bind().RemainingArgs().RemainingRets().Attr<int64_t>("kernel").Attr<int64_t>("threads"));
"""

_SCALAR = {np.dtype(np.float64): ("double", "ffi::F64"), np.dtype(np.float32): ("float", "ffi::F32")}


def _is_zero(x) -> bool:
    return not isinstance(x, _Sym) and x == 0


def _active(ops: list, seeds: set) -> set:
    """Names of the program's values that depend on the inputs named in ``seeds``."""
    active = set()
    for out, kind, args in ops:
        if kind == "input":
            if args[0] in seeds:
                active.add(out.name)
        elif kind == "stop":
            continue
        elif any(isinstance(a, _Sym) and a.name in active for a in args):
            active.update(o.name for o in (out if kind == "sincos" else (out,)))
    return active


def _tangent_program(ops: list, seeds: dict) -> dict:
    """Forward mode: the tangent of every value, emitted as code (zeros folded away).

    ``seeds`` maps input names to their tangents; returns value name -> tangent (a symbol,
    or ``0.0`` where the tangent is structurally zero).
    """
    tan = dict(seeds)

    def d(a):
        return tan.get(a.name, 0.0) if isinstance(a, _Sym) else 0.0

    for out, kind, args in ops:
        if kind in ("input", "stop"):
            continue
        ds = [d(a) for a in args]
        if all(_is_zero(x) for x in ds):
            continue
        if kind == "+":
            t = ds[0] + ds[1]
        elif kind == "-":
            t = ds[0] - ds[1]
        elif kind == "neg":
            t = -ds[0]
        elif kind == "*":
            t = ds[0] * args[1] + args[0] * ds[1]
        elif kind == "/":
            num = ds[0] - out * ds[1]
            t = 0.0 if _is_zero(num) else num / args[1]
        elif kind == "sincos":
            s, c = out
            tan[s.name], tan[c.name] = c * ds[0], -(s * ds[0])
            continue
        elif kind == "sqrt":
            t = ds[0] * 0.5 / out
        elif kind == "block":
            t = ds[0]
        elif kind == "attach":
            t = ds[1]
        elif kind == "atan2":
            y, x = args
            t = (x * ds[0] - y * ds[1]) / (x * x + y * y)
        elif kind == "select":
            cond = args[0]
            t = 0.0 if _is_zero(ds[1]) and _is_zero(ds[2]) else _where_negative(cond, ds[1], ds[2])
        else:
            raise AssertionError(f"no tangent rule for {kind!r}")
        tan[out.name] = t
    return tan


def _inverse_dynamics_block(em: _Emitter, model, q: list, v: list, acceleration: list, gravity, tau: list) -> list:
    """``tau`` (inverse dynamics at ``(q, v, acceleration)``, ``acceleration`` held) as the outputs
    of one block whose reverse-mode rule is the hand-derived :func:`jaxbody.unrolled._inverse_dynamics_vjp`
    (trees of hinges and slides, no body loads), not the reverse of the Newton–Euler operations."""
    group: dict = {"cts": [0.0] * len(tau)}

    def rule(lam):
        q_bar, v_bar = unrolled._inverse_dynamics_vjp(model, q, v, acceleration, gravity, lam)
        return list(zip(q, q_bar)) + list(zip(v, v_bar))

    group["rule"] = rule
    out = []
    for i, t in enumerate(tau):
        if not isinstance(t, _Sym):
            out.append(t)
            continue
        sym = em.emit(f"{t.name} /* inverse dynamics */", "block", (t,))
        em.blocks[sym.name] = (group, i)
        group.setdefault("first", i)  # the reverse pass reaches it last: the rule runs there
        out.append(sym)
    return out


def _adjoint_program(ops: list, active: set, seeds: list) -> dict:
    """Reverse mode: the adjoint of every active value, emitted as code, last operation first.

    ``seeds``: ``(value, cotangent)`` pairs; returns value name -> adjoint. The outputs of a
    hand-differentiated block (:func:`_inverse_dynamics_block`) collect their adjoints; at the
    block's first symbolic output (the last one reached) its rule emits the adjoints of its inputs.
    """
    adj: dict = {}

    def acc(a, g):
        if isinstance(a, _Sym) and a.name in active and not _is_zero(g):
            adj[a.name] = adj[a.name] + g if a.name in adj else g

    for value, ct in seeds:
        acc(value, ct)
    for out, kind, args in reversed(ops):
        if kind in ("input", "stop"):
            continue
        if kind == "sincos":
            s, c = out
            gs, gc = adj.get(s.name, 0.0), adj.get(c.name, 0.0)
            acc(args[0], gs * c - gc * s)
            continue
        if kind == "block":
            group, i = out.em.blocks[out.name]
            group["cts"][i] = adj.get(out.name, 0.0)
            if i == group["first"] and not all(_is_zero(x) for x in group["cts"]):
                for value, g in group["rule"](group["cts"]):
                    acc(value, g)
            continue
        g = adj.get(out.name)
        if g is None:
            continue
        if kind == "+":
            acc(args[0], g)
            acc(args[1], g)
        elif kind == "-":
            acc(args[0], g)
            if isinstance(args[1], _Sym) and args[1].name in active:
                acc(args[1], -g)
        elif kind == "neg":
            acc(args[0], -g)
        elif kind == "attach":
            acc(args[1], g)
        elif kind == "*":
            for a, b in ((args[0], args[1]), (args[1], args[0])):
                if isinstance(a, _Sym) and a.name in active:
                    acc(a, g * b)
        elif kind == "/":
            gy = g / args[1]
            acc(args[0], gy)
            if isinstance(args[1], _Sym) and args[1].name in active:
                acc(args[1], -(gy * out))
        elif kind == "sqrt":
            acc(args[0], g * 0.5 / out)
        elif kind == "atan2":
            y, x = args
            r = g / (x * x + y * y)
            acc(y, r * x)
            if isinstance(x, _Sym) and x.name in active:
                acc(x, -(r * y))
        elif kind == "select":
            cond = args[0]
            for branch, (a, b) in ((args[1], (g, 0.0)), (args[2], (0.0, g))):
                if isinstance(branch, _Sym) and branch.name in active:
                    acc(branch, _where_negative(cond, a, b))
        else:
            raise AssertionError(f"no adjoint rule for {kind!r}")
    return adj


def _acceleration(em, model, joints, q, v, f, g, ext, derivative):
    """Forward dynamics' acceleration on symbolic scalars; for ``derivative="vjp"`` written so
    that its reverse mode goes through inverse dynamics (below)."""
    M, bias, lam = unrolled._bias_and_mass(model, q, v, g, ext)
    L, inv_d = unrolled._ltdl_factor(M, lam)
    a = unrolled._ltdl_substitute(L, inv_d, lam, [fi - b for fi, b in zip(f, bias)])
    if derivative != "vjp":
        return a
    # The reverse-mode programs differentiate a = a₀ + M⁻¹ (f − τ(q, v, a₀)), a₀ and the factor
    # of M held constant: equal to a up to rounding, its derivative is forward dynamics'
    # (implicit function theorem on τ(q, v, a) = f): M⁻¹ (∂f − ∂τ/∂q ∂q − ∂τ/∂v ∂v). The
    # derivative passes go through inverse dynamics (Newton–Euler), not through the
    # composite inertias and the factorisation (forward mode stays on the direct program,
    # whose tangent is shorter than the tangent of inverse dynamics).
    a0 = [_stop(x) for x in a]
    L0 = {k: _stop(x) for k, x in L.items()}
    inv_d0 = [_stop(x) for x in inv_d]
    tau = unrolled._inverse_dynamics(model, q, v, a0, g, ext)
    if ext is None and unrolled.adjoint_applies(joints):
        tau = _inverse_dynamics_block(em, model, q, v, a0, g, tau)
    correction = unrolled._ltdl_substitute(L0, inv_d0, lam, [fi - t for fi, t in zip(f, tau)])
    # the value is a₀ itself (the correction is zero up to rounding): the stages that follow
    # do not wait on inverse dynamics and a second substitution, which only the reverse pass reads
    return [_with_derivative(x, x + c) for x, c in zip(a0, correction)]


def _generate(tree, joints, with_external: bool, dtype, mode: str = "fd") -> str:
    """C++ source of forward dynamics, or of one RK4 step, for this tree (parameters, gravity,
    loads as inputs).

    ``mode``: ``"fd"`` the acceleration; ``"jvp"`` its directional derivative along tangents
    ``(dq, dv, df)`` of the state and force (forward mode on the generated program);
    ``"vjp"`` the cotangents of ``(q, v, f)`` for a cotangent of the acceleration (reverse mode).
    ``"rk4"``, ``"rk4_jvp"``, ``"rk4_vjp"``: the same for one RK4 step of length ``h`` (an extra
    input) with the force held over the step (:func:`_rk4_scalars`: six results).
    """
    step = mode.startswith("rk4")
    if mode == "energy":
        return _generate_energy(tree, joints, dtype)
    slots = _STEP_SLOTS if step else _SLOTS
    em = _Emitter()
    model = _SymbolicModel(tree, joints, em, slots["p"])
    q = _inputs(em, "q", joints.nq, slots["q"])
    v = _inputs(em, "v", joints.nv, slots["v"])
    f = _inputs(em, "f", joints.nv, slots["f"])
    g = tuple(_inputs(em, "g", 3, slots["g"]))
    ext = None
    if with_external:
        flat = _inputs(em, "ext", 6 * tree.n_body, slots["ext"])
        ext = [tuple(flat[6 * b : 6 * b + 6]) for b in range(tree.n_body)]

    derivative = mode.split("_")[-1] if mode not in ("fd", "rk4") else None

    def acceleration(q, v, f):
        return _acceleration(em, model, joints, q, v, f, g, ext, derivative)

    if step:
        h = _inputs(em, "h", 1, slots["h"])[0]
        stiffness = _inputs(em, "k", joints.n_joint, slots["k"])
        reference = _inputs(em, "r", joints.nq, slots["r"])
        damping = _inputs(em, "d", joints.nv, slots["d"])

        def field(q, v):
            total, power = _joint_force(joints, q, v, f, stiffness, reference, damping)
            return acceleration(q, v, total), power

        outputs = list(_rk4_scalars(field, joints, q, v, h))
    else:
        outputs = [acceleration(q, v, f)]
    primal = list(em.ops)
    if derivative is None:
        results = outputs
    elif derivative == "jvp":
        seeds = {}
        for x, name in ((q, "dq"), (v, "dv"), (f, "df")):
            for xi, di in zip(x, _inputs(em, name, len(x), slots[name])):
                seeds[xi.name] = di
        tan = _tangent_program(primal, seeds)
        results = [[tan.get(o.name, 0.0) if isinstance(o, _Sym) else 0.0 for o in out] for out in outputs]
    elif derivative == "vjp":
        pairs = []
        for j, out in enumerate(outputs):
            cts = _inputs(em, f"ct{j}", len(out), slots["ct"] + j)
            pairs += [(o, c) for o, c in zip(out, cts)]
        active = _active(primal, {"q", "v", "f"})
        adj = _adjoint_program(primal, active, pairs)
        results = [[adj.get(xi.name, 0.0) for xi in x] for x in (q, v, f)]
    else:
        raise ValueError(f"unknown mode {mode!r}")

    return _source(em, results, dtype)


def _generate_energy(tree, joints, dtype) -> str:
    """C++ source of the energies of a state: ``(kinetic, gravity potential, spring potential)``
    (:func:`jaxbody.unrolled._energies`, :func:`_spring_potential`)."""
    slots = _ENERGY_SLOTS
    em = _Emitter()
    model = _SymbolicModel(tree, joints, em, slots["p"])
    q = _inputs(em, "q", joints.nq, slots["q"])
    v = _inputs(em, "v", joints.nv, slots["v"])
    g = tuple(_inputs(em, "g", 3, slots["g"]))
    stiffness = _inputs(em, "k", joints.n_joint, slots["k"])
    reference = _inputs(em, "r", joints.nq, slots["r"])
    kinetic, potential = unrolled._energies(model, q, v, g)
    return _source(em, [[kinetic, potential, _spring_potential(joints, q, stiffness, reference)]], dtype)


def _source(em: _Emitter, results: list, dtype) -> str:
    """The kernel's C++ source: the emitted lines, then every result stored."""

    body = ["  " + line for line in em.lines]
    body += [f"  st({j}, {i}, {_symbol_value(x)});" for j, xs in enumerate(results) for i, x in enumerate(xs)]
    return _KERNEL.replace("@ACCESS@", _ACCESS).replace("@COMMON@", _COMMON.replace("@T@", _SCALAR[np.dtype(dtype)][0])).replace(
        "@BODY@", "\n".join(body))


def _carried(em: _Emitter, name: str, n: int, array: str) -> list:
    """``n`` scalars read from the local array ``array`` (a loop's carried state)."""
    return _declared(em, name, n, lambda i: f"{array}[{i}]")


def _quaternion_coordinates(joints) -> list:
    """The ``q`` coordinates of every ball and free joint's quaternion, four at a time."""
    out = []
    for kind, _, qadr, _ in joints.kind_groups():
        if kind.quaternion is not None:
            out += [[int(a) + kind.quaternion + c for c in range(4)] for a in qadr]
    return out


def _run_operands(em: _Emitter, tree, joints):
    """The operands a whole solve holds over its steps (:data:`_RUN_SLOTS`), loaded first:
    ``(model, force, gravity, stiffness, reference, damping)``."""
    slots = _RUN_SLOTS
    model = _SymbolicModel(tree, joints, em, slots["p"])
    f = _inputs(em, "f", joints.nv, slots["f"])
    g = tuple(_inputs(em, "g", 3, slots["g"]))
    stiffness = _inputs(em, "k", joints.n_joint, slots["k"])
    reference = _inputs(em, "r", joints.nq, slots["r"])
    damping = _inputs(em, "d", joints.nv, slots["d"])
    return model, f, g, stiffness, reference, damping


def _run_step(em: _Emitter, joints, operands, q: list, v: list, h, derivative=None) -> tuple:
    """One step of a whole solve on symbolic scalars: the RK4 step of :func:`_rk4_scalars`, then
    the quaternions of ball and free joints renormalised (``q / sqrt(|q|²)``, as
    :func:`jaxbody.kinematics.normalize_qpos`). Returns ``(q1, v1, Δw)``."""
    model, f, g, stiffness, reference, damping = operands

    def field(q, v):
        total, power = _joint_force(joints, q, v, f, stiffness, reference, damping)
        return _acceleration(em, model, joints, q, v, total, g, None, derivative), power

    q1, v1, _, _, _, _, work = _rk4_scalars(field, joints, q, v, h)
    q1 = list(q1)
    for block in _quaternion_coordinates(joints):
        squares = [q1[i] * q1[i] for i in block]
        inverse = 1.0 / _sqrt(squares[0] + squares[1] + squares[2] + squares[3])
        for i in block:
            q1[i] = q1[i] * inverse
    return q1, list(v1), work[0]


def _symbol_value(x) -> str:
    return x.name if isinstance(x, _Sym) else f"U{{}} + T({float(x)!r})"


def _hoisted(lines: list) -> list:
    """``lines`` without operand loads (:func:`_run_operands` puts them before the loop)."""
    return [line for line in lines if " = ld(" not in line]


def _run_program(tree, joints, derivative=None) -> tuple:
    """One step of a whole solve on the carried state ``qc``, ``vc`` (:func:`_run_step`):
    ``(emitter, operand loads, step lines, (q, v), (q1, v1, Δw))``, the step lines ending in
    the stores of ``q1``, ``v1`` to ``qn``, ``vn``."""
    em = _Emitter()
    operands = _run_operands(em, tree, joints)
    invariant = len(em.lines)
    q = _carried(em, "q", joints.nq, "qc")
    v = _carried(em, "v", joints.nv, "vc")
    q1, v1, dw = _run_step(em, joints, operands, q, v, _Sym("h", em), derivative)
    step = em.lines[invariant:]
    step += [f"qn[{i}] = {_symbol_value(x)};" for i, x in enumerate(q1)]
    step += [f"vn[{i}] = {_symbol_value(x)};" for i, x in enumerate(v1)]
    return em, em.lines[:invariant], step, (q, v), (q1, v1, dw)


def _generate_run(tree, joints, dtype) -> str:
    """C++ source of a whole fixed-step RK4 solve (``"rk4_run"``, :data:`_RUN_BLOCK`): the
    step of :func:`_run_step` on the carried state, the operands loaded before the loop."""
    _, invariant, step, _, (_, _, dw) = _run_program(tree, joints)
    return _run_source(_RUN_BLOCK, invariant, {"BODY": step + [f"dw = {_symbol_value(dw)};"]}, joints, dtype)


def _generate_run_vjp(tree, joints, dtype) -> str:
    """C++ source of the reverse sweep of a whole solve (``"rk4_run_vjp"``, :data:`_RUN_VJP_BLOCK`):
    the same steps recomputed from the checkpoints, and the reverse-mode program of
    :func:`_run_step` (cotangents of ``(q1, v1, Δw)`` to those of ``(q, v)``) on a kept state
    (``bq``, ``bv``)."""
    _, invariant, step, _, _ = _run_program(tree, joints)
    rev, _, _, (q, v), (q1, v1, dw) = _run_program(tree, joints, derivative="vjp")
    primal = list(rev.ops)
    cq = _carried(rev, "cq", joints.nq, "aq")
    cv = _carried(rev, "cv", joints.nv, "av")
    pairs = list(zip(q1, cq)) + list(zip(v1, cv)) + [(dw, _Sym("aw", rev))]
    adj = _adjoint_program(primal, _active(primal, {"q", "v"}), pairs)
    # the kept state's reads, then the step's operations and their adjoints
    body = [f"const U q_{i} = bq[{i}];" for i in range(joints.nq)] + [f"const U v_{i} = bv[{i}];" for i in range(joints.nv)]
    body += _hoisted(rev.lines[len(invariant) + joints.nq + joints.nv :])
    body += [f"rq[{i}] = {_symbol_value(adj.get(x.name, 0.0))};" for i, x in enumerate(q)]
    body += [f"rv[{i}] = {_symbol_value(adj.get(x.name, 0.0))};" for i, x in enumerate(v)]
    return _run_source(_RUN_VJP_BLOCK, invariant, {"STEP": step, "BODY": body}, joints, dtype)


def _run_source(block: str, invariant: list, parts: dict, joints, dtype) -> str:
    text = block.replace("@ACCESS@", _ACCESS).replace("@INVARIANT@", "\n".join("  " + line for line in invariant))
    for key, lines in parts.items():
        text = text.replace(f"@{key}@", "\n".join("      " + line for line in lines))
    text = text.replace("@NQ@", str(joints.nq)).replace("@NV@", str(joints.nv))
    prelude = _KERNEL.split("// the generated function of the states")[0]
    return prelude.replace("@COMMON@", _COMMON.replace("@T@", _SCALAR[np.dtype(dtype)][0])) + text


# ----------------------------------------------------------------------------- build and load
def _compiler() -> str | None:
    return shutil.which(os.environ.get("CXX", "g++"))


@functools.cache
def available() -> bool:
    """Whether the native kernel can be built here: a C++ compiler, XLA's FFI headers, a CPU."""
    include = Path(jax.ffi.include_dir()) / "xla" / "ffi" / "api" / "ffi.h"
    return _compiler() is not None and include.is_file() and jax.default_backend() == "cpu"


def applies(model: Model) -> bool:
    """Whether ``kernel="auto"`` gives ``model`` the native kernel (small enough, buildable)."""
    return 0 < model.nv <= MAX_DOFS and available()


#: Nanoseconds the pool's threads spin waiting for the next call (or for each other) before
#: they sleep; ``$JAXBODY_NATIVE_SPIN_NS`` overrides it (0: sleep at once).
SPIN_NS = 100_000


def threads() -> int:
    """Threads one call splits a batch over: ``$JAXBODY_NATIVE_THREADS``, else the CPU count."""
    return int(os.environ.get("JAXBODY_NATIVE_THREADS", os.cpu_count() or 1))


def _cache_dir() -> Path:
    root = os.environ.get("JAXBODY_CACHE_DIR") or os.path.join(os.path.expanduser("~"), ".cache", "jaxbody")
    path = Path(root) / "native"
    path.mkdir(parents=True, exist_ok=True)
    return path


def _cpu_signature() -> str:
    # the library is built with -march=native: key it by the processor's instruction set too
    try:
        with open("/proc/cpuinfo") as fh:
            flags = next((line for line in fh if line.startswith("flags")), "")
    except OSError:
        flags = ""
    return platform.machine() + flags


# -ffp-contract=fast: fused multiply-adds; -fno-math-errno: sin/cos/sqrt without errno
_FLAGS = ("-O2", "-march=native", "-std=gnu++17", "-ffp-contract=fast", "-fno-math-errno", "-shared", "-fPIC", "-pthread", "-w")


def _build(source: str, stem: str) -> Path:
    """Compile ``source`` to a shared library in the cache (once per source, compiler and CPU)."""
    compiler = _compiler()
    if compiler is None:
        raise RuntimeError("the native kernel needs a C++ compiler (g++ or $CXX); use kernel='vectorised'")
    key = hashlib.sha256("\n".join((source, compiler, *_FLAGS, _cpu_signature(), jax.__version__)).encode()).hexdigest()[:24]
    target = _cache_dir() / f"{stem}_{key}.so"
    if target.is_file():
        return target
    # one builder of a library at a time across processes (test workers, a batch job's
    # processes): the others wait on the lock and load what it built
    with open(target.with_suffix(".lock"), "a") as lock, _exclusive(lock):
        if target.is_file():
            return target
        with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
            src = Path(tmp) / "src.cc"
            src.write_text(source)
            out = Path(tmp) / "lib.so"
            cmd = [compiler, *_FLAGS, f"-I{jax.ffi.include_dir()}", str(src), "-o", str(out)]
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode != 0:
                raise RuntimeError(f"building the native kernel failed ({' '.join(cmd)}):\n{proc.stderr[-4000:]}")
            os.replace(out, target)  # atomic: a process that does not take the lock never sees half a file
    return target


@contextlib.contextmanager
def _exclusive(fh):
    """Hold an exclusive advisory lock on the open file ``fh`` (POSIX ``flock``; no lock where the
    platform has none)."""
    if fcntl is None:
        yield
        return
    fcntl.flock(fh, fcntl.LOCK_EX)
    try:
        yield
    finally:
        fcntl.flock(fh, fcntl.LOCK_UN)


@functools.cache
def _handler(dtype) -> str:
    """The FFI target name of the (tree-independent) handler for ``dtype``; built and registered once."""
    scalar, ffi_type = _SCALAR[np.dtype(dtype)]
    source = (_HANDLER.replace("@COMMON@", _COMMON.replace("@T@", scalar)).replace("@DT@", ffi_type)
              .replace("@SPIN_NS@", str(int(os.environ.get("JAXBODY_NATIVE_SPIN_NS", SPIN_NS)))))
    path = _build(source, f"handler_{scalar}")
    lib = ctypes.cdll.LoadLibrary(str(path))
    name = f"jaxbody_native_{path.stem}"
    jax.ffi.register_ffi_target(name, jax.ffi.pycapsule(lib.jaxbody_fd), platform="cpu")
    _loaded.append(lib)
    return name


_loaded: list = []  # libraries stay loaded for the life of the process (XLA holds their addresses)


def _merge_batch(axis_size: int, args, batched) -> tuple[list, int]:
    """A new batch axis (leading where ``batched``) over ``(B_i, n_i)`` operands, merged with the
    inner one: ``(axis_size * B, n_i)`` operands (or ``(1, n_i)``, read with stride zero), and B."""
    inner = max(a.shape[1] if b else a.shape[0] for a, b in zip(args, batched))
    merged = []
    for a, b in zip(args, batched):
        n = a.shape[-1]
        if b:
            a = jnp.broadcast_to(a, (axis_size, inner, n)).reshape(axis_size * inner, n)
        elif a.shape[0] != 1:
            a = jnp.broadcast_to(a[None], (axis_size, inner, n)).reshape(axis_size * inner, n)
        merged.append(a)
    return merged, inner


class _Kernel:
    """One compiled tree, dtype and mode (:func:`_generate`): its address and the call."""

    def __init__(self, tree, joints, with_external: bool, dtype, mode: str = "fd"):
        self.tree, self.joints, self.with_external = tree, joints, with_external
        self.nv, self.nq, self.dtype, self.mode = joints.nv, joints.nq, np.dtype(dtype), mode
        self.widths = _widths(joints, mode)
        self.target = _handler(self.dtype)
        if mode == "rk4_run":
            self.source = _generate_run(tree, joints, self.dtype)
        elif mode == "rk4_run_vjp":
            self.source = _generate_run_vjp(tree, joints, self.dtype)
        else:
            self.source = _generate(tree, joints, with_external, self.dtype, mode)
        self._addresses = {}  # built on the first call (traced), where a build error then shows
        self._batched = {}
        if mode in ("fd", "rk4", "energy", "rk4_run", "rk4_run_vjp"):
            self.batched = self.batched_with(self.widths)

    def address(self, build: str) -> int:
        """The compiled program of one of :data:`BUILDS`, built on its first call."""
        with _lock:  # two threads tracing the same kernel build it once
            if build not in self._addresses:
                source = self.source.replace("@VECTOR_BYTES@", BUILDS[build])
                lib = ctypes.cdll.LoadLibrary(str(_build(source, f"{self.mode}_{build}")))
                _loaded.append(lib)
                self._addresses[build] = ctypes.cast(lib.jaxbody_range, ctypes.c_void_p).value
            return self._addresses[build]

    def call(self, *args, widths=None) -> list:
        """``args``: ``(B_i, n_i)`` arrays with ``B_i`` 1 or the batch size; returns ``(B, width)``
        arrays (``widths``: the results', default the program's)."""
        batch = max(a.shape[0] for a in args)
        out = [jax.ShapeDtypeStruct((batch, w), self.dtype) for w in (widths or self.widths)]
        fn = jax.ffi.ffi_call(self.target, out, vmap_method="sequential")
        # every lane of a SIMD register is one state: the kernel gathers W states' inputs; the
        # batch size is static here, so the build is chosen (and built) when the call is traced
        address = self.address(build_for(batch))
        return fn(*args, kernel=np.int64(address), threads=np.int64(threads()))

    def batched_with(self, widths: tuple):
        """The call with results of ``widths``, ``vmap`` batches merged into one call."""
        if widths not in self._batched:
            self._batched[widths] = self._batched_call(widths)
        return self._batched[widths]

    def _batched_call(self, widths):
        @jax.custom_batching.custom_vmap
        def batched(*args):
            return tuple(self.call(*args, widths=widths))

        @batched.def_vmap
        def rule(axis_size, in_batched, *args):
            merged, inner = _merge_batch(axis_size, args, in_batched)
            outs = batched(*merged)
            return tuple(o.reshape(axis_size, inner, o.shape[-1]) for o in outs), tuple(True for _ in outs)

        return batched


#: The builds of every program, by the bytes of one block of states (:func:`build_for`):
#: ``"one"`` (``0``: one scalar) scalar code for a single state; ``"narrow"`` 256-bit lanes (4
#: float64 or 8 float32 states) for batches below :data:`WIDE_BATCH`, and for all batches without
#: AVX-512; ``"wide"`` 512-bit lanes (8 or 16 states) for larger batches where the processor has
#: AVX-512, which read the states with gather and write the results with scatter instructions. On an AMD
#: EPYC, whose 512-bit operations cost two 256-bit ones, a batch runs about 1.4x (float64) and
#: 1.6x (float32) faster in 512-bit lanes, but a few states would fill only part of them.
BUILDS = {"one": "0", "narrow": "32", "wide": "64"}

#: Smallest batch a call runs in 512-bit lanes (where the processor has AVX-512).
WIDE_BATCH = 16


def build_for(batch: int) -> str:
    """Which of :data:`BUILDS` a call over ``batch`` states runs."""
    if batch == 1:
        return "one"
    return "wide" if batch >= WIDE_BATCH and _has_avx512() else "narrow"


@functools.cache
def _has_avx512() -> bool:
    return " avx512f" in _cpu_signature()


@functools.lru_cache(maxsize=256)
def _kernel(tree, joints, with_external: bool, dtype, mode: str = "fd") -> _Kernel:
    with _lock:
        return _Kernel(tree, joints, with_external, dtype, mode)


# ----------------------------------------------------------------------------- derivatives
# The acceleration's derivative with respect to the state and force, a(q, v, f) -> da, is a
# linear map of (dq, dv, df) evaluated by the generated forward-mode program ("jvp"); its
# transpose, ct -> (ctq, ctv, ctf), by the generated reverse-mode program ("vjp"). A primitive
# ties the two together so that JAX can transpose the tangent (reverse mode of any program
# around the kernel) and batch it (one call over the stacked states). Derivatives with
# respect to the model's parameters, gravity and external loads are rarer (identification,
# design) and come from the vectorised kernel; second derivatives from the unrolled kernel.
_linear_p = Primitive("jaxbody_native_linear")
_linear_p.multiple_results = True


def _linear(*args, tree, joints, with_external, dtype, mode):
    return _linear_p.bind(*args, tree=tree, joints=joints, with_external=with_external, dtype=dtype, mode=mode)


def _linear_abstract(*args, tree, joints, with_external, dtype, mode):
    batch = max(a.shape[0] for a in args)
    return [jax.core.ShapedArray((batch, w), np.dtype(dtype)) for w in _widths(joints, mode)]


def _linear_impl(*args, tree, joints, with_external, dtype, mode):
    return _kernel(tree, joints, with_external, np.dtype(dtype), mode).call(*args)


def _linear_batch(args, dims, **params):
    axis_size = next(a.shape[d] for a, d in zip(args, dims) if d is not None)
    args = [a if d is None else jnp.moveaxis(a, d, 0) for a, d in zip(args, dims)]
    merged, inner = _merge_batch(axis_size, args, [d is not None for d in dims])
    outs = _linear(*merged, **params)
    return [o.reshape(axis_size, inner, o.shape[-1]) for o in outs], [0] * len(outs)


_TRANSPOSED = {"jvp": "vjp", "vjp": "jvp", "rk4_jvp": "rk4_vjp", "rk4_vjp": "rk4_jvp"}


def _linear_transpose(cts, *args, mode, **params):
    n_res = _residual_count(mode)
    res, lin = args[:n_res], args[n_res:]
    if any(ad.is_undefined_primal(r) for r in res):
        raise NotImplementedError("the native kernel's derivative is linear in the tangents only")
    cts = [ad.instantiate_zeros(ct) for ct in cts]
    outs = _linear(*res, *cts, mode=_TRANSPOSED[mode], **params)
    result = []
    for x, o in zip(lin, outs):
        if not ad.is_undefined_primal(x):
            result.append(None)
            continue
        shape = x.aval.shape
        if o.shape != shape:  # an operand shared by the whole batch: sum its cotangents
            o = jnp.sum(o, axis=0, keepdims=True)
        result.append(o)
    return [None] * n_res + result


def _single_state(tree, joints, with_external, q, v, f, p, g, ext):
    """The acceleration of one state from the operands' rows, by the unrolled kernel."""
    model = _ParameterModel(tree, joints, p)
    sc = unrolled._scalars
    loads = [tuple(sc(ext[6 * b : 6 * b + 6])) for b in range(tree.n_body)] if with_external else None
    M, bias, lam = unrolled._bias_and_mass(model, sc(q), sc(v), tuple(sc(g)), loads)
    rhs = [unrolled._add(fi, -bi) for fi, bi in zip(sc(f), bias)]
    return unrolled._stack(unrolled._ltdl_solve(M, lam, rhs), p.dtype)


def _single_step(tree, joints, with_external, q, v, f, p, g, ext, h, k, r, d):
    """One RK4 step of one state from the operands' rows, by the unrolled kernel."""
    sc = unrolled._scalars

    def field(qs, vs):
        total, power = _joint_force(joints, qs, vs, sc(f), sc(k), sc(r), sc(d))
        a = _single_state(tree, joints, with_external, jnp.stack(qs), jnp.stack(vs), unrolled._stack(total, p.dtype), p, g, ext)
        return sc(a), power

    out = _rk4_scalars(field, joints, sc(q), sc(v), h[0])
    return tuple(unrolled._stack(o, p.dtype) for o in out)


def _linear_fallback(*args, tree, joints, with_external, dtype, mode):
    """The same linear map written in JAX (differentiable in its residuals: second derivatives)."""
    batch = max(a.shape[0] for a in args)
    rows = [jnp.broadcast_to(a, (batch, a.shape[1])) for a in args]
    n_res = _residual_count(mode)

    def one(*xs):
        res, lin = xs[:n_res], xs[n_res:]
        q, v, f, p, g, ext = res[:6]
        if mode.startswith("rk4"):
            fn = lambda q, v, f: _single_step(tree, joints, with_external, q, v, f, p, g, ext, *res[6:])  # noqa: E731
        else:
            fn = lambda q, v, f: (_single_state(tree, joints, with_external, q, v, f, p, g, ext),)  # noqa: E731
        if mode.endswith("jvp"):
            return list(jax.jvp(fn, (q, v, f), tuple(lin))[1])
        return list(jax.vjp(fn, q, v, f)[1](tuple(lin)))

    return jax.vmap(one)(*rows)


def _linear_jvp(primals, tangents, **params):
    outs = _linear(*primals, **params)
    n_res = _residual_count(params["mode"])
    res_t, lin_t = tangents[:n_res], tangents[n_res:]
    out_t = [ad.Zero(jax.typeof(o).to_tangent_aval()) for o in outs]
    if any(type(t) is not ad.Zero for t in lin_t):
        out_t = _linear(*primals[:n_res], *[ad.instantiate_zeros(t) for t in lin_t], **params)
    if any(type(t) is not ad.Zero for t in res_t):
        # second derivatives: the residuals' part from the same map written in JAX
        res_t = [ad.instantiate_zeros(t) for t in res_t]
        zero_lin = [jnp.zeros_like(x) for x in primals[n_res:]]
        _, extra = jax.jvp(lambda *xs: _linear_fallback(*xs, **params), tuple(primals), (*res_t, *zero_lin))
        out_t = [e if type(o) is ad.Zero else o + e for o, e in zip(out_t, extra)]
    return outs, out_t


_linear_p.def_impl(_linear_impl)
_linear_p.def_abstract_eval(_linear_abstract)
mlir.register_lowering(_linear_p, mlir.lower_fun(_linear_impl, multiple_results=True), platform="cpu")
batching.primitive_batchers[_linear_p] = _linear_batch
ad.primitive_jvps[_linear_p] = _linear_jvp
ad.primitive_transposes[_linear_p] = _linear_transpose


class _ParameterModel:
    """What the unrolled kernel reads of a model, sliced from the parameter vector."""

    def __init__(self, tree, joints, p):
        _unflatten_parameters(self, tree, joints, p, jnp.reshape)


#: Largest number of DoFs whose derivatives the generated programs serve; above it the
#: vectorised kernel gives the tangents. The derivative programs are about 2–2.5 times the
#: forward one in lines; they build in about 7 s (forward and reverse mode of forward
#: dynamics) for the Panda arm and 70 s for a 20-link chain, whose RK4 step builds in about a
#: minute and the step's reverse- and forward-mode programs in 50 s and 66 s (once per tree,
#: then cached; benchmarks/native_build.py, benchmarks/results/native_build_rk4_chain20.md). Taking the tangents of a 20-link chain from the
#: vectorised kernel made a rollout gradient about 50 times the native rollout.
MAX_DERIVATIVE_DOFS = 20


# ----------------------------------------------------------------------------- the JAX function
def _reference(model, q, v, force, gravity, external):
    from .kernels import _vectorised_acceleration

    return _vectorised_acceleration(model, q, v, force, gravity, external)


def _rows(model, q, v, force, gravity, external):
    row = lambda x: jnp.reshape(x, (1, -1))  # noqa: E731
    ext = row(external) if external is not None else jnp.zeros((1, 1), q.dtype)
    return (row(q), row(v), row(force), row(parameter_vector(model)), row(gravity), ext)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _forward_dynamics(kernel, model, q, v, force, gravity, external):
    return kernel.batched(*_rows(model, q, v, force, gravity, external))[0][0]


def _split_jvp(kernel, mode, rows, out, primals, tangents, reference):
    """The tangent of a native program's result: along (q, v, force) by its generated
    forward-mode program ``mode`` through the linear primitive (transposed to its reverse-mode
    program in reverse mode); along every other input (parameters, gravity, loads, ...) by
    ``reference``, the same function written in JAX. Only inputs that carry a tangent are
    differentiated. ``out``: the results (a tuple), ``rows``: the program's residual operands.
    ``mode=None``: a program without derivative programs (all of the tangent from ``reference``)."""
    model, q, v, force = primals[:4]
    leaves, treedef = jax.tree_util.tree_flatten(primals)
    dleaves = treedef.flatten_up_to(tangents)
    live = [i for i, d in enumerate(dleaves) if not isinstance(d, SymbolicZero)]
    n_model = len(jax.tree_util.tree_leaves(model))
    state = [n_model, n_model + 1, n_model + 2]  # q, v, force
    tangent = None
    if mode is not None and kernel.nv <= MAX_DERIVATIVE_DOFS and any(i in live for i in state):
        lin = []
        for i, x in zip(state, (q, v, force)):
            d = dleaves[i]
            lin.append(jnp.zeros((1, x.size), x.dtype) if isinstance(d, SymbolicZero) else jnp.reshape(d, (1, -1)))
        params = dict(tree=kernel.tree, joints=kernel.joints, with_external=kernel.with_external, dtype=kernel.dtype)
        tangent = tuple(t[0] for t in _linear(*rows, *lin, mode=mode, **params))
        live = [i for i in live if i not in state]
    if not live:
        return tuple(jnp.zeros_like(o) for o in out) if tangent is None else tangent

    def of_live(*xs):
        full = list(leaves)
        for i, x in zip(live, xs):
            full[i] = x
        return reference(*jax.tree_util.tree_unflatten(treedef, full))

    _, rest = jax.jvp(of_live, tuple(leaves[i] for i in live), tuple(dleaves[i] for i in live))
    return rest if tangent is None else tuple(a + b for a, b in zip(tangent, rest))


def _forward_dynamics_jvp(kernel, primals, tangents):
    # value: the native call; tangent: _split_jvp, the rest from the vectorised kernel
    out = _forward_dynamics(kernel, *primals)
    (tangent,) = _split_jvp(kernel, "jvp", _rows(*primals), (out,), primals, tangents, lambda *a: (_reference(*a),))
    return out, tangent


_forward_dynamics.defjvp(_forward_dynamics_jvp, symbolic_zeros=True)


def forward_dynamics(
    model: Model,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    force: Float[ArrayLike, " nv"] | None = None,
    *,
    gravity: Float[ArrayLike, "3"] | None = None,
    external: Float[ArrayLike, "n_body 6"] | None = None,
) -> Float[Array, " nv"]:
    """``a = M⁻¹ (force − bias + Jᵀ external)`` by the native kernel (no checks).

    Same arguments and result as :func:`jaxbody.unrolled.forward_dynamics`; ``jit``, ``vmap``
    (one call over the whole batch) and differentiation (tangents from the vectorised kernel)
    pass through. Builds and caches the tree's kernel on first use.
    """
    dtype = model.body_pos.dtype
    q = jnp.asarray(q, dtype)
    v = jnp.asarray(v, dtype)
    force = jnp.zeros(model.nv, dtype) if force is None else jnp.asarray(force, dtype)
    gravity = jnp.zeros(3, dtype) if gravity is None else jnp.asarray(gravity, dtype)
    if external is not None:
        external = jnp.asarray(external, dtype)
    kernel = _kernel(model.tree, model.joints, external is not None, np.dtype(dtype))
    return _forward_dynamics(kernel, model, q, v, force, gravity, external)


# ----------------------------------------------------------------------------- one RK4 step
def _step_rows(model, q, v, force, gravity, external, h, stiffness, reference, damping):
    row = lambda x: jnp.reshape(x, (1, -1))  # noqa: E731
    return (*_rows(model, q, v, force, gravity, external), row(h), row(stiffness), row(reference), row(damping))


def _rk4_composed(fd_kernel, model, q, v, force, gravity, external, h, stiffness, reference, damping):
    """The RK4 step written in JAX around the native forward dynamics (its derivatives with
    respect to the parameters, gravity, loads, ``h``, springs and dampers)."""
    sc = unrolled._scalars

    def field(qs, vs):
        total, power = _joint_force(model.joints, qs, vs, sc(force), sc(stiffness), sc(reference), sc(damping))
        a = _forward_dynamics(fd_kernel, model, jnp.stack(qs), jnp.stack(vs), unrolled._stack(total, q.dtype), gravity, external)
        return sc(a), power

    out = _rk4_scalars(field, model.joints, sc(q), sc(v), h)
    return tuple(unrolled._stack(o, q.dtype) for o in out)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _rk4_step(kernel, fd_kernel, model, q, v, force, gravity, external, h, stiffness, reference, damping):
    rows = _step_rows(model, q, v, force, gravity, external, h, stiffness, reference, damping)
    return tuple(o[0] for o in kernel.batched(*rows))


def _rk4_step_jvp(kernel, fd_kernel, primals, tangents):
    # value: the native step; tangent: _split_jvp with the step's generated programs, the rest
    # (parameters, gravity, loads, h, springs, dampers) from the step written in JAX around the
    # native forward dynamics
    out = _rk4_step(kernel, fd_kernel, *primals)
    reference = functools.partial(_rk4_composed, fd_kernel)
    return out, _split_jvp(kernel, "rk4_jvp", _step_rows(*primals), out, primals, tangents, reference)


_rk4_step.defjvp(_rk4_step_jvp, symbolic_zeros=True)


def rk4_step(
    model: Model,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    h: ArrayLike,
    force: Float[ArrayLike, " nv"] | None = None,
    *,
    gravity: Float[ArrayLike, "3"] | None = None,
    external: Float[ArrayLike, "n_body 6"] | None = None,
    stiffness: Float[ArrayLike, " n_joint"] | None = None,
    reference: Float[ArrayLike, " nq"] | None = None,
    damping: Float[ArrayLike, " nv"] | None = None,
) -> tuple[Array, Array, Array, Array, Array, Array, Array]:
    """One classical RK4 step of ``(q̇, v̇) = (q̇(q, v), a(q, v))`` in one native call.

    The joint force at each stage is ``force − k (q − q_ref) − c v``: ``force``, ``gravity`` and
    ``external`` are held over the step; ``stiffness`` (per joint; ball and free joints: a
    spring on the rotation vector from the reference orientation, as :class:`jaxbody.JointSprings`),
    ``reference`` (``(nq,)``) and ``damping`` (per DoF) default to none. Returns ``(q1, v1, k1q, k1v, k4q, k4v, work)``: the
    state after the step (quaternions not renormalised), the increments ``h·f`` of the first
    and last stage (the end slopes of the step's cubic Hermite dense output), and ``work =
    (Δw, k1w, k4w)``: the dampers' work over the step by the same RK4 rule and its first and
    last stage increments.

    The four stages, the quaternion rates and the combination run in the generated program of
    the tree: no intermediate state goes through memory, and a ``vmap`` batch is one call.
    Derivatives along ``(q, v, force)`` come from the step's generated forward- and
    reverse-mode programs (trees up to :data:`MAX_DERIVATIVE_DOFS`), the others from the same
    step written around :func:`forward_dynamics`.
    """
    dtype = model.body_pos.dtype
    q = jnp.asarray(q, dtype)
    v = jnp.asarray(v, dtype)
    h = jnp.asarray(h, dtype)
    force = jnp.zeros(model.nv, dtype) if force is None else jnp.asarray(force, dtype)
    gravity = jnp.zeros(3, dtype) if gravity is None else jnp.asarray(gravity, dtype)
    stiffness = jnp.zeros(model.joints.n_joint, dtype) if stiffness is None else jnp.asarray(stiffness, dtype)
    reference = jnp.zeros(model.nq, dtype) if reference is None else jnp.asarray(reference, dtype)
    damping = jnp.zeros(model.nv, dtype) if damping is None else jnp.asarray(damping, dtype)
    if external is not None:
        external = jnp.asarray(external, dtype)
    with_external = external is not None
    kernel = _kernel(model.tree, model.joints, with_external, np.dtype(dtype), "rk4")
    fd_kernel = _kernel(model.tree, model.joints, with_external, np.dtype(dtype))
    return _rk4_step(kernel, fd_kernel, model, q, v, force, gravity, external, h, stiffness, reference, damping)


# ----------------------------------------------------------------------------- a whole solve
def rk4_rollout(
    model: Model,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    t0: ArrayLike,
    t1: ArrayLike,
    dt0: ArrayLike,
    max_steps: int | None = None,
    force: Float[ArrayLike, " nv"] | None = None,
    *,
    gravity: Float[ArrayLike, "3"] | None = None,
    stiffness: Float[ArrayLike, " n_joint"] | None = None,
    reference: Float[ArrayLike, " nq"] | None = None,
    damping: Float[ArrayLike, " nv"] | None = None,
    work0: ArrayLike = 0.0,
    frozen: ArrayLike = False,
) -> tuple[Array, Array, Array, Array, Array, Array]:
    """A fixed-step RK4 solve from ``t0`` to ``t1`` in one native call.

    The steps are those of :func:`jaxbody.simulate` with ``solver="rk4"`` and ``dt0`` (diffrax's
    constant step size): ``N = ceil((t1 − t0) / dt0)`` steps ending at ``t_k = t0 + (t1 − t0)·k/N``,
    each one :func:`rk4_step` (same field: ``force``, ``gravity``, springs and dampers held),
    the quaternions of ball and free joints renormalised after every step. A step whose result
    is not finite ends that trajectory there (its state is that step's); ``max_steps`` (``None``:
    no bound) ends it after that many steps. ``work0``: the dampers' work at ``t0``; ``frozen``:
    take the steps without moving (as :func:`jaxbody.simulate` does for an input that failed
    its checks with ``throw=False``).

    Returns ``(q, v, work, t, steps, failed)``: the final state, the dampers' work there, the
    time reached (``t1``, or the end of the last step taken), the steps taken, and whether a step
    was not finite. A ``vmap`` batch is one call (split over the CPU cores), each state with its
    own times. No derivatives: :func:`jaxbody.simulate` differentiates through its
    step-by-step solve, which computes the same values. No checks; ``t1 >= t0``.
    """
    rows = _rollout_rows(model, q, v, t0, t1, dt0, max_steps, force, gravity, stiffness, reference, damping, work0,
                         frozen, 1)
    kernel = _kernel(model.tree, model.joints, False, np.dtype(model.body_pos.dtype), "rk4_run")
    return _rollout_outputs(kernel.batched(*rows))


def _rollout_rows(model, q, v, t0, t1, dt0, max_steps, force, gravity, stiffness, reference, damping, work0, frozen,
                  every) -> tuple:
    """The operands of the ``"rk4_run"`` programs (:data:`_RUN_SLOTS`), as ``(1, n)`` rows."""
    from equinox.internal import nextafter, prevbefore

    dtype = model.body_pos.dtype
    q = jnp.asarray(q, dtype)
    v = jnp.asarray(v, dtype)
    t0, t1, dt0 = (jnp.asarray(x, dtype) for x in (t0, t1, dt0))
    force = jnp.zeros(model.nv, dtype) if force is None else jnp.asarray(force, dtype)
    gravity = jnp.zeros(3, dtype) if gravity is None else jnp.asarray(gravity, dtype)
    stiffness = jnp.zeros(model.joints.n_joint, dtype) if stiffness is None else jnp.asarray(stiffness, dtype)
    reference = jnp.zeros(model.nq, dtype) if reference is None else jnp.asarray(reference, dtype)
    damping = jnp.zeros(model.nv, dtype) if damping is None else jnp.asarray(damping, dtype)
    # diffrax's ConstantStepSize: the step count, and the time 100 ulp below t1 above which a
    # step's end is rounded to t1
    steps = jnp.ceil((t1 - t0) / nextafter(dt0))
    t1_floor = t1
    for _ in range(100):
        t1_floor = prevbefore(t1_floor)
    limit = jnp.asarray(np.inf if max_steps is None else max_steps, dtype)
    schedule = jnp.stack([t0, t1, steps, t1_floor, limit, dt0, jnp.asarray(frozen, dtype), jnp.asarray(every, dtype)])
    row = lambda x: jnp.reshape(x, (1, -1))  # noqa: E731
    return (row(q), row(v), row(force), row(parameter_vector(model)), row(gravity), jnp.zeros((1, 1), dtype),
            row(stiffness), row(reference), row(damping), row(jnp.asarray(work0, dtype)), row(schedule))


def _rollout_outputs(outs) -> tuple:
    q1, v1, w1, status = (o[0] for o in outs[:4])
    return q1, v1, w1[0], status[0], status[1].astype(jnp.int32), status[2] > 0


def checkpoint_layout(model: Model, max_steps: int, checkpoints: int) -> tuple[int, int]:
    """``(every, width)``: steps between the checkpoints of a solve of at most ``max_steps``
    steps kept in ``checkpoints`` slots, and the width of their row (each: ``q``, ``v`` and the
    step's two times)."""
    every = max(1, -(-max_steps // max(checkpoints, 1)))
    slots = -(-max_steps // every)
    return every, slots * (model.nq + model.nv + 2)


def rk4_rollout_checkpointed(model: Model, q, v, t0, t1, dt0, max_steps: int, checkpoints: int, force=None, *,
                             gravity=None, stiffness=None, reference=None, damping=None, work0=0.0, frozen=False):
    """:func:`rk4_rollout` (bounded ``max_steps``) that also returns the checkpoints of its
    reverse sweep (:func:`rk4_rollout_vjp`): the state every ``every`` steps, ``every`` the
    fewest steps that fit ``max_steps`` into ``checkpoints`` slots (:func:`checkpoint_layout`).
    Returns ``(q, v, work, t, steps, failed, checkpoints)``."""
    every, width = checkpoint_layout(model, max_steps, checkpoints)
    rows = _rollout_rows(model, q, v, t0, t1, dt0, max_steps, force, gravity, stiffness, reference, damping, work0,
                         frozen, every)
    kernel = _kernel(model.tree, model.joints, False, np.dtype(model.body_pos.dtype), "rk4_run")
    outs = kernel.batched_with(kernel.widths + (width,))(*rows)
    return _rollout_outputs(outs) + (outs[4][0],)


def rk4_rollout_vjp(model: Model, q, v, t0, t1, dt0, max_steps: int, checkpoints: int, saved, steps, cotangent_q,
                    cotangent_v, cotangent_work=0.0, force=None, *, gravity=None, stiffness=None, reference=None,
                    damping=None, frozen=False):
    """Reverse mode of :func:`rk4_rollout` with respect to the initial ``(q, v)``, in one native call.

    ``saved``, ``steps``: the checkpoints and the steps taken, from
    :func:`rk4_rollout_checkpointed` with the same arguments; ``cotangent_*``: of the final ``q``,
    ``v`` and work. The steps between two checkpoints are recomputed (the same program as the
    solve's), then each step's generated reverse-mode program carries the cotangents back.
    Returns the cotangents of ``(q, v)``. A frozen trajectory passes them through."""
    every, _ = checkpoint_layout(model, max_steps, checkpoints)
    rows = _rollout_rows(model, q, v, t0, t1, dt0, max_steps, force, gravity, stiffness, reference, damping, 0.0,
                         frozen, every)
    dtype = model.body_pos.dtype
    row = lambda x: jnp.reshape(jnp.asarray(x, dtype), (1, -1))  # noqa: E731
    status = jnp.stack([jnp.zeros((), dtype), jnp.asarray(steps, dtype), jnp.zeros((), dtype)])
    kernel = _kernel(model.tree, model.joints, False, np.dtype(dtype), "rk4_run_vjp")
    ct_q, ct_v = kernel.batched(*rows, row(saved), row(status), row(cotangent_q), row(cotangent_v), row(cotangent_work))
    return ct_q[0], ct_v[0]


# ----------------------------------------------------------------------------- energies
def _energy_rows(model, q, v, gravity, stiffness, reference):
    row = lambda x: jnp.reshape(x, (1, -1))  # noqa: E731
    return (row(q), row(v), row(parameter_vector(model)), row(gravity), row(stiffness), row(reference))


def _energies_composed(model, q, v, gravity, stiffness, reference):
    """The energies written in JAX on the unrolled kernel's scalars (their derivatives)."""
    sc = unrolled._scalars
    kinetic, potential = unrolled._energies(model, sc(q), sc(v), tuple(sc(gravity)))
    spring = _spring_potential(model.joints, sc(q), sc(stiffness), sc(reference))
    dtype = q.dtype
    return tuple(jnp.asarray(e, dtype) for e in (kinetic, potential, spring))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _energies(kernel, model, q, v, gravity, stiffness, reference):
    out = kernel.batched(*_energy_rows(model, q, v, gravity, stiffness, reference))[0][0]
    return out[0], out[1], out[2]


def _energies_jvp(kernel, primals, tangents):
    # value: the native call; tangent: the same energies written in JAX (only the inputs that
    # carry a tangent are differentiated)
    out = _energies(kernel, *primals)
    return out, _split_jvp(kernel, None, None, out, primals, tangents, _energies_composed)


_energies.defjvp(_energies_jvp, symbolic_zeros=True)


def energies(
    model: Model,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    *,
    gravity: Float[ArrayLike, "3"] | None = None,
    stiffness: Float[ArrayLike, " n_joint"] | None = None,
    reference: Float[ArrayLike, " nq"] | None = None,
) -> tuple[Float[Array, ""], Float[Array, ""], Float[Array, ""]]:
    """``(kinetic energy, gravity potential, spring potential)`` of one state in one native call.

    Kinetic energy ``½ Σ_k V_k·(𝕀_k V_k) + ½ Σ_d a_d v_d²`` (armature ``a``); gravity potential
    ``−Σ_k m_k g·C_k`` (``gravity=None``: zero); spring potential ``½ Σ_j k_j |q_j ⊖ q_ref,j|²``
    (``stiffness`` per joint, ``reference`` ``(nq,)``, as :class:`jaxbody.JointSprings`; default
    none). A ``vmap`` batch (over states, saved times, or both) is one call; derivatives come
    from the same sums written in JAX (:func:`jaxbody.unrolled.energies`). No checks.
    """
    dtype = model.body_pos.dtype
    q = jnp.asarray(q, dtype)
    v = jnp.asarray(v, dtype)
    gravity = jnp.zeros(3, dtype) if gravity is None else jnp.asarray(gravity, dtype)
    stiffness = jnp.zeros(model.joints.n_joint, dtype) if stiffness is None else jnp.asarray(stiffness, dtype)
    reference = jnp.zeros(model.nq, dtype) if reference is None else jnp.asarray(reference, dtype)
    kernel = _kernel(model.tree, model.joints, False, np.dtype(dtype), "energy")
    return _energies(kernel, model, q, v, gravity, stiffness, reference)
