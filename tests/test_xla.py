"""jaxbody/_xla.py: the CPU fusion flag only for the jaxlib versions that know it."""

import importlib.metadata
import os
import pathlib
import subprocess
import sys

import pytest

from jaxbody import _xla

REPO = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(
    ("version", "flags"),
    [("0.10.2", _xla.CPU_FUSION_FLAG), ("0.10.0", _xla.CPU_FUSION_FLAG), ("0.11.2", ""), ("0.12.0.1", ""),
     ("0.9.2", ""), ("1.0.0", "")],
)
def test_default_flags_follow_the_installed_jaxlib(monkeypatch, version, flags):
    monkeypatch.setattr(importlib.metadata, "version", lambda name: version)
    assert _xla.jaxlib_version() == tuple(int(x) for x in version.split(".")[:3])
    assert _xla.default_xla_flags() == flags


def test_no_jaxlib_gives_no_flags(monkeypatch):
    def missing(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "version", missing)
    assert _xla.jaxlib_version() == () and _xla.default_xla_flags() == ""


def test_a_callers_flags_are_kept_and_the_fusion_flag_added_unless_they_set_it(monkeypatch):
    monkeypatch.setattr(importlib.metadata, "version", lambda name: "0.10.2")
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
    _xla.set_default_xla_flags()
    assert os.environ["XLA_FLAGS"] == f"--xla_force_host_platform_device_count=2 {_xla.CPU_FUSION_FLAG}"
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=true")  # the caller's own choice
    _xla.set_default_xla_flags()
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_use_fusion_emitters=true"
    monkeypatch.delenv("XLA_FLAGS")
    _xla.set_default_xla_flags()
    assert os.environ["XLA_FLAGS"] == _xla.CPU_FUSION_FLAG
    monkeypatch.setattr(importlib.metadata, "version", lambda name: "0.11.2")  # a jaxlib without the flag
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
    _xla.set_default_xla_flags()
    assert os.environ["XLA_FLAGS"] == "--xla_force_host_platform_device_count=2"


def test_importing_jaxbody_sets_the_flag_before_jax_starts():
    script = "import os, jaxbody, jax; jax.numpy.zeros(1).block_until_ready(); print(os.environ.get('XLA_FLAGS', ''))"
    for given, expected in (("", _xla.default_xla_flags()),
                            ("--xla_cpu_use_fusion_emitters=true", "--xla_cpu_use_fusion_emitters=true")):
        env = dict(os.environ, XLA_FLAGS=given) if given else {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
        out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True, timeout=120,
                             env=env, cwd=REPO).stdout.strip()
        assert out == expected


def test_script_prints_the_flags_for_this_environment():
    # ./run reads the flags this way, before JAX starts; the installed jaxlib decides
    out = subprocess.run([sys.executable, str(REPO / "jaxbody" / "_xla.py")], capture_output=True, text=True,
                         check=True, timeout=60).stdout.strip()
    assert out == _xla.default_xla_flags()
    major_minor = tuple(int(x) for x in importlib.metadata.version("jaxlib").split(".")[:2])
    assert (out == _xla.CPU_FUSION_FLAG) == ((0, 10) <= major_minor < (0, 11))
