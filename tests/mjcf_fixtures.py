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


# --- models nobody here wrote by hand for symmetry: ALOHA-like and SO-101-like --------------
# Right-angle tetrahedra with three different leg lengths: no reflection maps one onto
# itself, so each is chiral (like most CAD meshes of robot links).
_CHIRAL_MESHES = """
  <mesh name="forearm_shell" vertex="0 0 0  0.12 0 0  0 0.035 0  0 0 0.025"/>
  <mesh name="gripper_prop" vertex="0 0 0  0.04 0 0  0 0.02 0  0 0 0.012"/>
  <mesh name="finger_pad" vertex="0 0 0  0.03 0 0  0 0.008 0  0 0 0.015"/>"""

_ALOHA_ARM = """
<body name="{p}base_link" pos="{x} 0 0" {rot}>
  {mount_inertial}
  <geom type="box" size="0.05 0.05 0.01" pos="0 0 0.01" mass="0" contype="0" conaffinity="0"/>
  <body name="{p}shoulder_link" pos="0 0 0.079">
    <inertial pos="0 0 0.01" mass="0.8" diaginertia="0.001 0.001 0.001"/>
    <joint name="{p}waist" axis="0 0 1" range="-3.14158 3.14158"/>
    <geom type="cylinder" size="0.035 0.02" contype="0" conaffinity="0"/>
    <body name="{p}upper_arm_link" pos="0 0 0.04">
      <inertial pos="0.02 0 0.15" mass="0.8" diaginertia="0.008 0.008 0.001"/>
      <joint name="{p}shoulder" axis="0 1 0" range="-1.85 1.26"/>
      <geom type="capsule" fromto="0 0 0 0.05 0 0.3" size="0.02" contype="0" conaffinity="0"/>
      <body name="{p}upper_forearm_link" pos="0.05 0 0.3">
        <inertial pos="0.1 0 0" mass="0.4" diaginertia="0.0005 0.003 0.003"/>
        <joint name="{p}elbow" axis="0 1 0" range="-1.76 1.6"/>
        <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.018" contype="0" conaffinity="0"/>
        <body name="{p}lower_forearm_link" pos="0.2 0 0">
          <inertial pos="0.05 {com_y} 0" mass="0.3" diaginertia="0.0003 0.001 0.001"/>
          <joint name="{p}forearm_roll" axis="1 0 0" range="-3.14158 3.14158"/>
          <geom type="mesh" mesh="forearm_shell" contype="0" conaffinity="0"/>
          <body name="{p}wrist_link" pos="0.1 0 0">
            <inertial pos="0.04 0 0" mass="0.1" diaginertia="5e-5 5e-5 5e-5"/>
            <joint name="{p}wrist_angle" axis="0 1 0" range="-1.87 2.23"/>
            <geom type="box" size="0.03 0.02 0.015" pos="0.03 0 0" contype="0" conaffinity="0"/>
            <body name="{p}gripper_link" pos="0.07 0 0">
              <inertial pos="0.03 0 0" mass="0.1" diaginertia="5e-5 5e-5 5e-5"/>
              <joint name="{p}wrist_rotate" axis="1 0 0" range="-3.14158 3.14158"/>
              <geom type="mesh" mesh="gripper_prop" pos="0.02 0 0" contype="0" conaffinity="0"/>
              <site name="{p}ee" pos="0.1 0 0"/>
              <camera name="{p}wrist_cam" pos="0.05 0 0.05" xyaxes="0 -1 0 0 0 1" fovy="60"/>
              <body name="{p}left_finger_link">
                <inertial pos="0.06 0 0" mass="0.02" diaginertia="1e-6 1e-6 1e-6"/>
                <joint name="{p}left_finger" type="slide" axis="0 1 0" range="0.021 0.057"/>
                <geom type="mesh" mesh="finger_pad" pos="0.06 0 0"/>
              </body>
              <body name="{p}right_finger_link">
                <inertial pos="0.06 0 0" mass="0.02" diaginertia="1e-6 1e-6 1e-6"/>
                <joint name="{p}right_finger" type="slide" axis="0 1 0" range="-0.057 -0.021"/>
                <geom type="mesh" mesh="finger_pad" pos="0.06 0 0"/>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>
  </body>
</body>"""

_ALOHA_ACT = """
<position name="{p}waist" joint="{p}waist" kp="40" ctrlrange="-3.14158 3.14158"/>
<position name="{p}shoulder" joint="{p}shoulder" kp="40" ctrlrange="-1.85 1.26"/>
<position name="{p}elbow" joint="{p}elbow" kp="40" ctrlrange="-1.76 1.6"/>
<position name="{p}forearm_roll" joint="{p}forearm_roll" kp="20" ctrlrange="-3.14158 3.14158"/>
<position name="{p}wrist_angle" joint="{p}wrist_angle" kp="20" ctrlrange="-1.87 2.23"/>
<position name="{p}wrist_rotate" joint="{p}wrist_rotate" kp="20" ctrlrange="-3.14158 3.14158"/>
<position name="{p}left_finger" joint="{p}left_finger" kp="200" ctrlrange="0.021 0.057"/>
<position name="{p}right_finger" joint="{p}right_finger" kp="200" ctrlrange="-0.057 -0.021"/>"""

ALOHA_COM_OFFSET = 0.014
"""Built-in COM asymmetry of aloha_like_xml(): each lower forearm's centre of mass sits 7 mm
to the side of its arm's centre line, so it is 1.4 cm off its mirror image."""


def aloha_like_xml(right_rot='euler="0 0 3.1416"', com_y=ALOHA_COM_OFFSET / 2, x=0.469) -> str:
    """Two identical 6-DoF arms with two slide fingers each, facing each other across the
    plane x = 0 (mirror normal (1, 0, 0)), written like a published bimanual model:

    - the right arm is the left one turned by pi about z, written as ``euler="0 0 3.1416"``;
    - the arm bases are massless, and the left one carries an explicit inertial frame at a
      meaningless place (as an exported model may);
    - both lower forearms have their centre of mass ``com_y`` to the same side of the arm,
      so the two are ``2 * com_y`` off each other's mirror image;
    - the lower forearm, gripper and fingers carry chiral meshes (inline vertices), the same
      mesh on both arms;
    - a camera on the mirror plane (``cam_high``) and one wrist camera per arm.
    Fingers: ``left_finger`` slides along +y in [0.021, 0.057], ``right_finger`` along +y in
    [-0.057, -0.021] (so each maps to the other arm's opposite finger with sign -1).
    """
    arms = []
    for p, xx, rot, inertial in (
        ("left/", -x, "", '<inertial pos="-0.47 1.0 0" mass="0" diaginertia="0 0 0"/>'),
        ("right/", x, right_rot, ""),
    ):
        kw = dict(p=p, x=xx, rot=rot, mount_inertial=inertial, com_y=com_y)
        arms.append((_ALOHA_ARM.format(**kw), _ALOHA_ACT.format(p=p)))
    return f"""
<mujoco model="aloha_like">
  <compiler angle="radian"/>
  <asset>{_CHIRAL_MESHES}</asset>
  <worldbody>
    <geom name="table" type="box" size="0.6 0.4 0.02" pos="0 0 -0.02" rgba="0.6 0.5 0.4 1"/>
    <camera name="cam_high" pos="0 -0.3 0.8" xyaxes="1 0 0 0 0.8 0.6" fovy="70"/>
    {arms[0][0]}
    {arms[1][0]}
  </worldbody>
  <actuator>{arms[0][1]}{arms[1][1]}</actuator>
</mujoco>"""


_SO_ARM = """
<body name="{p}base" pos="0 {y} 0">
  <geom type="box" size="0.03 0.03 0.02" pos="0 {box_y} 0.02" mass="0.3"/>
  <body name="{p}shoulder" pos="0 0 0.05">
    <joint name="{p}shoulder_pan" axis="0 0 1" range="-1.92 1.92"/>
    <geom type="cylinder" size="0.025 0.02" mass="0.1"/>
    <body name="{p}upper_arm" pos="0 {lift_y} 0.05">
      <joint name="{p}shoulder_lift" axis="0 1 0" range="-1.75 1.75"/>
      <geom type="capsule" fromto="0 0 0 0.11 0 0.03" size="0.015" mass="0.1"/>
      <body name="{p}lower_arm" pos="0.11 0 0.03">
        <joint name="{p}elbow_flex" axis="0 1 0" range="-1.69 1.69"/>
        <geom type="capsule" fromto="0 0 0 0.13 0 0" size="0.013" mass="0.08"/>
        <body name="{p}wrist" pos="0.13 0 0">
          <joint name="{p}wrist_flex" axis="0 1 0" range="-1.66 1.66"/>
          <geom type="box" size="0.02 0.015 0.015" pos="0.02 0 0" mass="0.05"/>
          <body name="{p}gripper" pos="0.05 0 0">
            <joint name="{p}wrist_roll" axis="1 0 0" range="{roll_range}"/>
            <geom type="mesh" mesh="gripper_prop" pos="0.03 0 0" mass="0.05"/>
            <site name="{p}ee" pos="0.08 0 0"/>
            <body name="{p}jaw" pos="0.02 0 0.015">
              <joint name="{p}gripper" axis="0 1 0" range="-0.17 1.75"/>
              <geom type="box" size="0.03 0.004 0.004" pos="0.03 0 0" mass="0.02"/>
            </body>
          </body>
        </body>
      </body>
    </body>
  </body>
</body>"""

_SO_ACT = """
<position name="{p}shoulder_pan" joint="{p}shoulder_pan" kp="20" ctrlrange="-1.92 1.92"/>
<position name="{p}shoulder_lift" joint="{p}shoulder_lift" kp="20" ctrlrange="-1.75 1.75"/>
<position name="{p}elbow_flex" joint="{p}elbow_flex" kp="20" ctrlrange="-1.69 1.69"/>
<position name="{p}wrist_flex" joint="{p}wrist_flex" kp="10" ctrlrange="-1.66 1.66"/>
<position name="{p}wrist_roll" joint="{p}wrist_roll" kp="10" ctrlrange="{roll_range}"/>
<position name="{p}gripper" joint="{p}gripper" kp="10" ctrlrange="-0.17 1.75"/>"""

SO_LIFT_OFFSET = 0.018
"""Built-in offset of so101_pair_xml(): each shoulder-lift joint sits 1.8 cm to the left of its
arm's centre line, so every body from the upper arm on is 3.6 cm off its mirror image."""


def so101_pair_xml(lift_y=SO_LIFT_OFFSET, roll_range="-2.744 2.841", box_y=0.008, y=0.2) -> str:
    """Two copies of one SO-101-like 5-DoF arm (plus a hinged jaw) side by side at
    y = +-``y``, both facing +x; mirror plane y = 0. Not mirror-symmetric, the way two
    identical arms of a real robot are not:

    - the shoulder-lift joint sits ``lift_y`` to the left of the arm's centre line on both
      arms (the residual of every body from the upper arm on is ``2 * lift_y``);
    - the wrist-roll range ``roll_range`` is asymmetric (its mirror is its negation);
    - the base box is ``box_y`` off the centre line and the gripper carries a chiral mesh.
    """
    arms = [(_SO_ARM.format(p=p, y=yy, box_y=box_y, lift_y=lift_y, roll_range=roll_range),
             _SO_ACT.format(p=p, roll_range=roll_range)) for p, yy in (("l_", y), ("r_", -y))]
    return f"""
<mujoco model="so101_pair">
  <compiler angle="radian"/>
  <asset>{_CHIRAL_MESHES}</asset>
  <worldbody>
    <geom name="table" type="plane" size="0.5 0.5 0.01"/>
    <camera name="top" pos="0.2 0 0.7" xyaxes="0 -1 0 1 0 0" fovy="60"/>
    {arms[0][0]}
    {arms[1][0]}
  </worldbody>
  <actuator>{arms[0][1]}{arms[1][1]}</actuator>
</mujoco>"""
