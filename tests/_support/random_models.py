"""Seeded random spatial models built with :class:`jaxbody.ModelBuilder` (no MJCF involved)."""

import numpy as np

import jaxbody as jb


def random_rotation_quat(rng):
    q = rng.standard_normal(4)
    return q / np.linalg.norm(q)


def random_inertia(rng, scale=1.0):
    """A physically valid central inertia (from a random mass distribution) in random axes."""
    pts = rng.standard_normal((6, 3)) * rng.uniform(0.05, 0.3, 3)
    w = rng.uniform(0.1, 1.0, 6)
    w = w / w.sum()
    I = sum(wi * ((p @ p) * np.eye(3) - np.outer(p, p)) for wi, p in zip(w, pts))
    return scale * I


def random_model(
    seed: int,
    n_body: int = 6,
    kinds=("hinge", "slide", "ball", "hinge2", "slide_hinge"),
    free_root: bool = True,
    mass_ratio: float = 100.0,
    passive: bool = True,
    dtype=None,
    traversal=None,
):
    """Random tree mixing joint kinds, several joints per body, offsets and rotated frames."""
    rng = np.random.default_rng(seed)
    b = jb.ModelBuilder(gravity=rng.standard_normal(3) * 3 + np.array([0, 0, -9.81]))
    for k in range(n_body):
        parent = None if k == 0 else int(rng.integers(0, k))
        mass = float(np.exp(rng.uniform(0, np.log(mass_ratio))))
        if k == 0 and free_root:
            joints = [jb.Free()]
        else:
            kind = kinds[int(rng.integers(0, len(kinds)))]
            ax = lambda: rng.standard_normal(3)
            pos = lambda: rng.standard_normal(3) * 0.1
            extra = {}
            if passive:
                extra = dict(
                    armature=float(rng.uniform(0, 0.1)),
                    damping=float(rng.uniform(0, 0.5)),
                    stiffness=float(rng.uniform(0, 2.0)),
                )
            if kind == "hinge":
                joints = [jb.Hinge(axis=ax(), pos=pos(), ref=float(rng.uniform(-1, 1)), **extra)]
            elif kind == "slide":
                joints = [jb.Slide(axis=ax(), pos=pos(), **extra)]
            elif kind == "ball":
                joints = [jb.Ball(pos=pos(), **extra)]
            elif kind == "hinge2":
                joints = [jb.Hinge(axis=ax(), pos=pos(), **extra), jb.Hinge(axis=ax(), pos=pos(), **extra)]
            else:
                joints = [jb.Slide(axis=ax(), pos=pos(), **extra), jb.Hinge(axis=ax(), pos=pos(), **extra)]
        b.add_body(
            f"body{k}",
            parent,
            pos=rng.standard_normal(3) * 0.3,
            quat=random_rotation_quat(rng),
            mass=mass,
            com=rng.standard_normal(3) * 0.1,
            inertia=random_inertia(rng, mass),
            joints=joints,
        )
    return b.build(dtype=dtype, traversal=traversal)


def hinge_chain(n: int, dtype=None):
    """A planar-like chain of ``n`` hinge links about y, hanging along -z."""
    b = jb.ModelBuilder()
    for k in range(n):
        b.add_body(
            f"link{k}",
            None if k == 0 else f"link{k - 1}",
            pos=(0.0, 0.0, 0.0 if k == 0 else -0.3),
            mass=1.0 + 0.1 * k,
            com=(0.01, 0.0, -0.15),
            inertia=(0.01, 0.01, 0.002),
            joints=[jb.Hinge(axis=(0, 1, 0))],
        )
    return b.build(dtype=dtype)


def random_state(model, seed):
    import jax.numpy as jnp

    rng = np.random.default_rng(seed)
    q = np.asarray(model.qpos0) + 0.6 * rng.standard_normal(model.nq)
    q = jb.normalize_qpos(model, jnp.asarray(q, model.body_pos.dtype))
    v = jnp.asarray(rng.standard_normal(model.nv), model.body_pos.dtype)
    a = jnp.asarray(rng.standard_normal(model.nv), model.body_pos.dtype)
    return q, v, a
