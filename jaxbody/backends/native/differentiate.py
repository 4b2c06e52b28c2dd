"""Source-to-source differentiation of the native kernel's operation list.

A forward-mode pass emits the tangent of every operation (:func:`tangent_program`), a
reverse-mode pass the adjoint of every value that depends on the state, last operation first
(:func:`adjoint_program`); a block of hand-derived adjoint (inverse dynamics of hinge and slide
trees, :func:`inverse_dynamics_block`) is reversed by its own rule.
"""

from typing import no_type_check

from .. import scalar
from .symbolic import Emitter, Sym, where_negative

# run once per operation of the program they differentiate (``no_type_check``: exempt from the
# test suite's runtime type checks, as the scalar helpers of jaxbody.backends.scalar are)
@no_type_check
def _is_zero(x) -> bool:
    return not isinstance(x, Sym) and x == 0


def active_values(ops: list, seeds: set) -> set:
    """Names of the program's values that depend on the inputs named in ``seeds``."""
    active = set()
    for out, kind, args in ops:
        if kind == "input":
            if args[0] in seeds:
                active.add(out.name)
        elif kind == "stop":
            continue
        elif any(isinstance(a, Sym) and a.name in active for a in args):
            active.update(o.name for o in (out if kind == "sincos" else (out,)))
    return active


@no_type_check
def tangent_program(ops: list, seeds: dict) -> dict:
    """Forward mode: the tangent of every value, emitted as code (zeros folded away).

    ``seeds`` maps input names to their tangents; returns value name -> tangent (a symbol,
    or ``0.0`` where the tangent is structurally zero).
    """
    tan = dict(seeds)

    def d(a):
        return tan.get(a.name, 0.0) if isinstance(a, Sym) else 0.0

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
            t = 0.0 if _is_zero(ds[1]) and _is_zero(ds[2]) else where_negative(cond, ds[1], ds[2])
        else:
            raise AssertionError(f"no tangent rule for {kind!r}")
        tan[out.name] = t
    return tan


def inverse_dynamics_block(em: Emitter, model, q: list, v: list, acceleration: list, gravity, tau: list) -> list:
    """``tau`` (inverse dynamics at ``(q, v, acceleration)``, ``acceleration`` held) as the outputs
    of one block whose reverse-mode rule is the hand-derived :func:`jaxbody.scalar.inverse_dynamics_vjp`
    (trees of hinges and slides, no body loads), not the reverse of the Newton–Euler operations."""
    group: dict = {"cts": [0.0] * len(tau)}

    def rule(lam):
        q_bar, v_bar = scalar.inverse_dynamics_vjp(model, q, v, acceleration, gravity, lam)
        return list(zip(q, q_bar)) + list(zip(v, v_bar))

    group["rule"] = rule
    out = []
    for i, t in enumerate(tau):
        if not isinstance(t, Sym):
            out.append(t)
            continue
        sym = em.emit(f"{t.name} /* inverse dynamics */", "block", (t,))
        em.blocks[sym.name] = (group, i)
        group.setdefault("first", i)  # the reverse pass reaches it last: the rule runs there
        out.append(sym)
    return out


@no_type_check
def adjoint_program(ops: list, active: set, seeds: list) -> dict:
    """Reverse mode: the adjoint of every active value, emitted as code, last operation first.

    ``seeds``: ``(value, cotangent)`` pairs; returns value name -> adjoint. The outputs of a
    hand-differentiated block (:func:`inverse_dynamics_block`) collect their adjoints; at the
    block's first symbolic output (the last one reached) its rule emits the adjoints of its inputs.
    """
    adj: dict = {}

    def acc(a, g):
        if isinstance(a, Sym) and a.name in active and not _is_zero(g):
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
            if isinstance(args[1], Sym) and args[1].name in active:
                acc(args[1], -g)
        elif kind == "neg":
            acc(args[0], -g)
        elif kind == "attach":
            acc(args[1], g)
        elif kind == "*":
            for a, b in ((args[0], args[1]), (args[1], args[0])):
                if isinstance(a, Sym) and a.name in active:
                    acc(a, g * b)
        elif kind == "/":
            gy = g / args[1]
            acc(args[0], gy)
            if isinstance(args[1], Sym) and args[1].name in active:
                acc(args[1], -(gy * out))
        elif kind == "sqrt":
            acc(args[0], g * 0.5 / out)
        elif kind == "atan2":
            y, x = args
            r = g / (x * x + y * y)
            acc(y, r * x)
            if isinstance(x, Sym) and x.name in active:
                acc(x, -(r * y))
        elif kind == "select":
            cond = args[0]
            for branch, (a, b) in ((args[1], (g, 0.0)), (args[2], (0.0, g))):
                if isinstance(branch, Sym) and branch.name in active:
                    acc(branch, where_negative(cond, a, b))
        else:
            raise AssertionError(f"no adjoint rule for {kind!r}")
    return adj
