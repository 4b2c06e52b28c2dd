"""The JAX side of the native forward dynamics: the custom-JVP function, the primitive that is
linear in the tangents (its batching and transpose rules), and the fallbacks to the JAX kernels
for what the generated programs do not serve."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

from .. import scalar
from .. import vectorised
from ..._types import Array, ArrayLike, Float
from ...model import Model
from .symbolic import parameter_vector, unflatten_parameters
from .rk4 import joint_force, rk4_scalars
from .codegen import residual_count, result_widths
from .build import compiled_kernel, merge_batch

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
    return [jax.core.ShapedArray((batch, w), np.dtype(dtype)) for w in result_widths(joints, mode)]


def _linear_impl(*args, tree, joints, with_external, dtype, mode):
    return compiled_kernel(tree, joints, with_external, np.dtype(dtype), mode).call(*args)


def _linear_batch(args, dims, **params):
    axis_size = next(a.shape[d] for a, d in zip(args, dims) if d is not None)
    args = [a if d is None else jnp.moveaxis(a, d, 0) for a, d in zip(args, dims)]
    merged, inner = merge_batch(axis_size, args, [d is not None for d in dims])
    outs = _linear(*merged, **params)
    return [o.reshape(axis_size, inner, o.shape[-1]) for o in outs], [0] * len(outs)


_TRANSPOSED = {"jvp": "vjp", "vjp": "jvp", "rk4_jvp": "rk4_vjp", "rk4_vjp": "rk4_jvp"}


def _linear_transpose(cts, *args, mode, **params):
    n_res = residual_count(mode)
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
    sc = scalar.scalars
    loads = [tuple(sc(ext[6 * b : 6 * b + 6])) for b in range(tree.n_body)] if with_external else None
    M, bias, lam = scalar.bias_and_mass(model, sc(q), sc(v), tuple(sc(g)), loads)
    rhs = [scalar.add(fi, -bi) for fi, bi in zip(sc(f), bias)]
    return scalar.stack(scalar.ltdl_solve(M, lam, rhs), p.dtype)


def _single_step(tree, joints, with_external, q, v, f, p, g, ext, h, k, r, d):
    """One RK4 step of one state from the operands' rows, by the unrolled kernel."""
    sc = scalar.scalars

    def field(qs, vs, t):
        total, power = joint_force(joints, qs, vs, sc(f), sc(k), sc(r), sc(d))
        a = _single_state(tree, joints, with_external, jnp.stack(qs), jnp.stack(vs), scalar.stack(total, p.dtype), p, g, ext)
        return sc(a), power

    out = rk4_scalars(field, joints, sc(q), sc(v), h[0])
    return tuple(scalar.stack(o, p.dtype) for o in out)


def _linear_fallback(*args, tree, joints, with_external, dtype, mode):
    """The same linear map written in JAX (differentiable in its residuals: second derivatives)."""
    batch = max(a.shape[0] for a in args)
    rows = [jnp.broadcast_to(a, (batch, a.shape[1])) for a in args]
    n_res = residual_count(mode)

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
    n_res = residual_count(params["mode"])
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
        unflatten_parameters(self, tree, joints, p, jnp.reshape)


#: Largest number of DoFs whose derivatives the generated programs serve; above it the
#: vectorised kernel gives the tangents. The derivative programs are about 2–2.5 times the
#: forward one in lines; they build in seconds for the Panda arm, and for a 20-link chain the
#: reverse-mode program builds in about 21 s, the RK4 step in about a minute and the step's
#: reverse-mode program in 54 s (once per tree, then cached; `benchmarks/kernels.py build`,
#: benchmarks/results/native_build_rk4.md). Taking the tangents of a 20-link chain from the
#: vectorised kernel made a rollout gradient about 50 times the native rollout.
MAX_DERIVATIVE_DOFS = 20


# ----------------------------------------------------------------------------- the JAX function
def _reference(model, q, v, force, gravity, external):
    return vectorised.forward_dynamics(model, q, v, force, gravity=gravity, external=external)


def state_rows(model, q, v, force, gravity, external):
    """The forward-dynamics operands ``(q, v, f, p, g, ext)`` of one state as ``(1, n)`` rows."""
    row = lambda x: jnp.reshape(x, (1, -1))  # noqa: E731
    ext = row(external) if external is not None else jnp.zeros((1, 1), q.dtype)
    return (row(q), row(v), row(force), row(parameter_vector(model)), row(gravity), ext)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def forward_dynamics_call(kernel, model, q, v, force, gravity, external):
    """One native forward-dynamics call of the compiled ``kernel`` (its JVP rule below)."""
    return kernel.batched(*state_rows(model, q, v, force, gravity, external))[0][0]


def split_jvp(kernel, mode, rows, out, primals, tangents, reference):
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
    # value: the native call; tangent: split_jvp, the rest from the vectorised kernel
    out = forward_dynamics_call(kernel, *primals)
    (tangent,) = split_jvp(kernel, "jvp", state_rows(*primals), (out,), primals, tangents, lambda *a: (_reference(*a),))
    return out, tangent


forward_dynamics_call.defjvp(_forward_dynamics_jvp, symbolic_zeros=True)


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

    Same arguments and result as :func:`jaxbody.backends.unrolled.forward_dynamics`; ``jit``, ``vmap``
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
    kernel = compiled_kernel(model.tree, model.joints, external is not None, np.dtype(dtype))
    return forward_dynamics_call(kernel, model, q, v, force, gravity, external)
