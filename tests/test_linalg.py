"""Tests of ``jaxbody.linalg``: SPD factorisation and solves without LAPACK.

References we did not write: NumPy/SciPy (LAPACK) factors and solutions, residual and
backward-error bounds for ill-conditioned systems, finite differences
(``jax.test_util.check_grads``), and the gradient of ``jnp.linalg.solve`` at batch 1
(where it does not deadlock).
"""

import contextlib
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxtyping
import numpy as np
import pytest
import scipy.linalg
from jax.test_util import check_grads

from _support.jaxpr_tools import count_eqns

from jaxbody import linalg

LOOP_METHODS = ("crout", "right_looking")
ALL_METHODS = ("auto", "crout", "right_looking", "unrolled")
RUNTIME_ERRORS = (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError)


def spd(rng, n, cond=10.0, dtype=np.float64):
    """Random SPD matrix with eigenvalues log-spaced in [1, cond] (exactly symmetric)."""
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    lam = np.logspace(0.0, np.log10(cond), n) if n > 1 else np.ones(1)
    A = (Q * lam) @ Q.T
    return (0.5 * (A + A.T)).astype(dtype)


def spd_batch(rng, batch, n, dtype=np.float64):
    X = rng.standard_normal((batch, n, n))
    return (X @ X.transpose(0, 2, 1) / n + np.eye(n)).astype(dtype)


def methods_for(n):
    """The distinct algorithms for size n ("auto" picks one of them: see test_auto_method_choice_and_empty)."""
    return [m for m in ALL_METHODS[1:] if m != "unrolled" or n <= linalg.UNROLLED_MAX_N]


@contextlib.contextmanager
def no_jaxtyping():
    """Switch off the jaxtyping hook so our own trace-time ValueErrors are reached."""
    before = jaxtyping.config.jaxtyping_disable
    jaxtyping.config.update("jaxtyping_disable", True)
    try:
        yield
    finally:
        jaxtyping.config.update("jaxtyping_disable", before)


# Jitted entry points (one compile per shape and method; eager loops would recompile).
@partial(jax.jit, static_argnames="method")
def factor_and_solve(A, b, B, method):
    L = linalg.cholesky(A, method=method)
    return (
        L,
        linalg.solve_spd(A, b, method=method),
        linalg.solve_spd(A, B, method=method),
        linalg.cholesky_solve(L, b, method=method),
        linalg.failed_pivot(L),
    )


@partial(jax.jit, static_argnames="method")
def cholesky(A, method="auto"):
    return linalg.cholesky(A, method=method)


@partial(jax.jit, static_argnames="method")
def solve_spd(A, b, method="auto"):
    return linalg.solve_spd(A, b, method=method)


# ----------------------------------------------------------------------------- correctness
@pytest.mark.parametrize("n", [1, 2, 7, 20, 100])
def test_factor_and_solve_match_lapack(n):
    rng = np.random.default_rng(n)
    A = spd(rng, n)
    b = rng.standard_normal(n)
    B = rng.standard_normal((n, 3))
    L_ref = scipy.linalg.cholesky(A, lower=True)
    x_ref = scipy.linalg.solve(A, b, assume_a="pos")
    for method in methods_for(n):
        L, x, X, x2, code = map(np.asarray, factor_and_solve(A, b, B, method))
        np.testing.assert_allclose(L, L_ref, rtol=0, atol=1e-13 * np.abs(L_ref).max(), err_msg=method)
        assert np.all(np.triu(L, 1) == 0), method
        np.testing.assert_allclose(x, x_ref, rtol=1e-11, atol=1e-12, err_msg=method)
        assert X.shape == (n, 3)
        np.testing.assert_allclose(X, np.linalg.solve(A, B), rtol=1e-11, atol=1e-12, err_msg=method)
        np.testing.assert_allclose(x2, x, rtol=1e-12, atol=1e-13, err_msg=method)
        assert code == -1


@pytest.mark.parametrize("n", [7, 20, 100])
def test_ill_conditioned_float64_residuals(n):
    """cond(A) = 1e8: the forward error may be ~1e-8, but backward errors stay at n·eps."""
    rng = np.random.default_rng(100 + n)
    A = spd(rng, n, cond=1e8)
    x_true = rng.standard_normal(n)
    b = A @ x_true
    eps = np.finfo(np.float64).eps
    for method in methods_for(n):
        # Same shapes as test_factor_and_solve_match_lapack: reuses its compiled functions.
        L, x, *_ = map(np.asarray, factor_and_solve(A, b, np.zeros((n, 3)), method))
        assert np.linalg.norm(A - L @ L.T) / np.linalg.norm(A) < 10 * n * eps, method
        residual = np.linalg.norm(A @ x - b) / (np.linalg.norm(A) * np.linalg.norm(x))
        assert residual < 10 * n * eps, method
        assert np.linalg.norm(x - x_true) / np.linalg.norm(x_true) < 1e8 * 10 * n * eps, method


@pytest.mark.parametrize("n", [2, 7, 20, 100])
def test_float32_stability(n):
    """cond(A) = 1e3 in float32: relative error within 1e-4 of the float64 solution."""
    rng = np.random.default_rng(200 + n)
    for _ in range(3):
        A = spd(rng, n, cond=1e3, dtype=np.float32)
        b = rng.standard_normal(n).astype(np.float32)
        x_ref = np.linalg.solve(A.astype(np.float64), b.astype(np.float64))
        for method in methods_for(n):
            x = solve_spd(jnp.asarray(A), jnp.asarray(b), method)
            assert x.dtype == jnp.float32
            x = np.asarray(x, np.float64)
            assert np.all(np.isfinite(x)), method
            assert np.linalg.norm(x - x_ref) / np.linalg.norm(x_ref) < 1e-4, method


def test_only_lower_triangle_is_read():
    rng = np.random.default_rng(3)
    A = spd(rng, 6)
    b = rng.standard_normal(6)
    garbage = np.tril(A) + np.triu(rng.standard_normal((6, 6)) * 100.0, 1)
    for method in ALL_METHODS:
        np.testing.assert_allclose(
            solve_spd(garbage, b, method), np.linalg.solve(A, b), rtol=1e-12
        )
        np.testing.assert_allclose(cholesky(garbage, method), np.linalg.cholesky(A), atol=1e-14)


def test_auto_method_choice_and_empty():
    assert linalg.METHODS == ("auto", "crout", "right_looking", "unrolled")
    for n in (1, linalg.AUTO_UNROLLED_MAX_N, linalg.AUTO_UNROLLED_MAX_N + 1):
        A = spd(np.random.default_rng(n), n)
        expected = "unrolled" if n <= linalg.AUTO_UNROLLED_MAX_N else "crout"
        np.testing.assert_array_equal(cholesky(A), cholesky(A, expected))
    assert linalg.solve_spd(jnp.zeros((0, 0)), jnp.zeros(0)).shape == (0,)
    assert int(linalg.failed_pivot(jnp.zeros((0, 0)))) == -1


# ----------------------------------------------------------------------------- jit / vmap
def test_jit_and_vmap_agree_with_eager():
    rng = np.random.default_rng(4)
    A = spd_batch(rng, 5, 9)
    b = rng.standard_normal((5, 9))
    eager = np.stack([np.asarray(solve_spd(A[i], b[i])) for i in range(5)])
    batched = jax.jit(jax.vmap(linalg.solve_spd))(A, b)
    np.testing.assert_allclose(batched, eager, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(batched, np.linalg.solve(A, b[..., None])[..., 0], rtol=1e-11)


def _check_batch(batch, n, method, seed=0):
    rng = np.random.default_rng(seed)
    A = spd_batch(rng, batch, n)
    b = rng.standard_normal((batch, n))
    x = jax.jit(jax.vmap(lambda A, b: linalg.solve_spd(A, b, method=method)))(A, b)
    x = np.asarray(x.block_until_ready())
    assert np.all(np.isfinite(x))
    residual = np.linalg.norm(np.einsum("bij,bj->bi", A, x) - b, axis=1) / np.linalg.norm(b, axis=1)
    assert residual.max() < 1e-12


@pytest.mark.timeout(120)
@pytest.mark.parametrize(
    ("batch", "n", "method"),
    [(8192, 7, "auto"), (8192, 7, "crout"), (1024, 20, "auto"), (8192, 20, "auto")],
)
def test_vmap_large_batches_complete(batch, n, method):
    """Batched LAPACK deadlocks XLA at these sizes with jax 0.10.2; this must not."""
    _check_batch(batch, n, method)


@pytest.mark.slow
@pytest.mark.timeout(600)
@pytest.mark.parametrize(("batch", "n"), [(65536, 7), (65536, 20)])
def test_vmap_huge_batch_completes(batch, n):
    _check_batch(batch, n, "auto")


def test_no_lapack_custom_call_in_lowering():
    A = jnp.asarray(spd_batch(np.random.default_rng(5), 4, 12))
    b = jnp.ones((4, 12))
    for method in ALL_METHODS:
        f = jax.vmap(jax.grad(lambda A, b: linalg.solve_spd(A, b, method=method).sum(), argnums=(0, 1)))
        text = jax.jit(f).lower(A, b).as_text()
        assert "custom_call" not in text, method


# ----------------------------------------------------------------------------- trace size
def _eqns(fn, n):
    return count_eqns(jax.make_jaxpr(fn)(jnp.eye(n), jnp.ones(n)).jaxpr)


@pytest.mark.parametrize("method", LOOP_METHODS)
def test_trace_size_independent_of_n(method):
    solve = lambda A, b: linalg.solve_spd(A, b, method=method)  # noqa: E731
    functions = {
        "solve": solve,
        "grad solve": jax.grad(lambda A, b: solve(A, b).sum(), argnums=(0, 1)),
        "vmap solve": lambda A, b: jax.vmap(solve, in_axes=(None, 0))(A, jnp.stack([b, 2 * b])),
        "grad cholesky": jax.grad(lambda A, b: linalg.cholesky(A, method=method).sum()),
        "cholesky_solve": lambda A, b: linalg.cholesky_solve(A, b, method=method),
    }
    for name, fn in functions.items():
        assert _eqns(fn, 4) == _eqns(fn, 64), name


def test_default_trace_is_flat_above_the_unrolled_limit_and_bounded_below():
    limit = linalg.AUTO_UNROLLED_MAX_N
    auto = lambda A, b: linalg.solve_spd(A, b)  # noqa: E731
    crout = lambda A, b: linalg.solve_spd(A, b, method="crout")  # noqa: E731
    assert _eqns(auto, limit + 1) == _eqns(auto, 64) == _eqns(crout, 64)
    at_limit = _eqns(auto, limit)
    assert all(_eqns(auto, n) <= at_limit for n in range(1, limit))


# ----------------------------------------------------------------------------- gradients
@pytest.mark.parametrize("method", ["crout", "right_looking", "unrolled"])
def test_gradients_match_finite_differences(method):
    """Forward and reverse mode against central differences (random, non-symmetric
    perturbations: the JVP is the exact derivative of the lower-triangle-reading function,
    not only on the symmetric subspace)."""
    rng = np.random.default_rng(6)
    A = jnp.asarray(spd(rng, 5))
    b = jnp.asarray(rng.standard_normal(5))
    B = jnp.asarray(rng.standard_normal((5, 2)))
    solve = jax.jit(lambda A, b: linalg.solve_spd(A, b, method=method))
    check_grads(solve, (A, b), order=1, modes=("fwd", "rev"))
    check_grads(solve, (A, B), order=1, modes=("rev",))
    check_grads(jax.jit(lambda A: linalg.cholesky(A, method=method)), (A,), order=1, modes=("fwd", "rev"))
    # cholesky_solve has no custom rule: ordinary autodiff through the substitution loops.
    check_grads(
        jax.jit(lambda L, b: linalg.cholesky_solve(L, b, method=method)),
        (linalg.cholesky(A), b), order=1, modes=("rev",),
    )


def test_second_order_gradients():
    """Hessian-vector products go through the custom JVP twice (jvp of the jvp rule)."""
    rng = np.random.default_rng(11)
    A = jnp.asarray(spd(rng, 4))
    b = jnp.asarray(rng.standard_normal(4))
    check_grads(jax.jit(lambda A, b: linalg.solve_spd(A, b, method="crout")), (A, b), order=2, modes=("rev",))


def test_gradient_closed_form_and_vmap():
    """grad_b (c·x) = A⁻¹c; grad_A = −(λxᵀ) folded onto the lower triangle."""
    rng = np.random.default_rng(7)
    A = spd(rng, 6)
    b, c = rng.standard_normal(6), rng.standard_normal(6)
    grad = jax.jit(jax.grad(lambda A, b, c: jnp.dot(c, linalg.solve_spd(A, b, method="crout")), argnums=(0, 1)))
    gA, gb = grad(A, b, c)
    x, lam = np.linalg.solve(A, b), np.linalg.solve(A, c)
    G = -np.outer(lam, x)
    np.testing.assert_allclose(gb, lam, rtol=1e-12)
    np.testing.assert_allclose(gA, np.tril(G + G.T, -1) + np.diag(np.diag(G)), rtol=1e-11, atol=1e-14)
    As = spd_batch(rng, 3, 6)
    bs = rng.standard_normal((3, 6))
    gAs, gbs = jax.jit(jax.vmap(grad, in_axes=(0, 0, None)))(As, bs, c)
    for i in range(3):
        gAi, gbi = grad(As[i], bs[i], c)
        np.testing.assert_allclose(gAs[i], gAi, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(gbs[i], gbi, rtol=1e-12, atol=1e-15)


def test_parameter_gradient_matches_lapack_solve():
    """For A(θ) built symmetric, parameter gradients equal those through jnp.linalg.solve."""
    rng = np.random.default_rng(8)
    J = jnp.asarray(rng.standard_normal((7, 7)))
    f = jnp.asarray(rng.standard_normal(7))

    def loss(theta, solve):
        M = J.T @ jnp.diag(jnp.exp(theta)) @ J + jnp.eye(7)
        return jnp.sum(solve(M, f) ** 2)

    theta = jnp.asarray(rng.standard_normal(7) * 0.3)
    ref = jax.jit(jax.grad(loss), static_argnums=1)(theta, jnp.linalg.solve)
    for method in ("crout", "right_looking", "unrolled"):
        ours = jax.jit(jax.grad(lambda t: loss(t, lambda M, f: linalg.solve_spd(M, f, method=method))))(theta)
        np.testing.assert_allclose(ours, ref, rtol=1e-10, err_msg=method)


# ----------------------------------------------------------------------------- failures
def _not_pd(n=5, bad=2):
    A = spd(np.random.default_rng(9), n)
    A[bad, bad] = -100.0
    return A


@pytest.mark.parametrize("method", ALL_METHODS)
def test_non_positive_pivot_gives_nan_and_result_code(method):
    A, b = _not_pd(), np.ones(5)
    L, x, X, x2, code = map(np.asarray, factor_and_solve(A, b, b[:, None], method))
    assert code == 2
    assert np.all(np.isfinite(L[:, :2])) and np.all(np.isnan(np.diag(L)[2:]))
    assert np.all(np.isnan(x)) and np.all(np.isnan(X)) and np.all(np.isnan(x2))
    # Singular (zero pivot) and non-finite input are failures too, never silent garbage.
    code_of = jax.jit(lambda A: linalg.failed_pivot(linalg.cholesky(A, method=method)))
    assert int(code_of(np.zeros((4, 4)))) == 0
    A_nan = spd(np.random.default_rng(1), 4)
    A_nan[1, 1] = np.nan
    assert int(code_of(A_nan)) == 1
    A_nan = spd(np.random.default_rng(1), 4)
    A_nan[3, 1] = np.nan  # reaches the diagonal at pivot 3 (through L[3, 1])
    assert int(code_of(A_nan)) == 3
    A_inf = spd(np.random.default_rng(1), 4)
    A_inf[2, 2] = np.inf
    assert int(code_of(A_inf)) == 2


def test_vmapped_batch_survives_a_bad_member():
    As = np.stack([spd(np.random.default_rng(i), 5) for i in range(3)])
    As[1] = _not_pd()
    bs = np.ones((3, 5))
    x = jax.jit(jax.vmap(linalg.solve_spd))(As, bs)
    codes = jax.jit(jax.vmap(lambda A: linalg.failed_pivot(linalg.cholesky(A))))(As)
    np.testing.assert_array_equal(codes, [-1, 2, -1])
    x = np.asarray(x)
    assert np.all(np.isnan(x[1])) and np.all(np.isfinite(x[[0, 2]]))
    np.testing.assert_allclose(x[0], np.linalg.solve(As[0], bs[0]), rtol=1e-12)


PIVOT_MSG = r"{}: matrix is not positive definite: pivot 2 is not positive and finite \(the leading 3x3 block"


@pytest.mark.parametrize("method", ["auto", "crout"])
def test_check_raises_naming_the_pivot(method):
    A, b = _not_pd(), np.ones(5)
    solve = lambda A, b: linalg.solve_spd(A, b, method=method, check=True)  # noqa: E731
    chol = lambda A: linalg.cholesky(A, method=method, check=True)  # noqa: E731
    with pytest.raises(RUNTIME_ERRORS, match=PIVOT_MSG.format("solve_spd")):
        jax.jit(solve)(A, b).block_until_ready()
    with pytest.raises(eqx.EquinoxRuntimeError, match=PIVOT_MSG.format("solve_spd")):
        eqx.filter_jit(solve)(A, b).block_until_ready()
    with pytest.raises(RUNTIME_ERRORS, match=PIVOT_MSG.format("cholesky")):
        jax.jit(chol)(A).block_until_ready()
    with pytest.raises(RUNTIME_ERRORS, match=PIVOT_MSG.format("solve_spd")):
        jax.jit(jax.vmap(solve))(np.stack([spd(np.random.default_rng(0), 5), A]), np.ones((2, 5)))
    # A positive-definite matrix passes the check unchanged (and grad still works).
    good = spd(np.random.default_rng(0), 5)
    np.testing.assert_allclose(jax.jit(solve)(good, b), np.linalg.solve(good, b), rtol=1e-12)
    jax.grad(lambda A: solve(A, b).sum())(good)


def test_trace_time_errors_name_the_problem():
    with no_jaxtyping():
        with pytest.raises(ValueError, match=r"cholesky: A must be a square matrix of shape \(n, n\), got shape \(3, 4\)"):
            linalg.cholesky(jnp.ones((3, 4)))
        with pytest.raises(ValueError, match=r"solve_spd: A must be a square matrix .* got shape \(2, 3, 3\) \(batch with jax.vmap\)"):
            linalg.solve_spd(jnp.ones((2, 3, 3)), jnp.ones(3))
        with pytest.raises(ValueError, match=r"solve_spd: b must have shape \(n,\) or \(n, k\) with n = 3, got shape \(4,\)"):
            linalg.solve_spd(jnp.eye(3), jnp.ones(4))
        with pytest.raises(ValueError, match=r"cholesky_solve: b must have shape .* got shape \(3, 1, 1\)"):
            linalg.cholesky_solve(jnp.eye(3), jnp.ones((3, 1, 1)))
        with pytest.raises(ValueError, match=r"failed_pivot: L must be a square matrix"):
            linalg.failed_pivot(jnp.ones(3))
        with pytest.raises(TypeError, match=r"cholesky: A must have a real floating dtype, got int32"):
            linalg.cholesky(jnp.eye(3, dtype=jnp.int32))
        with pytest.raises(TypeError, match=r"solve_spd: b must have a real floating dtype, got int32"):
            linalg.solve_spd(jnp.eye(3), jnp.ones(3, dtype=jnp.int32))
    with pytest.raises(ValueError, match=r"solve_spd: unknown method 'lu'; expected one of \('auto', 'crout'"):
        linalg.solve_spd(jnp.eye(3), jnp.ones(3), method="lu")
    with pytest.raises(ValueError, match=r"cholesky: method='unrolled' is limited to n <= 16 .* got n = 17\. Use method='crout'"):
        linalg.cholesky(jnp.eye(17), method="unrolled")


def test_mixed_dtypes_follow_the_promotion_rules():
    # conftest.py sets strict promotion: float32 with float64 is refused, not silently cast.
    with pytest.raises(jax.dtypes.TypePromotionError, match="no available implicit dtype promotion path"):
        linalg.solve_spd(jnp.eye(3, dtype=jnp.float32), jnp.ones(3))
    x = linalg.solve_spd(jnp.eye(3, dtype=jnp.float32), 2.0 * jnp.ones(3, dtype=jnp.float32))
    assert x.dtype == jnp.float32


NO_FLAG_SCRIPT = """
import jax, numpy as np
jax.config.update("jax_enable_x64", True)

from jaxbody import linalg
rng = np.random.default_rng(0)
for n in (8, 20):
    X = rng.standard_normal((1024, n, n))
    A = X @ X.transpose(0, 2, 1) / n + np.eye(n)
    b = rng.standard_normal((1024, n))
    x = np.asarray(jax.jit(jax.vmap(linalg.solve_spd))(A, b))
    assert np.abs(np.einsum("bij,bj->bi", A, x) - b).max() < 1e-10, n
print("ok")
"""


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_default_methods_without_the_fusion_emitter_flag():
    """conftest.py and ``import jaxbody`` set --xla_cpu_use_fusion_emitters=false; the defaults
    must work with the emitters on (a caller's own setting of the flag is kept)."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, XLA_FLAGS="--xla_cpu_use_fusion_emitters=true")
    out = subprocess.run([sys.executable, "-c", NO_FLAG_SCRIPT], env=env, capture_output=True, text=True, timeout=280)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]
