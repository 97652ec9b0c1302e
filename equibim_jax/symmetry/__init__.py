"""Mirror symmetry ``S``: pure operators per modality, and ``S`` derived from an MJCF.

Quick use::

    from equibim_jax.symmetry import Mirror, derive_symmetry, Symmetry, image_op, point_cloud_op
    mirror = Mirror.from_axis("y")                      # the sagittal plane y = 0
    ms = derive_symmetry(model, mirror)                 # joint maps from the MJCF, verified
    print(ms.report())                                  # residuals and the dynamic report
    save_mirror_map(ms, "map.json")                     # portable JSON; load_mirror_map(path, model)
    S = Symmetry({"qpos": ms.qpos, "image": image_op("NHWC"), "point_cloud": point_cloud_op(mirror)})
    mirrored = S(batch)                                 # any leading batch dims
"""

from equibim_jax.symmetry.derive import (
    APPROX_TOL,
    DEFAULT_TOL,
    DYN_RTOL,
    Asymmetry,
    DynamicsReport,
    ModelSymmetry,
    SymmetryError,
    SymmetryWarning,
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
from equibim_jax.symmetry.mirror_map import FORMAT_VERSION, check_mirror_map, load_mirror_map, save_mirror_map
from equibim_jax.symmetry.structure import (
    JointMap,
    Symmetry,
    arm_swap_pose_op,
    camera_pair_op,
    identity_op,
    image_op,
    point_cloud_op,
)

__all__ = [
    "APPROX_TOL", "Asymmetry", "DEFAULT_TOL", "DYN_RTOL", "DynamicsReport", "FORMAT_VERSION", "JointMap",
    "Mirror", "ModelSymmetry", "Symmetry", "SymmetryError", "SymmetryWarning",
    "arm_swap_pose_op", "axis_reflection", "camera_pair_op", "check_mirror_map", "derive_symmetry", "flip_image",
    "identity_op", "image_op", "load_mirror_map", "matrix_to_rot6d", "point_cloud_op", "quat_reflection_matrix", "reflect_axial",
    "reflect_point_cloud", "reflect_point_cloud_camera", "reflect_points", "reflect_polar",
    "reflect_pose_6d", "reflect_pose_quat", "reflect_quat", "reflect_rot6d", "reflect_rotmat",
    "rot6d_to_matrix", "save_mirror_map", "verify_symmetry",
]
