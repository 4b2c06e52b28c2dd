"""The figures the commands write: the trajectory plot and the skeleton animation of
``jaxbody simulate``, the plot of ``jaxbody demo``. matplotlib and Pillow are imported when a
figure is asked for."""

import math

import jax
import jax.numpy as jnp
import numpy as np

from ..joints import FREE
from ..kinematics import forward_kinematics
from ..planar import body_positions
from .sources import Source

__all__ = ["pyplot", "plot_trajectory", "skeleton", "project", "animate", "plot_demo"]


def pyplot():
    """matplotlib's pyplot on the Agg backend (files only, no display)."""
    import matplotlib  # optional and slow to import: only when a figure is written

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_trajectory(path, src, t, q, energy, args):
    """Coordinates, energy and relative energy drift against time."""
    plt = pyplot()
    path.parent.mkdir(parents=True, exist_ok=True)
    scalar = [i for i, s in enumerate(src.q_labels) if "." not in s]
    cols = scalar or list(range(q.shape[1]))
    fig, axes = plt.subplots(3, 1, sharex=True, figsize=(8, 8), constrained_layout=True)
    for i in cols:
        axes[0].plot(t, q[:, i], label=src.q_labels[i])
    axes[0].set_ylabel("joint coordinates [rad or m]" if scalar else "q")
    if len(cols) <= 12:
        axes[0].legend(loc="upper right", fontsize="small", ncol=2)
    axes[0].set_title(f"{src.name}: {args.solver}, rtol={args.rtol:g}, atol={args.atol:g}")
    if np.all(np.isfinite(energy)):
        e0 = energy[0]
        axes[1].plot(t, energy)
        axes[2].plot(t, (energy - e0) / max(abs(e0), np.finfo(float).tiny))
    axes[1].set_ylabel("energy E [J]")
    axes[1].ticklabel_format(axis="y", useOffset=False)
    axes[2].set_ylabel(r"$(E - E_0)/|E_0|$")
    axes[2].set_xlabel("t [s]")
    axes[2].ticklabel_format(axis="y", style="sci", scilimits=(0, 0))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def skeleton(src: Source, t, q):
    """Per frame, one polyline per body: parent point → joint point → body point.

    Spatial models: parent's origin → joint anchor ``O_0k`` → body origin, in 3-D.
    Planar systems: parent's hinge (or the base point) → hinge ``O_k`` → centre of mass, 2-D.
    Returns ``(lines (frames, n_body, 3, dim), dim)``.
    """
    if src.kind == "model":
        model = src.system
        parent = np.asarray(model.tree.parent)

        def frame(qk):
            kin = forward_kinematics(model, qk)
            return kin.body_position, kin.base_point

        origin, anchor = jax.jit(jax.vmap(frame))(jnp.asarray(q))
        origin, anchor = np.asarray(origin), np.asarray(anchor)
        # A root hangs from the world origin unless it floats (free joint): then no link.
        free = np.zeros(model.n_body, dtype=bool)
        free[[b for kind, b in zip(model.joints.type, model.joints.body) if kind == FREE]] = True
        root_start = np.where(free[None, :, None], anchor, 0.0)
        start = np.where(parent[None, :, None] >= 0, origin[:, np.maximum(parent, 0)], root_start)
        return np.stack([start, anchor, origin], axis=2), 3

    embedded = src.kind == "embedded"
    psys = src.system.system if embedded else src.system

    def frame(tk, qk):
        Q = src.system.embed(tk, qk) if embedded else qk
        hinge, com = body_positions(psys, Q)
        base = Q[:2] if psys.translating_base else jnp.zeros(2, Q.dtype)
        return hinge, com, base

    hinge, com, base = jax.jit(jax.vmap(frame))(jnp.asarray(t), jnp.asarray(q))
    hinge, com, base = np.asarray(hinge), np.asarray(com), np.asarray(base)
    parent = np.asarray(psys.tree.parent)
    start = np.where(parent[None, :, None] >= 0, hinge[:, np.maximum(parent, 0)], base[:, None, :])
    return np.stack([start, hinge, com], axis=2), 2


def project(points, azimuth=math.radians(45.0), elevation=math.radians(25.0)):
    """Orthographic view of world points (z up) from azimuth/elevation: (..., 3) -> (..., 2)."""
    ca, sa, ce, se = math.cos(azimuth), math.sin(azimuth), math.cos(elevation), math.sin(elevation)
    right = np.array([-sa, ca, 0.0])
    up = np.array([-se * ca, -se * sa, ce])
    return np.stack([points @ right, points @ up], axis=-1)


def animate(path, src, t, q, max_frames):
    """GIF of the skeleton moving (matplotlib frames, assembled by Pillow)."""
    from PIL import Image  # optional: only when an animation is asked for

    plt = pyplot()
    path.parent.mkdir(parents=True, exist_ok=True)
    idx = np.unique(np.linspace(0, len(t) - 1, min(max_frames, len(t))).round().astype(int))
    lines, dim = skeleton(src, t[idx], q[idx])
    if dim == 3:
        lines = project(lines)
    lo, hi = lines.reshape(-1, 2).min(axis=0), lines.reshape(-1, 2).max(axis=0)
    pad = 0.1 * max(float(np.max(hi - lo)), 1e-3)
    fig, ax = plt.subplots(figsize=(5, 5), dpi=90, constrained_layout=True)
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_title(src.name + (" (oblique view, z up)" if dim == 3 else " (plane of motion)"))
    if dim == 2:  # the horizontal through the world origin
        ax.plot([lo[0] - pad, hi[0] + pad], [0, 0], color="0.85", lw=0.8, zorder=0)
    n_body = lines.shape[1]
    links = [ax.plot([], [], "-", color="C0", lw=2)[0] for _ in range(n_body)]
    joints = ax.plot([], [], "o", color="C3", ms=4)[0]
    points = ax.plot([], [], "o", color="C0", ms=3)[0]
    label = ax.text(0.02, 0.96, "", transform=ax.transAxes, va="top")
    fig.canvas.draw()
    # The layout is fixed after the first draw: re-solving it for every frame is most of
    # the cost of a frame.
    fig.set_layout_engine("none")
    frames = []
    for f in range(len(idx)):
        for k in range(n_body):
            links[k].set_data(lines[f, k, :, 0], lines[f, k, :, 1])
        joints.set_data(lines[f, :, 1, 0], lines[f, :, 1, 1])
        points.set_data(lines[f, :, 2, 0], lines[f, :, 2, 1])
        label.set_text(f"t = {t[idx][f]:.3f} s")
        fig.canvas.draw()
        rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3]
        frames.append(Image.fromarray(rgb).quantize(colors=64, method=Image.Quantize.MEDIANCUT))
    plt.close(fig)
    span = float(t[idx][-1] - t[idx][0])
    fps = max(1, min(30, round(len(idx) / span))) if span > 0 else 10
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=round(1000 / fps), loop=0)


def plot_demo(path, t, q, rel_err, args):
    """The demo's angles and relative energy error against time."""
    plt = pyplot()
    fig, (ax_angle, ax_drift) = plt.subplots(2, 1, sharex=True, figsize=(8, 6), constrained_layout=True)
    ax_angle.plot(t, q[:, 0], label=r"$\alpha_1$")
    ax_angle.plot(t, q[:, 1], label=r"$\alpha_2$")
    ax_angle.set_ylabel("angle from downward vertical [rad]")
    ax_angle.legend(loc="upper right")
    ax_angle.set_title(f"Double pendulum (Example 1), {args.solver}, rtol={args.rtol:g}, atol={args.atol:g}")
    ax_drift.plot(t, rel_err)
    ax_drift.set_ylabel(r"$(E - E_0)/|E_0|$")
    ax_drift.set_xlabel("t [s]")
    ax_drift.ticklabel_format(axis="y", style="sci", scilimits=(0, 0))
    fig.savefig(path, dpi=120)
    plt.close(fig)
