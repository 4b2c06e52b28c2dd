"""Seeded random MJCF trees for tests against MuJoCo (random trees come from a seed, so a failure reproduces).

Import from a test file with (pytest puts ``tests/`` on ``sys.path``)::

    from _support.mjcf_random import random_mjcf, random_state

:func:`random_mjcf` writes a kinematic tree that always compiles in MuJoCo and mixes every
joint kind jaxbody supports: a free joint (on root bodies only), ball, hinge and slide joints,
several joints on one body (two hinges = a universal joint, slide + hinge, ball + slide ...),
joints off the body origin, rotated body frames (``quat``, ``euler``, ``axisangle``,
``xyaxes``), rotated inertial frames (``quat`` + ``diaginertia`` or ``fullinertia``), mass
ratios up to ``mass_ratio``, random armature, damping, stiffness, ``springref`` and ``ref``,
welded (jointless) bodies, several trees and a random gravity vector.

With ``rigid_only=True`` (default) the model has nothing but rigid bodies, joints, springs and
dampers, and its ``<option><flag>`` disables contacts, constraints, limits, equality, friction
loss and actuation, so MuJoCo computes exactly what jaxbody models. With ``rigid_only=False``
the generator adds what jaxbody does not model (joint limits, friction loss, collision geoms,
an actuator, a tendon, an equality constraint) and no disable flags: use it for import
warnings.
"""

import numpy as np

__all__ = ["random_mjcf", "random_state", "RIGID_ONLY_FLAGS"]

# MJCF <flag> attributes (= mjtDisableBit names without "mjDSBL_", lower case) that
# rigid_only=True disables; springs, dampers and gravity stay on.
RIGID_ONLY_FLAGS = ("contact", "constraint", "limit", "equality", "frictionloss", "actuation")


def _f(x) -> str:
    return " ".join(f"{float(v):.17g}" for v in np.atleast_1d(np.asarray(x, dtype=np.float64)))


def _unit(rng, n=3):
    v = rng.normal(size=n)
    return v / np.linalg.norm(v)


def _quat_to_matrix(q):
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _orientation(rng) -> str:
    r = rng.integers(5)
    if r == 0:
        return ""
    if r == 1:
        return f' quat="{_f(_unit(rng, 4))}"'
    if r == 2:
        return f' euler="{_f(rng.uniform(-np.pi, np.pi, 3))}"'
    if r == 3:
        return f' axisangle="{_f(np.r_[_unit(rng), rng.uniform(-np.pi, np.pi)])}"'
    x = _unit(rng)
    y = _unit(rng)
    y = y - x * (x @ y)
    return f' xyaxes="{_f(np.r_[x, y / np.linalg.norm(y)])}"'


def _axis(rng):
    if rng.random() < 0.3:  # axis-aligned, sometimes negative
        a = np.zeros(3)
        a[rng.integers(3)] = rng.choice([-1.0, 1.0])
        return a
    return _unit(rng) * rng.uniform(0.5, 2.0)  # MuJoCo normalises


def _maybe(rng, p, hi):
    return float(rng.uniform(0.0, hi)) if rng.random() < p else 0.0


def random_mjcf(
    seed: int,
    n_body: int = 8,
    *,
    rigid_only: bool = True,
    free_root: bool | None = None,
    n_root: int | None = None,
    max_joints: int = 3,
    mass_ratio: float = 1e4,
    n_key: int = 2,
    springs: bool = True,
    name: str | None = None,
) -> str:
    """A random MJCF tree that MuJoCo compiles, as an XML string.

    Args:
        seed: the random seed (same seed, same XML).
        n_body: number of bodies (the world body not counted).
        rigid_only: disable everything jaxbody does not model (see the module docstring);
            ``False`` adds limits, friction loss, collision geoms, an actuator, a tendon and an
            equality constraint instead.
        free_root: whether the first root body carries a free joint (random when None).
        n_root: number of bodies attached to the world (random 1..2 when None).
        max_joints: most joints on one body (at most one ball; at most 6 DoFs a body).
        mass_ratio: body masses are log-uniform in ``[m0, m0 * mass_ratio]``.
        n_key: number of keyframes (random ``qpos``/``qvel``, normalised quaternions).
        springs: give joints random stiffness (all kinds, ``springref`` for hinge/slide).
        name: the model name (default ``random<seed>``).
    """
    rng = np.random.default_rng(seed)
    if n_root is None:
        n_root = int(rng.integers(1, 3))
    n_root = max(1, min(n_root, n_body))
    if free_root is None:
        free_root = bool(rng.random() < 0.5)
    parent = [-1] * n_root + [
        int(rng.integers(max(0, k - 3), k)) for k in range(n_root, n_body)
    ]
    children = {k: [] for k in range(-1, n_body)}
    for k, p in enumerate(parent):
        children[p].append(k)
    m0 = 0.05
    masses = m0 * np.exp(rng.uniform(0.0, np.log(mass_ratio), n_body))
    if n_body >= 2:  # make the full ratio appear
        masses[int(rng.integers(n_body))] = m0
        masses[int(rng.integers(n_body))] = m0 * mass_ratio

    joints = []  # (name, kind) in MuJoCo's order (depth-first = XML order)
    scalar_joints = []
    lines = []

    def emit_body(k, depth):
        ind = "  " * (depth + 2)
        pos = rng.uniform(-0.5, 0.5, 3)
        lines.append(f'{ind}<body name="b{k}" pos="{_f(pos)}"{_orientation(rng)}>')
        # inertial frame
        m = masses[k]
        dims = np.exp(rng.uniform(np.log(0.03), np.log(1.0), 3))
        x2 = dims**2
        diag = m / 12.0 * np.array([x2[1] + x2[2], x2[0] + x2[2], x2[0] + x2[1]])
        ipos = rng.uniform(-0.3, 0.3, 3)
        if rng.random() < 0.5:
            iq = _unit(rng, 4)
            lines.append(
                f'{ind}  <inertial pos="{_f(ipos)}" quat="{_f(iq)}" mass="{_f(m)}" '
                f'diaginertia="{_f(diag)}"/>'
            )
        else:
            R = _quat_to_matrix(_unit(rng, 4))
            I = R @ np.diag(diag) @ R.T
            full = [I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]]
            lines.append(
                f'{ind}  <inertial pos="{_f(ipos)}" mass="{_f(m)}" fullinertia="{_f(full)}"/>'
            )
        # joints
        if parent[k] == -1 and k == 0 and free_root:
            kinds = ["free"]
        else:
            nj = int(rng.choice(np.arange(max_joints + 1), p=_njoint_probs(max_joints)))
            kinds, dofs, has_ball = [], 0, False
            for _ in range(nj):
                # MuJoCo: a ball joint may be followed only by slides in the same body
                opts = ["slide"] if has_ball else ["hinge", "hinge", "slide", "ball"]
                kd = str(rng.choice(opts))
                nd = 3 if kd == "ball" else 1
                if dofs + nd > 6:
                    continue
                kinds.append(kd)
                dofs += nd
                has_ball |= kd == "ball"
        axes = _independent_axes(rng, kinds)
        for i, kd in enumerate(kinds):
            jn = f"j{k}_{i}"
            attrs = [f'name="{jn}"', f'type="{kd}"']
            if kd != "free":
                attrs.append(f'pos="{_f(rng.uniform(-0.2, 0.2, 3))}"')
            if kd in ("hinge", "slide"):
                attrs.append(f'axis="{_f(axes[i])}"')
                if rng.random() < 0.3:
                    attrs.append(f'ref="{_f(rng.uniform(-1, 1))}"')
                if springs and rng.random() < 0.6:
                    attrs.append(f'springref="{_f(rng.uniform(-1, 1))}"')
                if not rigid_only and rng.random() < 0.5:
                    lo = rng.uniform(-2.0, -0.5)
                    attrs.append(f'range="{_f([lo, lo + rng.uniform(1.0, 3.0)])}"')
                scalar_joints.append(jn)
            arm = _maybe(rng, 0.6, 0.1)
            damp = _maybe(rng, 0.6, 1.0)
            stiff = _maybe(rng, 0.6, 5.0) if springs else 0.0
            if arm:
                attrs.append(f'armature="{_f(arm)}"')
            if damp:
                attrs.append(f'damping="{_f(damp)}"')
            if stiff:
                attrs.append(f'stiffness="{_f(stiff)}"')
            if not rigid_only and rng.random() < 0.3:
                attrs.append(f'frictionloss="{_f(rng.uniform(0.01, 0.5))}"')
            lines.append(f'{ind}  <joint {" ".join(attrs)}/>')
            joints.append((jn, kd))
        if rng.random() < 0.3:
            lines.append(f'{ind}  <site name="s{k}" pos="{_f(rng.uniform(-0.2, 0.2, 3))}"/>')
        if not rigid_only and rng.random() < 0.5:
            # mass="0": explicit <inertial> already fixes the body's mass properties
            lines.append(f'{ind}  <geom name="g{k}" type="sphere" size="0.05" mass="0"/>')
        for c in children[k]:
            emit_body(c, depth + 1)
        lines.append(f"{ind}</body>")

    for r in children[-1]:
        emit_body(r, 0)

    g = np.array([0.0, 0.0, -9.81]) + rng.normal(scale=3.0, size=3)
    flags = ""
    if rigid_only:
        flags = "<flag " + " ".join(f'{f}="disable"' for f in RIGID_ONLY_FLAGS) + "/>"
    head = [
        f'<mujoco model="{name or f"random{seed}"}">',
        '  <compiler angle="radian" autolimits="true"/>',
        f'  <option gravity="{_f(g)}">{flags}</option>',
        "  <worldbody>",
    ]
    tail = ["  </worldbody>"]
    if not rigid_only:
        if scalar_joints:
            tail += [
                "  <actuator>",
                f'    <motor name="m0" joint="{scalar_joints[0]}" gear="2"/>',
                "  </actuator>",
                "  <tendon>",
                f'    <fixed name="t0"><joint joint="{scalar_joints[0]}" coef="1"/></fixed>',
                "  </tendon>",
            ]
        if len(scalar_joints) >= 2:
            tail += [
                "  <equality>",
                f'    <joint name="e0" joint1="{scalar_joints[0]}" joint2="{scalar_joints[1]}"/>',
                "  </equality>",
            ]
    if n_key:
        tail.append("  <keyframe>")
        for i in range(n_key):
            qpos, qvel = [], []
            for jn, kd in joints:
                if kd == "free":
                    qpos += list(rng.uniform(-1, 1, 3)) + list(_unit(rng, 4))
                    qvel += list(rng.normal(size=6))
                elif kd == "ball":
                    qpos += list(_unit(rng, 4))
                    qvel += list(rng.normal(size=3))
                else:
                    qpos.append(rng.uniform(-1, 1))
                    qvel.append(rng.normal())
            if joints:
                tail.append(f'    <key name="key{i}" qpos="{_f(qpos)}" qvel="{_f(qvel)}"/>')
            else:
                tail.append(f'    <key name="key{i}"/>')
        tail.append("  </keyframe>")
    tail.append("</mujoco>")
    return "\n".join(head + lines + tail) + "\n"


def _independent_axes(rng, kinds):
    """Hinge/slide axes of one body, well apart so the body's DoFs stay independent.

    Hinges of one body get pairwise non-parallel axes (a ball counts as spanning every
    rotation, so a hinge never follows it: MuJoCo forbids that anyway); slides get axes whose
    span is well conditioned. Otherwise MuJoCo's mass matrix would be singular.
    """
    axes = {}
    for group in ("hinge", "slide"):
        idx = [i for i, k in enumerate(kinds) if k == group]
        for _ in range(1000):
            cand = [_axis(rng) for _ in idx]
            if not cand:
                break
            u = np.array([c / np.linalg.norm(c) for c in cand])
            sv = np.linalg.svd(u, compute_uv=False)
            if sv[-1] > 0.3:
                break
        axes.update(zip(idx, cand))
    return axes


def _njoint_probs(max_joints):
    base = np.array([0.15, 0.5, 0.25, 0.1, 0.05, 0.05, 0.05][: max_joints + 1])
    return base / base.sum()


def random_state(mj_model, rng, *, scale: float = 1.0):
    """Random ``(qpos, qvel, qacc)`` for a compiled ``mujoco.MjModel`` (unit quaternions).

    Hinge and slide coordinates are ``qpos0`` plus a uniform offset in ``[-scale*pi, scale*pi]``
    (slides: ``[-scale, scale]``); ball and free quaternions are uniform random unit
    quaternions; free positions lie in ``[-1, 1]^3``; ``qvel`` and ``qacc`` are standard normal
    times ``scale``.
    """
    m = mj_model
    q = np.array(m.qpos0, dtype=np.float64)
    for j in range(m.njnt):
        a, t = int(m.jnt_qposadr[j]), int(m.jnt_type[j])
        if t == 0:  # free
            q[a : a + 3] = rng.uniform(-1, 1, 3)
            q[a + 3 : a + 7] = _unit(rng, 4)
        elif t == 1:  # ball
            q[a : a + 4] = _unit(rng, 4)
        elif t == 2:  # slide
            q[a] += rng.uniform(-scale, scale)
        else:  # hinge
            q[a] += rng.uniform(-scale * np.pi, scale * np.pi)
    v = scale * rng.normal(size=m.nv)
    acc = scale * rng.normal(size=m.nv)
    return q, v, acc
