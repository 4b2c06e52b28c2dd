"""``jaxbody info SOURCE``: the tree, joints, masses, augmented bodies, declared effects and the
content of the file that jaxbody ignores."""

import numpy as np

from ..dynamics import augmented_bodies
from ..effects import Actuation, BodyLoads, Gravity, JointDampers, JointSprings
from ..joints import BALL, FREE, HINGE, SLIDE
from ..planar import augmented_bodies as planar_augmented_bodies
from .arguments import SOURCE_HELP, add_scene_options, setup_jax
from .scene_options import scene_from_options
from .sources import load

__all__ = ["add_parser", "run", "print_tree", "loop_lines"]


def add_parser(sub):
    """The ``info`` sub-command and its options."""
    info = sub.add_parser(
        "info",
        help="print the tree, joints, masses, augmented bodies and ignored model content",
        description=(
            "Print the body tree and joints of SOURCE, total and subtree masses, the static "
            "moments and augmented inertias (at --keyframe or the reference configuration), "
            "the effects the scene declares (the model's, changed by the same scene options as "
            "`jaxbody simulate`) and what of an MJCF/URDF file jaxbody ignores."
        ),
    )
    info.add_argument("source", metavar="SOURCE", help=SOURCE_HELP)
    info.add_argument("--keyframe", default=None, help="evaluate at this keyframe")
    add_scene_options(info, "declare")


def print_tree(parent, body):
    """Print a body tree depth first, each root then its children indented below it.

    ``parent[k]`` is the parent of body ``k`` (negative for a root); ``body(k, indent)``
    prints the lines of body ``k`` after the indent of its depth.
    """
    n = len(parent)

    def show(k, depth):
        body(k, "  " * depth)
        for c in range(n):
            if parent[c] == k:
                show(c, depth + 1)

    for k in range(n):
        if parent[k] < 0:
            show(k, 0)


def _vec(x, fmt="{:+.6g}"):
    return "(" + ", ".join(fmt.format(float(c)) for c in x) + ")"


def run(args) -> int:
    """``jaxbody info``: returns the exit status."""
    src = load(args.source, args.keyframe)
    setup_jax()
    system = src.system
    scene = scene_from_options(src, args)
    print(f"{src.name}: {src.origin}")
    if src.kind == "model":
        _info_model(src, system)
    else:
        _info_planar(src, system)
    _effects(src, scene)
    print("content of the file that jaxbody does not model (ignored):")
    if src.ignored:
        for line in src.ignored:
            print(f"  - {line}")
    elif src.kind == "model":
        print("  none")
    else:
        print("  none (a built-in example)")
    return 0


def _info_model(src, model):
    names = model.body_names
    parent = list(model.tree.parent)
    kinds = {HINGE: "hinge", SLIDE: "slide", BALL: "ball", FREE: "free"}
    joints_of = {k: [] for k in range(model.n_body)}
    for j, (kind, body) in enumerate(zip(model.joints.type, model.joints.body)):
        joints_of[body].append(j)
    mass = np.asarray(model.body_mass)
    print(f"  {model.n_body} bodies, {model.n_joint} joints, nq = {model.nq}, nv = {model.nv} "
          "(q, v laid out as MuJoCo's qpos, qvel; body k = MuJoCo body k+1)")
    print(f"  total mass {mass.sum():.6g} kg")
    print("tree (body k, name, mass; joints with their q/v addresses and axes in the body frame):")

    def body(k, indent):
        print(f"  {indent}{k:>3} {names[k]}  mass {mass[k]:.6g} kg")
        for j in joints_of[k]:
            kind = model.joints.type[j]
            axis = "" if kind in (BALL, FREE) else f", axis {_vec(np.asarray(model.joint_axis[j]), '{:.4g}')}"
            print(f"  {indent}      {kinds[kind]} joint {model.joint_names[j]!r}: "
                  f"q[{model.joints.qposadr[j]}], v[{model.joints.dofadr[j]}]{axis}")

    print_tree(parent, body)
    aug = augmented_bodies(model, src.q0)
    m_sub = np.asarray(aug.subtree_mass)
    mbar = np.asarray(aug.static_moment)
    inertia = np.asarray(aug.augmented_inertia)
    print(f"augmented bodies at {src.start} (world frame, about each body's joint point O_0k):")
    print("    k  name                    subtree mass m_k [kg]   static moment m̄_k [kg m]")
    for k in range(model.n_body):
        print(f"  {k:>3}  {names[k]:<22}  {m_sub[k]:<22.6g}  {_vec(mbar[k])}")
    print("  augmented inertia I_k [kg m²] (xx, yy, zz, xy, xz, yz):")
    for k in range(model.n_body):
        I = inertia[k]
        print(f"  {k:>3}  {names[k]:<22}  {_vec([I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]])}")


def _effects(src, scene):
    """The effects the scene declares, as ``jaxbody simulate`` with the same options integrates them."""
    by_kind = {type(e): e for e in scene.effects}
    spatial = src.kind == "model"
    print(f"effects the scene declares (what `jaxbody simulate` integrates; path {scene.path!r}):")
    if spatial:
        g = by_kind.get(Gravity)
        g = None if g is None else np.asarray(g.vector)
    else:
        g = getattr(scene.system, "gravity", None)
        g = np.asarray(scene.system.system.gravity if g is None else g)
        g = g if np.any(g != 0) else None
    print(f"  gravity          {'on, ' + _vec(g, '{:.4g}') + ' m/s²' if g is not None and np.any(g != 0) else 'off'}")
    if spatial:
        model = src.system
        names = model.joint_names
        springs = by_kind.get(JointSprings)
        on = [] if springs is None else [names[j] for j in np.nonzero(np.asarray(springs.stiffness) != 0)[0]]
        print(f"  joint springs    {len(on)} joints" + (f" ({', '.join(on)})" if on else ""))
        dampers = by_kind.get(JointDampers)
        dofs = [] if dampers is None else np.nonzero(np.asarray(dampers.damping) != 0)[0]
        print(f"  joint dampers    {len(dofs)} DoFs" + (f" (v[{', '.join(map(str, dofs))}])" if len(dofs) else ""))
        print(f"  armature         {int(np.count_nonzero(np.asarray(model.dof_armature)))} DoFs")
        if scene.constraints is not None:
            rows = getattr(scene.constraints, "constraint_names", None) or ()
            loops = [spec.label for spec in model.loops]
            print(f"  constraints      {len(rows)} rows (Maggi): loop closures {', '.join(loops)}")
            for line in loop_lines(model, scene.constraints):
                print(f"    {line}")
    elif src.kind == "embedded":
        print(f"  constraints      solved explicitly by {type(src.system).__name__} (coordinates "
              f"{', '.join(src.q_labels)})")
    act = by_kind.get(Actuation)
    if act is None:
        print("  actuation        none (no joint forces are applied)")
    else:
        tau = np.asarray(act.law.value)
        parts = [f"{src.v_labels[i]} = {tau[i]:.6g}" for i in np.nonzero(tau)[0]]
        what = "generalized forces" if spatial else "drives"
        print(f"  actuation        constant {what}: {', '.join(parts) or 'all zero'}")
    loads = by_kind.get(BodyLoads)
    if loads is None:
        print("  external loads   none")
    else:
        w = np.asarray(loads.wrench.value)
        for k in np.nonzero(np.any(w != 0, axis=1))[0]:
            print(f"  external load    {src.system.body_names[k]}: force {_vec(w[k, :3], '{:.4g}')} N, "
                  f"moment {_vec(w[k, 3:], '{:.4g}')} N·m at the centre of mass")


def loop_lines(model, constraints):
    """One line per loop closure of the scene (its bodies, frame and kept directions) and one per
    direction left out, saying why."""
    names = model.body_names
    body = lambda b: "the world" if b < 0 else repr(names[b])
    out = []
    by_label = {spec.label: spec for spec in model.loops}
    for c in getattr(constraints, "constraints", ()):
        spec = by_label.get(getattr(c, "label", None))
        if spec is None or not hasattr(c, "axes"):
            continue
        frame = "world axes" if c.frame < 0 else f"axes of body {names[c.frame]!r}"
        dirs = ", ".join(_vec(a, "{:.4g}") for a in np.asarray(c.axes))
        out.append(f"{spec.label}: point {_vec(spec.point_a, '{:.4g}')} of {body(spec.body_a)} on point "
                   f"{_vec(spec.point_b, '{:.4g}')} of {body(spec.body_b)}; {c.size} rows along {dirs} ({frame})")
        out += [f"  dropped {d}" for d in spec.dropped]
    return out


def _info_planar(src, system):
    embedded = src.kind == "embedded"
    psys = system.system if embedded else system
    names = psys.tree.names
    parent = list(psys.tree.parent)
    mass = np.asarray(psys.body_mass)
    Q = system.embed(0.0, src.q0) if embedded else src.q0
    print(f"  planar system in absolute angles: {psys.n_body} hinged bodies, nq = nv = {system.nq} "
          f"({', '.join(src.q_labels)})" + (f"; a constrained example of a {psys.nq}-coordinate tree"
                                           if embedded else ""))
    base = float(np.asarray(psys.base_mass)) if psys.translating_base else 0.0
    print(f"  total mass {mass.sum() + base:.6g} kg"
          + (f" (translating base {base:.6g} kg)" if psys.translating_base else ""))
    print("tree (body k, name, mass, hinge position in the parent's axes):")

    def body(k, indent):
        print(f"  {indent}{k:>3} {names[k]}  mass {mass[k]:.6g} kg, hinge at "
              f"{_vec(np.asarray(psys.hinge_pos[k]), '{:.4g}')}")

    print_tree(parent, body)
    aug = planar_augmented_bodies(psys, Q)
    print(f"augmented bodies at {src.start} (world axes in the plane, about each hinge O_k):")
    print("    k  name                    m_k [kg]     m̄_k [kg m]                J_k [kg m²]")
    for k in range(psys.n_body):
        print(f"  {k:>3}  {names[k]:<22}  {float(aug.subtree_mass[k]):<11.6g}  "
              f"{_vec(np.asarray(aug.static_moment[k])):<24}  {float(aug.augmented_inertia[k]):.6g}")


