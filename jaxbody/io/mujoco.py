"""Import MJCF and URDF models through MuJoCo's own compiler.

Nothing here parses XML for physics: :func:`from_mjcf` and :func:`from_urdf` hand the file
(or string) to ``mujoco.MjModel.from_xml_path`` / ``from_xml_string`` and :func:`from_mujoco`
reads the compiled arrays, so defaults classes, ``childclass``, ``inertiafromgeom``,
``fusestatic``, angle units, Euler sequences and URDF conversion all behave exactly as in
MuJoCo. The result compares one-to-one with MuJoCo (DESIGN.md):

* body ``k`` of jaxbody is MuJoCo body ``k + 1`` (the world body is dropped); MuJoCo's
  numbering is already topological (``parent < child``); ``q``/``v`` are ``qpos``/``qvel``;
* ``body_com`` = ``body_ipos``; ``body_inertia`` = ``R(body_iquat) diag(body_inertia) Rᵀ``,
  the central inertia tensor in body axes;
* joints keep MuJoCo's order (the joints of one body are consecutive and applied in order)
  with ``jnt_pos``, ``jnt_axis``, ``jnt_stiffness``, ``dof_armature``, ``dof_damping``,
  ``qpos0`` and ``qpos_spring``; keyframes keep ``key_qpos``, ``key_qvel`` and their names;
* a body with a free joint keeps its ``body_pos``/``body_quat`` (they are its pose in
  ``qpos0``), although MuJoCo's kinematics ignore them: ``qpos`` sets the pose;
* what MuJoCo's dynamics would not see is not imported either: ``<flag gravity="disable">``
  gives zero gravity, ``spring="disable"`` zero joint stiffness and ``damper="disable"`` zero
  damping;
* armature and damping that MuJoCo adds to a joint from an actuator (MuJoCo 4 ``actuator
  armature``/``damping`` on a hinge or slide joint transmission, scaled by ``gear²``) are
  folded into ``dof_armature``/``dof_damping``, as MuJoCo does in ``M`` and ``qfrc_passive``.

* active ``<equality><connect>`` constraints become the model's loop closures
  (``Model.loops``, :func:`connect_loops`); scenes impose them as Maggi constraints.

Everything jaxbody does not model (contacts, joint limits, friction loss, tendons, equality
constraints other than active connects, actuator forces, fluid forces, gravity compensation, nonlinear or plastic
springs, flexes, plugins, mocap bodies) is reported in one ``UserWarning`` that names the
elements, or raised as ``ValueError`` with ``strict=True``; see :func:`unsupported_features`.
Features that MuJoCo has switched off with ``<option><flag .../>`` are not reported.
"""

import dataclasses
import os
import pathlib
import re
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from ..joints import HINGE, JOINT_KIND_NAMES, SLIDE, JointLayout
from .._util import quat_to_matrix
from ..loop_directions import close_loops, loop_frame, loop_rows
from ..loops import LoopSpec
from ..model import Model, validate_parameters
from ..tree import BodyTree

__all__ = ["from_mjcf", "from_urdf", "from_mujoco", "unsupported_features"]

# Lines of the report are "<what>: <count> (<names>)"; at most this many names are listed.
_MAX_NAMES = 8

_HINTS = (
    (
        "mass and inertia of moving bodies",
        "body {name!r} moves (it carries a joint) but its mass or inertia is not positive",
    ),
    (
        "free joint can only be used on top level",
        "body {name!r} has a free joint but is not attached to the world: free joints are "
        "allowed only on root bodies",
    ),
    (
        "inertia must satisfy A + B >= C",
        "body {name!r}: the principal moments of inertia violate the triangle inequality "
        "(A + B >= C)",
    ),
    (
        "inertia must have positive eigenvalues",
        "body {name!r}: the inertia tensor is not positive definite",
    ),
)


def _mujoco():
    try:
        import mujoco
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(
            "jaxbody.from_mjcf/from_urdf/from_mujoco need the `mujoco` package: "
            "pip install 'jaxbody[mujoco]'"
        ) from e
    return mujoco


# ---------------------------------------------------------------------------- public API
def from_mjcf(source, *, strict: bool = False, dtype=None) -> Model:
    """Load an MJCF model (a file path or an XML string) through MuJoCo's compiler.

    Args:
        source: path to an ``.xml`` file (``str`` or ``os.PathLike``), or the XML itself as a
            string starting with ``<``. Relative includes and assets resolve as in MuJoCo.
        strict: raise instead of warning when the model has features jaxbody does not model.
        dtype: floating dtype of the parameters (default ``None``: JAX's default float,
            float64 under ``jax_enable_x64``, else float32). ``float64`` without
            ``jax_enable_x64`` is refused (JAX would silently narrow it to float32).

    Returns:
        The :class:`~jaxbody.Model` (see the module docstring for the conventions).

    Raises:
        FileNotFoundError: ``source`` is a path that does not exist.
        ValueError: MuJoCo's compiler rejects the model (the message names the element, e.g.
            a moving body without mass, an inertia breaking the triangle inequality, a free
            joint below a root body); the compiled parameters fail
            :func:`~jaxbody.validate_parameters` (naming the body or joint); or, with
            ``strict=True``, the model has features jaxbody does not model; ``dtype`` is not a
            floating dtype, or is float64 while ``jax_enable_x64`` is off.

    Warns:
        UserWarning: one warning listing every feature jaxbody ignores (``strict=False``).
    """
    return _from_mujoco(compile_source(source, "from_mjcf", "MJCF"), strict, dtype, "from_mjcf")


def from_urdf(source, *, strict: bool = False, dtype=None) -> Model:
    """Load a URDF model through MuJoCo's compiler (which converts URDF to MJCF).

    MuJoCo's URDF defaults apply: links joined by fixed joints are fused into their parent
    (``fusestatic``), the first link is welded to the world unless the file adds a floating
    joint through a ``<mujoco>`` extension, and URDF joint limits become MuJoCo limits (which
    jaxbody reports as not modelled). Arguments, returns, raises and warnings as in
    :func:`from_mjcf`.
    """
    m = compile_source(source, "from_urdf", "URDF")
    return _from_mujoco(m, strict, dtype, "from_urdf", extra=_urdf_ignored_elements(source))


# What MuJoCo's URDF reader reads; any other element is skipped without a word, so it is reported
_URDF_READ = {"robot": {"link", "joint", "material", "mujoco"}, "joint": {"origin", "parent", "child", "axis", "limit", "dynamics"}}


def _urdf_ignored_elements(source) -> list[str]:
    """One report line naming the URDF elements MuJoCo's URDF reader skips (``<gazebo>``,
    ``<transmission>``, a joint's ``<mimic>`` ...), with their counts; empty when none."""
    import xml.etree.ElementTree as ET

    try:
        text = source if isinstance(source, str) and source.lstrip().startswith("<") else pathlib.Path(source).read_text()
        root = ET.fromstring(text)
    except (OSError, ET.ParseError, UnicodeDecodeError):  # MuJoCo has read it: nothing more to say
        return []
    counts: dict[str, int] = {}
    for child in root:
        if isinstance(child.tag, str) and child.tag not in _URDF_READ["robot"]:
            counts[f"<{child.tag}>"] = counts.get(f"<{child.tag}>", 0) + 1
    for joint in root.iter("joint"):
        for child in joint:
            if isinstance(child.tag, str) and child.tag not in _URDF_READ["joint"]:
                counts[f"<joint><{child.tag}>"] = counts.get(f"<joint><{child.tag}>", 0) + 1
    if not counts:
        return []
    listed = ", ".join(f"{n} {tag}" for tag, n in sorted(counts.items()))
    return [f"URDF elements MuJoCo's URDF reader skips (ignored): {sum(counts.values())} elements ({listed})"]


def from_mujoco(mj_model, *, strict: bool = False, dtype=None) -> Model:
    """Convert a compiled ``mujoco.MjModel`` (its current arrays; it is not modified).

    Reads ``body_parentid``, ``body_pos``, ``body_quat``, ``body_mass``, ``body_ipos``,
    ``body_iquat``, ``body_inertia``, ``jnt_type``, ``jnt_bodyid``, ``jnt_pos``, ``jnt_axis``,
    ``jnt_stiffness``, ``dof_armature``, ``dof_damping``, ``qpos0``, ``qpos_spring``,
    ``opt.gravity``, ``key_qpos``, ``key_qvel`` and the names. Arguments, returns, raises and
    warnings as in :func:`from_mjcf`; arrays edited after compilation are validated too
    (non-finite values, negative masses, a moving body without mass, inertias breaking the
    triangle inequality, negative armature/damping/stiffness), naming the body or joint.
    """
    return _from_mujoco(mj_model, strict, dtype, "from_mujoco")


# called inside a traced function (a jit that imports its model), the model is a constant of the
# program: its arrays are made, and checked, now rather than staged into it
@jax.ensure_compile_time_eval()
def _from_mujoco(mj_model, strict: bool, dtype, _caller: str, extra=()) -> Model:
    """:func:`from_mujoco`, with the public function's name (``_caller``) for messages."""
    dtype = _check_dtype(dtype, _caller)
    mujoco = _mujoco()
    m = mj_model
    if not isinstance(m, mujoco.MjModel):
        raise TypeError(f"{_caller}: expected a mujoco.MjModel, got {type(m).__name__}")
    model_name = _model_name(m)
    where = f"{_caller}: MuJoCo model {model_name!r}"

    nb = int(m.nbody) - 1
    if nb < 1:
        raise ValueError(f"{where} has no bodies besides the world body")
    body_names = _unique_names(
        [_name(m, mujoco.mjtObj.mjOBJ_BODY, i) for i in range(1, nb + 1)], "body"
    )
    joint_types = [int(t) for t in np.asarray(m.jnt_type)]
    joint_body = [int(b) - 1 for b in np.asarray(m.jnt_bodyid)]
    joint_names = []
    count = {}
    for j in range(int(m.njnt)):
        b = joint_body[j]
        i = count.get(b, 0)
        count[b] = i + 1
        nm = _name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
        if nm is None:
            kind = JOINT_KIND_NAMES.get(joint_types[j], "joint")
            nm = f"{body_names[b]}_{kind}{i}"
        joint_names.append(nm)
    joint_names = _unique_names(joint_names, "joint")
    for j, t in enumerate(joint_types):
        if t not in JOINT_KIND_NAMES:
            raise ValueError(
                f"{where}: joint {j} ({joint_names[j]!r}) of body {body_names[joint_body[j]]!r} "
                f"has MuJoCo joint type {t}, which jaxbody does not know "
                "(free=0, ball=1, slide=2, hinge=3)"
            )
    try:
        tree = BodyTree([int(p) - 1 for p in np.asarray(m.body_parentid)[1:]], body_names)
        layout = JointLayout(tree, joint_types, joint_body, joint_names)
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None
    if layout.qposadr != tuple(int(a) for a in m.jnt_qposadr) or layout.dofadr != tuple(
        int(a) for a in m.jnt_dofadr
    ):  # pragma: no cover - MuJoCo's layout is always this one
        raise ValueError(f"{where}: joint addresses differ from MuJoCo's jnt_qposadr/jnt_dofadr")
    # Mocap bodies are jointless children of the world, i.e. welded, as jaxbody reads them.

    dis = int(m.opt.disableflags)
    D = mujoco.mjtDisableBit
    f64 = lambda a: np.array(a, dtype=np.float64)
    body_quat = f64(m.body_quat[1:])
    qn = np.linalg.norm(body_quat, axis=1, keepdims=True)
    body_quat = np.where(qn > 0, body_quat / np.where(qn > 0, qn, 1.0), body_quat)
    iquat = f64(m.body_iquat[1:])
    inertia = np.zeros((nb, 3, 3))
    for k in range(nb):
        R = quat_to_matrix(iquat[k]) if np.linalg.norm(iquat[k]) > 0 else np.eye(3)
        I = R @ np.diag(f64(m.body_inertia[k + 1])) @ R.T
        inertia[k] = 0.5 * (I + I.T)
    armature = f64(m.dof_armature)
    damping = f64(m.dof_damping)
    _fold_actuator_joint_terms(m, mujoco, armature, damping)
    stiffness = f64(m.jnt_stiffness)
    gravity = f64(m.opt.gravity)
    if dis & int(D.mjDSBL_GRAVITY):
        gravity[:] = 0.0
    if dis & int(D.mjDSBL_SPRING):
        stiffness[:] = 0.0
    if dis & int(D.mjDSBL_DAMPER):
        damping[:] = 0.0
    nkey = int(m.nkey)
    key_names = tuple(
        _unique_names([_name(m, mujoco.mjtObj.mjOBJ_KEY, i) for i in range(nkey)], "key")
    )

    f = dtype
    arr = lambda a, shape: jnp.asarray(np.asarray(a, dtype=np.float64).reshape(shape), dtype=f)
    nj, nq, nv = layout.n_joint, layout.nq, layout.nv
    model = Model(
        tree=tree,
        joints=layout,
        body_pos=arr(m.body_pos[1:], (nb, 3)),
        body_quat=arr(body_quat, (nb, 4)),
        body_mass=arr(m.body_mass[1:], (nb,)),
        body_com=arr(m.body_ipos[1:], (nb, 3)),
        body_inertia=arr(inertia, (nb, 3, 3)),
        joint_pos=arr(m.jnt_pos, (nj, 3)),
        joint_axis=arr(m.jnt_axis, (nj, 3)),
        joint_stiffness=arr(stiffness, (nj,)),
        dof_armature=arr(armature, (nv,)),
        dof_damping=arr(damping, (nv,)),
        qpos0=arr(m.qpos0, (nq,)),
        qpos_spring=arr(m.qpos_spring, (nq,)),
        gravity=arr(gravity, (3,)),
        keyframe_qpos=arr(m.key_qpos, (nkey, nq)),
        keyframe_qvel=arr(m.key_qvel, (nkey, nv)),
        keyframe_names=key_names,
        name=model_name,
    )
    try:
        validate_parameters(model)
        _validate_mujoco_rules(model)
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None
    loops = connect_loops(m)
    if loops:  # the directions each loop constrains, found once here from the concrete model
        try:
            loops = _loop_directions(m, mujoco, model, loops)
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None
        model = Model(**{f.name: getattr(model, f.name) for f in dataclasses.fields(model) if f.name != "loops"},
                      loops=loops)

    issues = list(extra) + unsupported_features(m)
    if issues:
        lines = "\n".join(f"  - {s}" for s in issues)
        if strict:
            raise ValueError(
                f"{where} has features jaxbody does not model (strict=True):\n{lines}"
            )
    if issues:
        warnings.warn(
            f"{where} has features jaxbody does not model; they are ignored:\n{lines}",
            UserWarning,
            stacklevel=4 if _caller != "from_mujoco" else 3,
        )
    return model


def connect_loops(m, active_only: bool = True) -> tuple[LoopSpec, ...]:
    """The ``<equality><connect>`` constraints of a compiled ``mujoco.MjModel`` as loop
    closures (:class:`jaxbody.loops.LoopSpec`, in MuJoCo's order, named after them).

    MuJoCo's connect keeps an anchor point of ``body1`` on a point of ``body2``; its compiled
    ``eq_data`` holds the anchor in both body frames (site-based connects: the sites'
    positions in their bodies). Connects inactive at start (``eq_active0 = 0``) are skipped
    unless ``active_only=False``; none are returned when the model disables equality
    constraints (``<flag equality="disable"/>`` or ``constraint="disable"``).
    """
    mujoco = _mujoco()
    D = mujoco.mjtDisableBit
    if int(m.opt.disableflags) & (int(D.mjDSBL_EQUALITY) | int(D.mjDSBL_CONSTRAINT)):
        return ()
    out = []
    for i in range(int(m.neq)):
        if int(m.eq_type[i]) != int(mujoco.mjtEq.mjEQ_CONNECT) or (active_only and not bool(m.eq_active0[i])):
            continue
        data = np.asarray(m.eq_data[i], dtype=np.float64)
        o1, o2 = int(m.eq_obj1id[i]), int(m.eq_obj2id[i])
        if int(m.eq_objtype[i]) == int(mujoco.mjtObj.mjOBJ_SITE):
            b1, b2 = int(m.site_bodyid[o1]), int(m.site_bodyid[o2])
            p1, p2 = np.asarray(m.site_pos[o1], np.float64), np.asarray(m.site_pos[o2], np.float64)
        else:
            b1, b2 = o1, o2
            p1, p2 = data[:3], data[3:6]
        name = _name(m, mujoco.mjtObj.mjOBJ_EQUALITY, i) or f"connect{i}"
        out.append(LoopSpec(name, b1 - 1, tuple(float(x) for x in p1), b2 - 1, tuple(float(x) for x in p2)))
    return tuple(out)


def _loop_directions(m, mujoco, model, loops):
    """``loops`` with their frames, independent directions and dropped rows
    (:mod:`jaxbody.loop_directions`), found with MuJoCo's kinematics at ``qpos0`` (projected
    onto the loops when it does not close them: a site-based connect): no program is compiled."""
    d = mujoco.MjData(m)
    nv = int(m.nv)
    names = model.body_names
    specs = [s._replace(frame=loop_frame(model.tree.parent, s.body_a, s.body_b)) for s in loops]

    def point(body, p):
        if body < 0:
            return np.asarray(p, np.float64), np.zeros((3, nv))
        X = d.xpos[body + 1] + d.xmat[body + 1].reshape(3, 3) @ np.asarray(p, np.float64)
        jacp = np.zeros((3, nv))
        mujoco.mj_jac(m, d, jacp, None, X, body + 1)
        return X, jacp

    def gaps_and_jacobians(q):
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)  # the DoF motions mj_jac reads
        parts = [(point(s.body_a, s.point_a), point(s.body_b, s.point_b)) for s in specs]
        return (np.array([a[0] - b[0] for a, b in parts]).reshape(-1, 3),
                np.array([a[1] - b[1] for a, b in parts]).reshape(-1, 3, nv))

    def integrate(q, dv):
        q = np.array(q, np.float64)
        mujoco.mj_integratePos(m, q, np.asarray(dv, np.float64), 1.0)
        return q

    labels = [s.label for s in specs]
    q = close_loops(np.array(m.qpos0, np.float64), gaps_and_jacobians, integrate, labels=labels)
    _, J = gaps_and_jacobians(q)
    R = np.stack([np.eye(3) if s.frame < 0 else d.xmat[s.frame + 1].reshape(3, 3) for s in specs])
    frame_names = ["the world" if s.frame < 0 else f"body {names[s.frame]!r}" for s in specs]
    rows = loop_rows(np.einsum("lji,ljn->lin", R, J), labels, frame_names)
    return tuple(s._replace(axes=tuple(map(tuple, a.tolist())), dropped=dr)
                 for s, a, dr in zip(specs, rows.axes, rows.dropped))


def unsupported_features(mj_model) -> list[str]:
    """What a compiled ``mujoco.MjModel`` has that jaxbody does not model, one line each.

    Each line reads ``"<feature> (<what jaxbody does>): <count> <elements> (<names>)"``. A
    feature that MuJoCo's ``<option><flag>`` disables is not listed (contacts with
    ``contact``/``constraint`` disabled, limits with ``limit``, friction loss with
    ``frictionloss``, equality constraints with ``equality``, actuator forces with
    ``actuation``). Sensors, sites, cameras, lights and visual geoms are harmless and not
    listed. An empty list means jaxbody models everything MuJoCo's smooth dynamics compute.
    """
    mujoco = _mujoco()
    m = mj_model
    O = mujoco.mjtObj
    D = mujoco.mjtDisableBit
    dis = int(m.opt.disableflags)
    off = lambda *bits: any(dis & int(b) for b in bits)
    out = []

    def listing(objtype, ids, fallback):
        names = []
        for i in ids[:_MAX_NAMES]:
            nm = _name(m, objtype, int(i))
            names.append(repr(nm) if nm is not None else fallback(int(i)))
        more = f", ... and {len(ids) - _MAX_NAMES} more" if len(ids) > _MAX_NAMES else ""
        return ", ".join(names) + more

    body_label = lambda b: repr(_name(m, O.mjOBJ_BODY, b) or f"body{b - 1}")
    jnt_fb = lambda j: f"#{j} on body {body_label(int(m.jnt_bodyid[j]))}"
    num_fb = lambda kind: (lambda i: f"{kind} #{i}")

    # contacts: geoms that can collide with a geom of another weld group (MuJoCo's filter)
    if not off(D.mjDSBL_CONTACT, D.mjDSBL_CONSTRAINT):
        ng = int(m.ngeom)
        if ng:
            ct = np.asarray(m.geom_contype, dtype=np.int64)
            ca = np.asarray(m.geom_conaffinity, dtype=np.int64)
            weld = np.asarray(m.body_weldid)[np.asarray(m.geom_bodyid)]
            can = ((ct[:, None] & ca[None, :]) | (ca[:, None] & ct[None, :])) != 0
            can &= weld[:, None] != weld[None, :]
            ids = np.nonzero(can.any(axis=1))[0]
            if ids.size:
                bodies = sorted({int(m.geom_bodyid[i]) for i in ids})
                out.append(
                    "contacts (collision geoms are ignored; their mass, if any, is already in "
                    f"the body inertias): {ids.size} collision geoms on {len(bodies)} bodies "
                    f"({listing(O.mjOBJ_BODY, bodies, lambda b: 'world' if b == 0 else f'body{b - 1}')})"
                )
        if int(m.npair):
            ids = list(range(int(m.npair)))
            out.append(
                f"explicit contact pairs (ignored): {len(ids)} pairs "
                f"({listing(O.mjOBJ_PAIR, ids, num_fb('pair'))})"
            )
    # active <connect> equalities are loop closures the Model carries (connect_loops)
    eq_other = [i for i in range(int(m.neq))
                if int(m.eq_type[i]) != int(mujoco.mjtEq.mjEQ_CONNECT) or not bool(m.eq_active0[i])]
    if eq_other and not off(D.mjDSBL_EQUALITY, D.mjDSBL_CONSTRAINT):
        ids = eq_other
        out.append(
            "equality constraints other than active <connect> loops (ignored): "
            f"{len(ids)} constraints ({listing(O.mjOBJ_EQUALITY, ids, num_fb('equality'))})"
        )
    if int(m.ntendon):
        ids = list(range(int(m.ntendon)))
        out.append(
            "tendons (their stiffness, damping, limits, friction loss and actuation are "
            f"ignored): {len(ids)} tendons ({listing(O.mjOBJ_TENDON, ids, num_fb('tendon'))})"
        )
    if int(m.nu) and not off(D.mjDSBL_ACTUATION):
        ids = list(range(int(m.nu)))
        out.append(
            "actuators (actuator forces, gains, biases, activation dynamics and control "
            "ranges are ignored; pass joint forces instead): "
            f"{len(ids)} actuators ({listing(O.mjOBJ_ACTUATOR, ids, num_fb('actuator'))})"
        )
    unfolded = [
        i for i in range(int(m.nu))
        if (float(m.actuator_armature[i]) != 0 or float(m.actuator_damping[i]) != 0)
        and _actuator_joint_dof(m, mujoco, i) is None
    ]
    if unfolded:
        out.append(
            "actuator armature/damping on transmissions other than a hinge or slide joint "
            f"(ignored): {len(unfolded)} actuators "
            f"({listing(O.mjOBJ_ACTUATOR, unfolded, num_fb('actuator'))})"
        )
    if not off(D.mjDSBL_LIMIT, D.mjDSBL_CONSTRAINT):
        ids = list(np.nonzero(np.asarray(m.jnt_limited))[0])
        if ids:
            out.append(
                f"joint limits (ignored): {len(ids)} limited joints "
                f"({listing(O.mjOBJ_JOINT, ids, jnt_fb)})"
            )
    if not off(D.mjDSBL_FRICTIONLOSS, D.mjDSBL_CONSTRAINT):
        dofs = np.nonzero(np.asarray(m.dof_frictionloss) > 0)[0]
        ids = sorted({int(m.dof_jntid[d]) for d in dofs})
        if ids:
            out.append(
                f"joint friction loss (ignored): {len(ids)} joints "
                f"({listing(O.mjOBJ_JOINT, ids, jnt_fb)})"
            )
    ids = list(np.nonzero(np.asarray(m.body_gravcomp) != 0)[0])
    if ids:
        out.append(
            f"gravity compensation (body gravcomp, ignored): {len(ids)} bodies "
            f"({listing(O.mjOBJ_BODY, ids, lambda b: f'body{b - 1}')})"
        )
    if not off(D.mjDSBL_SPRING):
        nonlin = (np.asarray(m.jnt_stiffnesspoly) != 0).any(axis=1)
        nonlin |= np.asarray(m.jnt_springyield) > 0
        nonlin |= np.asarray(m.jnt_plasticadr) >= 0
        ids = list(np.nonzero(nonlin)[0])
        if ids:
            out.append(
                "nonlinear or plastic joint springs (only the linear stiffness is kept): "
                f"{len(ids)} joints ({listing(O.mjOBJ_JOINT, ids, jnt_fb)})"
            )
    if not off(D.mjDSBL_DAMPER):
        dofs = np.nonzero((np.asarray(m.dof_dampingpoly) != 0).any(axis=1))[0]
        ids = sorted({int(m.dof_jntid[d]) for d in dofs})
        if ids:
            out.append(
                "nonlinear joint damping (only the linear damping is kept): "
                f"{len(ids)} joints ({listing(O.mjOBJ_JOINT, ids, jnt_fb)})"
            )
        acts = list(np.nonzero((np.asarray(m.actuator_dampingpoly) != 0).any(axis=1))[0])
        if acts:
            out.append(
                "nonlinear actuator damping (ignored): "
                f"{len(acts)} actuators ({listing(O.mjOBJ_ACTUATOR, acts, num_fb('actuator'))})"
            )
    density, viscosity = float(m.opt.density), float(m.opt.viscosity)
    if density > 0 or viscosity > 0:
        out.append(
            f"fluid forces (option density={density:g}, viscosity={viscosity:g}; ignored)"
        )
    if int(m.nflex):
        ids = list(range(int(m.nflex)))
        out.append(
            f"flexes (deformable bodies, ignored): {len(ids)} flexes "
            f"({listing(O.mjOBJ_FLEX, ids, num_fb('flex'))})"
        )
    if int(m.nplugin):
        ids = list(range(int(m.nplugin)))
        out.append(
            f"engine plugins (ignored): {len(ids)} plugins "
            f"({listing(O.mjOBJ_PLUGIN, ids, num_fb('plugin'))})"
        )
    ids = list(np.nonzero(np.asarray(m.body_mocapid) >= 0)[0])
    if ids:
        out.append(
            "mocap bodies (treated as welded to the world at their model pose; mocap_pos and "
            f"mocap_quat are ignored): {len(ids)} bodies "
            f"({listing(O.mjOBJ_BODY, ids, lambda b: f'body{b - 1}')})"
        )
    return out


# ---------------------------------------------------------------------------- helpers
def _check_dtype(dtype, caller):
    """The floating dtype the parameters get: ``None`` is JAX's default float.

    Refuses a dtype JAX would silently narrow: ``float64`` without ``jax_enable_x64`` gives
    float32 arrays, which is not what the caller asked for.
    """
    if dtype is None:
        return jnp.result_type(float)
    try:
        want = np.dtype(dtype)
    except TypeError:
        raise ValueError(f"{caller}: dtype must be a floating dtype, got {dtype!r}") from None
    if not np.issubdtype(want, np.floating):
        raise ValueError(f"{caller}: dtype must be a floating dtype, got {want}")
    got = np.dtype(jax.dtypes.canonicalize_dtype(want))
    if got != want:
        raise ValueError(
            f"{caller}: dtype={want} needs 64-bit JAX, which is off (JAX would silently give "
            f"{got}); enable it before creating arrays with "
            'jax.config.update("jax_enable_x64", True) or JAX_ENABLE_X64=1, or pass dtype=jnp.float32'
        )
    return want


def compile_source(source, caller, fmt):
    """Compile ``source`` (a file path or an XML string starting with ``<``) with MuJoCo.

    ``caller`` (the public function's name) and ``fmt`` (``"MJCF"``, ``"URDF"``) name the
    request in messages.

    Returns:
        The compiled ``mujoco.MjModel``.

    Raises:
        FileNotFoundError: ``source`` is a path that does not exist.
        TypeError: ``source`` is neither a path nor a string.
        ValueError: MuJoCo's compiler rejects it (the message names the element).
    """
    mujoco = _mujoco()
    if isinstance(source, str) and source.lstrip().startswith("<"):
        label = f"{fmt} string"
        load = lambda: mujoco.MjModel.from_xml_string(source)
    elif isinstance(source, (str, os.PathLike)):
        path = pathlib.Path(source)
        if not path.is_file():
            raise FileNotFoundError(f"{caller}: {fmt} file not found: {str(path)!r}")
        label = f"{fmt} file {str(path)!r}"
        load = lambda: mujoco.MjModel.from_xml_path(str(path))
    else:
        raise TypeError(
            f"{caller}: expected a file path or an XML string, got {type(source).__name__}"
        )
    try:
        return load()
    except ValueError as e:
        raise ValueError(f"{caller}: MuJoCo's compiler rejected the {label}: {_explain(str(e))}") from None


def _explain(msg: str) -> str:
    """MuJoCo's error message on one line, led by a plain statement naming the element."""
    text = msg.strip()
    first = text.splitlines()[0] if text else text
    first = re.sub(r"^Error:\s*", "", first)
    elem = re.search(r"Element name '([^']*)', id (\d+)(?:, line (\d+))?", text)
    name = elem.group(1) if elem else None
    where = ""
    if elem:
        where = f"; element {name!r}, id {elem.group(2)}"
        if elem.group(3):
            where += f", line {elem.group(3)}"
    for key, hint in _HINTS:
        if key in first and name is not None:
            return f"{hint.format(name=name)} [MuJoCo: {first}{where}]"
    rest = " ".join(line.strip() for line in text.splitlines()[1:] if line.strip())
    return f"{first}{where if elem else ('; ' + rest if rest else '')}"


def _fold_actuator_joint_terms(m, mujoco, armature, damping):
    """Add ``gear² · actuator_armature/damping`` of joint transmissions to the joint's DoF."""
    for i in range(int(m.nu)):
        arm, damp = float(m.actuator_armature[i]), float(m.actuator_damping[i])
        if arm == 0 and damp == 0:
            continue
        d = _actuator_joint_dof(m, mujoco, i)
        if d is None:
            continue
        g2 = float(m.actuator_gear[i, 0]) ** 2
        armature[d] += g2 * arm
        damping[d] += g2 * damp


def _actuator_joint_dof(m, mujoco, i):
    T = mujoco.mjtTrn
    if int(m.actuator_trntype[i]) not in (int(T.mjTRN_JOINT), int(T.mjTRN_JOINTINPARENT)):
        return None
    j = int(m.actuator_trnid[i, 0])
    if int(m.jnt_type[j]) not in (HINGE, SLIDE):
        return None
    return int(m.jnt_dofadr[j])


def _validate_mujoco_rules(model: Model) -> None:
    """Rules MuJoCo's compiler enforces that jaxbody's own validation does not.

    MuJoCo requires positive mass on every body that carries a joint (jaxbody only needs a
    positive subtree mass); this catches arrays edited after compilation.
    """
    mass = np.asarray(model.body_mass)
    names = model.tree.names
    for k in range(model.n_body):
        if model.joints.body_joint_count[k] > 0 and not mass[k] > 0:
            raise ValueError(
                f"body {k} ({names[k]!r}) moves (has joints) but its body_mass is {mass[k]}: "
                "MuJoCo requires positive mass on every moving body"
            )


def _name(m, objtype, i):
    nm = _mujoco().mj_id2name(m, objtype, int(i))
    return nm if nm else None


def _unique_names(names, kind):
    out, seen = [], set()
    for i, nm in enumerate(names):
        nm = nm if nm else f"{kind}{i}"
        base, n = nm, 1
        while nm in seen:
            nm = f"{base}_{n}"
            n += 1
        seen.add(nm)
        out.append(nm)
    return out


def _model_name(m) -> str:
    raw = bytes(m.names).split(b"\0", 1)[0].decode("utf-8", "replace")
    return raw or "model"
