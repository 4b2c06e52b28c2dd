"""Static topology (tree.py): ancestor sums against dense walks, hashable immutable trees,
errors naming the body, the dense and segment-sum traversals."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxbody as jb
from jaxbody.tree import CONSTANT_MASK_ENTRIES

from _support.random_models import hinge_chain, random_model, random_state



def random_parents(draw_ints):
    return [-1] + [int(draw_ints(k)) for k in range(1, len(draw_ints.__self__))]


@st.composite
def parent_arrays(draw, max_n=12):
    n = draw(st.integers(1, max_n))
    return [-1] + [draw(st.integers(-1, k - 1)) for k in range(1, n)]


def dense_reference(parent):
    """Ancestor relation by walking parents (independent of the pair construction)."""
    n = len(parent)
    anc = np.zeros((n, n), bool)
    for k in range(n):
        p = parent[k]
        while p != -1:
            anc[p, k] = True
            p = parent[p]
    return anc


@settings(max_examples=15, deadline=None)
@given(parent_arrays())
def test_sums_match_dense_walks(parent):
    tree = jb.BodyTree(parent)
    anc = dense_reference(parent)
    np.testing.assert_array_equal(tree.carrier_mask, anc)
    x = np.random.default_rng(len(parent)).standard_normal((len(parent), 3))
    sub = (anc | np.eye(len(parent), dtype=bool)).astype(float)
    np.testing.assert_allclose(tree.subtree_sum(jnp.asarray(x)), sub @ x, atol=1e-12)
    np.testing.assert_allclose(tree.path_sum(jnp.asarray(x)), sub.T @ x, atol=1e-12)
    ch = np.zeros((len(parent), len(parent)))
    for k, p in enumerate(parent):
        if p >= 0:
            ch[p, k] = 1
    np.testing.assert_allclose(tree.children_sum(jnp.asarray(x)), ch @ x, atol=1e-12)
    # c(i, k) is a child of i and an ancestor-or-self of k
    for i, k, c in zip(tree.carrier_pair_ancestor, tree.carrier_pair_body, tree.carrier_pair_child):
        assert parent[c] == i and (c == k or anc[c, k])
    # pointer-jumping composition equals the sequential root-to-leaf composition
    R = jnp.asarray(np.random.default_rng(1).standard_normal((len(parent), 2, 2)))
    out = tree.accumulate_from_root(R, lambda a, b: a @ b)
    for k in range(len(parent)):
        path = [k]
        while parent[path[-1]] != -1:
            path.append(parent[path[-1]])
        ref = np.eye(2)
        for i in reversed(path):
            ref = ref @ np.asarray(R[i])
        np.testing.assert_allclose(out[k], ref, rtol=1e-12, atol=1e-12)


def test_tree_is_hashable_and_static():
    t1, t2 = jb.BodyTree([-1, 0, 0, 1]), jb.BodyTree([-1, 0, 0, 1])
    assert t1 == t2 and hash(t1) == hash(t2)
    assert all(isinstance(v, int) for v in t1.carrier_pair_child)
    with pytest.raises(AttributeError):
        t1.parent = (1,)


@pytest.mark.parametrize(
    "parent, names, match",
    [
        ([-1, 5], None, r"body 1 \('body1'\) has unknown parent 5"),
        ([-1, -2], None, r"body 1 \('body1'\) has unknown parent -2"),
        ([1, 0], ["a", "b"], r"body 0 \('a'\) lies on a cycle"),
        ([-1, 2, 0], ["a", "b", "c"], r"body 1 \('b'\) has parent 2 \('c'\); bodies must be numbered"),
        ([-1, 0], ["a"], r"parent array has 2 entries but 1 body names"),
        ([-1, 0.5], None, r"parent of body 1 \('body1'\) must be an integer"),
    ],
)
def test_bad_trees_name_the_body(parent, names, match):
    with pytest.raises(ValueError, match=match):
        jb.BodyTree(parent, names)


# ----------------------------------------------------------------------------- static structure
def test_static_structure_is_immutable():
    model = hinge_chain(3)
    with pytest.raises(AttributeError, match="JointLayout is immutable"):
        model.joints.nv = 5
    with pytest.raises(AttributeError, match="BodyTree is immutable"):
        model.tree.traversal = "segment"
    with pytest.raises(ValueError, match=r"body tree: unknown traversal 'sparse'; choose from \('dense', 'segment'\)"):
        jb.BodyTree([-1, 0], traversal="sparse")
    assert jb.BodyTree([-1, 0]) != jb.BodyTree([-1, 0], traversal="segment")
    assert jb.BodyTree([-1] + list(range(300))).traversal == "segment"


@pytest.mark.slow  # 25 s; the segment-sum traversal serves trees of more than 256 bodies
def test_segment_sum_traversal_equals_dense():
    dense = random_model(11, n_body=7)
    seg = random_model(11, n_body=7, traversal="segment")
    assert seg.tree.traversal == "segment" and seg.joints.frame_tree.traversal == "segment"
    q, v, a = random_state(dense, 2)
    ext = jnp.asarray(np.random.default_rng(5).standard_normal((7, 6)))
    for fn in (
        lambda m: jb.mass_matrix(m, q),
        lambda m: jb.inverse_dynamics(m, q, v, a, external=ext),
        lambda m: jb.forward_dynamics(m, q, v, a, include_passive=True),
        lambda m: jb.joint_reactions(m, q, v, a),
        lambda m: jb.kinetic_energy(m, q, v),
        lambda m: jb.augmented_bodies(m, q),
    ):
        jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12), jax.jit(fn)(seg), jax.jit(fn)(dense))
    tree = jb.BodyTree([-1, 0, 0, 1, -1, 4, 3], traversal="segment")
    x = jnp.asarray(np.random.default_rng(0).standard_normal((7, 2)))
    d = tree.with_traversal("dense")
    for name in ("subtree_sum", "path_sum", "children_sum"):
        np.testing.assert_allclose(getattr(tree, name)(x), getattr(d, name)(x), atol=1e-14)


@pytest.mark.parametrize("n, constant", [(10, True), (80, False)])
def test_small_masks_are_constants_large_ones_are_built_in_the_program(n, constant):
    """A mask of at most CONSTANT_MASK_ENTRIES entries is a constant of the program (nothing to
    trace); a larger one is built in the program from its index vectors; both sum alike."""
    tree = jb.BodyTree(list(range(-1, n - 1)))  # a chain: the path sum is the prefix sum
    assert (n * n <= CONSTANT_MASK_ENTRIES) == constant
    x = jnp.arange(float(n))
    np.testing.assert_allclose(tree.path_sum(x), np.cumsum(np.arange(float(n))))
    np.testing.assert_allclose(tree.subtree_sum(x), np.cumsum(np.arange(float(n))[::-1])[::-1])
    eqns = len(jax.make_jaxpr(tree.path_sum)(x).eqns)
    assert (eqns <= 3) if constant else (eqns > 5), eqns
