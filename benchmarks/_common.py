"""Shared helpers of the benchmarks: run stamps, timing, isolated workers.

Nothing here imports JAX: a benchmark's parent process stays free of XLA so that a worker
that deadlocks or runs out of memory can be killed without taking the record with it.
"""

import datetime
import gc
import importlib.metadata
import json
import os
import pathlib
import platform
import re
import shlex
import signal
import statistics
import subprocess
import sys
import time

REPO = pathlib.Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"


def _load_xla_flags():
    # jaxbody/_xla.py by path: importing the package would import JAX before the flags are set
    import importlib.util

    spec = importlib.util.spec_from_file_location("_jaxbody_xla", REPO / "jaxbody" / "_xla.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_xla = _load_xla_flags()
#: XLA_FLAGS the benchmarks add unless told otherwise: the CPU fusion flag on jaxlib 0.10, else "".
DEFAULT_XLA_FLAGS = _xla.default_xla_flags()
set_default_xla_flags = _xla.set_default_xla_flags

__all__ = [
    "REPO",
    "RESULTS",
    "DEFAULT_XLA_FLAGS",
    "set_default_xla_flags",
    "git_stamp",
    "cpu_model",
    "core_count",
    "versions",
    "stamp",
    "stamp_markdown",
    "time_per_call",
    "write_record",
    "run_worker",
    "checkouts",
    "alternate",
    "markdown_table",
    "load_average",
    "mem_available_bytes",
    "ADJOINTS",
    "simulate_adjoint",
]


# ----------------------------------------------------------------------------- stamps
def git_stamp(repo: pathlib.Path = REPO) -> dict:
    """Short commit and dirty flag (read-only git commands only)."""

    def git(*args):
        out = subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, timeout=30)
        if out.returncode:
            raise RuntimeError(out.stderr.strip())
        return out.stdout.strip()

    try:
        commit = git("rev-parse", "--short", "HEAD")
        dirty = bool(git("status", "--porcelain"))  # untracked files count: they may be imported
    except (OSError, RuntimeError, subprocess.TimeoutExpired) as e:
        return {"commit": "unknown", "dirty": None, "git_error": str(e)}
    return {"commit": commit, "dirty": dirty}


def cpu_model() -> str:
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def core_count() -> int:
    """Cores this process may run on (affinity), else ``os.cpu_count()``."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def _version(dist):
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def versions() -> dict:
    """Versions of the packages a benchmark depends on, without importing them."""
    names = ("jax", "jaxlib", "jax-cuda13-plugin", "jax-cuda12-plugin", "mujoco", "mujoco-mjx", "diffrax", "numpy",
             "equinox", "pin", "jaxbody")
    out = {n: _version(n) for n in names}
    out["python"] = platform.python_version()
    return out


def load_average():
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:  # pragma: no cover
        return None


def mem_available_bytes():
    try:
        for line in pathlib.Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def gpu_model() -> str | None:
    """``nvidia-smi``'s GPU name, memory and driver, or None where there is none."""
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=name,memory.total,driver_version", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return "; ".join(line.strip() for line in out.stdout.splitlines() if line.strip()) or None


def stamp(argv=None) -> dict:
    """Commit, machine, versions, date and the exact command line of this run."""
    argv = sys.argv if argv is None else argv
    return {
        **git_stamp(),
        "cpu": cpu_model(),
        "cores": core_count(),
        "gpu": gpu_model(),
        "versions": versions(),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": shlex.join([sys.executable, *argv]),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "load_average_start": load_average(),
        "hostname": platform.node(),
    }


def stamp_markdown(s: dict) -> str:
    v = s["versions"]
    dirty = {True: " (dirty)", False: "", None: " (dirty: unknown)"}[s.get("dirty")]
    lines = [
        f"- commit: `{s['commit']}`{dirty}",
        f"- date: {s['date']}",
        f"- machine: {s['cpu']}, {s['cores']} cores (host `{s['hostname']}`)"
        + (f"; GPU: {s['gpu']}" if s.get("gpu") else ""),
        f"- versions: jax {v['jax']}, jaxlib {v['jaxlib']}"
        + (f", jax-cuda13-plugin {v['jax-cuda13-plugin']}" if v.get('jax-cuda13-plugin') else "")
        + (f", mujoco-mjx {v['mujoco-mjx']}" if v.get('mujoco-mjx') else "")
        + f", mujoco {v['mujoco']}, numpy {v['numpy']}, "
        f"pinocchio (pin) {v['pin'] or 'absent'}, python {v['python']}",
        f"- XLA_FLAGS: `{s['xla_flags'] or '(unset)'}`",
        f"- load average at start / end: {s['load_average_start']} / {s.get('load_average_end')}",
        f"- command: `{s['command']}`",
    ]
    if s.get("note_on_commit"):
        lines.insert(1, f"- about the commit: {s['note_on_commit']}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- timing
def time_per_call(
    fn,
    *,
    min_time: float = 0.2,
    repeats: int = 7,
    budget: float | None = None,
    warmup: bool = True,
    max_number: int = 1_000_000,
) -> dict:
    """Median seconds per call of ``fn()`` (which must block until its result is ready).

    ``fn`` is called once to warm up (unless ``warmup=False``: it has just run), then
    ``number`` calls per repeat are timed, ``number`` chosen (as ``timeit.autorange``) so
    that one repeat lasts about ``min_time / repeats``. Slow calls get fewer repeats: no
    repeat starts once ``budget`` seconds (default ``5 * min_time``) have been spent, so a
    call of tens of seconds is timed once instead of ``repeats`` times (``repeats`` in the
    result says how many samples the median has). Python's garbage collector is off while
    timing, as in :mod:`timeit` (a full collection of JAX's object graph lands on a random
    call and costs milliseconds).
    """
    gc_was_enabled = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        return _time_per_call(fn, min_time=min_time, repeats=repeats, budget=budget, warmup=warmup,
                              max_number=max_number)
    finally:
        if gc_was_enabled:
            gc.enable()


def _time_per_call(fn, *, min_time, repeats, budget, warmup, max_number) -> dict:
    budget = 5.0 * min_time if budget is None else budget
    if warmup:
        fn()
    start = time.perf_counter()
    number, target = 1, max(min_time / repeats, 1e-4)
    while True:
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        dt = time.perf_counter() - t0
        if dt >= target or number >= max_number:
            break
        number = min(max_number, max(number * 2, int(number * target / max(dt, 1e-9) * 1.2)))
    samples = [dt / number]
    while len(samples) < repeats and time.perf_counter() - start + dt <= budget:
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        dt = time.perf_counter() - t0
        samples.append(dt / number)
    return {
        "median_s": statistics.median(samples),
        "min_s": min(samples),
        "max_s": max(samples),
        "repeats": len(samples),
        "number": number,
    }


# ----------------------------------------------------------------------------- isolation
_NOT_LAUNCHED = {"parameter", "get-tuple-element", "tuple", "constant", "bitcast"}


def count_eqns(jax, jaxpr) -> int:
    """Equations of a jaxpr, including those of every sub-jaxpr (calls, loops, custom rules)."""
    total = 0
    for eqn in jaxpr.eqns:
        total += 1
        for param in eqn.params.values():
            for sub in param if isinstance(param, (list, tuple)) else (param,):
                if isinstance(sub, jax.extend.core.ClosedJaxpr):
                    total += count_eqns(jax, sub.jaxpr)
                elif isinstance(sub, jax.extend.core.Jaxpr):
                    total += count_eqns(jax, sub)
    return total


def loop_body_ops(hlo_text: str) -> dict:
    """What one iteration of a compiled program's loops runs: for each ``while`` of the optimised
    HLO text (``compiled.as_text()``), the top-level operations of its body other than
    parameters, tuples, constants and bitcasts (on a GPU each is about one kernel launch or
    copy), by opcode. Returns ``{"max": n, "bodies": [{"body": name, "ops": n, "by_opcode":
    {...}}, ...]}``, largest body first."""
    comps, current, bodies = {}, None, []
    for line in hlo_text.splitlines():
        if current is None:
            if line and not line[0].isspace() and line.rstrip().endswith("{"):
                name = line.split()[1] if line.startswith("ENTRY") else line.split()[0]
                current = comps.setdefault(name.lstrip("%"), {})
            continue
        if line.strip() == "}":
            current = None
            continue
        m = re.search(r"=\s.*?\s([a-z][a-z0-9\-]*)\(", line)
        if m:
            current[m.group(1)] = current.get(m.group(1), 0) + 1
            if m.group(1) == "while":
                b = re.search(r"body=%?([\w.\-]+)", line)
                if b:
                    bodies.append(b.group(1))
    out = []
    for name in dict.fromkeys(bodies):
        ops = {k: v for k, v in comps.get(name, {}).items() if k not in _NOT_LAUNCHED}
        out.append({"body": name, "ops": sum(ops.values()), "by_opcode": ops})
    out.sort(key=lambda d: -d["ops"])
    return {"max": out[0]["ops"] if out else 0, "bodies": out[:4]}


def parse_cases(text: str, known: tuple, cassie: str | None) -> list[str]:
    """The comma-separated cases of ``text``, each one of ``known``; ``cassie`` needs its MJCF
    (``--cassie PATH``). Exits with a message naming the case otherwise."""
    cases = [c.strip() for c in text.split(",") if c.strip()]
    for case in cases:
        if case not in known:
            raise SystemExit(f"unknown case {case!r}: one of {known}")
        if case == "cassie" and not cassie:
            raise SystemExit("case 'cassie' needs --cassie PATH (its MJCF)")
    return cases


def checkouts(baseline: pathlib.Path | None) -> tuple[dict, dict | None]:
    """The jaxbody checkouts a before/after benchmark times: ``{label: path}`` (``None``: this
    tree), the baseline (another checkout, e.g. a ``git worktree`` of an older commit) first;
    and the record's ``baseline`` entry (``None`` without one)."""
    if baseline is None:
        return {"this tree": None}, None
    commit = subprocess.run(["git", "-C", str(baseline), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip()
    path = pathlib.Path(baseline).resolve()
    return {f"baseline {commit or baseline}": path, "this tree": None}, dict(path=str(path), commit=commit)


def alternate(script, cases: list, trees: dict, repeats: int, extra=()) -> list[dict]:
    """Run ``script --worker CASE *extra`` in a fresh process for every repeat, case and
    checkout, in that nesting (a drift in the machine's speed hits every case and checkout
    alike); each worker prints one JSON line last. Returns those results, each with its
    checkout's label as ``tree``."""
    runs = []
    for _ in range(repeats):
        for case in cases:
            for tree, path in trees.items():
                env = dict(os.environ)
                if path is not None:
                    env["PYTHONPATH"] = os.pathsep.join([str(path), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
                out = subprocess.run([sys.executable, str(script), "--worker", case, *extra], check=True,
                                     capture_output=True, text=True, env=env)
                runs.append(dict(json.loads(out.stdout.strip().splitlines()[-1]), tree=tree))
                print(runs[-1], flush=True)
    return runs


def run_worker(cmd, *, timeout: float, result_file: pathlib.Path, env=None) -> dict:
    """Run ``cmd`` in its own process group; return the JSON it left in ``result_file``.

    The worker writes its (partial) results to ``result_file`` as it goes. On timeout the
    whole process group is killed (a deadlocked XLA thread pool cannot hang the benchmark)
    and whatever the worker had written is returned with ``status = "timeout"``.
    """
    result_file = pathlib.Path(result_file)
    if result_file.exists():
        result_file.unlink()
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    try:
        out, err = proc.communicate(timeout=timeout)
        status = "ok" if proc.returncode == 0 else f"error (exit {proc.returncode})"
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        status = "timeout"
    wall = time.perf_counter() - t0
    try:
        result = json.loads(result_file.read_text())
    except (OSError, ValueError):
        result = {}
    result["status"] = status
    result["worker_wall_s"] = wall
    if status != "ok":
        result["stderr_tail"] = (err or "")[-2000:]
    return result


# ----------------------------------------------------------------------------- adjoints
ADJOINTS = ("checkpoint", "backsolve", "forward")


def simulate_adjoint(name: str):
    """The ``adjoint=`` argument of ``jb.simulate`` for a preset name.

    ``"checkpoint"``: recursive checkpointing (reverse mode, jaxbody's default);
    ``"backsolve"``: the continuous adjoint, integrated backwards (reverse mode, O(1) memory);
    ``"forward"``: forward mode (for ``jax.jacfwd``/``jax.jvp``). ``jb.simulate`` takes these
    names itself.
    """
    if name not in ("checkpoint", "backsolve", "forward"):
        raise ValueError(f"unknown adjoint {name!r}; choose from checkpoint, backsolve, forward")
    return name


def markdown_table(headers, rows) -> str:
    def cell(x):
        return "" if x is None else str(x).replace("|", "\\|")

    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(cell(x) for x in r) + " |" for r in rows]
    return "\n".join(lines)


#: The papers' Example 1 (masses 1, 0.6 kg; centres 0.4, 0.3 m; L1 = 0.8 m; central inertias
#: 0.05, 0.02 kg·m²) as hinges about y (MuJoCo's joint angles are the relative ones), with
#: contacts, limits and actuation off: the scene the accuracy benchmarks share with MuJoCo.
DOUBLE_PENDULUM_MJCF = """<mujoco model="double_pendulum">
  <option gravity="0 0 -9.81" timestep="0.001"><flag contact="disable" limit="disable" actuation="disable"/></option>
  <worldbody>
    <body name="link1">
      <joint name="alpha1" type="hinge" axis="0 1 0"/>
      <inertial pos="0 0 -0.4" mass="1.0" diaginertia="0.05 0.05 0.05"/>
      <body name="link2" pos="0 0 -0.8">
        <joint name="alpha2" type="hinge" axis="0 1 0"/>
        <inertial pos="0 0 -0.3" mass="0.6" diaginertia="0.02 0.02 0.02"/>
      </body>
    </body>
  </worldbody>
</mujoco>"""


def write_record(name: str, record: dict, title: str, text: str, headers, rows, out: pathlib.Path = RESULTS) -> str:
    """Write ``out/name.json`` (the record) and ``out/name.md``: ``title``, the record's stamp,
    ``text`` and one table; returns the markdown."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(record, indent=1))
    md = "\n".join([f"# {title}", "", stamp_markdown(record["stamp"]), "", text, "", markdown_table(headers, rows), ""])
    (out / f"{name}.md").write_text(md)
    return md


def shared_legend(fig, axes, n_used: int, **legend):
    """Turn off the panels of ``axes`` past the first ``n_used`` and draw one legend for the figure,
    each label once (the panels share their series), below the plots; returns the labels."""
    for ax in list(axes.flat)[n_used:]:
        ax.axis("off")
    handles, labels = [], []
    for ax in axes.flat:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    fig.legend(handles, labels, loc="lower center", **legend)
    return labels
