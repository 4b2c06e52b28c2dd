"""Dense symmetric positive-definite factorisation and solves, without LAPACK.

The mass matrix ``M(q)`` of every jaxbody model is symmetric positive definite, and the
equations of motion need ``M⁻¹ f`` once per right-hand-side evaluation, usually under
``vmap`` over thousands of states. This module provides Cholesky factorisation
``A = L Lᵀ`` and the two triangular solves written with plain array operations:

* **No LAPACK custom call.** On jax/jaxlib 0.10.2 (CPU), batched
  ``jnp.linalg.solve``/``cholesky`` under ``vmap`` intermittently deadlocks XLA's thread
  pool (reproduced for 7×7 at batch 8192 and 20×20 at batch 1024–8192; see
  ``benchmarks/linalg.py``). Nothing here calls LAPACK.
* **Trace size independent of ``n``** for the loop methods: one ``lax.fori_loop`` over
  columns whose body is a handful of array operations. Under ``vmap`` the batch becomes
  the leading axis of every operation in the body, so the batch is never looped over.
* **Exact, cheap derivatives.** :func:`solve_spd` and :func:`cholesky` carry a
  ``jax.custom_jvp`` (``dx = A⁻¹(db − dA x)``; ``dL = L Φ(L⁻¹ dA L⁻ᵀ)``), so forward and
  reverse mode never differentiate through the factorisation.

Methods (keyword ``method``):

``"crout"`` (loop; ``"auto"`` for ``n > 8``)
    Left-looking Cholesky–Crout. Step ``j`` forms column ``j`` of ``L`` from the
    finished columns with one matrix–vector product, ``v = A[:, j] − L L[j, :]ᵀ`` (the
    columns ``≥ j`` of ``L`` are still zero, so the full product is the partial sum),
    then writes ``L[:, j] = v / √v_j`` (rows ``≥ j``) in place. Per step: one batched
    matvec plus a few fused elementwise ops on ``(batch, n)`` arrays; the solves are one
    loop step per row. Constant trace, compile ≈ 0.6–1 s for any ``n``.
``"right_looking"`` (loop)
    Outer-product Cholesky: step ``j`` subtracts the rank-one update ``l lᵀ`` from the
    whole ``(n, n)`` Schur complement. Same trace size, but every step rewrites the
    whole matrix: about 1.5–3× slower than ``"crout"`` in batch. Kept for comparison.
``"unrolled"`` (``"auto"`` for ``n ≤ 8``)
    Element-by-element Cholesky and substitutions with Python loops: ``n³/6`` scalar
    (per-batch-member) operations and no loop, which XLA fuses into a few kernels. For
    ``n ≤ 8`` it solves 2–7× faster than ``"crout"`` at batch 1024–8192 and compiles in
    under 2 s; the trace and compile time grow as ``n³`` (≈ 4 s at ``n = 10``, 7 s at
    ``n = 12``, 30–60 s at ``n = 20`` with ``--xla_cpu_use_fusion_emitters=false``), so
    it is limited to ``n ≤ 16`` and is not the default above ``n = 8``.

``benchmarks/linalg.py`` (record in ``benchmarks/results/linalg.md``) measures all of
them against LAPACK.

Conventions: only the lower triangle of ``A`` is read (LAPACK ``potrf`` with
``uplo='L'``); the strict upper triangle is ignored. The custom JVPs are the exact
derivatives of that function: a perturbation ``dA`` acts through its lower triangle,
``tril(dA) + tril(dA, -1)ᵀ``, so reverse-mode cotangents for ``A`` are lower triangular
(off-diagonal entries carry both ``(i, j)`` and ``(j, i)``). For ``A`` built symmetric
from parameters (a mass matrix), the chain rule gives the same parameter gradients as a
symmetric convention, without a symmetrising pass over ``A``.
A pivot that is not positive and finite (``A`` not positive definite, or NaN/inf in
``A``) is not silently ignored: the factor becomes NaN from that column on and every
solution component becomes NaN. :func:`failed_pivot` turns a factor
into a per-matrix result code (``-1`` or the index of the first failed pivot), which
survives ``vmap``; ``check=True`` instead raises inside ``jit`` via
:func:`equinox.branched_error_if`, naming the pivot.
"""

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ._types import Array, ArrayLike, Float, Int

__all__ = [
    "METHODS",
    "AUTO_UNROLLED_MAX_N",
    "UNROLLED_MAX_N",
    "cholesky",
    "cholesky_solve",
    "solve_spd",
    "failed_pivot",
]

#: Accepted values of the ``method`` keyword.
METHODS = ("auto", "crout", "right_looking", "unrolled")

#: Largest ``n`` accepted by ``method="unrolled"`` (its trace has ``n³/6`` operations).
UNROLLED_MAX_N = 16

#: ``method="auto"`` uses ``"unrolled"`` up to this ``n`` and ``"crout"`` above it.
AUTO_UNROLLED_MAX_N = 8


# ---------------------------------------------------------------------------------------
# Validation (shapes and static options: trace-time ValueError)
# ---------------------------------------------------------------------------------------


def _as_matrix(fn: str, name: str, A) -> Array:
    A = jnp.asarray(A)
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(
            f"{fn}: {name} must be a square matrix of shape (n, n), got shape {tuple(A.shape)}"
            " (batch with jax.vmap)"
        )
    if not jnp.issubdtype(A.dtype, jnp.floating):
        raise TypeError(f"{fn}: {name} must have a real floating dtype, got {A.dtype}")
    return A


def _as_rhs(fn: str, b, n: int) -> Array:
    b = jnp.asarray(b)
    if b.ndim not in (1, 2) or b.shape[0] != n:
        raise ValueError(
            f"{fn}: b must have shape (n,) or (n, k) with n = {n}, got shape {tuple(b.shape)}"
        )
    if not jnp.issubdtype(b.dtype, jnp.floating):
        raise TypeError(f"{fn}: b must have a real floating dtype, got {b.dtype}")
    return b


def _resolve_method(fn: str, method: str, n: int) -> str:
    if method not in METHODS:
        raise ValueError(f"{fn}: unknown method {method!r}; expected one of {METHODS}")
    if method == "auto":
        return "unrolled" if n <= AUTO_UNROLLED_MAX_N else "crout"
    if method == "unrolled" and n > UNROLLED_MAX_N:
        raise ValueError(
            f"{fn}: method='unrolled' is limited to n <= {UNROLLED_MAX_N} (its trace and compile"
            f" time grow as n**3); got n = {n}. Use method='crout'."
        )
    return method


def _from_lower(A: Array) -> Array:
    """The symmetric matrix whose lower triangle is that of ``A`` (what the kernels read)."""
    return jnp.tril(A) + jnp.tril(A, -1).T


def _pivot_ok(d: Array) -> Array:
    return (d > 0) & jnp.isfinite(d)


def _failed_pivot(L: Array) -> Array:
    if L.shape[0] == 0:
        return jnp.asarray(-1, jnp.int32)
    bad = ~_pivot_ok(jnp.diagonal(L))
    return jnp.where(jnp.any(bad), jnp.argmax(bad).astype(jnp.int32), jnp.int32(-1))


def _pivot_sqrt(d: Array) -> Array:
    # A non-positive, NaN or infinite pivot gives NaN, never sqrt(0) = 0 followed by
    # inf/garbage: NaN then propagates to every later column and to the whole solution.
    return jnp.sqrt(jnp.where(_pivot_ok(d), d, jnp.nan))


# ---------------------------------------------------------------------------------------
# Factorisation kernels: symmetric S (n, n) -> lower-triangular L, S = L Lᵀ
# ---------------------------------------------------------------------------------------


def _factor_crout(S: Array) -> Array:
    n = S.shape[-1]
    rows = jnp.arange(n)

    def column(j, L):
        # Row j of L is zero in columns >= j (not computed yet), so the full matvec
        # L @ L[j] equals the partial sum over k < j: no masking, one dot per step.
        l_j = lax.dynamic_index_in_dim(L, j, axis=0, keepdims=False)
        s_j = lax.dynamic_index_in_dim(S, j, axis=1, keepdims=False)
        v = s_j - L @ l_j
        pivot = _pivot_sqrt(lax.dynamic_index_in_dim(v, j, keepdims=False))
        col = jnp.where(rows >= j, v / pivot, jnp.zeros((), S.dtype))
        return lax.dynamic_update_index_in_dim(L, col[:, None], j, axis=1)

    return lax.fori_loop(0, n, column, jnp.zeros_like(S))


def _factor_right_looking(S: Array) -> Array:
    n = S.shape[-1]
    rows = jnp.arange(n)

    def column(j, W):
        # W holds L in columns < j and the Schur complement in the trailing block.
        # After the rank-one update column j of the complement is exactly zero, so
        # storing l there keeps a single (n, n) carry.
        w_j = lax.dynamic_index_in_dim(W, j, axis=1, keepdims=False)
        pivot = _pivot_sqrt(lax.dynamic_index_in_dim(w_j, j, keepdims=False))
        col = jnp.where(rows >= j, w_j / pivot, jnp.zeros((), S.dtype))
        # Finished columns (< j) are left untouched, so a NaN pivot cannot leak into them
        # through 0 * NaN.
        updated = jnp.where(rows[None, :] > j, W - col[:, None] * col[None, :], W)
        return jnp.where(rows[None, :] == j, col[:, None], updated)

    W = lax.fori_loop(0, n, column, S)
    return jnp.where(rows[:, None] >= rows[None, :], W, jnp.zeros((), S.dtype))


def _factor_unrolled(S: Array) -> Array:
    n = S.shape[-1]
    if n == 0:
        return S
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        s = S[j, j]
        for k in range(j):
            s = s - L[j][k] * L[j][k]
        pivot = _pivot_sqrt(s)
        L[j][j] = pivot
        inv = 1 / pivot
        for i in range(j + 1, n):
            s = S[i, j]
            for k in range(j):
                s = s - L[i][k] * L[j][k]
            L[i][j] = s * inv
    zero = jnp.zeros((), S.dtype)
    return jnp.stack([jnp.stack([L[i][j] if j <= i else zero for j in range(n)]) for i in range(n)])


_FACTOR = {
    "crout": _factor_crout,
    "right_looking": _factor_right_looking,
    "unrolled": _factor_unrolled,
}


# ---------------------------------------------------------------------------------------
# Triangular solves with the factor: L (n, n) lower, B (n, k)
# ---------------------------------------------------------------------------------------


def _forward_loop(L: Array, B: Array) -> Array:
    """``L⁻¹ B`` by forward substitution (dot-product form), one row per step."""
    n = L.shape[0]

    def row(j, Y):
        # Rows >= j of Y are still zero, so the full product is the sum over k < j.
        # Both forms read row j of L, contiguous in memory.
        l_j = lax.dynamic_index_in_dim(L, j, axis=0, keepdims=False)
        b_j = lax.dynamic_index_in_dim(B, j, axis=0, keepdims=False)
        # A vector RHS uses multiply+sum (fuses; a batched dot of two vectors does not).
        acc = jnp.sum(l_j * Y) if Y.ndim == 1 else l_j @ Y
        y_j = (b_j - acc) / lax.dynamic_index_in_dim(l_j, j, keepdims=False)
        return lax.dynamic_update_index_in_dim(Y, y_j, j, axis=0)

    return lax.fori_loop(0, n, row, jnp.zeros_like(B))


def _backward_loop(L: Array, Y: Array) -> Array:
    """``L⁻ᵀ Y`` by back substitution (column-sweep form), from the bottom row up."""
    n = L.shape[0]
    rows = jnp.arange(n).reshape((n,) + (1,) * (Y.ndim - 1))

    def row(i, X):
        j = n - 1 - i
        # Column j of Lᵀ is row j of L (contiguous): x_j = X_j / L_jj, then eliminate
        # x_j from the rows above, X_k -= L_jk x_j for k < j.
        l_j = lax.dynamic_index_in_dim(L, j, axis=0, keepdims=False)
        x_j = lax.dynamic_index_in_dim(X, j, axis=0, keepdims=False) / lax.dynamic_index_in_dim(
            l_j, j, keepdims=False
        )
        update = X - (l_j * x_j if X.ndim == 1 else l_j[:, None] * x_j[None, :])
        return jnp.where(rows == j, x_j, jnp.where(rows < j, update, X))

    return lax.fori_loop(0, n, row, Y)


def _forward_unrolled(L: Array, B: Array) -> Array:
    n = L.shape[0]
    y = []
    for j in range(n):
        s = B[j]
        for k in range(j):
            s = s - L[j, k] * y[k]
        y.append(s / L[j, j])
    return jnp.stack(y) if n else B


def _backward_unrolled(L: Array, Y: Array) -> Array:
    n = L.shape[0]
    x = [None] * n
    for j in reversed(range(n)):
        s = Y[j]
        for k in range(j + 1, n):
            s = s - L[k, j] * x[k]
        x[j] = s / L[j, j]
    return jnp.stack(x) if n else Y


def _solve_factored(L: Array, B: Array, method: str) -> Array:
    if method == "unrolled":
        return _backward_unrolled(L, _forward_unrolled(L, B))
    return _backward_loop(L, _forward_loop(L, B))


def _forward(L: Array, B: Array, method: str) -> Array:
    return _forward_unrolled(L, B) if method == "unrolled" else _forward_loop(L, B)


# ---------------------------------------------------------------------------------------
# Differentiable cores (custom JVPs: exact derivatives, no AD through the loops)
# ---------------------------------------------------------------------------------------


@partial(jax.custom_jvp, nondiff_argnums=(1,))
def _cholesky(A: Array, method: str) -> Array:
    return _FACTOR[method](A)


@_cholesky.defjvp
def _cholesky_jvp(method, primals, tangents):
    (A,), (dA,) = primals, tangents
    L = _cholesky(A, method)
    # dL = L Φ(L⁻¹ dS L⁻ᵀ), Φ = lower triangle with the diagonal halved. With W = L⁻¹ dS,
    # L⁻¹ dS L⁻ᵀ = L⁻¹ Wᵀ because dS is symmetric.
    W = _forward(L, _from_lower(dA), method)
    Z = _forward(L, W.T, method)
    Phi = jnp.tril(Z) - 0.5 * jnp.diag(jnp.diagonal(Z))
    return L, L @ Phi


@partial(jax.custom_jvp, nondiff_argnums=(2,))
def _solve(A: Array, B: Array, method: str) -> tuple[Array, Array]:
    L = _cholesky(A, method)
    return _solve_factored(L, B, method), _failed_pivot(L)


@_solve.defjvp
def _solve_jvp(method, primals, tangents):
    (A, B), (dA, dB) = primals, tangents
    L = _cholesky(A, method)
    X = _solve_factored(L, B, method)
    # A X = B  =>  A dX = dB - dA X, with dA read through its lower triangle like A.
    dX = _solve_factored(L, dB - _from_lower(dA) @ X, method)
    info = _failed_pivot(L)
    return (X, info), (dX, np.zeros(info.shape, dtype=jax.dtypes.float0))


# ---------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------


def _pivot_messages(fn: str, n: int) -> list[str]:
    return [
        f"{fn}: matrix is not positive definite: pivot {j} is not positive and finite"
        f" (the leading {j + 1}x{j + 1} block is not positive definite, or the matrix has NaN/inf)"
        for j in range(n)
    ]


def failed_pivot(L: Float[ArrayLike, "n n"]) -> Int[Array, ""]:
    """Result code of a factorisation: ``-1`` if it succeeded, else the first failed pivot.

    A pivot fails when it is not positive and finite (``A`` not positive definite, or
    NaN/inf in ``A``); :func:`cholesky` then leaves NaN on the diagonal from that column
    on. Under ``vmap`` this gives one code per batch member, so a batch survives a bad
    member (a result code per member, never an exception inside a loop).

    Args:
        L: factor returned by :func:`cholesky`, shape ``(n, n)``.

    Returns:
        ``int32`` scalar: ``-1`` on success, otherwise the index ``j`` (0-based) of the
        first column whose pivot ``A_jj − Σ_k L_jk²`` was not positive and finite.

    Raises:
        ValueError: at trace time if ``L`` is not square.
    """
    return _failed_pivot(_as_matrix("failed_pivot", "L", L))


def cholesky(
    A: Float[ArrayLike, "n n"], *, method: str = "auto", check: bool = False
) -> Float[Array, "n n"]:
    """Cholesky factor of a symmetric positive-definite matrix: ``A = L Lᵀ``.

    Only the lower triangle of ``A`` is read. Works under ``jit``, ``vmap`` (any
    batch size; the batch is never looped over) and forward/reverse differentiation
    (exact custom JVP ``dL = L Φ(L⁻¹ dA L⁻ᵀ)``, ``Φ`` = lower triangle with the diagonal
    halved).

    Args:
        A: symmetric positive-definite matrix, shape ``(n, n)``, real floating dtype.
        method: ``"auto"`` (``"unrolled"`` for ``n ≤ 8``, else ``"crout"``),
            ``"crout"``, ``"right_looking"`` or ``"unrolled"`` (``n ≤ 16``); see the
            module docstring.
        check: if ``True``, raise (inside ``jit`` too, via ``eqx.branched_error_if``) when
            a pivot fails, naming its index. Under ``vmap`` one bad member
            raises for the whole batch; use :func:`failed_pivot` to keep going instead.

    Returns:
        Lower-triangular ``L`` with positive diagonal, shape ``(n, n)``. If pivot ``j``
        fails (not positive and finite: ``A`` not positive definite, or NaN/inf in
        ``A``), ``L[i, k]`` is NaN for ``i ≥ k ≥ j``; columns ``< j`` are the valid
        partial factor.

    Raises:
        ValueError: at trace time, if ``A`` is not square or ``method`` is unknown (or
            ``"unrolled"`` with ``n > 16``).
        TypeError: at trace time, if ``A`` is not real floating point.
        equinox.EquinoxRuntimeError: at run time with ``check=True``, if a pivot fails:
            ``"cholesky: matrix is not positive definite: pivot j is not positive and finite
            ..."``.
    """
    A = _as_matrix("cholesky", "A", A)
    method = _resolve_method("cholesky", method, A.shape[0])
    with jax.named_scope("cholesky"):
        L = _cholesky(A, method)
    if check and A.shape[0] > 0:
        info = _failed_pivot(L)
        L = eqx.branched_error_if(
            L, info >= 0, jnp.maximum(info, 0), _pivot_messages("cholesky", A.shape[0])
        )
    return L


def cholesky_solve(
    L: Float[ArrayLike, "n n"], b: Float[ArrayLike, "n *k"], *, method: str = "auto"
) -> Float[Array, "n *k"]:
    """Solve ``L Lᵀ x = b`` given the Cholesky factor from :func:`cholesky`.

    Forward then back substitution, one ``fori_loop`` step per row (or unrolled with
    ``method="unrolled"``). Only the lower triangle of ``L`` is read. Differentiable in
    ``L`` and ``b`` by ordinary autodiff (the loops are linear in ``b``); for derivatives
    with respect to the matrix prefer :func:`solve_spd`, whose custom JVP avoids
    differentiating the factorisation.

    Args:
        L: lower-triangular factor, shape ``(n, n)``.
        b: right-hand side, shape ``(n,)`` or ``(n, k)`` (``k`` right-hand sides).
        method: ``"auto"`` (``"unrolled"`` for ``n ≤ 8``, else loop substitution),
            ``"crout"``/``"right_looking"`` (loop substitution) or ``"unrolled"``.

    Returns:
        ``x`` with the shape of ``b``; NaN everywhere if ``L`` came from a failed
        factorisation.

    Raises:
        ValueError: at trace time, if ``L`` is not square or ``b`` does not have ``n``
            rows.
        TypeError: at trace time, if ``L`` or ``b`` is not real floating point.
    """
    L = _as_matrix("cholesky_solve", "L", L)
    n = L.shape[0]
    b = _as_rhs("cholesky_solve", b, n)
    dtype = jnp.result_type(L, b)  # raises under strict promotion if they differ
    L, b = L.astype(dtype), b.astype(dtype)
    method = _resolve_method("cholesky_solve", method, n)
    L = jnp.tril(L)
    with jax.named_scope("cholesky_solve"):
        return _solve_factored(L, b, method)


def solve_spd(
    A: Float[ArrayLike, "n n"],
    b: Float[ArrayLike, "n *k"],
    *,
    method: str = "auto",
    check: bool = False,
) -> Float[Array, "n *k"]:
    """Solve ``A x = b`` for symmetric positive-definite ``A`` (Cholesky factor + solve).

    Only the lower triangle of ``A`` is read. Works under ``jit``,
    ``vmap`` (any batch size, no LAPACK call, batch never looped over) and
    forward/reverse differentiation in ``A`` and ``b``: a custom JVP
    ``dx = A⁻¹(db − dA x)`` reuses the factor, so ``grad`` costs two more triangular
    solves and is exact (no differentiation through the factorisation loop).

    Args:
        A: symmetric positive-definite matrix, shape ``(n, n)``, real floating dtype.
        b: right-hand side, shape ``(n,)`` or ``(n, k)``.
        method: ``"auto"`` (``"unrolled"`` for ``n ≤ 8``, else ``"crout"``),
            ``"crout"``, ``"right_looking"`` or ``"unrolled"`` (``n ≤ 16``); see the
            module docstring.
        check: if ``True``, raise (inside ``jit`` too) when a pivot fails,
            naming its index. Under ``vmap`` one bad member raises for the whole batch;
            without ``check`` a bad member just gets an all-NaN ``x``.

    Returns:
        ``x`` with the shape of ``b``. All NaN if ``A`` is not positive definite.

    Raises:
        ValueError: at trace time, if ``A`` is not square, ``b`` does not have ``n`` rows
            or ``method`` is unknown (or ``"unrolled"`` with ``n > 16``).
        TypeError: at trace time, if ``A`` or ``b`` is not real floating point.
        equinox.EquinoxRuntimeError: at run time with ``check=True``, if a pivot fails:
            ``"solve_spd: matrix is not positive definite: pivot j is not positive and finite
            ..."``.
    """
    A = _as_matrix("solve_spd", "A", A)
    n = A.shape[0]
    b = _as_rhs("solve_spd", b, n)
    dtype = jnp.result_type(A, b)  # raises under strict promotion if they differ
    A, b = A.astype(dtype), b.astype(dtype)
    method = _resolve_method("solve_spd", method, n)
    with jax.named_scope("solve_spd"):
        X, info = _solve(A, b, method)
    if check and n > 0:
        X = eqx.branched_error_if(X, info >= 0, jnp.maximum(info, 0), _pivot_messages("solve_spd", n))
    return X


# ---------------------------------------------------------------------------------------
# Dense general solve (no symmetry, no definiteness): Gauss–Jordan with row pivoting
# ---------------------------------------------------------------------------------------

__all__ += ["solve_general", "gauss_jordan"]


def solve_general(M: Float[ArrayLike, "n n"], B: Float[ArrayLike, "n k"]) -> tuple[Float[Array, "n k"], Float[Array, ""]]:
    """Solve ``M·X = B`` by Gauss–Jordan elimination with partial (row) pivoting.

    Plain array operations in one ``lax.fori_loop`` over columns (no LAPACK call, so it
    is safe under ``vmap`` on CPU; trace size independent of ``n``); differentiable by
    ordinary autodiff.

    Args:
        M: square matrix ``(n, n)``.
        B: right-hand sides ``(n, k)``.

    Returns:
        ``(X, pivot_ratio)``: the solution and ``min |pivot| / max |M_ij|`` (``0`` for a
        singular ``M``; a conditioning measure, compare with :data:`jaxbody.maggi.SINGULAR_PIVOT`).
    """
    X, ratio, _, _ = gauss_jordan(M, B)
    return X, ratio


def gauss_jordan(M: Float[ArrayLike, "n n"], B: Float[ArrayLike, "n k"]):
    """Gauss–Jordan elimination of :func:`solve_general`; also returns ``det M`` as
    ``(sign, log|det|)`` (product of the pivots and the parity of the row exchanges).

    Returns:
        ``(X, pivot_ratio, sign, log_abs_det)``.
    """
    M = jnp.asarray(M)
    B = jnp.asarray(B, M.dtype)
    n = M.shape[0]
    if M.ndim != 2 or M.shape != (n, n) or B.ndim != 2 or B.shape[0] != n:
        raise ValueError(f"solve_general: M must be (n, n) and B (n, k), got {M.shape} and {B.shape}")
    if n == 0:
        return B, jnp.ones((), M.dtype), jnp.ones((), M.dtype), jnp.zeros((), M.dtype)
    scale = jnp.maximum(jnp.max(jnp.abs(M)), jnp.finfo(M.dtype).tiny)
    rows = jnp.arange(n)

    def step(k, carry):
        M, B, smallest, sign, logdet = carry
        col = jnp.where(rows >= k, jnp.abs(M[:, k]), -1.0)
        p = jnp.argmax(col)
        perm = rows.at[k].set(p).at[p].set(k)
        M, B = M[perm], B[perm]
        pivot = M[k, k]
        smallest = jnp.minimum(smallest, jnp.abs(pivot))
        sign = sign * jnp.where(p == k, 1.0, -1.0) * jnp.sign(pivot)
        logdet = logdet + jnp.log(jnp.abs(pivot))
        safe = jnp.where(pivot == 0, jnp.ones_like(pivot), pivot)
        row_m, row_b = M[k] / safe, B[k] / safe
        factor = jnp.where(rows == k, 0.0, M[:, k])
        M = (M - factor[:, None] * row_m[None, :]).at[k].set(row_m)
        B = (B - factor[:, None] * row_b[None, :]).at[k].set(row_b)
        return M, B, smallest, sign, logdet

    one, zero = jnp.ones((), M.dtype), jnp.zeros((), M.dtype)
    _, X, smallest, sign, logdet = lax.fori_loop(0, n, step, (M, B, jnp.asarray(jnp.inf, M.dtype), one, zero))
    return X, smallest / scale, sign, logdet
