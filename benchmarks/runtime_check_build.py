"""What the run-time check's library adds to a new user's first call: its build on an empty cache.

    python benchmarks/runtime_check_build.py [--repeats 5] [--name NAME]

Builds the check's handler (``jaxbody/runtime_check.cc``, written against XLA's FFI C API alone)
with ``jaxbody.cxx.build_library`` and the check's flags (``jaxbody.runtime_check.FLAGS``) into an
empty cache directory, ``--repeats`` times, and, for comparison, the same handler written with
XLA's C++ binding (``xla/ffi/api/ffi.h``, below). The native kernel's handler
(``jaxbody/backends/native/handler.cc``: the thread pool and the program registry, written
against the C API too) is built the same way with the kernel's own flags, the library every
native program is called through, and so the first build of a new user's first native call.
Then, in fresh processes on an empty and on a warm cache, the whole first use:
``jaxbody.runtime_check.target()`` (build or load, and register with XLA). Writes ``NAME.json``
and ``NAME.md`` (default ``runtime_check_build``) to ``benchmarks/results``.
"""

import argparse
import json
import os
import pathlib
import statistics
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _common import REPO, RESULTS, load_average, markdown_table, stamp, stamp_markdown  # noqa: E402

#: The same check with XLA's C++ binding: decoding, the metadata query and the error through
#: ffi.h's templates (what a handler usually looks like; the shipped one does it by hand).
CXX_BINDING = r"""
#include <cstring>
#include <string>
#include <string_view>
#include "xla/ffi/api/ffi.h"
namespace ffi = xla::ffi;

static ffi::Error Check(ffi::Buffer<ffi::PRED> flags, ffi::AnyBuffer x, std::string_view messages,
                        ffi::Result<ffi::AnyBuffer> out) {
  const auto dims = flags.dimensions();
  const int64_t n = dims.size() == 0 ? 1 : dims.back();
  const int64_t members = n ? int64_t(flags.element_count()) / n : 0;
  const bool* f = flags.typed_data();
  for (int64_t i = 0; i < members; ++i)
    for (int64_t j = 0; j < n; ++j)
      if (f[i * n + j]) {
        std::string_view rest = messages;
        for (int64_t k = 0; k < j; ++k) rest = rest.substr(rest.find('\n') + 1);
        std::string msg(rest.substr(0, rest.find('\n')));
        if (dims.size() > 1) msg += " (batch member " + std::to_string(i) + " of " + std::to_string(members) + ")";
        return ffi::Error::InvalidArgument(msg);
      }
  if (out->untyped_data() != x.untyped_data()) std::memcpy(out->untyped_data(), x.untyped_data(), x.size_bytes());
  return ffi::Error::Success();
}

XLA_FFI_DEFINE_HANDLER_SYMBOL(jaxbody_check, Check,
                              ffi::Ffi::Bind().Arg<ffi::Buffer<ffi::PRED>>().Arg<ffi::AnyBuffer>()
                                  .Attr<std::string_view>("messages").Ret<ffi::AnyBuffer>());
"""

_FIRST_USE = ("import time; t = time.perf_counter(); from jaxbody import runtime_check; t1 = time.perf_counter(); "
              "assert runtime_check.target() == runtime_check.TARGET; print(time.perf_counter() - t1)")


def _build_seconds(source: str, repeats: int) -> list[float]:
    from jaxbody import cxx, runtime_check

    times = []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as cache:
            os.environ["JAXBODY_CACHE_DIR"] = cache
            start = time.perf_counter()
            cxx.build_library(source, "runtime_check_probe", "the probe", runtime_check.FLAGS)
            times.append(time.perf_counter() - start)
    return times


def _handler_seconds(repeats: int) -> list[float]:
    import numpy as np

    from jaxbody.backends.native import build

    times = []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as cache:
            os.environ["JAXBODY_CACHE_DIR"] = cache
            start = time.perf_counter()
            build.handler_library(np.float64)
            times.append(time.perf_counter() - start)
    return times


def _first_use_seconds(cache: str) -> float:
    env = dict(os.environ, JAXBODY_CACHE_DIR=cache, PYTHONPATH=str(REPO))
    out = subprocess.run([sys.executable, "-c", _FIRST_USE], env=env, capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--name", default="runtime_check_build")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    args = p.parse_args(argv)
    sys.path.insert(0, str(REPO))
    from importlib import resources

    from jaxbody import runtime_check

    rec = {"stamp": stamp(), "repeats": args.repeats}
    shipped = resources.files("jaxbody").joinpath("runtime_check.cc").read_text()
    saved = os.environ.get("JAXBODY_CACHE_DIR")
    rec["build_c_api_s"] = _build_seconds(shipped, args.repeats)
    rec["build_cxx_binding_s"] = _build_seconds(CXX_BINDING, args.repeats)
    rec["build_native_handler_s"] = _handler_seconds(args.repeats)
    if saved is None:
        os.environ.pop("JAXBODY_CACHE_DIR", None)
    else:
        os.environ["JAXBODY_CACHE_DIR"] = saved
    empty, warm = [], []
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory() as cache:
            empty.append(_first_use_seconds(cache))
            warm.append(_first_use_seconds(cache))
    rec["first_use_empty_cache_s"], rec["first_use_warm_cache_s"] = empty, warm
    rec["stamp"]["load_average_end"] = load_average()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.json").write_text(json.dumps(rec, indent=1))

    def row(what, xs):
        return (what, f"{statistics.median(xs):.3f}", f"{min(xs):.3f}", f"{max(xs):.3f}")

    rows = [row("build: C API (`jaxbody/runtime_check.cc`, shipped)", rec["build_c_api_s"]),
            row("build: the same handler with XLA's C++ binding (`ffi.h`)", rec["build_cxx_binding_s"]),
            row("build: the native kernel's handler (C API, the kernel's flags, float64)", rec["build_native_handler_s"]),
            row("first use in a fresh process, empty cache (build, load, register)", empty),
            row("first use in a fresh process, warm cache (load, register)", warm)]
    md = ["# The run-time check's library: build time on an empty cache", "", stamp_markdown(rec["stamp"]), "",
          f"Seconds, {args.repeats} runs each (compiler flags `{' '.join(runtime_check.FLAGS)}`):", "",
          markdown_table(["what", "median s", "min s", "max s"], rows), ""]
    (args.out / f"{args.name}.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
