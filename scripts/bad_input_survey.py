"""Classify how jaxbody answers each malformed input of the bad-input table.

Runs every case of ``tests/_support/bad_inputs.py`` (the table ``tests/test_bad_inputs.py``
pins) and prints one line per case and the counts: ``clear`` (an error whose first line names
the input), ``misleading`` (an error that does not, or names it only further down), ``silent``
(no error) and ``crash`` (an error from deep inside JAX, NumPy or equinox).

    PYTHONPATH=$PWD python scripts/bad_input_survey.py [--quiet]
"""

import collections
import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "tests"))

from _support.bad_inputs import all_cases, classify  # noqa: E402


def main(argv):
    quiet = "--quiet" in argv
    counts = collections.Counter()
    start = time.perf_counter()
    cases = all_cases()
    for case in cases:
        verdict, text = classify(case)
        counts[verdict] += 1
        if not quiet or verdict != "clear":
            print(f"{verdict:10s} {case.id}: {text[:160]}")
    print(f"\n{len(cases)} cases in {time.perf_counter() - start:.0f} s: "
          + ", ".join(f"{counts[k]} {k}" for k in ("clear", "misleading", "silent", "crash")))


if __name__ == "__main__":
    main(sys.argv[1:])
