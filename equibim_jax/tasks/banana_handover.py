"""``banana_handover``: the arm on the banana's side picks a banana up from the table and
hands it over to the other arm above the mirror plane (robot B).

Scene
-----
* **Banana**: one free body (joint ``banana``) made of three capsules of radius
  ``radius`` (1.5 cm: 3 cm thick) lying in the body's x-y plane: a straight middle
  capsule along the body's y axis (``mid_half`` either side of the body origin) and two
  end capsules of length ``end_length`` bent by ``bend`` towards the body's +x, so the
  whole banana is about 17 cm long and curves towards +x. Total mass ``mass`` (100 g),
  split by capsule length. The shape is its own mirror image about the body's x-z
  plane, so the mirror maps the banana at yaw ``psi`` to the banana at yaw ``-psi``
  (body local reflection ``diag(1, -1, 1)``). Collisions: the middle capsule (the only
  part the grippers squeeze) is an ordinary object (:func:`robots.object_collision`:
  table, jaws, palms); the end capsules touch the table and the jaws only
  (``contype 0``, ``conaffinity TABLE | PAD``), which saves their palm pairs (a palm sits
  3 cm behind the jaws' centre, along the approach, and does not reach them from a grasp
  on the middle capsule).

Initial state
-------------
``s = +1`` (banana on the left, y > 0) or ``-1`` (:meth:`ShiftScene.draw_side`). The
banana lies flat on the table (body origin at height ``radius``) at ``x ~ U(x_range)``,
``y = s U(y_range)``, yaw ``s u`` with ``u ~ U(yaw_range)`` (:meth:`ShiftScene.draw_yaw`:
``-s u`` with ``mirrored_orientation``), as the quaternion ``s (cos(yaw/2), 0, 0,
sin(yaw/2))`` (its sign follows the side, so that ``env.mirror_state``, which maps
``(w, 0, 0, z)`` to ``(-w, 0, 0, z)``, maps a start exactly onto the start drawn with the
other side). At yaw 0 the banana lies along the world y axis
with its ends curving forward (+x). ``y_range[0]`` keeps the whole banana on its side of
the mirror plane at any yaw (checked). Arms at home. ``init`` splits its key into five
subkeys (side, x, |y|, yaw, perturbed) whatever the options, so an option changes only
what it names. ``info``: ``side`` (s), ``yaw`` and ``perturbed`` (see
:mod:`equibim_jax.tasks._shifts`); the mirror flips ``side`` and negates ``yaw``.

The shift the paper applies to this task is ``mirrored_orientation`` (train on one
orientation, test on the mirrored one).

Success (from the simulated state, every control step, latched by the env)
-------------------------------------------------------------------------
The giver is the arm on the start side ``info["side"]``, the receiver the other arm.
All of: both of the receiver's jaws touch the banana; neither of the giver's jaws does;
the banana's lowest point (from its capsules' poses) is more than ``min_height`` (3 cm)
above the table, and it does not touch the table. Two geoms *touch* when some contact of
theirs in MJX's contact list (``data._impl.contact``) has a distance below ``touch_tol``
(1 mm); after a step that list is the one of the control step's last physics substep.
The metrics hold the named terms: ``receiver_jaw_dist`` (the larger of the receiver's two
jaw-banana distances), ``giver_jaw_dist`` (the smaller of the giver's), ``table_dist``,
``banana_height`` (the lowest point), and the checks ``receiver_holds``, ``giver_free``,
``lifted`` (distances are capped at 1000 m when no contact of the pair is listed).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx

from equibim_jax.sim import robots
from equibim_jax.sim.env import Env
from equibim_jax.tasks import TaskEntry
from equibim_jax.tasks._shifts import ShiftScene

__all__ = ["BananaHandover", "TASK"]

_CAPSULE = mujoco.mjtGeom.mjGEOM_CAPSULE
_PARTS = ("banana_mid", "banana_end_a", "banana_end_b")


@dataclasses.dataclass(frozen=True)
class BananaHandover(ShiftScene):
    """The ``banana_handover`` task as an env scene (robot B).

    Attributes (besides the shift options of :class:`ShiftScene`):
      x_range, y_range: banana origin x and |y| ranges (m).
      yaw_range: range of ``u`` in the yaw ``s u`` (rad).
      radius: capsule radius (m); the banana is ``2 radius`` thick.
      mid_half: half length of the straight middle capsule's segment (m).
      end_length: segment length of each end capsule (m).
      bend: angle between the end capsules and the middle one (rad), towards body +x.
      mass: total mass (kg).
      min_height: the banana's lowest point must be above this height (m) for success.
      touch_tol: a contact with a distance below this counts as a touch (m).
    """

    x_range: tuple[float, float] = (0.13, 0.19)
    y_range: tuple[float, float] = (0.11, 0.16)
    yaw_range: tuple[float, float] = (0.2, 0.6)
    radius: float = 0.015
    mid_half: float = 0.045
    end_length: float = 0.03
    bend: float = 0.5
    mass: float = 0.1
    min_height: float = 0.03
    touch_tol: float = 0.001
    name = "banana_handover"
    main_object = "banana"
    # In front of the arms' bases (x > 0.05), up to above the handover height.
    point_cloud_crop = ((0.05, -0.35, 0.002), (0.4, 0.35, 0.3))

    def __post_init__(self):
        super().__post_init__()
        for f in ("x_range", "y_range", "yaw_range"):
            r = getattr(self, f)
            if len(r) != 2 or not r[0] <= r[1]:
                raise ValueError(f"{self.name}: {f} must be (low, high) with low <= high, got {r}")
        for f in ("radius", "mid_half", "end_length", "mass", "min_height"):
            if not getattr(self, f) > 0:
                raise ValueError(f"{self.name}: {f} must be positive, got {getattr(self, f)}")
        if not 0.0 <= self.bend < math.pi / 2:
            raise ValueError(f"{self.name}: bend must be in [0, pi/2) rad, got {self.bend}")
        if self.touch_tol < 0:
            raise ValueError(f"{self.name}: touch_tol must be >= 0, got {self.touch_tol}")
        if self.y_range[0] <= self.footprint_radius():
            raise ValueError(
                f"{self.name}: y_range[0] = {self.y_range[0]} must exceed the banana's footprint "
                f"radius {self.footprint_radius():.4f} m so that it lies wholly on its side of "
                f"the mirror plane at any yaw")

    # ------------------------------------------------------------------ geometry
    def segments(self) -> tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...]:
        """Body-frame segments (from, to) of the three capsules: middle, end a (+y), end b (-y)."""
        a, l, b = self.mid_half, self.end_length, self.bend
        tip = (l * math.sin(b), a + l * math.cos(b), 0.0)
        return (
            ((0.0, -a, 0.0), (0.0, a, 0.0)),
            ((0.0, a, 0.0), tip),
            ((0.0, -a, 0.0), (tip[0], -tip[1], 0.0)),
        )

    def footprint_radius(self) -> float:
        """Largest distance (m) of the banana's surface from the body origin in the x-y plane."""
        ends = [p for seg in self.segments() for p in seg]
        return max(math.hypot(p[0], p[1]) for p in ends) + self.radius

    def length(self) -> float:
        """Chord length of the banana, end to end (m)."""
        return 2 * self.segments()[1][1][1] + 2 * self.radius

    # ------------------------------------------------------------------ model
    def build(self, spec: mujoco.MjSpec, info: robots.RobotInfo) -> None:
        """Add the free banana (three capsules) to robot B's spec."""
        if info.name != "robot_b":
            raise ValueError(f"{self.name} is built for robot_b, got {info.name!r}")
        # Reference pose on the mirror plane (qpos0 mirror-symmetric); init moves it.
        body = spec.worldbody.add_body(name="banana", pos=[0.3, 0.0, info.table_height + self.radius])
        body.add_freejoint(name="banana")
        lengths = [2 * self.mid_half, self.end_length, self.end_length]
        total = sum(lengths)
        mid_coll = robots.object_collision()
        end_coll = {"contype": 0, "conaffinity": robots.TABLE_BIT | robots.PAD_BIT}
        for name, (p, q), n, coll in zip(_PARTS, self.segments(), lengths,
                                         (mid_coll, end_coll, end_coll)):
            body.add_geom(
                name=name, type=_CAPSULE, size=[self.radius, 0.0, 0.0], fromto=[*p, *q],
                mass=self.mass * n / total, rgba=[0.95, 0.85, 0.2, 1.0], condim=4,
                friction=[1.0, 0.005, 0.0001], **coll,
            )

    # ------------------------------------------------------------------ ids
    @staticmethod
    def _ids(env: Env) -> dict:
        m = env.mj_model
        pads = env.info.gripper_pads
        return {
            "body": m.body("banana").id,
            "qadr": int(m.jnt_qposadr[m.joint("banana").id]),
            "geoms": tuple(m.geom(n).id for n in _PARTS),
            "pads": tuple(tuple(m.geom(p).id for p in side) for side in pads),
            "table": m.geom("table").id,
        }

    def pose_from_qpos(self, qpos: jax.Array, env: Env) -> tuple[jax.Array, jax.Array]:
        """Banana origin [3] and quaternion [4] (w, x, y, z) read from ``qpos`` [nq]."""
        a = self._ids(env)["qadr"]
        return qpos[a : a + 3], qpos[a + 3 : a + 7]

    def placed_qpos(self, qpos: jax.Array, env: Env, xyz, yaw=0.0, quat=None, sign=1.0) -> jax.Array:
        """``qpos`` [nq] with the banana's free joint at ``xyz`` [3] and yaw ``yaw`` (about
        z) as the quaternion ``sign * (cos(yaw / 2), 0, 0, sin(yaw / 2))``, or the
        quaternion ``quat`` [4] if given (for building states by hand)."""
        a = self._ids(env)["qadr"]
        if quat is None:
            quat = self.signed_yaw_quat(jnp.asarray(yaw, qpos.dtype), jnp.asarray(sign, qpos.dtype))
        pose = jnp.concatenate([jnp.asarray(xyz, qpos.dtype), jnp.asarray(quat, qpos.dtype)])
        return qpos.at[a : a + 7].set(pose)

    # ------------------------------------------------------------------ episode
    def init(self, key: jax.Array, env: Env) -> tuple[jax.Array, dict]:
        """Home arms, banana flat on side ``s``.

        Returns qpos [nq] and ``{"side": [] float32, "yaw": [] float32, "perturbed": [] bool}``.
        """
        k_side, k_x, k_y, k_yaw, k_pert = jax.random.split(key, 5)
        s = self.draw_side(k_side)
        x = self.uniform(k_x, self.x_range)
        y = s * self.uniform_abs(k_y, self.y_range, self.footprint_radius() + 0.005)
        yaw = self.draw_yaw(k_yaw, s, self.yaw_range)
        perturbed = self.draw_perturbed(k_pert, s)
        z = jnp.asarray(env.info.table_height + self.radius, jnp.float32)
        # The quaternion's sign follows the side: the mirror maps (w, 0, 0, z) to
        # (-w, 0, 0, z) (the same rotation as yaw -> -yaw), so that a start's mirror image
        # is, coordinate by coordinate, the start drawn on the other side.
        qpos = self.placed_qpos(jnp.asarray(env.home_qpos), env, jnp.stack([x, y, z]), yaw, sign=s)
        return qpos, {"side": s.astype(jnp.float32), "yaw": yaw.astype(jnp.float32),
                      "perturbed": perturbed}

    # ------------------------------------------------------------------ success
    def lowest_point(self, data: mjx.Data, env: Env) -> jax.Array:
        """[] height (m) of the banana's lowest surface point (from its capsules' poses)."""
        ids = jnp.asarray(self._ids(env)["geoms"])
        pos = data.geom_xpos[ids]  # [3, 3]
        axis_z = data.geom_xmat[ids].reshape(-1, 3, 3)[:, 2, 2]  # z of each capsule's axis
        half = jnp.asarray(env.mj_model.geom_size[self._ids(env)["geoms"], 1], pos.dtype)
        return jnp.min(pos[:, 2] - jnp.abs(axis_z) * half) - self.radius

    def _min_dist(self, data: mjx.Data, a: tuple[int, ...], b: tuple[int, ...]) -> jax.Array:
        """[] smallest contact distance between any geom of ``a`` and any of ``b`` in MJX's
        contact list (a large value when there is none)."""
        c = data._impl.contact
        g1, g2 = c.geom[:, 0], c.geom[:, 1]
        in_a = lambda g: jnp.isin(g, jnp.asarray(a))
        in_b = lambda g: jnp.isin(g, jnp.asarray(b))
        pair = (in_a(g1) & in_b(g2)) | (in_b(g1) & in_a(g2))
        big = jnp.asarray(1e10, c.dist.dtype)
        return jnp.min(jnp.where(pair, c.dist, big), initial=big)

    def terms(self, data: mjx.Data, info: dict, env: Env) -> dict[str, jax.Array]:
        """Named success terms: per-jaw contact distances (m), the lowest point (m) and
        [] bool checks."""
        ids = self._ids(env)
        banana = ids["geoms"]
        # per jaw: [2 sides, 2 jaws] smallest contact distance to the banana
        d = jnp.stack([jnp.stack([self._min_dist(data, (p,), banana) for p in side])
                       for side in ids["pads"]])
        left_gives = info["side"] > 0
        giver = jnp.where(left_gives, d[0], d[1])
        receiver = jnp.where(left_gives, d[1], d[0])
        table = self._min_dist(data, (ids["table"],), banana)
        low = self.lowest_point(data, env) - env.info.table_height
        tol = self.touch_tol
        return {
            "receiver_jaw_dist": jnp.max(receiver),
            "giver_jaw_dist": jnp.min(giver),
            "table_dist": table,
            "banana_height": low,
            "receiver_holds": jnp.all(receiver < tol),
            "giver_free": jnp.all(giver >= tol),
            "lifted": (low > self.min_height) & (table >= tol),
        }

    def evaluate(self, data: mjx.Data, info: dict, env: Env) -> tuple[jax.Array, jax.Array, dict]:
        """Sparse reward (1 on success), success [] bool, and the named terms as metrics."""
        t = self.terms(data, info, env)
        success = t["receiver_holds"] & t["giver_free"] & t["lifted"]
        metrics = {k: jnp.minimum(v.astype(jnp.float32), 1e3) for k, v in t.items()}
        return success.astype(jnp.float32), success, metrics


TASK = TaskEntry(
    name="banana_handover",
    scene=BananaHandover,
    robot="robot_b",
    step_limit=600,
    expert="equibim_jax.experts.banana_handover:make_expert",
    env_defaults={"obs": ("qpos", "point_cloud"), "action": "joint", "n_points": 64},
)
