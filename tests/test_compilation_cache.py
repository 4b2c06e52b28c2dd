"""JAX's persistent compilation cache, on by default in jaxbody's cache directory.

What importing jaxbody sets (and what it leaves to a user who configured JAX's cache or
switched it off), and — in the slow job — that a native-kernel program compiled in one
process is loaded from the cache by the next one and gives the same numbers.
"""

import json
import os
import pathlib
import subprocess
import sys

import jax
import pytest

from jaxbody import compilation_cache

REPO = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture
def jax_cache_settings(monkeypatch):
    """JAX's cache settings as a fresh process has them, restored afterwards. (Changing them
    here does not change the cache this process uses: JAX decided that at its first compile.)"""
    names = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")
    saved = {n: getattr(jax.config, n) for n in names}
    for var in ("JAX_COMPILATION_CACHE_DIR", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "JAX_COMPILATION_CACHE_MAX_SIZE",
                compilation_cache.ENV_SWITCH):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(compilation_cache, "_enabled", None)
    jax.config.update("jax_compilation_cache_dir", None)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    try:
        yield
    finally:
        for n, value in saved.items():
            jax.config.update(n, value)


def test_on_by_default_in_the_user_cache_directory(jax_cache_settings, monkeypatch, tmp_path):
    monkeypatch.setenv("JAXBODY_CACHE_DIR", str(tmp_path))
    path = compilation_cache.enable()
    assert path == tmp_path / "jax" and path.is_dir() and compilation_cache.enabled_dir() == path
    assert jax.config.jax_compilation_cache_dir == str(tmp_path / "jax")
    assert jax.config.jax_persistent_cache_min_compile_time_secs == compilation_cache.MIN_COMPILE_SECONDS
    # the native kernel's libraries live beside it
    assert compilation_cache.cache_root() == tmp_path


@pytest.mark.parametrize("switch", ["0", "off", "False", "no"])
def test_switched_off_by_the_environment(jax_cache_settings, monkeypatch, tmp_path, switch):
    monkeypatch.setenv("JAXBODY_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv(compilation_cache.ENV_SWITCH, switch)
    assert compilation_cache.enable() is None
    assert jax.config.jax_compilation_cache_dir is None and not (tmp_path / "jax").exists()


def test_a_users_own_cache_is_left_alone(jax_cache_settings, monkeypatch, tmp_path):
    monkeypatch.setenv("JAXBODY_CACHE_DIR", str(tmp_path / "jaxbody"))
    jax.config.update("jax_compilation_cache_dir", str(tmp_path / "mine"))
    assert compilation_cache.enable() is None
    assert jax.config.jax_compilation_cache_dir == str(tmp_path / "mine")
    assert jax.config.jax_persistent_cache_min_compile_time_secs == 1.0
    jax.config.update("jax_compilation_cache_dir", None)
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "mine"))
    assert compilation_cache.enable() is None and jax.config.jax_compilation_cache_dir is None


_WORKER = r"""
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import jaxbody as jb
events = []
jax.monitoring.register_event_listener(lambda name, **kw: events.append(name))
model = jb.from_mjcf(sys.argv[1])
q = model.qpos0 + 0.1 * jnp.arange(model.nq)
v = jnp.linspace(-1.0, 1.0, model.nv)
# the kernel alone under jit (no run-time checks: programs with host callbacks are never stored)
fd = jax.jit(jax.vmap(lambda q, v: jb.backends.acceleration(model, q, v, gravity=model.gravity, kernel="native")))
a = fd(jnp.stack([q, q + 0.2]), jnp.stack([v, -v]))
print(json.dumps({"a": [float(x) for x in a.ravel()], "hits": events.count("/jax/compilation_cache/cache_hits"),
                  "dir": str(jb.compilation_cache.enabled_dir())}))
"""


@pytest.mark.slow  # two fresh processes, each building or loading Panda's native forward dynamics (about 20 s)
def test_native_program_is_loaded_from_the_cache_by_the_next_process(tmp_path, models_dir):
    """The program calls the native kernel by a key of its source, not by its address (which
    changes from process to process), so the second process finds the first one's program in
    the cache and runs it on its own copy of the kernel: same numbers, a cache hit."""
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR", "JAXBODY_JAX_CACHE")}
    # every program stored, however fast it compiled
    env.update(JAXBODY_CACHE_DIR=str(tmp_path), PYTHONPATH=str(REPO), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
    runs = []
    for _ in range(2):
        out = subprocess.run([sys.executable, "-c", _WORKER, str(models_dir / "panda.xml")], capture_output=True,
                             text=True, timeout=600, env=env)
        assert out.returncode == 0, out.stderr[-3000:]
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    assert runs[0]["dir"] == str(tmp_path / "jax")
    assert runs[1]["hits"] > 0, runs
    assert runs[0]["a"] == runs[1]["a"]


_SOLVE_WORKER = r"""
import json, logging
import jax
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_explain_cache_misses", True)  # JAX then logs each hit and miss by program name
import jax.numpy as jnp
import jaxbody as jb
messages = []
handler = logging.Handler()
handler.emit = lambda record: messages.append(record.getMessage())
logger = logging.getLogger("jax._src.compiler")
logger.addHandler(handler)
logger.setLevel(logging.DEBUG)  # hits are logged at DEBUG level
b = jb.ModelBuilder()
b.add_body("arm", mass=1.0, com=(0, 0, -0.2), inertia=(0.01, 0.01, 0.002), joints=[jb.Hinge(axis=(0, 1, 0))])
model = b.build()
sol = jb.simulate(model, jnp.array([0.3]), jnp.array([0.0]), 1.0)
print(json.dumps({"q": [float(x) for x in sol.q[:, 0]],
                  # the solve's program: traced (jit__integrate; the suite turns jaxbody.program_store off)
                  "solve_hits": sum("cache hit for 'jit__integrate'" in m
                                    for m in messages),
                  "callbacks": [m for m in messages if "host callbacks" in m]}))
"""


@pytest.mark.slow  # two fresh processes, each compiling or loading a solve (about 15 s)
def test_the_solve_is_loaded_from_the_cache_by_the_next_process(tmp_path):
    """A first ``jb.simulate`` compiles its solve once: the next process loads the program from
    the cache (it holds no host callback, which JAX's cache would refuse) and gets the same numbers."""
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR", "JAXBODY_JAX_CACHE")}
    env.update(JAXBODY_CACHE_DIR=str(tmp_path), PYTHONPATH=str(REPO), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
    runs = []
    for _ in range(2):
        out = subprocess.run([sys.executable, "-c", _SOLVE_WORKER], capture_output=True, text=True, timeout=600, env=env)
        assert out.returncode == 0, out.stderr[-3000:]
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    assert runs[0]["callbacks"] == [] and runs[1]["callbacks"] == [], runs
    assert runs[0]["solve_hits"] == 0 and runs[1]["solve_hits"] == 1, runs
    assert runs[0]["q"] == runs[1]["q"]
