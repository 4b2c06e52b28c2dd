"""The native kernel's tracer: symbolic scalars whose arithmetic emits C++.

The tree algorithm of :mod:`jaxbody.backends.scalar` runs on :class:`Sym` scalars instead of
arrays; every operation appends one line of C++ to an :class:`Emitter` and records itself as an
operation ``(outputs, kind, args)``, from which the derivative programs are generated
(:mod:`jaxbody.backends.native.differentiate`). Structural zeros and ones fold as in the JAX
kernel and repeated expressions are shared. The model's parameters are inputs
(:class:`SymbolicModel`), so one compilation serves every parameter value.
"""

from typing import no_type_check

import jax.numpy as jnp
import numpy as np

from ..._types import Array, Float
from ...model import Model

# ----------------------------------------------------------------------------- symbolic scalars
# Every operation of a generated program goes through these (``no_type_check``: exempt from
# the test suite's runtime type checks, as the scalar helpers of jaxbody.backends.scalar are)
@no_type_check
class Emitter:
    """Collects the lines of one generated function and shares repeated expressions.

    Besides the C++ lines it records the program as operations ``(outputs, kind, args)`` in
    order, so that its derivatives can be generated from it (:func:`tangent_program`,
    :func:`adjoint_program`).
    """

    def __init__(self):
        self.lines: list[str] = []
        self.memo: dict[str, "Sym"] = {}
        self.ops: list[tuple] = []
        # value name -> (group, index) of the outputs of a hand-differentiated block
        # (:func:`inverse_dynamics_block`): the reverse pass emits the block's adjoint rule
        # instead of reversing the operations inside it
        self.blocks: dict[str, tuple[dict, int]] = {}

    def emit(self, expr: str, kind: str = "", args: tuple = ()) -> "Sym":
        sym = self.memo.get(expr)
        if sym is None:
            name = f"t{len(self.lines)}"
            self.lines.append(f"const U {name} = {expr};")
            sym = self.memo[expr] = Sym(name, self)
            self.ops.append((sym, kind, args))
        return sym

    def sincos(self, x):
        key = f"sincos({x.name})"
        pair = self.memo.get(key)
        if pair is None:
            n = len(self.lines)
            self.lines.append(f"U s{n}, c{n}; sc({x.name}, s{n}, c{n});")
            pair = self.memo[key] = (Sym(f"s{n}", self), Sym(f"c{n}", self))
            self.ops.append((pair, "sincos", (x,)))
        return pair


@no_type_check
def _lit(x) -> str:
    if isinstance(x, Sym):
        return x.name
    return f"T({float(x)!r})"


@no_type_check
def _value(x) -> str:
    """``x`` as a vector expression (a constant broadcast to every lane)."""
    return x.name if isinstance(x, Sym) else f"(U{{}} + T({float(x)!r}))"


@no_type_check
class Sym:
    """A scalar of the generated program: a C++ name; arithmetic emits code.

    Python floats mixed in are constants known at generation time (the unrolled kernel's
    structural ``0.0``/``1.0``); they fold as in :func:`jaxbody.scalar.add` and friends.
    """

    symbolic = True
    __slots__ = ("name", "em")

    def __init__(self, name: str, em: Emitter):
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


@no_type_check
def with_derivative(value, derivative):
    """``value``, whose derivative the derivative programs take to be ``derivative``'s: the
    computation of ``derivative``'s own value is left to the compiler to drop where nothing else
    reads it."""
    if not isinstance(derivative, Sym):
        return value
    return derivative.em.emit(f"{_value(value)} /* derivative: {derivative.name} */", "attach", (value, derivative))


@no_type_check
def stop_derivative(x):
    """``x`` with no derivative in the generated derivative programs (constants pass through)."""
    return x.stop() if isinstance(x, Sym) else x


class SymbolicModel:
    """What the unrolled passes read of a model, with every parameter a symbol ``p[i]``."""

    FIELDS = ("body_pos", "body_quat", "body_mass", "body_com", "body_inertia", "joint_pos", "joint_axis", "dof_armature", "qpos0")

    def __init__(self, tree, joints, em: Emitter, slot: int = 3):
        n = sum(int(np.prod(shape)) for shape in _field_shapes(tree, joints))
        p = np.empty(n, dtype=object)
        p[:] = input_scalars(em, "p", n, slot)
        unflatten_parameters(self, tree, joints, p, np.reshape)


def unflatten_parameters(target, tree, joints, flat, reshape) -> None:
    """Set the fields the unrolled passes read on ``target``, sliced from the flat parameter
    vector ``flat`` (order of :func:`parameter_vector`) with ``reshape``."""
    target.tree, target.joints = tree, joints
    target.n_body, target.nv, target.nq = tree.n_body, joints.nv, joints.nq
    offset = 0
    for name, shape in zip(SymbolicModel.FIELDS, _field_shapes(tree, joints)):
        size = int(np.prod(shape))
        setattr(target, name, reshape(flat[offset : offset + size], shape))
        offset += size


@no_type_check
def where_negative(c, a, b):
    """``a`` where ``c < 0``, else ``b``: on symbols, JAX scalars or constants."""
    if isinstance(c, Sym):
        if not isinstance(a, Sym) and not isinstance(b, Sym) and a == b:
            return a
        return c.where_negative(a, b)
    if isinstance(c, float | int):
        return a if c < 0 else b
    return jnp.where(c < 0, a, b)


@no_type_check
def sym_sqrt(x):
    """``√x`` on a symbol (emitted C++) or a JAX scalar."""
    return x.sqrt() if isinstance(x, Sym) else jnp.sqrt(x)


@no_type_check
def sym_atan2(y, x):
    """``atan2(y, x)`` on symbols (emitted C++) or JAX scalars."""
    return y.atan2(x) if isinstance(y, Sym) else jnp.arctan2(y, x)


def declared_scalars(em: Emitter, name: str, n: int, source) -> list:
    """``n`` input scalars ``name_i`` of the program, declared as ``source(i)`` (a C++ expression)."""
    out = []
    for i in range(n):
        em.lines.append(f"const U {name}_{i} = {source(i)};")
        sym = Sym(f"{name}_{i}", em)
        em.ops.append((sym, "input", (name,)))
        out.append(sym)
    return out


def input_scalars(em: Emitter, name: str, n: int, slot: int) -> list:
    """``n`` scalars of operand ``slot``, loaded (one lane per state) where they are emitted."""
    return declared_scalars(em, name, n, lambda i: f"ld({slot}, {i})")


def _field_shapes(tree, joints):
    nb, nj = tree.n_body, joints.n_joint
    return ((nb, 3), (nb, 4), (nb,), (nb, 3), (nb, 3, 3), (nj, 3), (nj, 3), (joints.nv,), (joints.nq,))


def parameter_vector(model: Model) -> Float[Array, " n_param"]:
    """The model's parameters flattened in the order the native kernel reads them."""
    return jnp.concatenate([jnp.ravel(getattr(model, name)) for name in SymbolicModel.FIELDS])
