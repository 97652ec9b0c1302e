"""Mirror-consistent normaliser: S commutes with normalisation when fitted on data ∪ S(data)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from equibim_jax.data.normalizer import (
    FieldNormalizer,
    Normalizer,
    conjugate_op,
    fit_normalizer,
    mirror_in_normalized_space,
    normalized_symmetry,
    signed_permutation,
)
from equibim_jax.symmetry import JointMap, Mirror, Symmetry, point_cloud_op

# Two 3-joint arms swapped, plus a self-mapped joint. Joint 1 <-> 4 flips sign about 0.15
# (offset 0.3 on both, so the map stays an involution: s_i b_{p(i)} + b_i = 0); joint 6 maps
# to itself as x -> -x + 0.2.
PERM = [3, 4, 5, 0, 1, 2, 6]
SIGNS = [1, -1, 1, 1, -1, 1, -1]
OFFSETS = [0.0, 0.3, 0.0, 0.0, 0.3, 0.0, 0.2]


def _joint_map():
    return JointMap(PERM, SIGNS, OFFSETS)


def _data(n=500, seed=0):
    rng = np.random.default_rng(seed)
    # Deliberately asymmetric: the left arm moves over other ranges than the right.
    scales = np.array([1.0, 0.5, 2.0, 0.3, 1.5, 0.7, 0.4])
    shifts = np.array([0.5, -1.0, 0.0, 2.0, 0.3, -0.2, 0.9])
    return (rng.uniform(-1, 1, (n, 7)) * scales + shifts).astype(np.float32)


def test_joint_map_is_involution():
    x = jnp.asarray(_data(20))
    jm = _joint_map()
    np.testing.assert_allclose(jm(jm(x)), x, atol=1e-6)


@pytest.mark.parametrize("mode", ["minmax", "meanstd"])
def test_normalize_commutes_with_mirror(mode):
    jm = _joint_map()
    x = jnp.asarray(_data())
    norm = fit_normalizer({"qpos": x}, {"qpos": jm}, mode=mode).fields["qpos"]
    perm, signs = mirror_in_normalized_space(jm.perm, jm.signs, jm.offsets, norm)
    np.testing.assert_array_equal(perm, PERM)
    np.testing.assert_array_equal(signs, SIGNS)
    s_n = signed_permutation(perm, signs)
    lhs = norm.normalize(jm(x))
    rhs = s_n(norm.normalize(x))
    np.testing.assert_allclose(lhs, rhs, atol=2e-5)
    # Generic conjugation agrees with the exact signed permutation.
    generic = lambda y: norm.normalize(jm(norm.unnormalize(y)))  # noqa: E731
    np.testing.assert_allclose(generic(norm.normalize(x)), rhs, atol=2e-5)


def test_minmax_range_is_minus_one_to_one():
    jm = _joint_map()
    x = jnp.asarray(_data())
    norm = fit_normalizer({"qpos": x}, {"qpos": jm}).fields["qpos"]
    both = jnp.concatenate([norm.normalize(x), norm.normalize(jm(x))])
    np.testing.assert_allclose(both.min(0), -1.0, atol=1e-5)
    np.testing.assert_allclose(both.max(0), 1.0, atol=1e-5)
    np.testing.assert_allclose(norm.unnormalize(norm.normalize(x)), x, atol=1e-5)


def test_normaliser_fitted_without_mirror_is_refused():
    jm = _joint_map()
    norm = fit_normalizer({"qpos": _data()}, None).fields["qpos"]
    with pytest.raises(ValueError, match="not mirror-consistent"):
        mirror_in_normalized_space(jm.perm, jm.signs, jm.offsets, norm)
    with pytest.raises(ValueError, match="not mirror-consistent"):
        conjugate_op(jm, norm)


def test_conjugate_joint_map_is_exact_signed_permutation():
    jm = _joint_map()
    norm = fit_normalizer({"qpos": _data()}, Symmetry({"qpos": jm}))
    op = normalized_symmetry(Symmetry({"qpos": jm}), norm)["qpos"]
    y = jax.random.normal(jax.random.key(0), (4, 3, 7))
    np.testing.assert_array_equal(op(op(y)), y)  # exact involution
    np.testing.assert_array_equal(op(y), jnp.asarray(SIGNS, jnp.float32) * y[..., PERM])


def test_point_cloud_reflection_is_linear_in_normalised_space():
    mirror = Mirror.from_axis("y")
    rng = np.random.default_rng(1)
    pts = (rng.normal(size=(50, 32, 3)) * [0.3, 0.2, 0.1] + [0.5, 0.15, 0.8]).astype(np.float32)
    sym = Symmetry({"point_cloud": point_cloud_op(mirror)})
    norm = fit_normalizer({"point_cloud": pts}, sym)
    f = norm.fields["point_cloud"]
    # Union is symmetric in y: the y channel is centred exactly at 0.
    assert float(f.offset[1]) == 0.0
    op = normalized_symmetry(sym, norm)["point_cloud"]
    y = f.normalize(jnp.asarray(pts))
    np.testing.assert_allclose(op(y), y * jnp.array([1.0, -1.0, 1.0]), atol=1e-6)
    np.testing.assert_allclose(op(y), f.normalize(point_cloud_op(mirror)(jnp.asarray(pts))), atol=1e-6)


def test_callable_symmetry_is_accepted():
    jm = _joint_map()
    x = _data()
    a = fit_normalizer({"qpos": x}, lambda d: {k: jm(v) for k, v in d.items()})
    b = fit_normalizer({"qpos": x}, {"qpos": jm})
    np.testing.assert_array_equal(a.fields["qpos"].scale, b.fields["qpos"].scale)


def test_degenerate_channel_gets_unit_scale_and_maps_to_zero():
    x = _data()
    x[:, 2] = 3.0
    x[:, 5] = 3.0  # joint 2 <-> 5, both constant: still mirror-consistent
    jm = _joint_map()
    norm = fit_normalizer({"qpos": x}, {"qpos": jm}).fields["qpos"]
    assert float(norm.scale[2]) == 1.0 and float(norm.scale[5]) == 1.0
    y = norm.normalize(jnp.asarray(x))
    assert np.all(np.isfinite(y))
    np.testing.assert_allclose(y[:, 2], 0.0, atol=1e-6)
    mirror_in_normalized_space(jm.perm, jm.signs, jm.offsets, norm)  # does not raise


def test_bad_data_errors():
    with pytest.raises(ValueError, match="NaN or inf"):
        fit_normalizer({"qpos": np.array([[0.0, np.nan]])})
    with pytest.raises(ValueError, match="empty"):
        fit_normalizer({"qpos": np.zeros((0, 3))})
    with pytest.raises(ValueError, match="mode must be"):
        fit_normalizer({"qpos": np.ones((3, 2))}, mode="robust")
    with pytest.raises(ValueError, match="channels"):
        mirror_in_normalized_space([0, 1], [1, 1], [0, 0], FieldNormalizer(jnp.ones(3), jnp.zeros(3)))


def test_normalizer_is_a_pytree_and_round_trips_state_dict():
    norm = fit_normalizer({"qpos": _data(), "action": _data(seed=3)}, {"qpos": _joint_map(), "action": _joint_map()})
    assert len(jax.tree.leaves(norm)) == 4
    out = jax.jit(lambda n, b: n.normalize(b))(norm, {"qpos": jnp.ones((2, 7))})
    assert out["qpos"].shape == (2, 7)
    back = Normalizer.from_state_dict(norm.to_state_dict())
    for k in norm.fields:
        np.testing.assert_array_equal(back.fields[k].scale, norm.fields[k].scale)
        np.testing.assert_array_equal(back.fields[k].offset, norm.fields[k].offset)


def test_identity_channels_are_unscaled_and_stay_mirror_consistent():
    """Channels named in ``identity`` keep their raw values (scale 1, offset 0) however
    narrow their range; the others are fitted as before, and ``S`` stays a signed
    permutation in normalised space when the mask is mapped to itself by ``S``."""
    jm = _joint_map()
    x = _data()
    x[:, 0] = 0.7 + 1e-3 * x[:, 0]  # a narrow channel (half-range 1e-3 would give scale ~1e3)
    x[:, 3] = 0.7 + 1e-3 * x[:, 3]
    keep = np.zeros(7, bool)
    keep[[0, 3]] = True  # channel 0 <-> 3 under S, sign +1, offset 0
    plain = fit_normalizer({"qpos": x}, {"qpos": jm}).fields["qpos"]
    norm = fit_normalizer({"qpos": x}, {"qpos": jm}, identity={"qpos": keep}).fields["qpos"]
    assert float(plain.scale[0]) > 100
    np.testing.assert_array_equal(np.asarray(norm.scale)[[0, 3]], [1.0, 1.0])
    np.testing.assert_array_equal(np.asarray(norm.offset)[[0, 3]], [0.0, 0.0])
    np.testing.assert_array_equal(np.asarray(norm.scale)[~keep], np.asarray(plain.scale)[~keep])
    np.testing.assert_array_equal(np.asarray(norm.offset)[~keep], np.asarray(plain.offset)[~keep])
    perm, signs = mirror_in_normalized_space(jm.perm, jm.signs, jm.offsets, norm)
    np.testing.assert_array_equal(perm, PERM)
    s_n = signed_permutation(perm, signs)
    np.testing.assert_allclose(norm.normalize(jm(jnp.asarray(x))), s_n(norm.normalize(jnp.asarray(x))), atol=2e-5)


def test_identity_mask_errors():
    x = _data()
    with pytest.raises(ValueError, match=r"identity\['qpos'\] must be a bool mask of shape \(7,\)"):
        fit_normalizer({"qpos": x}, identity={"qpos": np.ones(6, bool)})
    with pytest.raises(ValueError, match="bool mask"):
        fit_normalizer({"qpos": x}, identity={"qpos": np.ones(7)})
    with pytest.raises(ValueError, match=r"identity names fields \['ee'\]"):
        fit_normalizer({"qpos": x}, identity={"ee": np.ones(7, bool)})
