"""How closely does jaxbody agree with MuJoCo? Worst relative error per function (float64).

Models: the shipped robots (jaxbody/models: panda, ur5e, anymal_c) and seeded random MJCF trees that mix
free, ball, hinge and slide joints, several joints per body, offset anchors, rotated
inertial frames and mass ratios up to 1e4 (``tests/_support/mjcf_random.py``). For each model and
random state (quaternions normalised) it compares with MuJoCo on the same MJCF:

  mass_matrix ~ mj_fullM, bias_forces ~ qfrc_bias, inverse_dynamics ~ mj_inverse (passive
  off), forward_dynamics ~ qacc, joint_reactions ~ cfrc_int (after mj_rnePostConstraint,
  moved to the joint point), passive_forces ~ qfrc_passive, kinetic/potential energy ~
  mj_energyVel/mj_energyPos.

Relative error = max |jaxbody - MuJoCo| / max |MuJoCo| per quantity. Writes
``benchmarks/results/mujoco_agreement.{md,json}``.

    .venv/bin/python benchmarks/mujoco_agreement.py [--random 10] [--states 3]
"""

import argparse
import json
import pathlib
import sys
import warnings

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "benchmarks"))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--random", type=int, default=10, help="number of random MJCF trees")
    p.add_argument("--states", type=int, default=3, help="random states per model")
    p.add_argument("--out", type=pathlib.Path, default=REPO / "benchmarks" / "results")
    args = p.parse_args(argv)

    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import mujoco

    import _common
    import jaxbody as jb
    from _support.mjcf_random import random_mjcf

    shipped = REPO / "jaxbody" / "models"
    sources = [(n, (shipped / f"{n}.xml").read_text()) for n in ("panda", "ur5e", "anymal_c")]
    sources += [(f"random{s}", random_mjcf(s, n_body=8, rigid_only=True)) for s in range(args.random)]
    rigid = (
        mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
        | mujoco.mjtDisableBit.mjDSBL_CONTACT
        | mujoco.mjtDisableBit.mjDSBL_ACTUATION
    )
    fns = {
        "M": jax.jit(jb.mass_matrix),
        "bias": jax.jit(jb.bias_forces),
        "inv": jax.jit(jb.inverse_dynamics),
        "fwd": jax.jit(jb.forward_dynamics),
        "react": jax.jit(jb.joint_reactions),
        "passive": jax.jit(jb.passive_forces),
        "T": jax.jit(jb.kinetic_energy),
        "V": jax.jit(jb.potential_energy),
        "kin": jax.jit(jb.forward_kinematics),
    }
    rel = lambda x, y: float(np.abs(np.asarray(x) - y).max() / max(np.abs(y).max(), 1e-300))
    table = {}
    for name, xml in sources:
        m = mujoco.MjModel.from_xml_string(xml)
        m.opt.disableflags |= rigid
        m.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = jb.from_mujoco(m)
        d = mujoco.MjData(m)
        rng = np.random.default_rng(0)
        worst = {}
        for _ in range(args.states):
            q = np.asarray(jb.normalize_qpos(model, jnp.asarray(m.qpos0 + 0.5 * rng.standard_normal(m.nq))))
            v, a = rng.standard_normal(m.nv), rng.standard_normal(m.nv)
            d.qpos[:], d.qvel[:] = q, v
            mujoco.mj_forward(m, d)
            mujoco.mj_rnePostConstraint(m, d)
            M = np.zeros((m.nv, m.nv))
            mujoco.mj_fullM(m, d, M)
            passive = d.qfrc_passive.copy()
            qacc = d.qacc.copy()
            # rigid-body quantities with passive forces as an applied generalized force
            out = {
                "M": rel(fns["M"](model, q), M),
                "bias": rel(fns["bias"](model, q, v), d.qfrc_bias),
                "fwd": rel(fns["fwd"](model, q, v, passive), qacc),
                "passive": rel(fns["passive"](model, q, v), passive) if np.abs(passive).max() > 0 else 0.0,
                "T": rel(fns["T"](model, q, v), np.array([d.energy[1]])),
                "V": rel(fns["V"](model, q), np.array([d.energy[0]])),
            }
            F, Mo = fns["react"](model, q, v, qacc)
            P = np.asarray(fns["kin"](model, q).base_point)
            cf = d.cfrc_int[1:]
            c = d.subtree_com[m.body_rootid[1:]]
            out["react_force"] = rel(F, cf[:, 3:])
            out["react_moment"] = rel(Mo, cf[:, :3] + np.cross(c - P, cf[:, 3:]))
            d.qacc[:] = a
            m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_SPRING | mujoco.mjtDisableBit.mjDSBL_DAMPER
            mujoco.mj_inverse(m, d)
            m.opt.disableflags &= ~(mujoco.mjtDisableBit.mjDSBL_SPRING | mujoco.mjtDisableBit.mjDSBL_DAMPER)
            out["inv"] = rel(fns["inv"](model, q, v, a), d.qfrc_inverse)
            for k, e in out.items():
                worst[k] = max(worst.get(k, 0.0), e)
        table[name] = dict(nq=m.nq, nv=m.nv, **worst)
        print(name, {k: f"{e:.1e}" for k, e in worst.items()}, flush=True)

    cols = ["M", "bias", "inv", "fwd", "react_force", "react_moment", "passive", "T", "V"]
    overall = {c: max(r[c] for r in table.values()) for c in cols}
    stamp = _common.stamp(sys.argv if argv is None else [sys.argv[0], *argv])
    rows = [[n, f"{r['nq']}/{r['nv']}", *(f"{r[c]:.1e}" for c in cols)] for n, r in table.items()]
    rows.append(["**worst**", "", *(f"**{overall[c]:.1e}**" for c in cols)])
    md = [
        "# jaxbody vs MuJoCo: worst relative error (float64)", "",
        _common.stamp_markdown(stamp), "",
        f"{args.states} random states per model; relative error = max|jaxbody - MuJoCo| / max|MuJoCo|.", "",
        _common.markdown_table(["model", "nq/nv", *cols], rows),
    ]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "mujoco_agreement.md").write_text("\n".join(md) + "\n")
    (args.out / "mujoco_agreement.json").write_text(json.dumps(dict(stamp=stamp, models=table, worst=overall), indent=1))
    print("worst:", {k: f"{e:.1e}" for k, e in overall.items()})
    print("wrote", args.out / "mujoco_agreement.md")


if __name__ == "__main__":
    main()
