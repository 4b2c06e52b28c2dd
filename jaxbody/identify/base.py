"""Base (identifiable) parameters: a rank-revealing QR of the stacked regressor, and which
augmented-body quantities they determine."""

from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._types import ArrayLike
from ..dynamics import augmented_bodies
from ..kinematics import forward_kinematics
from ..model import Model
from .inertial import check_extra, n_extra, parameter_names, reference_parameters, with_parameters
from ..sampling import random_states
from .regression import stacked_regressor

__all__ = ["BaseParameters", "base_parameters"]


class BaseParameters(NamedTuple):
    """Identifiable combinations of the parameters (from :func:`base_parameters`).

    Attributes:
        independent: indices (into ``π``) of the base columns, ``(r,)``.
        dependent: indices of the other columns with a non-zero regressor column.
        unidentifiable: indices whose regressor column is zero at every state.
        combination: ``(r, n_param)`` matrix ``B`` with ``β = B π`` (``B[:, independent] = E``).
        names: names of all parameters (:func:`parameter_names`).
        singular_values: singular values of the scaled stacked regressor (conditioning).
        null_space: ``(n_param, n_param − r)`` orthonormal basis of the non-identifiable
            directions of ``π``.
        extra: the extra column groups.
    """

    independent: np.ndarray
    dependent: np.ndarray
    unidentifiable: np.ndarray
    combination: np.ndarray
    names: list
    singular_values: np.ndarray
    null_space: np.ndarray
    extra: tuple

    @property
    def rank(self) -> int:
        return int(self.independent.size)

    def base(self, pi: ArrayLike) -> np.ndarray:
        """Base parameters ``β = B π`` of a parameter vector (NumPy)."""
        return self.combination @ np.asarray(pi, dtype=np.float64)

    def reduce(self, Y: ArrayLike) -> np.ndarray:
        """Base regressor ``Y₁ = Y[..., independent]`` (``Y π = Y₁ β``)."""
        return np.asarray(Y)[..., self.independent]

    def describe(self, digits: int = 4, atol: float = 1e-9) -> list[str]:
        """One line per base parameter: ``β_i = π_a + k π_b + ...`` in parameter names."""
        lines = []
        for i, row in enumerate(self.combination):
            lead = self.independent[i]
            terms = [self.names[lead]]
            for j in np.nonzero(np.abs(row) > atol)[0]:
                if j == lead:
                    continue
                c = row[j]
                sign = "-" if c < 0 else "+"
                mag = abs(c)
                coef = "" if abs(mag - 1) < atol else f"{mag:.{digits}g} "
                terms.append(f"{sign} {coef}{self.names[j]}")
            lines.append(f"beta[{i}] = " + " ".join(terms))
        return lines

    def is_identifiable(self, functional: ArrayLike, rtol: float = 1e-8) -> bool:
        """Whether ``a · π`` is identifiable (``a`` orthogonal to the null space)."""
        a = np.asarray(functional, dtype=np.float64)
        nrm = np.linalg.norm(a)
        if nrm == 0:
            return True
        return bool(np.linalg.norm(self.null_space.T @ a) <= rtol * nrm)

    def augmented_identifiability(self, model: Model, q: ArrayLike | None = None) -> list[str]:
        """Which augmented-body quantities are identifiable, in words (one line per body).

        For each moving body ``k``: its subsystem mass ``m_k``, the components of the static
        moment ``m̄_k`` of the augmented body (spec eq. 5) and of its inertia ``I_k`` about the
        base point (eq. 6), in body-``k`` axes at configuration ``q`` (default ``qpos0``). Each
        is a linear functional of ``π`` (obtained by differentiating
        :func:`jaxbody.augmented_bodies`); it is identifiable when it is orthogonal to the
        null space of the stacked regressor.
        """
        return _augmented_lines(self, model, q)


def _augmented_functionals(model: Model, q):
    """Jacobians of body-axes augmented quantities with respect to the inertial parameters."""
    dtype = model.body_mass.dtype
    q = model.qpos0 if q is None else jnp.asarray(q, dtype)
    rot = forward_kinematics(model, q).body_rotation

    def f(pi):
        aug = augmented_bodies(with_parameters(model, pi), q)
        mbar = jnp.einsum("nji,nj->ni", rot, aug.static_moment)
        Ik = jnp.einsum("nji,njk,nkl->nil", rot, aug.augmented_inertia, rot)
        return aug.subtree_mass, mbar, Ik

    return jax.jacfwd(f)(reference_parameters(model, dtype))


def _augmented_lines(base: BaseParameters, model: Model, q):
    dm, dmbar, dI = (np.asarray(x, dtype=np.float64) for x in _augmented_functionals(model, q))
    pad = len(base.names) - dm.shape[-1]

    def ok(vec):
        return base.is_identifiable(np.concatenate([vec, np.zeros(pad)]))

    lines = []
    joints = model.joints.body_joint_count
    for k, name in enumerate(model.body_names):
        carriers = np.nonzero(model.tree.carrier_mask[:, k])[0]
        if joints[k] == 0 and not any(joints[i] > 0 for i in carriers):
            lines.append(f"{name}: fixed to the ground, nothing identifiable")
            continue
        if joints[k] == 0:
            name = f"{name} (welded to its parent)"
        mass = "identifiable" if ok(dm[k]) else "not identifiable"
        axes = "xyz"
        mb_yes = [axes[i] for i in range(3) if ok(dmbar[k, i])]
        comps = {"xx": (0, 0), "yy": (1, 1), "zz": (2, 2), "xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}
        I_yes = [c for c, (i, j) in comps.items() if ok(dI[k, i, j])]
        for c, (i1, i2) in (("xx-yy", (0, 1)), ("xx-zz", (0, 2)), ("yy-zz", (1, 2))):
            if ok(dI[k, i1, i1] - dI[k, i2, i2]) and not (axes[i1] * 2 in I_yes and axes[i2] * 2 in I_yes):
                I_yes.append(c)
        lines.append(
            f"{name}: subsystem mass m_k {mass}; static moment m̄_k components "
            f"{', '.join(mb_yes) or 'none'} identifiable; augmented inertia I_k components "
            f"{', '.join(I_yes) or 'none'} identifiable (body axes, about the joint)"
        )
    return lines


def base_parameters(
    model: Model,
    n_samples: int = 64,
    seed: int = 0,
    extra: Sequence[str] = (),
    rtol: float = 1e-9,
) -> BaseParameters:
    """Base (identifiable) parameters by column-pivoted QR of the stacked regressor.

    The regressor is stacked over ``n_samples`` states of :func:`random_states`; columns are
    scaled to unit norm before the decomposition (so units do not bias the pivoting), and the
    rank is the number of diagonal entries of ``R`` above ``rtol`` times the largest. With
    ``W[:, P] = Q [R₁₁ R₁₂]`` the dependent columns are ``W₂ = W₁ K``, ``K = R₁₁⁻¹ R₁₂``, and
    ``β = π₁ + K π₂`` (returned as ``B`` with ``β = B π``). Runs outside ``jit`` (NumPy/SciPy).
    """
    import scipy.linalg  # SciPy loads only when base parameters are computed

    extra = check_extra(extra)
    q, v, a = random_states(model, n_samples, seed)
    W = stacked_regressor(model, q, v, a, extra).reshape(-1, 10 * model.n_body + n_extra(model, extra))
    P = W.shape[1]
    norms = np.linalg.norm(W, axis=0)
    zero = norms <= rtol * norms.max()
    nz = np.nonzero(~zero)[0]
    Ws = W[:, nz] / norms[nz]
    _, R, perm = scipy.linalg.qr(Ws, mode="economic", pivoting=True)
    d = np.abs(np.diag(R))
    r = int(np.sum(d > rtol * d[0]))
    K = scipy.linalg.solve_triangular(R[:r, :r], R[:r, r:])
    ind_s, dep_s = perm[:r], perm[r:]
    independent, dependent = nz[ind_s], nz[dep_s]
    order = np.argsort(independent)
    B = np.zeros((r, P))
    B[np.arange(r), independent] = 1.0
    # undo the column scaling: W₂ = W₁ diag(n₁)⁻¹ K diag(n₂)
    B[:, dependent] = (K * norms[dependent][None, :]) / norms[independent][:, None]
    B = B[order]
    independent = independent[order]
    # null space of W in π coordinates: directions z with W z = 0
    Wsc = W / np.where(norms > 0, norms, 1.0)
    _, sv, Vt = np.linalg.svd(Wsc, full_matrices=True)
    ns = Vt[r:].T / np.where(norms > 0, norms, 1.0)[:, None]
    ns, _ = np.linalg.qr(ns)
    return BaseParameters(
        independent=independent,
        dependent=np.sort(dependent),
        unidentifiable=np.nonzero(zero)[0],
        combination=B,
        names=parameter_names(model, extra),
        singular_values=sv,
        null_space=ns,
        extra=extra,
    )
