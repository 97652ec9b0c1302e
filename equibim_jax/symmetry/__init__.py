"""Mirror symmetry ``S``: pure operators per modality, and ``S`` derived from an MJCF.

Quick use::

    from equibim_jax.symmetry import Mirror, derive_symmetry, Symmetry, image_op, point_cloud_op
    mirror = Mirror.from_axis("y")                      # the sagittal plane y = 0
    ms = derive_symmetry(model, mirror)                 # joint maps from the MJCF, verified
    S = Symmetry({"qpos": ms.qpos, "image": image_op("NHWC"), "point_cloud": point_cloud_op(mirror)})
    mirrored = S(batch)                                 # any leading batch dims
"""

from equibim_jax.symmetry.derive import (
    DEFAULT_TOL,
    ModelSymmetry,
    SymmetryError,
    derive_symmetry,
    verify_symmetry,
)
from equibim_jax.symmetry.mirror import (
    Mirror,
    axis_reflection,
    flip_image,
    matrix_to_rot6d,
    quat_reflection_matrix,
    reflect_axial,
    reflect_point_cloud,
    reflect_point_cloud_camera,
    reflect_points,
    reflect_polar,
    reflect_pose_6d,
    reflect_pose_quat,
    reflect_quat,
    reflect_rot6d,
    reflect_rotmat,
    rot6d_to_matrix,
)
from equibim_jax.symmetry.structure import (
    JointMap,
    Symmetry,
    arm_swap_pose_op,
    identity_op,
    image_op,
    point_cloud_op,
)

__all__ = [
    "DEFAULT_TOL", "JointMap", "Mirror", "ModelSymmetry", "Symmetry", "SymmetryError",
    "arm_swap_pose_op", "axis_reflection", "derive_symmetry", "flip_image", "identity_op",
    "image_op", "matrix_to_rot6d", "point_cloud_op", "quat_reflection_matrix", "reflect_axial",
    "reflect_point_cloud", "reflect_point_cloud_camera", "reflect_points", "reflect_polar",
    "reflect_pose_6d", "reflect_pose_quat", "reflect_quat", "reflect_rot6d", "reflect_rotmat",
    "rot6d_to_matrix", "verify_symmetry",
]
