"""XLA flags jaxbody sets by default, chosen by the installed jaxlib (no JAX import).

jaxlib 0.10's XLA CPU fusion emitters take minutes, and much memory, to compile the deep
straight-line programs of long chains; ``--xla_cpu_use_fusion_emitters=false`` turns them
off. jaxlib 0.11 removed the flag (XLA aborts at start-up on a flag it does not know), so
it is set only where the installed jaxlib has it.

Run as a script (``python jaxbody/_xla.py``) it prints the default flags, for shell scripts.
"""

import importlib.metadata
import os
import re

#: The flag, for jaxlib versions that know it (:func:`default_xla_flags`).
CPU_FUSION_FLAG = "--xla_cpu_use_fusion_emitters=false"


def jaxlib_version() -> tuple[int, ...]:
    """The installed jaxlib's ``(major, minor, patch)``; ``()`` if it is not installed."""
    try:
        text = importlib.metadata.version("jaxlib")
    except importlib.metadata.PackageNotFoundError:
        return ()
    return tuple(int(x) for x in re.findall(r"\d+", text)[:3])


def default_xla_flags() -> str:
    """``XLA_FLAGS`` jaxbody uses when the caller sets none: the CPU fusion flag on jaxlib 0.10."""
    version = jaxlib_version()
    return CPU_FUSION_FLAG if version and (0, 10) <= version[:2] < (0, 11) else ""


def set_default_xla_flags() -> None:
    """Set ``XLA_FLAGS`` to :func:`default_xla_flags` unless the caller set it (before JAX starts)."""
    flags = default_xla_flags()
    if flags:
        os.environ.setdefault("XLA_FLAGS", flags)


if __name__ == "__main__":
    print(default_xla_flags())
