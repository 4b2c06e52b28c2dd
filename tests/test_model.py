"""Building models (model.py): ``ModelBuilder`` rejects bad parameters naming the culprit."""

import pytest

import jaxbody as jb


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


def test_builder_rejects_a_model_without_a_degree_of_freedom():
    b = jb.ModelBuilder()
    b.add_body("plate", mass=1.0, inertia=(0.1, 0.1, 0.1))
    b.add_body("bracket", "plate", mass=0.5, inertia=(0.01, 0.01, 0.01))
    with pytest.raises(ValueError, match=r"model has no degree of freedom: no body has a joint \(2 bodies welded"):
        b.build()


def test_free_joint_must_be_alone():
    b = jb.ModelBuilder()
    b.add_body("a", mass=1.0, inertia=(0.1, 0.1, 0.1), joints=[jb.Free(), jb.Hinge()])
    with pytest.raises(ValueError, match=r"a free joint must be the only joint of body 0 \('a'\)"):
        b.build()


def test_builder_rejects_a_moving_body_without_inertia_as_mujoco_does():
    b = jb.ModelBuilder()
    b.add_body("p", mass=1.0, com=(0, 0, -1), inertia=(0.0, 0.0, 0.0), joints=[jb.Hinge()])
    with pytest.raises(ValueError, match=r"body 0 \('p'\) moves \(has joints\) but a principal moment of "
                                         r"inertia is not positive \(principal moments \[0.0, 0.0, 0.0\]\)"):
        b.build()
    # a moving body that carries a welded child with inertia is fine (MuJoCo accepts it too)
    b = jb.ModelBuilder()
    b.add_body("p", mass=1.0, com=(0, 0, -1), inertia=(0.0, 0.0, 0.0), joints=[jb.Hinge()])
    b.add_body("w", "p", mass=1.0, inertia=(0.1, 0.1, 0.1))
    b.build()


def test_a_model_built_inside_jit_from_numbers_is_a_constant_of_the_program():
    """The builder and the MJCF importer called inside ``jax.jit`` give the model built outside
    (checked on concrete values); traced numbers are refused naming the field (the bad-input table)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    mjcf = ('<mujoco><worldbody><body name="b"><joint name="j" type="hinge" axis="0 1 0"/>'
            '<geom type="sphere" size=".1" pos="0 0 -.3" mass="1"/></body></worldbody></mujoco>')

    def mass_matrices(q):
        built = good_builder().build()
        return jb.mass_matrix(built, q), jb.mass_matrix(jb.from_mjcf(mjcf), q)

    q = jnp.array([0.3])
    inside = jax.jit(mass_matrices)(q)
    outside = (jb.mass_matrix(good_builder().build(), q), jb.mass_matrix(jb.from_mjcf(mjcf), q))
    for a, b in zip(inside, outside):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-14)
