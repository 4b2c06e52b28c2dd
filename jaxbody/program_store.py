"""Traced programs stored on disk: a later process runs a solve without tracing it again.

JAX's persistent compilation cache (:mod:`jaxbody.compilation_cache`) spares a second process
XLA's compilation, not the Python work before it: tracing a solve through diffrax and
lowering it to XLA's language took 0.7 s of a warm iiwa arm's 1.05 s first ``simulate``, and
1.4 s of a four-bar's 2.0 s. :func:`call` runs a function of a solve's arguments as a program
exported with :mod:`jax.export` and stored in ``<cache>/programs``, keyed by a fingerprint of
everything the traced program is a function of except the values of its input arrays
(:mod:`jaxbody.program_fingerprint`: the input arrays' shapes and dtypes, every other argument
by value, the functions among them by their code and what it reads, jaxbody's source, the
packages' versions, JAX's settings and jaxbody's environment variables).

An argument that cannot be fingerprinted (an object of a class that is neither a dataclass nor
a module) makes :func:`call` trace as before: a program is reused only when the fingerprint
proves it is the one tracing would give. So do arguments that are traced (inside the user's
``jit``, ``vmap`` or ``grad``, where the user's program holds the solve) and programs that
cannot be exported (a host callback: a progress meter).

:func:`call` takes the derivative of a stored program in reverse mode (a stored reverse
program, run when the cotangents arrive) or, where the caller offers a forward-mode
differentiable variant of the function and at most :data:`FORWARD_MAX_INPUTS` input scalars are
differentiated, in forward mode: one stored program computes the outputs and their Jacobians
with respect to those scalars, and the reverse pass contracts the cotangents with them. A
forward-mode program is smaller than a reverse one (no second sweep, no checkpoints): a first
gradient of the rolling disk's simulation took 7.8 s instead of 21.6 s, of a 7-DoF arm's with
respect to up to four gains 5.3-6.7 s instead of 9.0-9.8 s (``benchmarks/forward_derivative.py``).

:func:`call_then` runs two functions, the second on the outputs of the first, and prepares the
second's program (found, or traced and stored, then compiled) in a background thread while the
first's compiles and runs.

The store is bounded (:data:`MAX_BYTES`; the least recently used programs go first).
``JAXBODY_PROGRAM_STORE=0`` (or ``off``, ``false``, ``no``) turns it off.
"""

import atexit
import dataclasses
import json
import os
import pickle
import threading
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero
from jax.flatten_util import ravel_pytree

from .compilation_cache import cache_root
from .ffi_targets import needed, register, targets
from .program_fingerprint import TRUSTED, Undescribable, describe, input_aval, is_input, jax_settings
from .program_fingerprint import fingerprint as _fingerprint
from .program_outputs import arrays_in, rebuild, skeleton
from .stored_executables import SUFFIX as EXECUTABLE_SUFFIX
from .stored_executables import executable_path, load_executable, store_executable
from .tiered_compilation import ENV_SWITCH as TIERED_SWITCH
from .tiered_compilation import MARK_SUFFIX, compile_once, compile_tiered

__all__ = ["ENV_SWITCH", "FORWARD_MAX_INPUTS", "MAX_BYTES", "TRUSTED", "Undescribable", "call", "call_then", "counts",
           "describe", "enabled", "fingerprint", "forget", "store_dir", "wait"]

#: The environment variable that turns the store off (``0``, ``off``, ``false``, ``no``).
ENV_SWITCH = "JAXBODY_PROGRAM_STORE"

#: The most differentiated input scalars for which :func:`call` takes a derivative in forward
#: mode (where the caller offers a forward-mode variant): forward mode pushes one tangent per
#: scalar through every step, reverse mode one sweep back whatever their number, so past a few
#: scalars the reverse sweep is cheaper to run. Measured on later runs of a 7-DoF arm's
#: gradient: forward mode 0.62-0.78x reverse's time for 1-4 scalars, 1.23x for 8 and 1.87x for
#: 14; the rolling disk's 5 (its initial velocities), 0.85x (``benchmarks/forward_derivative.py``).
FORWARD_MAX_INPUTS = 5

#: Size bound of the store (bytes): past it, the least recently used programs are removed.
MAX_BYTES = 512 * 1024**2

# bump when the stored format changes
_FORMAT = 3


def enabled() -> bool:
    """Whether :func:`call` may store and reuse programs (``$JAXBODY_PROGRAM_STORE``)."""
    return os.environ.get(ENV_SWITCH, "1").strip().lower() not in ("0", "off", "false", "no")


def fingerprint(name: str, args, differentiated: tuple = ()) -> str:
    """The key a program ``name`` of ``args`` (or, where ``differentiated`` marks input arrays,
    its derivative) is stored under: :func:`jaxbody.program_fingerprint.fingerprint` with the
    store's format, its switch left out. Raises :class:`Undescribable` where the arguments
    cannot be fingerprinted."""
    # the switches of the store and of tiered compilation change how a program is kept and
    # compiled, not what it is
    return _fingerprint(name, args, differentiated, context=(_FORMAT,), unkeyed=(ENV_SWITCH, TIERED_SWITCH))


def store_dir() -> Path:
    """Where programs are stored: ``<cache>/programs`` (:func:`jaxbody.compilation_cache.cache_root`)."""
    return cache_root() / "programs"


# ---------------------------------------------------------------------------------------------
# storing and running


@dataclasses.dataclass(frozen=True)
class _Entry:
    exported: object  # jax.export.Exported
    outputs: object  # the outputs' skeleton
    notes: tuple  # the registrations the program needs (ffi_targets.needed)
    path: Path | None = None  # the file it is stored in (beside it: tiered_compilation's marker)


_entries: dict = {}  # in this process: (function, static structure, input shapes) -> _Entry or None
# how each call was served in this process (counts)
_counts = {"loaded": 0, "stored": 0, "declined": 0, "traced": 0, "ahead": 0, "optimised": 0, "forward": 0,
           "executable": 0}
_compiled: dict = {}  # id of an _Entry -> (the entry, its executable: _executable)
_calls: dict = {}  # id of an _Entry -> (the entry, its jitted call: _jitted)
_lock = threading.Lock()  # the two dicts above, written by call_then's background thread too


def _count(kind: str) -> None:
    with _lock:
        _counts[kind] += 1


def counts() -> dict:
    """How this process's programs were found, by entry (the first call of each program
    structure; later calls reuse it in memory): ``loaded`` from the store, ``stored`` (traced
    and written), ``declined`` (traced: arguments that cannot be fingerprinted, or a program
    that cannot be stored), and ``traced`` calls in all that did not run a stored program
    (switched off, or traced arguments); ``ahead``: programs compiled in a background thread
    while another ran (:func:`call_then`); ``optimised``: programs whose optimised compile,
    made in the background, replaced a quick first one (:mod:`jaxbody.tiered_compilation`);
    ``forward``: derivatives taken in forward mode (see the module docstring); ``executable``:
    programs whose optimised executable was loaded as an earlier process kept it
    (:mod:`jaxbody.stored_executables`)."""
    with _lock:
        return dict(_counts)


def forget() -> None:
    """Forget the programs held in this process's memory (the store on disk stays): the next
    call of each reads the store again."""
    with _lock:
        _entries.clear()
        _compiled.clear()
        _calls.clear()
        _mask_files.clear()
        _remembered.clear()


def _export(fn, args, leaves, treedef):
    """Trace ``fn(*args)`` once, as a program of the input arrays ``leaves``."""
    structures = []

    def flat(*arrays):
        out = fn(*eqx.combine(jax.tree.unflatten(treedef, arrays), static_part))
        outputs: list = []
        structures.append(skeleton(out, outputs))
        return outputs

    static_part = eqx.partition(args, is_input)[1]
    specs = _specs(leaves)
    program = jax.jit(flat)
    # traced first: the FFI targets it registers are then known to the export's custom-call
    # check (which reuses this trace); which of them it calls is read from its text
    program.trace(*specs)
    exported = _exported(program, specs)
    return _Entry(exported, structures[-1], _needed(exported))


def _exported(program, specs):
    # jaxbody's own custom calls are allowed (export refuses unknown ones)
    checks = [jax.export.DisabledSafetyCheck.custom_call(target) for target in targets()]
    return jax.export.export(program, disabled_checks=checks)(*specs)


def _needed(exported) -> tuple:
    """The registrations of FFI targets and native programs ``exported`` calls."""
    try:
        return needed(exported.mlir_module())
    except KeyError as err:
        raise Undescribable(str(err)) from None


def _specs(leaves) -> list:
    return [jax.ShapeDtypeStruct(shape, dtype, weak_type=weak) for shape, dtype, weak in map(input_aval, leaves)]


def _reverse_function(fn, static_part, treedef, n_out, in_mask, out_mask):
    """The reverse derivative of ``fn`` as a function of its input arrays and the cotangents
    of the outputs ``out_mask`` marks (of ``n_out``), returning the cotangents of the inputs
    ``in_mask`` marks: ``jax.vjp`` of ``fn``, whose forward pass it runs again (the forward pass
    the caller sees is the primal program), restricted to the outputs that carry a cotangent
    (the rest of the forward pass is dead code to XLA: a loss of the final state alone does not
    differentiate the energies and reactions of the saved states)."""
    n_in = len(in_mask)

    def reverse(*arrays_and_cotangents):
        arrays, cotangents = arrays_and_cotangents[:n_in], arrays_and_cotangents[n_in:]

        def marked(*diff):
            it = iter(diff)
            full = [next(it) if m else a for a, m in zip(arrays, in_mask)]
            out: list = []
            skeleton(fn(*eqx.combine(jax.tree.unflatten(treedef, full), static_part)), out)
            assert len(out) == n_out
            return [o for o, keep in zip(out, out_mask) if keep]

        _, pullback = jax.vjp(marked, *(a for a, m in zip(arrays, in_mask) if m))
        return list(pullback(list(cotangents)))

    return reverse


def _reverse_specs(leaves, outputs, out_mask) -> list:
    """The inputs of a reverse program: the primal's input arrays and the cotangents of the
    outputs ``out_mask`` marks (of avals ``outputs``)."""
    return _specs(leaves) + [jax.ShapeDtypeStruct(a.shape, a.dtype) for a, keep in zip(outputs, out_mask) if keep]


def _export_derivative(fn, args, leaves, treedef, primal: _Entry, mask) -> _Entry:
    """The program of :func:`_reverse_function` (``mask``: the input and output masks)."""
    in_mask, out_mask = mask
    outputs = primal.exported.out_avals
    reverse = _reverse_function(fn, eqx.partition(args, is_input)[1], treedef, len(outputs), in_mask, out_mask)
    specs = _reverse_specs(leaves, outputs, out_mask)
    exported = _exported(jax.jit(reverse), specs)
    return _Entry(exported, None, _needed(exported))


def _differentiated(fn, args, name, primal: _Entry, leaves, treedef, static_part, in_mask):
    """The primal program's outputs as a function JAX differentiates in reverse mode through a
    stored reverse program (``jax.custom_vjp``), found or made when the cotangents arrive: one
    per set of outputs that carry one. The unmarked inputs are constants."""
    outputs = primal.exported.out_avals
    inexact = [np.issubdtype(a.dtype, np.inexact) for a in outputs]
    constants = [None if m else x for x, m in zip(leaves, in_mask)]

    def full(diff):
        it = iter(diff)
        return [next(it) if m else c for c, m in zip(constants, in_mask)]

    # the reverse programs an earlier process used after this forward pass, loaded and compiled
    # in background threads while the forward pass and the rest of the loss run
    ahead = _reverse_ahead(fn, args, name, primal, leaves, treedef, static_part, in_mask)

    @jax.custom_vjp
    def run(diff):
        return tuple(primal.exported.call(*full(diff)))

    def run_fwd(diff):
        values = tuple(d.value for d in diff)
        return tuple(_run_entry(primal, full(values), _specs(leaves))), values

    def run_bwd(values, cotangents):
        out_mask = tuple(f and not isinstance(c, SymbolicZero) for c, f in zip(cotangents, inexact))
        if not any(out_mask):
            return (tuple(jnp.zeros_like(v) for v in values),)
        kept = [c for c, keep in zip(cotangents, out_mask) if keep]
        mask = (in_mask, out_mask)
        for thread in ahead.values():  # this mask's entry, being read by its thread: waited for, not read twice
            thread.join()
        entry = _entry(fn, args, name, leaves, treedef, static_part, mask, primal)
        if entry is None or not _registered(entry):  # not stored: the same derivative, traced
            _count("traced")
            reverse = _reverse_function(fn, static_part, treedef, len(outputs), in_mask, out_mask)
            return (tuple(jax.jit(reverse)(*full(values), *kept)),)
        _remember_mask(name, args, primal, in_mask, out_mask)
        return (tuple(_run_entry(entry, [*full(values), *kept], _reverse_specs(leaves, outputs, out_mask))),)

    # symbolic zeros: the outputs no cotangent reaches are known to the reverse pass
    run.defvjp(run_fwd, run_bwd, symbolic_zeros=True)
    return run(tuple(x for x, m in zip(leaves, in_mask) if m))


def _forward_function(fn, static_part, treedef, in_mask, structures: list):
    """``fn`` as a function of its input arrays returning its outputs followed by the Jacobian
    of each inexact output with respect to the inputs ``in_mask`` marks, raveled into one vector
    of ``k`` scalars (shape ``output.shape + (k,)``): ``jax.jacfwd``, one tangent per scalar
    pushed through the whole program beside its values. The outputs' skeleton
    (:func:`jaxbody.program_outputs.skeleton`) is appended to ``structures``."""

    def forward(*arrays):
        diff = [a for a, m in zip(arrays, in_mask) if m]
        flat, unravel = ravel_pytree(diff)

        def outputs(x):
            it = iter(unravel(x))
            full = [next(it) if m else a for a, m in zip(arrays, in_mask)]
            out: list = []
            structures.append(skeleton(fn(*eqx.combine(jax.tree.unflatten(treedef, full), static_part)), out))
            # integer outputs (counts, result codes) have no derivative: carried beside
            return [o for o in out if jnp.issubdtype(o.dtype, jnp.inexact)], out

        jacobians, out = jax.jacfwd(outputs, has_aux=True)(flat)
        return list(out) + list(jacobians)

    return forward


def _export_forward(fn, args, leaves, treedef, in_mask) -> _Entry:
    """The program of :func:`_forward_function`; its entry's skeleton is the outputs'."""
    structures: list = []
    forward = _forward_function(fn, eqx.partition(args, is_input)[1], treedef, in_mask, structures)
    program = jax.jit(forward)
    specs = _specs(leaves)
    program.trace(*specs)  # registers the FFI targets it calls before the export checks them
    exported = _exported(program, specs)
    return _Entry(exported, structures[-1], _needed(exported))


def _forward_parts(leaves, in_mask, forward_args) -> tuple | None:
    """``(treedef, static part)`` of the forward-mode variant ``forward_args`` of a call whose
    input arrays are ``leaves`` (``in_mask``: the differentiated ones), where its derivative is
    taken in forward mode: at most :data:`FORWARD_MAX_INPUTS` scalars differentiated, and the
    variant's input arrays the call's own, in the same order; else ``None``."""
    if forward_args is None or not any(in_mask):
        return None
    if sum(int(np.size(x)) for x, m in zip(leaves, in_mask) if m) > FORWARD_MAX_INPUTS:
        return None
    dynamic, static_part = eqx.partition(forward_args, is_input)
    forward_leaves, treedef = jax.tree.flatten(dynamic)
    if len(forward_leaves) != len(leaves) or any(a is not b for a, b in zip(forward_leaves, leaves)):
        return None
    return treedef, static_part


def _forward_differentiated(fn, forward_args, name, leaves, parts, in_mask):
    """The outputs of ``fn(*forward_args)`` (flat, and their skeleton) as a function JAX
    differentiates in reverse mode through a stored forward-mode program (see
    :func:`_forward_function`): its forward pass computes the outputs' Jacobians with respect
    to the marked inputs, its reverse pass contracts the cotangents with them. ``None`` where
    that program cannot be stored (the reverse program serves instead). ``parts``: from
    :func:`_forward_parts`."""
    treedef, static_part = parts
    specs = _specs(leaves)
    entry = _entry(fn, forward_args, name, leaves, treedef, static_part, ("forward", in_mask))
    if entry is None:
        return None
    _count("forward")
    if _registered(entry):
        def program(inputs):
            return _run_entry(entry, inputs, specs)
    else:  # a native library it calls is not built: the same program traced, which builds it
        _count("traced")
        traced = jax.jit(_forward_function(fn, static_part, treedef, in_mask, []))

        def program(inputs):
            return traced(*inputs)
    n_out = arrays_in(entry.outputs)
    outputs = entry.exported.out_avals[:n_out]
    inexact = [np.issubdtype(a.dtype, np.inexact) for a in outputs]
    constants = [None if m else x for x, m in zip(leaves, in_mask)]

    def full(diff):
        it = iter(diff)
        return [next(it) if m else c for c, m in zip(constants, in_mask)]

    @jax.custom_vjp
    def run(diff):
        return tuple(program(full(diff))[:n_out])

    def run_fwd(diff):
        values = tuple(d.value for d in diff)
        results = program(full(values))
        return tuple(results[:n_out]), (values, tuple(results[n_out:]))

    def run_bwd(residuals, cotangents):
        values, jacobians = residuals
        flat, unravel = ravel_pytree(list(values))
        gradient = jnp.zeros_like(flat)
        for cotangent, jacobian in zip((c for c, f in zip(cotangents, inexact) if f), jacobians):
            if not isinstance(cotangent, SymbolicZero):
                gradient = gradient + jnp.tensordot(cotangent, jacobian, axes=cotangent.ndim)
        return (tuple(unravel(gradient)),)

    run.defvjp(run_fwd, run_bwd, symbolic_zeros=True)
    return run(tuple(x for x, m in zip(leaves, in_mask) if m)), entry.outputs


_mask_files: dict = {}  # (id of a primal _Entry, input mask) -> its masks file (_masks_path)
_remembered: set = set()  # (id of a primal _Entry, input mask, output mask) written in this process


def _masks_path(name, args, primal, in_mask) -> Path | None:
    """The file listing the output masks of the reverse programs used after the forward pass of
    ``name`` on ``args`` differentiated with respect to ``in_mask`` (``None``: not describable);
    fingerprinted once per primal program and mask in a process."""
    key = (id(primal), in_mask)
    with _lock:
        if key in _mask_files:
            return _mask_files[key]
    try:
        path = store_dir() / f"{name}-masks-{fingerprint(name, args, ('reverse masks', in_mask))}.json"
    except Undescribable:
        path = None
    with _lock:
        _mask_files[key] = path
    return path


def _remember_mask(name, args, primal, in_mask, out_mask) -> None:
    key = (id(primal), in_mask, out_mask)
    with _lock:
        if key in _remembered:
            return
        _remembered.add(key)
    path = _masks_path(name, args, primal, in_mask)
    if path is None:
        return
    masks = _known_masks(path)
    if list(out_mask) in masks:
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")
        tmp.write_text(json.dumps(masks + [list(out_mask)]))
        os.replace(tmp, path)  # atomic: a reader sees the old list or the new one
    except OSError:
        pass


def _known_masks(path: Path) -> list:
    try:
        masks = json.loads(path.read_text())
    except (OSError, ValueError):
        return []
    return [m for m in masks if isinstance(m, list)] if isinstance(masks, list) else []


def _reverse_ahead(fn, args, name, primal, leaves, treedef, static_part, in_mask) -> dict:
    """Threads, by output mask, that read and compile the stored reverse programs an earlier
    process used after this forward pass (:func:`_remember_mask`): in a warm process loading a
    reverse program's executable is most of a gradient (about 0.9 s for a 1 MB program), and
    the forward pass and the rest of the loss then run meanwhile. A program not stored is left
    to the reverse pass, which makes it."""
    path = _masks_path(name, args, primal, in_mask)
    if path is None:
        return {}
    outputs = primal.exported.out_avals
    threads = {}
    settings = jax_settings()
    for out_mask in map(tuple, _known_masks(path)):
        if len(out_mask) != len(outputs):
            continue
        specs = _reverse_specs(leaves, outputs, out_mask)

        def work(out_mask=out_mask, specs=specs):
            try:
                if jax_settings() != settings:
                    return
                entry = _entry(fn, args, name, leaves, treedef, static_part, (in_mask, out_mask), primal, make=False)
                if entry is not None:
                    _compile_ahead(entry, specs)
            except Exception:  # noqa: BLE001 (the reverse pass does the same work and reports)
                pass

        threads[out_mask] = _start(work, "jaxbody-reverse-ahead")
    return threads


def _compile_ahead(entry: "_Entry", specs) -> None:
    """Compile ``entry``'s program for inputs ``specs`` in this (background) thread."""
    if _registered(entry) and _executable(entry, specs)[1]:
        _count("ahead")


def _registered(entry: "_Entry") -> bool:
    """Register what ``entry``'s program calls (FFI targets, native programs) in this process;
    ``False`` where a native library it calls is not built (removed from the cache, or an
    optimised build an earlier process did not finish): the program is then traced again, which
    builds it."""
    try:
        register(entry.notes)
    except OSError:
        return False
    return True


def _jitted(entry: "_Entry"):
    """The jitted call of ``entry``'s program (one per entry in a process)."""
    with _lock:
        if id(entry) not in _calls:
            _calls[id(entry)] = (entry, jax.jit(entry.exported.call))
        return _calls[id(entry)][1]


def _executable(entry: "_Entry", specs, once: bool = False) -> tuple:
    """``(executable, compiled now)``: ``entry``'s program compiled for the inputs ``specs``
    (once per entry in a process). Compiled from the shapes alone, in the thread that prepares
    it ahead and in the call that needs it alike: the same XLA program whichever did, so that
    JAX's persistent cache finds in a later process what an earlier one compiled (a call on
    the arrays themselves would key the program by where each array is placed, too). A program
    not yet compiled optimised on this machine is compiled quickly first, and its optimised
    executable replaces the quick one when a background thread has compiled it
    (:func:`jaxbody.tiered_compilation.compile_tiered`). The optimised executable is kept
    beside the stored program and a later process loads it as it is
    (:mod:`jaxbody.stored_executables`). ``once``: a program that runs about once per system
    (:func:`call`), compiled quickly and kept so (:func:`jaxbody.tiered_compilation.compile_once`)."""
    with _lock:
        if id(entry) in _compiled:
            return _compiled[id(entry)][1], False

    # the executable an earlier process kept: no lowering, no compile. Not for programs that
    # call jaxbody's native code: deserialised, those crashed when run (JAX's cache loads them)
    kept = None if entry.notes else executable_path(entry.path, "quick" if once else "")

    def keep(executable):
        if store_executable(kept, executable):
            _bound(kept.parent)

    compiled = load_executable(kept)
    if compiled is not None:
        _count("executable")
    elif once:
        compiled = compile_once(_jitted(entry).lower(*specs), keep)
    else:
        def install(optimised):  # the optimised program, compiled in the background, runs from now on
            with _lock:
                _compiled[id(entry)] = (entry, optimised)
            _count("optimised")

        compiled = compile_tiered(_jitted(entry).lower(*specs), entry.path, install, _start, keep)
    with _lock:
        if id(entry) in _compiled:  # another thread compiled it meanwhile
            return _compiled[id(entry)][1], False
        _compiled[id(entry)] = (entry, compiled)
    return compiled, True


def _run_entry(entry: "_Entry", inputs: list, specs, once: bool = False):
    """``entry``'s program on concrete ``inputs`` of shapes ``specs``, by its executable
    (:func:`_executable`, ``once`` as there); inputs typed unlike the shapes it was compiled for
    go through its jitted call instead."""
    executable = _executable(entry, specs, once)[0]
    try:
        return executable(*inputs)
    except (TypeError, ValueError):
        return _jitted(entry)(*inputs)


def _read(path: Path):
    try:
        data = pickle.loads(path.read_bytes())
    except FileNotFoundError:
        return None
    except Exception:  # noqa: BLE001  (a damaged or foreign file: traced and stored anew)
        return None
    if not isinstance(data, dict) or data.get("format") != _FORMAT:
        return None
    try:
        os.utime(path)  # used now: the last to be removed when the store is full
    except OSError:
        pass
    if data.get("exported") is None:
        return False  # a program that cannot be stored: trace it
    try:
        exported = jax.export.deserialize(bytearray(data["exported"]))
    except Exception:  # noqa: BLE001
        return None
    return _Entry(exported, data["outputs"], tuple(data["notes"]), path)


def _write(path: Path, entry: "_Entry | None", reason: str = "") -> None:
    try:
        if entry is None:
            data = {"format": _FORMAT, "exported": None, "reason": reason}
        else:
            data = {"format": _FORMAT, "exported": bytes(entry.exported.serialize()), "outputs": entry.outputs,
                    "notes": list(entry.notes)}
    except ImportError:  # jax.export's serialiser needs the flatbuffers package: kept in memory only
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # written whole, then renamed: a reader never sees half a file
        tmp = path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")
        tmp.write_bytes(pickle.dumps(data))
        os.replace(tmp, path)
    except OSError:  # a read-only cache: the program is traced again next time
        return
    _bound(path.parent)


def _bound(directory: Path) -> None:
    """Remove the least recently used programs of ``directory`` until it holds at most
    :data:`MAX_BYTES` (another process may remove the same ones: errors are ignored)."""
    try:
        entries = []
        for entry in os.scandir(directory):
            # programs and their machines' executables, each removed on its own (an executable
            # stays valid for its program, which is traced and stored again under the same name)
            if entry.name.endswith((".pickle", EXECUTABLE_SUFFIX)):
                stat = entry.stat()
                entries.append((stat.st_mtime, stat.st_size, entry.path))
    except OSError:
        return
    total = sum(size for _, size, _ in entries)
    for _, size, path in sorted(entries):
        if total <= MAX_BYTES:
            break
        for gone in (path, path + MARK_SUFFIX):  # the program, and its tiered compilation's mark
            try:
                os.remove(gone)
            except OSError:
                pass
        total -= size


def _local_key(name, leaves, treedef, static_part):
    """What ``jax.jit`` would key its own cache by in this process: the static structure and the
    input shapes (``None``: a static part that cannot be hashed)."""
    static_leaves, static_def = jax.tree.flatten(static_part)
    key = (name, treedef, static_def, tuple(static_leaves), tuple(input_aval(x) for x in leaves))
    try:
        hash(key)
    except TypeError:
        return None
    return key


def call(fn, args: tuple, name: str, forward_args: tuple | None = None, once: bool = False):
    """``fn(*args)``, as the program stored for it where there is one (see the module
    docstring), else traced, stored and run; as ``fn(*args)`` itself where the arguments are
    traced, cannot be fingerprinted, or the program cannot be exported. ``fn`` must be a pure
    function of ``args`` whose outputs are arrays in tuples, lists, dicts and dataclasses;
    ``name`` tells its programs apart from other functions'. ``forward_args``: arguments with
    the same input arrays under which ``fn`` computes the same outputs and can be differentiated
    in forward mode (``None``: derivatives in reverse mode only). ``once``: a program that runs
    about once per system (a check of its inputs), compiled quickly and never optimised."""
    if not enabled():
        return _traced(fn, args)
    dynamic, static_part = eqx.partition(args, is_input)
    leaves, treedef = jax.tree.flatten(dynamic)
    mask = tuple(isinstance(x, jax.core.Tracer) for x in leaves)
    # traced: only under reverse-mode differentiation of an eager call (jax.grad of a function
    # of concrete values), where the derivative program is stored too; any other trace (the
    # user's jit or vmap, forward mode) holds the solve in its own program
    if any(mask) and not all(_reverse_of_concrete(x) for x, m in zip(leaves, mask) if m):
        return _traced(fn, args)
    if not _single_device(leaves):
        return _traced(fn, args)
    parts = _forward_parts(leaves, mask, forward_args)
    if parts is not None:
        found = _forward_differentiated(fn, forward_args, name, leaves, parts, mask)
        if found is not None:
            outputs, structure = found
            return rebuild(structure, iter(outputs))
    primal = _entry(fn, args, name, leaves, treedef, static_part, ())
    if primal is None or not _registered(primal):
        return _traced(fn, args)
    if not any(mask):
        outputs = _run_entry(primal, list(leaves), _specs(leaves), once)
    else:
        outputs = _differentiated(fn, args, name, primal, leaves, treedef, static_part, mask)
    return rebuild(primal.outputs, iter(outputs))


def call_then(first, first_args: tuple, first_name: str, second, second_args, second_name: str,
              first_forward_args: tuple | None = None):
    """``(a, b)`` with ``a = first(*first_args)`` and ``b = second(*second_args(a))``, each run as
    :func:`call` runs it. Where ``first`` runs as a stored program on concrete inputs, the
    program of ``second`` is looked up (or traced and stored) and compiled in a background
    thread as soon as the shapes of ``a`` are known, that is while ``first``'s program compiles
    and runs: with an empty cache XLA then compiles the two side by side, one core each, and
    with a warm one loads them side by side. ``second_args`` must build its arguments from
    ``a`` alone (it is called with shapes first, then with the values). ``first_forward_args``:
    ``first``'s forward-mode variant (:func:`call`'s ``forward_args``)."""
    if not enabled():
        a = _traced(first, first_args)
        return a, _traced(second, second_args(a))
    ahead = None
    dynamic, static_part = eqx.partition(first_args, is_input)
    leaves, treedef = jax.tree.flatten(dynamic)
    # on concrete inputs, or under reverse-mode differentiation of concrete ones (as call runs)
    if all(_reverse_of_concrete(x) for x in leaves if isinstance(x, jax.core.Tracer)) and _single_device(leaves):
        in_mask = tuple(isinstance(x, jax.core.Tracer) for x in leaves)
        parts = _forward_parts(leaves, in_mask, first_forward_args)
        if parts is not None:
            # the forward-mode program's outputs are the primal's: it gives their shapes
            entry = _entry(first, first_forward_args, first_name, leaves, *parts, ("forward", in_mask))
        else:
            entry = _entry(first, first_args, first_name, leaves, treedef, static_part, ())
        if entry is not None:
            shapes = iter([jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type)
                           for a in entry.exported.out_avals])
            ahead = _ahead(second, second_args(rebuild(entry.outputs, shapes)), second_name)
    a = call(first, first_args, first_name, first_forward_args)
    if ahead is not None:
        ahead.join()  # its failures are left to the call below, which makes the program itself
    return a, call(second, second_args(a), second_name)


def _ahead(fn, args, name) -> threading.Thread | None:
    """Start a thread that finds or makes the program of ``fn(*args)`` (``args``: its input
    arrays as shapes) and compiles it for :func:`call` (see :func:`call_then`)."""
    settings = jax_settings()

    def work():
        try:
            # JAX's settings in a context manager are the caller's thread's own: a thread that
            # sees others would trace another program, so it leaves the work to the call
            if jax_settings() != settings:
                return
            dynamic, static_part = eqx.partition(args, is_input)
            leaves, treedef = jax.tree.flatten(dynamic)
            entry = _entry(fn, args, name, leaves, treedef, static_part, ())
            if entry is not None:
                _compile_ahead(entry, _specs(leaves))
        except Exception:  # noqa: BLE001 (the call that follows does the same work and reports)
            pass

    return _start(work, "jaxbody-program-ahead")


_threads: list = []  # the background threads started (joined at exit: see _start)


def _start(work, name: str) -> threading.Thread:
    """Start ``work`` in a background thread. The interpreter waits for it at exit: tearing
    Python down under an XLA compile still running on another thread can crash the process."""
    thread = threading.Thread(target=work, name=name, daemon=True)
    with _lock:
        _threads[:] = [t for t in _threads if t.is_alive()]
        _threads.append(thread)
    thread.start()
    return thread


@atexit.register
def wait() -> None:
    """Wait for this process's background work: programs prepared ahead (:func:`call_then`),
    reverse programs compiled ahead, optimised compiles replacing quick ones
    (:mod:`jaxbody.tiered_compilation`). The interpreter waits for it at exit: the optimised
    programs are what makes the next process's first calls fast."""
    while True:
        with _lock:
            running = [t for t in _threads if t.is_alive()]
        if not running:
            return
        for thread in running:  # a thread may start another (a quick compile ahead starts its optimised one)
            thread.join()


def _single_device(leaves) -> bool:
    # arrays placed on one device as JAX's default: a program is stored without placements
    return not any(isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer) and len(x.sharding.device_set) != 1
                   for x in leaves)


def _traced(fn, args):
    _count("traced")
    return fn(*args)


def _reverse_of_concrete(x) -> bool:
    """Whether ``x`` is traced by reverse-mode differentiation (``jax.grad``, ``jax.vjp``) of a
    concrete value, and nothing else."""
    primal = getattr(x, "primal", None)
    return (type(x).__name__ == "LinearizeTracer" and primal is not None and not isinstance(primal, jax.core.Tracer)
            and np.issubdtype(jax.typeof(x).dtype, np.inexact))


def _entry(fn, args, name, leaves, treedef, static_part, mask, primal=None, make=True):
    """The program of ``fn(*args)`` (``mask`` empty) or its derivative with respect to the
    marked inputs (``primal``: the program's own entry), from this process's memory, the store,
    or traced and stored; ``None`` where it is traced as before."""
    local = _local_key(name, leaves, treedef, static_part)
    if local is not None:
        local = (local, mask)
        with _lock:
            if local in _entries:
                return _entries[local]
    entry = _lookup(fn, args, name, leaves, treedef, mask, primal, make)
    # a program only looked for (make=False) and not found is still to be made by the next call
    if local is not None and (entry is not None or make):
        with _lock:
            _entries[local] = entry
    return entry


def _kind(mask) -> str:
    """The kind of program a mask names: ``()`` the primal, ``("forward", inputs)`` its
    forward-mode derivative (:func:`_forward_function`), ``(inputs, outputs)`` a reverse one."""
    if not mask:
        return "primal"
    return "forward" if mask[0] == "forward" else "reverse"


def _lookup(fn, args, name, leaves, treedef, mask, primal, make=True):
    """The entry of ``fn(*args)`` or its derivative (:func:`_entry`): read from the store, or
    (``make``) exported and written there; ``None`` where the program is traced instead (or,
    without ``make``, not stored)."""
    try:
        key = fingerprint(name, args, mask)
    except Undescribable:
        _count("declined")
        return None
    kind = _kind(mask)
    path = store_dir() / f"{name}{'' if kind == 'primal' else '-' + kind}-{key}.pickle"
    entry = _read(path)
    if entry is False:
        _count("declined")
        return None
    if entry is not None:
        _count("loaded")
        return entry
    if not make:
        return None
    try:
        if kind == "primal":
            entry = _export(fn, args, leaves, treedef)
        elif kind == "forward":
            entry = _export_forward(fn, args, leaves, treedef, mask[1])
        else:
            entry = _export_derivative(fn, args, leaves, treedef, primal, mask)
    except Exception as err:  # noqa: BLE001  (an output the store cannot rebuild, a host
        # callback: traced as before; a genuine error in the user's code is raised again there)
        _write(path, None, f"{type(err).__name__}: {err}")
        _count("declined")
        return None
    entry = dataclasses.replace(entry, path=path)
    _write(path, entry)
    _count("stored")
    return entry
