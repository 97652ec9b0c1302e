"""Small hand-written MJCFs for the symmetry tests: side-by-side and facing arms."""

import mujoco

_ARM = """
<body name="{p}base" pos="{pos}" {rot}>
  <joint name="{p}yaw" type="hinge" axis="0 0 1" range="{yaw_range}"/>
  <geom type="capsule" fromto="0 0 0 0 0 0.1" size="0.02" contype="0" conaffinity="0"/>
  <body name="{p}link1" pos="0 0 0.1">
    <joint name="{p}pitch" type="hinge" axis="{pitch_axis}" range="-1 1"/>
    <geom type="capsule" fromto="0 0 0 {l1} 0 0" size="0.02" contype="0" conaffinity="0"/>
    <body name="{p}link2" pos="{l1} 0 0">
      <joint name="{p}roll" type="hinge" axis="1 0 0" range="{roll_range}"/>
      <geom type="box" size="0.05 0.02 0.02" pos="0.05 0 0"/>
      <body name="{p}hand" pos="0.1 0 0">
        <site name="{p}ee" pos="0.05 0 0"/>
        <body name="{p}finger_a">
          <inertial pos="0 0 0" mass="0.05" diaginertia="1e-5 1e-5 1e-5"/>
          <joint name="{p}finger_a" type="slide" axis="0 1 0" range="0 0.04"/>
          <geom type="box" size="0.01 0.005 0.02" pos="0.04 0 0"/>
        </body>
        <body name="{p}finger_b">
          <inertial pos="0 0 0" mass="0.05" diaginertia="1e-5 1e-5 1e-5"/>
          <joint name="{p}finger_b" type="slide" axis="0 -1 0" range="0 0.04"/>
          <geom type="box" size="0.01 0.005 0.02" pos="0.04 0 0"/>
        </body>
      </body>
    </body>
  </body>
</body>"""

_ACT = """
<position name="{p}yaw" joint="{p}yaw" kp="50" ctrlrange="{yaw_range}"/>
<position name="{p}pitch" joint="{p}pitch" kp="50" ctrlrange="-1 1"/>
<position name="{p}roll" joint="{p}roll" kp="20" ctrlrange="{roll_range}"/>
<position name="{p}finger_a" joint="{p}finger_a" kp="100" ctrlrange="0 0.04"/>
<position name="{p}finger_b" joint="{p}finger_b" kp="100" ctrlrange="0 0.04"/>"""


def _arm(p, pos, rot="", yaw_range="-1.5 2.5", roll_range="-2 0.5", l1="0.3", pitch_axis="0 1 0"):
    kw = dict(p=p, pos=pos, rot=rot, yaw_range=yaw_range, roll_range=roll_range, l1=l1, pitch_axis=pitch_axis)
    return _ARM.format(**kw), _ACT.format(**kw)


def _model(arms, extra="", table_pos="0.4 0 -0.02"):
    bodies = "".join(a[0] for a in arms)
    acts = "".join(a[1] for a in arms)
    return f"""
<mujoco>
  <compiler angle="radian"/>
  <asset><material name="m" rgba="0.8 0.8 0.8 1"/></asset>
  <worldbody>
    <geom name="table" type="box" size="0.5 0.6 0.02" pos="{table_pos}" material="m"/>
    <camera name="head" pos="0 0 1.2" xyaxes="0 -1 0 1 0 0"/>
    {bodies}
    {extra}
  </worldbody>
  <actuator>{acts}</actuator>
</mujoco>"""


CUP = """
<body name="cup" pos="0.4 0.15 0.05" quat="0.9238795 0 0 0.3826834">
  <freejoint name="cup"/>
  <geom type="capsule" size="0.03 0.03" mass="0.05"/>
  <geom type="box" size="0.005 0.02 0.01" pos="0 0.04 0" mass="0.01"/>
</body>"""


def side_by_side_xml(right_l1="0.3", right_pitch_axis="0 1 0", right_roll_range="-0.5 2",
                     with_cup=True) -> str:
    """Two arms at y = +-0.3 facing +x; mirror plane y = 0.

    The right arm is the mirror image: yaw (axial, along z) flips sign, so its range is the
    negated left range; roll (axial, along x) flips too; pitch (along y) keeps its sign.
    Finger a of the left gripper (slides +y) mirrors to finger b of the right (slides -y).
    """
    left = _arm("l_", "0 0.3 0")
    right = _arm("r_", "0 -0.3 0", yaw_range="-2.5 1.5", roll_range=right_roll_range,
                 l1=right_l1, pitch_axis=right_pitch_axis)
    return _model([left, right], CUP if with_cup else "")


def facing_xml(quat="0 0 0 1") -> str:
    """Two identical arms facing each other across the plane x = 0.

    Arm b is arm a rotated 180 degrees about z (``quat``; "0 0 0 1" is exact, an
    ``euler="0 0 3.1416"`` rounding can be passed as ``rot``).
    """
    rot = f'quat="{quat}"' if not quat.startswith("euler") else quat
    a = _arm("a_", "-0.4 0 0", roll_range="-1 1", yaw_range="-1 1")
    b = _arm("b_", "0.4 0 0", rot=rot, roll_range="-1 1", yaw_range="-1 1")
    return _model([a, b], table_pos="0 0 -0.02")


def load(xml: str) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(xml)
