"""Data: demos on disk, generation, training windows and the mirror-consistent normaliser."""

from equibim_jax.data.normalizer import (
    FieldNormalizer,
    Normalizer,
    conjugate_op,
    fit_normalizer,
    mirror_in_normalized_space,
    normalized_symmetry,
    signed_permutation,
)
from equibim_jax.data.windows import (
    OnDeviceDataset,
    frames_from_demos,
    make_dataset,
    sample_batch,
    window_indices,
)

__all__ = [
    "FieldNormalizer",
    "Normalizer",
    "OnDeviceDataset",
    "conjugate_op",
    "fit_normalizer",
    "frames_from_demos",
    "make_dataset",
    "mirror_in_normalized_space",
    "normalized_symmetry",
    "sample_batch",
    "signed_permutation",
    "window_indices",
]
