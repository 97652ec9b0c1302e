"""Data: demos, datasets and the mirror-consistent normaliser."""

from equibim_jax.data.normalizer import (
    FieldNormalizer,
    Normalizer,
    conjugate_op,
    fit_normalizer,
    mirror_in_normalized_space,
    normalized_symmetry,
    signed_permutation,
)

__all__ = [
    "FieldNormalizer",
    "Normalizer",
    "conjugate_op",
    "fit_normalizer",
    "mirror_in_normalized_space",
    "normalized_symmetry",
    "signed_permutation",
]
