"""A portable mirror map: :class:`ModelSymmetry` as JSON, and back.

``save_mirror_map(sym, path)`` writes everything ``S`` needs to act on the data of one
model, by index and by name, so that code without the derivation (or without MuJoCo) can
apply it:

- ``qpos``, ``qvel``, ``ctrl``: ``{"perm", "sign", "offset", "names"}``, meaning
  ``x'[i] = sign[i] * x[perm[i]] + offset[i]``;
- ``residual_m`` (the largest forward-kinematics residual), the residual of every body and
  site, the mirror-consistent joint and control ranges, and the dynamic report;
- body, joint, geom, site and camera pairs (with each camera's image flip), and the
  end-effector action map (site pairs with their local reflections ``L``).

``load_mirror_map(path, model)`` rebuilds the :class:`ModelSymmetry` and, given the model it
is used with, checks its sizes and names and re-verifies the residual.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path

import mujoco
import numpy as np

from equibim_jax._io import atomic_write_json
from equibim_jax.symmetry.derive import (
    DynamicsReport,
    ModelSymmetry,
    SymmetryError,
    _check_sizes,
    _residual_lines,
    _verify,
)
from equibim_jax.symmetry.mirror import Mirror
from equibim_jax.symmetry.structure import JointMap

FORMAT_VERSION = 1

def _num(x):
    x = float(x)
    return x if math.isfinite(x) else None


def _range(r):
    if r is None or not np.all(np.isfinite(r)):
        return None
    return [float(r[0]), float(r[1])]


def _mat(a) -> list:
    return np.round(np.asarray(a, dtype=np.float64), 12).tolist()


def _jm(jm: JointMap) -> dict:
    return {"perm": jm.perm.tolist(), "sign": jm.signs.tolist(), "offset": jm.offsets.tolist(),
            "names": list(jm.names) if jm.names is not None else None}


def mirror_map_dict(sym: ModelSymmetry, ee_sites=None) -> dict:
    """The JSON-ready dict of ``sym`` (see the module docstring). ``ee_sites``: optional
    names of the end-effector sites (one per arm) for the ``ee_action`` entry."""
    nbody, njnt = len(sym.bodies), len(sym.joints)
    site_names = sym.site_names or tuple(f"#{i}" for i in range(len(sym.sites)))
    cam_names = sym.camera_names or tuple(f"#{i}" for i in range(len(sym.cameras)))
    geom_names = sym.geom_names or tuple(f"#{i}" for i in range(len(sym.geoms)))
    act_names = sym.ctrl.names or tuple(f"#{i}" for i in range(sym.ctrl.size))
    body_res = sym.body_residual if sym.body_residual is not None else np.full(nbody, np.nan)
    site_res = sym.site_residual if sym.site_residual is not None else np.full(len(sym.sites), np.nan)
    jr = sym.joint_ranges if sym.joint_ranges is not None else np.full((njnt, 2), np.nan)
    cr = sym.ctrl_ranges if sym.ctrl_ranges is not None else np.full((sym.ctrl.size, 2), np.nan)
    flips = sym.camera_flip
    cam_local = sym.camera_local if sym.camera_local is not None else np.tile(np.eye(3), (len(sym.cameras), 1, 1))
    sites = [
        {"site": site_names[s], "mirror": site_names[sym.sites[s]], "mirror_index": int(sym.sites[s]),
         "residual_m": _num(site_res[s]), "local": _mat(sym.site_local[s])}
        for s in range(len(sym.sites))
    ]
    if ee_sites is not None:
        missing = [n for n in ee_sites if n not in site_names]
        if missing:
            raise ValueError(f"ee_sites {missing} are not sites of the model ({list(site_names)})")
        ee_pairs = [sites[site_names.index(n)] for n in ee_sites]
    else:
        ee_pairs = sites
    m = sym.mirror
    return {
        "format_version": FORMAT_VERSION,
        "mirror": {"normal": list(m.normal), "point": list(m.point), "matrix": _mat(m.matrix)},
        "approximate": bool(sym.approximate),
        "dynamics_mode": sym.dynamics_mode,
        "tol_m": float(sym.tol),
        "model": {"nq": sym.qpos.size, "nv": sym.qvel.size, "nu": sym.ctrl.size, "nbody": nbody,
                  "njnt": njnt, "ngeom": len(sym.geoms), "nsite": len(sym.sites), "ncam": len(sym.cameras)},
        "qpos": _jm(sym.qpos),
        "qvel": _jm(sym.qvel),
        "ctrl": _jm(sym.ctrl),
        "residual_m": _num(sym.residual),
        "bodies": [
            {"body": sym.body_names[b], "mirror": sym.body_names[sym.bodies[b]], "mirror_index": int(sym.bodies[b]),
             "residual_m": _num(body_res[b]), "local": _mat(sym.body_local[b])}
            for b in range(nbody)
        ],
        "joints": [
            {"joint": sym.joint_names[j], "mirror": sym.joint_names[sym.joints[j]],
             "mirror_index": int(sym.joints[j]), "sign": float(sym.joint_signs[j]), "range": _range(jr[j])}
            for j in range(njnt)
        ],
        "actuators": [
            {"actuator": act_names[a], "mirror": act_names[int(np.flatnonzero(sym.ctrl.perm == a)[0])],
             "range": _range(cr[a])}
            for a in range(sym.ctrl.size)
        ],
        "geoms": [
            {"geom": geom_names[g], "mirror": geom_names[sym.geoms[g]] if sym.geoms[g] >= 0 else None,
             "mirror_index": int(sym.geoms[g])}
            for g in range(len(sym.geoms))
        ],
        "sites": sites,
        "cameras": [
            {"camera": cam_names[c], "mirror": cam_names[sym.cameras[c]] if sym.cameras[c] >= 0 else None,
             "mirror_index": int(sym.cameras[c]), "flip": flips[c], "local": _mat(cam_local[c])}
            for c in range(len(sym.cameras))
        ],
        "ee_action": {
            "ee_sites": list(ee_sites) if ee_sites is not None else None,
            "position": "p' = point + M (p - point)",
            "rotation": "R' = M R L, L = the local reflection of the pose's site",
            "layout": "per arm [position, rotation, extras]; the mirrored pose of one arm's site becomes "
                      "the pose of its mirror site (arms swap), extras such as a gripper opening are kept",
            "pairs": ee_pairs,
        },
        "dynamics": sym.dynamics.to_dict(),
        "warnings": list(sym.warnings),
    }


def save_mirror_map(sym: ModelSymmetry, path: str | os.PathLike, ee_sites=None) -> None:
    """Write ``sym`` as JSON to ``path`` atomically (a crash never leaves half a file)."""
    atomic_write_json(path, mirror_map_dict(sym, ee_sites))


def _arr(x, default=np.nan) -> np.ndarray:
    return np.asarray([default if v is None else v for v in x], dtype=np.float64)


def mirror_map_from_dict(d: dict, source: str = "mirror map") -> ModelSymmetry:
    """Rebuild a :class:`ModelSymmetry` from :func:`mirror_map_dict`'s output."""
    version = d.get("format_version")
    if not isinstance(version, int) or version < 1 or version > FORMAT_VERSION:
        raise SymmetryError(f"{source}: format_version {version!r} is not supported (this library reads "
                            f"1..{FORMAT_VERSION})")
    try:
        def jm(k):
            e = d[k]
            return JointMap(np.asarray(e["perm"]), np.asarray(e["sign"]), np.asarray(e["offset"]),
                            tuple(e["names"]) if e.get("names") is not None else None)

        bodies, joints, sites, cams, geoms = d["bodies"], d["joints"], d["sites"], d["cameras"], d["geoms"]
        ranges = lambda rows: (np.asarray([r["range"] if r["range"] is not None else [np.nan, np.nan]
                                           for r in rows], dtype=np.float64).reshape(-1, 2))
        return ModelSymmetry(
            mirror=Mirror(tuple(d["mirror"]["normal"]), tuple(d["mirror"]["point"])),
            qpos=jm("qpos"), qvel=jm("qvel"), ctrl=jm("ctrl"),
            bodies=np.asarray([b["mirror_index"] for b in bodies], dtype=np.int64),
            joints=np.asarray([j["mirror_index"] for j in joints], dtype=np.int64),
            joint_signs=np.asarray([j["sign"] for j in joints], dtype=np.float64),
            geoms=np.asarray([g["mirror_index"] for g in geoms], dtype=np.int64),
            sites=np.asarray([s["mirror_index"] for s in sites], dtype=np.int64),
            cameras=np.asarray([c["mirror_index"] for c in cams], dtype=np.int64),
            body_local=np.asarray([b["local"] for b in bodies], dtype=np.float64).reshape(-1, 3, 3),
            site_local=np.asarray([s["local"] for s in sites], dtype=np.float64).reshape(-1, 3, 3),
            residual=float(d["residual_m"]) if d.get("residual_m") is not None else float("nan"),
            body_names=tuple(b["body"] for b in bodies),
            joint_names=tuple(j["joint"] for j in joints),
            dynamics=DynamicsReport.from_dict(d.get("dynamics", {})),
            body_residual=_arr([b.get("residual_m") for b in bodies]),
            site_residual=_arr([s.get("residual_m") for s in sites]),
            joint_ranges=ranges(joints),
            ctrl_ranges=ranges(d["actuators"]),
            camera_local=np.asarray([c["local"] for c in cams], dtype=np.float64).reshape(-1, 3, 3),
            approximate=bool(d.get("approximate", False)),
            tol=float(d["tol_m"]),
            dynamics_mode=str(d.get("dynamics_mode", "report")),
            warnings=tuple(d.get("warnings", ())),
            geom_names=tuple(g["geom"] for g in geoms),
            site_names=tuple(s["site"] for s in sites),
            camera_names=tuple(c["camera"] for c in cams),
        )
    except (KeyError, TypeError, ValueError) as e:
        if isinstance(e, SymmetryError):
            raise
        raise SymmetryError(f"{source}: malformed mirror map ({type(e).__name__}: {e})") from None


def check_mirror_map(sym: ModelSymmetry, model: mujoco.MjModel, n_verify: int = 64, seed: int = 0,
                     source: str = "mirror map") -> ModelSymmetry:
    """Check that ``sym`` belongs to ``model``: sizes, names of bodies, joints, actuators,
    sites and cameras, and the forward-kinematics residual re-verified at ``n_verify``
    random postures against the map's tolerance.

    Returns:
      ``sym`` with the re-verified residuals.
    Raises:
      SymmetryError: naming the first mismatch, or the bodies whose residual is too large.
    """
    try:
        _check_sizes(model, sym)
    except SymmetryError as e:
        raise SymmetryError(f"{source}: {e}") from None
    obj = mujoco.mjtObj
    lists = (
        ("body", obj.mjOBJ_BODY, sym.body_names, model.nbody),
        ("joint", obj.mjOBJ_JOINT, sym.joint_names, model.njnt),
        ("actuator", obj.mjOBJ_ACTUATOR, sym.ctrl.names, model.nu),
        ("site", obj.mjOBJ_SITE, sym.site_names, model.nsite),
        ("camera", obj.mjOBJ_CAMERA, sym.camera_names, model.ncam),
    )
    for kind, o, names, n in lists:
        if not names:
            continue
        for i in range(n):
            have = mujoco.mj_id2name(model, o, i) or ("world" if kind == "body" and i == 0 else f"#{i}")
            if have != names[i]:
                raise SymmetryError(f"{source}: {kind} {i} is '{names[i]}' in the mirror map but '{have}' in "
                                    f"this model; the map was derived for another model")
    res, per_body, per_site = _verify(model, sym, n_verify, seed)
    out = dataclasses.replace(sym, residual=res, body_residual=per_body, site_residual=per_site)
    if res > sym.tol:
        raise SymmetryError(
            f"{source}: re-verified forward-kinematics residual {res:.3g} m exceeds the map's tolerance "
            f"{sym.tol:g} m on this model:\n" + _residual_lines(out, sym.tol)
        )
    return out


def load_mirror_map(path: str | os.PathLike, model: mujoco.MjModel | str | os.PathLike | None = None,
                    n_verify: int = 64, seed: int = 0) -> ModelSymmetry:
    """Read a mirror map written by :func:`save_mirror_map`.

    Args:
      path: the JSON file.
      model: the model it will be used with (an ``MjModel`` or an MJCF path). When given,
        the map is checked against it (:func:`check_mirror_map`); when None, it is returned
        unchecked.
    Raises:
      SymmetryError: unsupported format, malformed file, or a map that does not fit ``model``.
    """
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise SymmetryError(f"{path}: not a JSON mirror map ({e})") from None
    sym = mirror_map_from_dict(d, str(path))
    if model is None:
        return sym
    if not isinstance(model, mujoco.MjModel):
        model = mujoco.MjModel.from_xml_path(str(model))
    return check_mirror_map(sym, model, n_verify=n_verify, seed=seed, source=str(path))
