"""jaxbody's cache directory, and JAX's persistent compilation cache in it, on by default.

A simulation's first call spends seconds compiling (XLA, and the native kernel's C++); the
second process that runs the same program should not. The native kernel keeps its libraries
in ``<cache>/native``; importing jaxbody points JAX's persistent compilation cache at
``<cache>/jax``, so a program XLA compiled once is loaded from disk by every later process.
``<cache>`` is ``$JAXBODY_CACHE_DIR``, else ``~/.cache/jaxbody`` (:func:`cache_root`).

What is left as it is:

* ``JAXBODY_JAX_CACHE=0`` (or ``off``, ``false``, ``no``) before importing jaxbody: JAX's cache
  is not touched (the native kernel's libraries are still cached: they are jaxbody's own);
* a user's own JAX cache: when ``jax_compilation_cache_dir`` is already set (by
  ``jax.config.update`` before importing jaxbody, or ``$JAX_COMPILATION_CACHE_DIR``), jaxbody
  changes none of JAX's cache settings.

Otherwise :func:`enable` sets ``jax_compilation_cache_dir``, stores compilations of at least
:data:`MIN_COMPILE_SECONDS` (JAX's default is 1 s: a first simulation is a dozen programs of
0.2-1 s each, and the checks compiled quickly at a system's construction take less), and
bounds the directory to :data:`MAX_BYTES` (least recently used entries go first; where the
``filelock`` package is installed, which JAX needs for that) unless
``$JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS`` or ``$JAX_COMPILATION_CACHE_MAX_SIZE`` say
otherwise. JAX decides whether to use its cache at
the process's first compilation: import jaxbody before compiling anything.
"""

import importlib.util
import os
from pathlib import Path

import jax

__all__ = ["ENV_SWITCH", "MAX_BYTES", "MIN_COMPILE_SECONDS", "cache_root", "enable", "enabled_dir"]

#: The environment variable that turns JAX's persistent cache off (``0``, ``off``, ``false``, ``no``).
ENV_SWITCH = "JAXBODY_JAX_CACHE"
#: Shortest compilation stored (seconds); shorter ones cost less to repeat than to read back.
#: The construction-time checks compiled quickly (:func:`jaxbody._util.compiled_when_eager`)
#: take less than 0.2 s each (``benchmarks/first_call.py --log-compiles`` lists every compile).
MIN_COMPILE_SECONDS = 0.05
#: Size bound of ``<cache>/jax`` (bytes).
MAX_BYTES = 2 * 1024**3

_enabled: Path | None = None


def cache_root() -> Path:
    """jaxbody's cache directory: ``$JAXBODY_CACHE_DIR``, else ``~/.cache/jaxbody`` (not created here)."""
    root = os.environ.get("JAXBODY_CACHE_DIR") or os.path.join(os.path.expanduser("~"), ".cache", "jaxbody")
    return Path(root)


def enabled_dir() -> Path | None:
    """The directory :func:`enable` pointed JAX's cache at in this process (``None``: it did not)."""
    return _enabled


def enable() -> Path | None:
    """Turn JAX's persistent compilation cache on in ``<cache>/jax`` unless switched off or
    configured by the user (see the module docstring); returns the directory, or ``None``.

    Called once when jaxbody is imported; calling it again does nothing new."""
    global _enabled
    if _enabled is not None:
        return _enabled
    if os.environ.get(ENV_SWITCH, "1").strip().lower() in ("0", "off", "false", "no"):
        return None
    # a user's own cache (set in the configuration or the environment) is theirs to tune
    if jax.config.jax_compilation_cache_dir is not None or os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return None
    path = cache_root() / "jax"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:  # a read-only home: compile every time rather than fail on import
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    # JAX evicts entries only with the filelock package (it refuses a bound without it)
    if "JAX_COMPILATION_CACHE_MAX_SIZE" not in os.environ and importlib.util.find_spec("filelock") is not None:
        jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    _enabled = path
    return path
