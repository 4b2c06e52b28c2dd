"""Static topology (tree.py, joints.py) and build-time validation of models (model.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxbody as jb


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


@settings(max_examples=40, deadline=None)
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


def good_builder():
    b = jb.ModelBuilder()
    b.add_body("base", mass=1.0, inertia=(0.1, 0.1, 0.1), joints=[jb.Hinge(axis=(0, 0, 1))])
    return b


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(mass=-1.0), r"body 1 \('link'\): body_mass is negative"),
        (dict(inertia=(1.0, 0.1, 0.1)), r"body 1 \('link'\): body_inertia violates the triangle inequality"),
        (dict(inertia=(-0.1, 0.1, 0.1)), r"body 1 \('link'\): body_inertia has a negative principal moment"),
        (dict(inertia=[[0.1, 0.05, 0], [0.0, 0.1, 0], [0, 0, 0.1]]), r"body_inertia is not symmetric"),
        (dict(mass=0.0, inertia=(0, 0, 0)), r"body 1 \('link'\) moves \(has joints\) but its subtree mass is 0"),
        (dict(com=(0.0, float("nan"), 0.0)), r"body 'link' com is not finite"),
        (dict(inertia=(0.1, 0.1)), r"body 'link': inertia must have 3, 6 or 3x3 values"),
        (dict(joints=[jb.Hinge(axis=(0, 0, 0))]), r"joint 'link_hinge0' of body 'link': axis is zero"),
        (dict(joints=[jb.Free()]), r"joint 1 \('link_free0'\) is a free joint on body 1 \('link'\), which is not a root"),
        (dict(joints=[jb.Hinge(damping=-1.0)]), r"joint 1 \('link_hinge0'\): dof_damping is negative"),
        (dict(joints=["hinge"]), r"body 'link': joints must be Hinge/Slide/Ball/Free"),
    ],
)
def test_builder_rejects_bad_parameters_naming_the_culprit(kwargs, match):
    b = good_builder()
    args = dict(pos=(0, 0, -0.5), mass=1.0, inertia=(0.1, 0.1, 0.1), joints=[jb.Hinge(axis=(0, 1, 0))])
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        b.add_body("link", "base", **args)
        b.build()


def test_builder_rejects_unknown_parent_and_duplicates():
    b = good_builder()
    with pytest.raises(ValueError, match=r"body 'x': unknown parent body 'nope'"):
        b.add_body("x", "nope", mass=1.0)
    with pytest.raises(ValueError, match=r"body 'base' is defined twice"):
        b.add_body("base", mass=1.0)
    with pytest.raises(ValueError, match=r"model has no bodies"):
        jb.ModelBuilder().build()


def test_free_joint_must_be_alone():
    b = jb.ModelBuilder()
    b.add_body("a", mass=1.0, inertia=(0.1, 0.1, 0.1), joints=[jb.Free(), jb.Hinge()])
    with pytest.raises(ValueError, match=r"a free joint must be the only joint of body 0 \('a'\)"):
        b.build()


def test_nan_parameters_in_a_model_are_reported_by_field():
    model = good_builder().build()
    bad = jax.tree_util.tree_map(lambda x: x, model)
    import equinox as eqx

    bad = eqx.tree_at(lambda m: m.body_mass, model, jnp.array([jnp.nan]))
    with pytest.raises(ValueError, match=r"body 0 \('base'\): body_mass is not finite"):
        jb.validate_parameters(bad)


def test_layout_addresses_follow_mujoco():
    b = jb.ModelBuilder()
    b.add_body("f", mass=1.0, inertia=(0.1, 0.1, 0.1), joints=[jb.Free()])
    b.add_body("u", "f", mass=1.0, inertia=(0.1, 0.1, 0.1), joints=[jb.Hinge(), jb.Hinge(axis=(1, 0, 0))])
    b.add_body("s", "u", mass=1.0, inertia=(0.1, 0.1, 0.1), joints=[jb.Ball()])
    m = b.build()
    assert (m.nq, m.nv) == (7 + 2 + 4, 6 + 2 + 3)
    assert m.joints.qposadr == (0, 7, 8, 9) and m.joints.dofadr == (0, 6, 7, 8)
    assert m.joints.dof_body == (0,) * 6 + (1, 1) + (2,) * 3
    np.testing.assert_allclose(m.qpos0[3:7], [1, 0, 0, 0])
