"""Names that moved when the package was split into one package per concept stay reachable at
their old places for a while, with a DeprecationWarning naming the new place."""

import pytest

import jaxbody as jb
from jaxbody import backends, simulation


@pytest.mark.parametrize("name", ["acceleration", "resolve_kernel", "KERNELS", "DEFAULT_KERNEL"])
def test_kernel_dispatch_names_moved_to_backends(name):
    with pytest.warns(DeprecationWarning, match=rf"jaxbody\.kernels\.{name} moved to jaxbody\.backends\.{name}"):
        old = getattr(jb.kernels, name)
    assert old is getattr(backends, name)


@pytest.mark.parametrize("name", ["PartitionSolver", "partition_solver", "partition_report", "with_best_partition"])
def test_partition_solver_moved_to_simulation(name):
    with pytest.warns(DeprecationWarning, match=rf"jaxbody\.maggi\.{name} moved to jaxbody\.simulation\.{name}"):
        old = getattr(jb.maggi, name)
    assert old is getattr(simulation, name)


@pytest.mark.parametrize("name", ["native", "unrolled"])
def test_backend_modules_moved(name):
    with pytest.warns(DeprecationWarning, match=rf"jaxbody\.{name} moved to jaxbody\.backends\.{name}"):
        old = getattr(jb, name)
    assert old is getattr(backends, name)


def test_unknown_names_still_raise_attribute_error():
    with pytest.raises(AttributeError, match="jaxbody.kernels.*no attribute 'nonexistent'"):
        jb.kernels.nonexistent  # noqa: B018
    with pytest.raises(AttributeError, match="'jaxbody' has no attribute 'nonexistent'"):
        jb.nonexistent  # noqa: B018
