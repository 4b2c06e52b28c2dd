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
    """Add :func:`default_xla_flags` to ``XLA_FLAGS`` unless the caller's flags set that flag
    themselves (either way). XLA reads ``XLA_FLAGS`` when JAX's backend starts, so this acts
    only before the first computation: ``import jaxbody`` calls it. Its effect on first calls:
    ``benchmarks/first_call.py --xla-flags=--xla_cpu_use_fusion_emitters=true`` against the
    defaults."""
    flags = default_xla_flags()
    current = os.environ.get("XLA_FLAGS", "")
    if flags and flags.split("=")[0] not in current:
        os.environ["XLA_FLAGS"] = f"{current} {flags}".strip()


if __name__ == "__main__":
    print(default_xla_flags())
