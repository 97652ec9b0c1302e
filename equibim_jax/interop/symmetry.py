"""The mirror ``S`` of an imported dataset, from a mirror map JSON (``equibim symmetry --out``).

An imported dataset has no simulated env to derive ``S`` from, so training takes it from
the robot's mirror map, checked against the dataset's features:

=============  ====================================  ==========================================
field          needs (from ``meta["interop"]``)      operator built from the map
=============  ====================================  ==========================================
qpos, joint    entry names: joint names of the map   ``JointMap``: each entry takes its mirror
action         (``qpos.names``) or one side of a     joint's value times the map's sign plus
               declared pair (gripper openings)      offset; a pair's entries swap unchanged
image, depth   one camera, its own mirror partner    horizontal flip (``image_op("HWC")``)
               with a ``horizontal`` flip
wrist_image    two cameras, mirror partners of each  swap the views, flip each
               other with ``horizontal`` flips       (``camera_pair_op("HWC")``)
point_cloud    (nothing)                             reflect points in the map's plane
ee, ee action  size 2 * (3 + R + 1), R = 6 or 4      mirror each arm's pose with the
                                                     end-effector site's local reflection, swap
=============  ====================================  ==========================================

Any mismatch (a name the map does not know, a size that differs from the names, a camera
missing from the map or not paired as needed, a field with no operator) is a
:class:`~equibim_jax.interop.mapping.InteropError` that names it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from equibim_jax.interop.mapping import DEFAULT_PAIRS, InteropError, describe

__all__ = ["MapEnv", "map_env", "symmetry_ops_from_map", "read_map", "training_env"]


def read_map(path: str | os.PathLike) -> dict:
    """The JSON mirror map at ``path`` (written by ``equibim symmetry --out``)."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise InteropError(f"mirror map {path} does not exist (write one with `equibim symmetry --out {path}`)") \
            from None
    except json.JSONDecodeError as e:
        raise InteropError(f"mirror map {path} is not valid JSON: {e}") from None
    for k in ("qpos", "cameras", "mirror"):
        if not isinstance(d, dict) or k not in d:
            raise InteropError(f"mirror map {path} has no {k!r} entry (not written by `equibim symmetry --out`?)")
    return d


def _joint_op(field: str, names: list[str], size: int, m: Mapping, pairs, source: str):
    from equibim_jax.symmetry import JointMap

    if len(names) != size:
        raise InteropError(f"{source}: size mismatch: {field!r} has {size} entries but {len(names)} names")
    q = m["qpos"]
    qnames = list(q.get("names") or [])
    pos = {n: i for i, n in enumerate(names)}
    if len(pos) != len(names):
        raise InteropError(f"{source}: {field!r} has duplicate entry names {names}")
    partner = {}
    for a, b in pairs:
        partner[a], partner[b] = b, a
    perm, sign, off = [], [], []
    for n in names:
        if n in qnames:
            a = qnames.index(n)
            src = qnames[int(q["perm"][a])]
            if src not in pos:
                raise InteropError(f"{source}: {field!r} entry {n!r} mirrors to joint {src!r}, which the dataset's "
                                   f"{field!r} does not have")
            perm.append(pos[src])
            sign.append(float(q["sign"][a]))
            off.append(float(q["offset"][a]))
        elif n in partner:
            if partner[n] not in pos:
                raise InteropError(f"{source}: {field!r} entry {n!r} pairs with {partner[n]!r}, which is not an "
                                   f"entry of {field!r}")
            perm.append(pos[partner[n]])
            sign.append(1.0)
            off.append(0.0)
        else:
            raise InteropError(f"{source}: {field!r} entry {n!r} is neither a joint of the mirror map "
                               f"({qnames[:4]}... {len(qnames)} joints) nor in the declared pairs "
                               f"{[list(p) for p in pairs]}; name the entries after the map's joints (mapping "
                               f"'names') or declare the pair")
    return JointMap(np.array(perm), np.array(sign), np.array(off), tuple(names))


def _cameras(m: Mapping) -> dict:
    return {c["camera"]: c for c in m["cameras"]}


def _image_op(field: str, cams: list[str] | None, m: Mapping, source: str):
    from equibim_jax.symmetry import camera_pair_op, image_op

    known = _cameras(m)
    if not cams:
        raise InteropError(f"{source}: the camera of {field!r} is unknown; declare it in the mapping's 'cameras' "
                           f"(the map's cameras: {sorted(known)})")
    missing = [c for c in cams if c not in known]
    if missing:
        raise InteropError(f"{source}: camera(s) {missing} of {field!r} are not in the mirror map's camera list "
                           f"{sorted(known)}")
    if len(cams) == 1:
        c = known[cams[0]]
        if c.get("mirror") != cams[0] or c.get("flip") != "horizontal":
            raise InteropError(f"{source}: camera {cams[0]!r} of {field!r} is not its own mirror image with a "
                               f"horizontal flip (map: mirror {c.get('mirror')!r}, flip {c.get('flip')!r}); a "
                               f"single view needs a camera on the mirror plane")
        if field == "depth":
            import jax.numpy as jnp

            return lambda d: jnp.flip(d, axis=-1)
        return image_op("HWC")
    if len(cams) == 2:
        a, b = (known[c] for c in cams)
        if a.get("mirror") != cams[1] or b.get("mirror") != cams[0] or a.get("flip") != "horizontal" \
                or b.get("flip") != "horizontal":
            raise InteropError(f"{source}: cameras {cams} of {field!r} are not mirror partners with horizontal "
                               f"flips in the map ({cams[0]!r} -> {a.get('mirror')!r}, {cams[1]!r} -> "
                               f"{b.get('mirror')!r}; flips {a.get('flip')!r}, {b.get('flip')!r})")
        return camera_pair_op("HWC")
    raise InteropError(f"{source}: {field!r} has {len(cams)} camera views; one camera on the mirror plane or a "
                       f"mirror pair of two is supported")


def _ee_op(field: str, size: int, m: Mapping, source: str):
    from equibim_jax.symmetry import Mirror, arm_swap_pose_op

    rot = {20: "6d", 16: "quat"}.get(size)
    if rot is None:
        raise InteropError(f"{source}: size mismatch: end-effector field {field!r} has {size} entries; expected "
                           f"20 (2 x (3 + 6 + 1)) or 16 (2 x (3 + 4 + 1))")
    pairs = (m.get("ee_action") or {}).get("pairs") or []
    local = np.asarray(pairs[0]["local"]) if pairs else None
    mir = Mirror(tuple(m["mirror"]["normal"]), tuple(m["mirror"]["point"]))
    return arm_swap_pose_op(mir, None if local is None else np.round(local, 6), rot, extra=1)


def symmetry_ops_from_map(m: Mapping, shapes: Mapping[str, tuple], desc: Mapping, fields, action_key: str = "action",
                          action_space: str = "joint", source: str = "dataset") -> dict:
    """``S`` in raw units as ``{field: op}`` for observation ``fields`` and the action.

    Args:
      m: the mirror map dict (:func:`read_map`).
      shapes: ``{field: per-frame shape}`` of the dataset (``"action"`` included).
      desc: :func:`~equibim_jax.interop.mapping.describe` of the dataset (names, cameras, pairs).
      fields: observation fields the policy reads.
      action_key: key of the action in the returned dict.
      action_space: ``"joint"`` or ``"ee"``: the layout of the dataset's action.
    Raises:
      InteropError: a field, name, size or camera that does not fit the map.
    """
    from equibim_jax.symmetry import Mirror, point_cloud_op

    names, cams = desc.get("names") or {}, desc.get("cameras") or {}
    pairs = [tuple(p) for p in desc.get("pairs", DEFAULT_PAIRS)]

    def op_for(field: str, kind: str):
        if field not in shapes:
            raise InteropError(f"{source}: the policy reads {field!r}, which the dataset does not have "
                               f"(it has {sorted(k for k in shapes if k != 'action')})")
        shape = tuple(shapes[field])
        if kind == "joint":
            if field not in names:
                raise InteropError(f"{source}: {field!r} has no entry names to match against the mirror map; give "
                                   f"them in the import mapping's 'names'")
            return _joint_op(field, list(names[field]), shape[-1], m, pairs, source)
        if kind in ("image", "depth", "wrist_image"):
            return _image_op(kind, cams.get(field), m, source)
        if kind == "point_cloud":
            if shape[-1] < 3:
                raise InteropError(f"{source}: point_cloud has per-point size {shape[-1]}; expected >= 3 (xyz)")
            return point_cloud_op(Mirror(tuple(m["mirror"]["normal"]), tuple(m["mirror"]["point"])))
        if kind == "ee":
            return _ee_op(field, shape[-1], m, source)
        raise InteropError(f"{source}: no mirror operator for field {field!r}; fields with one: qpos, ee, image, "
                           f"depth, wrist_image, point_cloud")

    ops = {f: op_for(f, "joint" if f == "qpos" else f) for f in fields}
    ops[action_key] = op_for("action", "joint" if action_space == "joint" else "ee")
    return ops


class MapEnv:
    """What training needs from an env, for a dataset without one: ``task``,
    ``task_options`` (recorded in the run's config) and :meth:`symmetry_ops` from a map."""

    def __init__(self, mirror_map: Mapping, map_path: str, demos, source: str = "dataset"):
        self.map = dict(mirror_map)
        self.map_path = str(map_path)
        self.source = source
        self.desc = describe(demos)
        self.shapes = {k: tuple(v.shape[2:]) for k, v in demos.obs.items()}
        self.shapes["action"] = tuple(demos.action.shape[2:])
        meta = dict(demos.meta)
        self.action_space = meta.get("action_space", (meta.get("task_options") or {}).get("action", "joint"))
        rec = meta.get("interop") or {}
        self.task = "imported"
        self.task_options: dict[str, Any] = {"source": rec.get("source"), "format": rec.get("format"),
                                             "symmetry": self.map_path}
        self.check()

    def check(self) -> None:
        """Check the action and every field whose names or cameras the dataset declares (or
        that needs nothing declared: point_cloud, ee) against the map; a field without
        declared names or cameras is checked when a policy reads it (:meth:`symmetry_ops`)."""
        declared = set(self.desc.get("names") or {}) | set(self.desc.get("cameras") or {}) | {"point_cloud", "ee"}
        fields = [f for f in self.shapes
                  if f in ("qpos", "ee", "image", "depth", "wrist_image", "point_cloud") and f in declared]
        symmetry_ops_from_map(self.map, self.shapes, self.desc, fields, "action", self.action_space, self.source)

    def symmetry_ops(self, fields: tuple[str, ...], action_key: str = "action") -> dict:
        """``S`` in raw units as ``{field: op}`` (as ``Env.symmetry_ops``)."""
        return symmetry_ops_from_map(self.map, self.shapes, self.desc, tuple(fields), action_key,
                                     self.action_space, self.source)


def map_env(data, map_path: str | os.PathLike) -> MapEnv:
    """A :class:`MapEnv` for dataset ``data`` (a path or Demos) and the mirror map at ``map_path``."""
    from equibim_jax.data.dataset import Demos, load

    demos = data if isinstance(data, Demos) else load(data)
    src = str(data) if not isinstance(data, Demos) else "dataset"
    return MapEnv(read_map(map_path), str(map_path), demos, source=f"{src} with mirror map {map_path}")


def training_env(data, symmetry: str | os.PathLike | None) -> MapEnv | None:
    """The env ``equibim train`` passes to training: a :class:`MapEnv` when a mirror map is
    given, else None (training rebuilds the simulated env from the dataset's metadata).

    Raises:
      InteropError: no map for a dataset that has no simulated env (imported from another
        format without an equibim task), or a map that does not fit the dataset.
    """
    if symmetry is not None:
        return map_env(data, symmetry)
    from equibim_jax.data.dataset import Demos

    if isinstance(data, Demos):
        meta = dict(data.meta)
    else:  # the metadata only; training loads (and validates) the arrays
        import zarr

        try:
            meta = dict(zarr.open_group(str(data), mode="r").attrs.get("equibim", {}))
        except Exception:  # not readable here: training's own load names the problem
            return None
    if "interop" in meta and "task" not in meta:
        raise InteropError(f"{data} was imported from {meta['interop'].get('format')} and has no simulated env to "
                           f"derive the mirror S from; pass --symmetry map.json (write one with "
                           f"`equibim symmetry --robot NAME --out map.json`, or --mjcf for your robot)")
    return None
