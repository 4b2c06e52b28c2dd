"""The native kernel: forward dynamics of a tree compiled to machine code, called from XLA.

XLA's CPU backend runs a traced program as a sequence of fused loops, each writing its
outputs to memory; for multibody dynamics — thousands of scalar operations along short
chains of bodies — that is dominated by memory traffic and per-loop overhead, not by
arithmetic (docs/performance.md). The native kernel removes both: the same algorithm as
the unrolled kernel (:mod:`jaxbody.backends.unrolled`: kinematics root to leaves, composite
(augmented) inertias and subtree forces leaves to root, the tree-sparse ``LᵀDL``
factorisation), written out at build time for the model's static tree, is emitted as C++
and compiled once per tree with the system's C++ compiler. Every intermediate stays in
registers; one call evaluates a whole batch of states, split over the CPU cores.

How it plugs into JAX:

* **Code generation.** :func:`jaxbody.backends.scalar.bias_and_mass` and ``ltdl_solve`` run on
  *symbolic* scalars (:class:`~jaxbody.backends.native.symbolic.Sym`) instead of arrays; every operation appends one line
  of C++. Structural zeros and ones are folded as in the unrolled kernel and repeated
  expressions are shared. The model's parameters (offsets, axes, masses, centres of mass,
  inertias, armature, ``qpos0``) are *inputs* of the compiled function, not constants, so
  one compilation serves every parameter value, batches over parameters and gradients
  with respect to them.
* **XLA FFI.** The compiled function is registered as an XLA foreign-function target
  (:func:`jax.ffi.ffi_call`); XLA calls it inside jitted programs and solver loops.
* **Batches.** A :func:`jax.custom_batching.custom_vmap` rule turns ``vmap`` (nested or
  not) into one call over the stacked states; inputs that are not batched (the model under
  a ``vmap`` over states) are passed once and read with stride zero.
* **Derivatives.** The generated program is differentiated at build time too (on first
  use): a forward-mode pass emits the tangent of every operation along ``(dq, dv, dτ)``
  (:func:`~jaxbody.backends.native.differentiate.tangent_program`), a reverse-mode pass the adjoint of every value that depends on
  the state, last operation first (:func:`~jaxbody.backends.native.differentiate.adjoint_program`); each is compiled like the
  forward program. The reverse-mode program differentiates forward dynamics implicitly: with
  ``a₀`` the computed acceleration and ``M = LᵀDL`` its factor held constant, it reverses
  ``a₀ + M⁻¹ (τ − ID(q, v, a₀))`` (``ID``: inverse dynamics by the Newton–Euler passes), whose
  derivative is that of ``a``, so its reverse sweep goes through the Newton–Euler passes once
  and one solve with the factor, not through the composite inertias and the factorisation.
  For trees of hinges and slides without body loads, the adjoint of those passes is emitted
  in closed form (:func:`jaxbody.backends.scalar.inverse_dynamics_vjp`, about half the operations
  of their operation-by-operation reverse). A :func:`jax.custom_jvp` rule takes the value from the native call and the
  tangent along the state and force from a primitive that is linear in the tangents, runs
  the forward-mode program, and transposes to the reverse-mode one (so ``jvp``/``jacfwd``
  and ``grad``/``vjp``/``jacrev``, under ``vmap`` too, are native calls). Tangents of the
  model's parameters, gravity and body loads come from the vectorised JAX kernel
  (:mod:`jaxbody.kernels`), which computes the same function, as do the tangents of trees
  above :data:`MAX_DERIVATIVE_DOFS`; second derivatives differentiate the same linear map
  written in JAX on the unrolled kernel (:mod:`jaxbody.backends.unrolled`).

* **Whole solves.** A fixed-step RK4 solve is one program too (:func:`rk4_rollout`, mode
  ``"rk4_run"``): each block of states is loaded once and carried in registers through every
  step (each lane with its own times, step count and failure flag), with diffrax's step times,
  the quaternions renormalised after each step, requested times saved from each step's cubic
  Hermite dense output as diffrax saves them. Its reverse sweep (:func:`rk4_rollout_vjp`,
  ``"rk4_run_vjp"``) recomputes the steps between checkpoints that the forward call wrote and
  runs the reverse-mode program of each step, last first, the saved states' cotangents entering
  through the dense output: the gradient with respect to the initial state.
  :func:`jaxbody.simulate` takes both where a solve saves its end state and/or requested times.
  An adaptive solve by an embedded pair (Tsit5, Dopri5, Dopri8: :func:`adaptive_solve`, modes
  ``"adaptive:<method>"``) is one program as well: the field generated once, the stages looped
  over diffrax's tableau, diffrax's PID step-size control and dense output per lane; its reverse
  sweep (:func:`adaptive_solve_vjp`) replays the accepted steps from checkpoints and reverses them.

It needs a C++17 compiler (``g++``, or ``$CXX``) when a tree is first used; compiled
kernels are cached in ``$JAXBODY_CACHE_DIR`` (default ``~/.cache/jaxbody``) under a hash of
their source. :func:`available` says whether the kernel can be used here; with
``kernel="auto"`` jaxbody falls back to the vectorised kernel where it cannot.

The package, one job per module: :mod:`.symbolic` (the tracer), :mod:`.rk4` (the RK4 step,
springs and dampers on scalars), :mod:`.differentiate` (forward and reverse mode of the
operation list), :mod:`.codegen` (the C++ programs, from the templates shipped next to it),
:mod:`.build` (compiler, cache, FFI target), :mod:`.primitives` (the JAX rules of forward
dynamics), :mod:`.step`, :mod:`.solve` and :mod:`.energy` (one RK4 step, whole solves, energies),
:mod:`.tableaux` and :mod:`.adaptive` (the embedded pairs, whole adaptive solves).
"""

from .adaptive import Control, adaptive_checkpoint_layout, adaptive_solve, adaptive_solve_vjp
from .build import (BUILDS, MAX_MASS_ENTRIES, SPIN_NS, WIDE_BATCH, applies, available, build_for, mass_matrix_entries,
                    prefetch, threads, too_large_reason, unavailable_reason)
from .codegen import MODES
from .energy import energies
from .primitives import MAX_DERIVATIVE_DOFS, forward_dynamics
from .solve import checkpoint_layout, rk4_rollout, rk4_rollout_checkpointed, rk4_rollout_vjp
from .step import rk4_step
from .symbolic import parameter_vector

__all__ = [
    "BUILDS",
    "Control",
    "adaptive_checkpoint_layout",
    "adaptive_solve",
    "adaptive_solve_vjp",
    "MAX_DERIVATIVE_DOFS",
    "MAX_MASS_ENTRIES",
    "MODES",
    "SPIN_NS",
    "WIDE_BATCH",
    "applies",
    "prefetch",
    "available",
    "build_for",
    "checkpoint_layout",
    "energies",
    "forward_dynamics",
    "mass_matrix_entries",
    "parameter_vector",
    "rk4_rollout",
    "rk4_rollout_checkpointed",
    "rk4_rollout_vjp",
    "rk4_step",
    "threads",
    "too_large_reason",
    "unavailable_reason",
]
