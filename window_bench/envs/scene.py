"""The composed MuJoCo scene: arena + objects + robot + tool, built with ``MjSpec``.

robosuite composes a task from an arena, objects and a robot with its gripper; we do the
same in code with MuJoCo's ``MjSpec`` so that every dimension (panel size, clearance, buck
depth) is a parameter and the wall opening is always sized from the panel.

Frames. The world frame is the robot base frame: the iiwa base sits on the floor at the
origin, z up. The wall is on the robot's right: its face is the plane ``y = -WALL_Y`` with
outward normal ``+y``; windows are inserted along ``-y``. The ground region of Table 9
(x in [0.4, 0.6] m, y in [-0.3, 0.3] m) is in front of the robot, the staging rack of
Experiment A is in front as well. See ``docs/environments.md`` for a picture.

Contact model. The panel touches the world only through explicit ``<pair>`` elements, so
the friction and solref that the environment samples per episode are exactly the values
MuJoCo uses for each pair (geom friction mixing never applies to them):

* ``friction_buck``   - panel vs the wood-buck lining (sill, head, both jambs);
* ``friction_window`` - panel vs the window frame it bears on: the back stop strips, the
  wall face, the staging rack and the floor;
* ``friction_cup``    - the vacuum cup vs everything it touches (the cup geoms carry
  ``priority=1`` so their friction wins the mix), and the shear limit of the suction grip.

The cup-panel contact is a dynamic contact (collision bit 2) that the env switches off
while the suction weld is latched, so the weld and the lip contact never fight. Robot
links collide with the world (floor, wall, buck, rack) but not with each other or with the
panel (the panel is only ever in the robot's hand or out of its way).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

# ----------------------------------------------------------------------------- robot
# KUKA LBR iiwa 14 R820: joint offsets along the straight (zero) configuration, metres.
# base->J2 0.36, J2->J4 0.42, J4->J6 0.40, J6->flange 0.126 (J1 at 0.1575 above the base).
IIWA_JOINT_Z = (0.1575, 0.2025, 0.2045, 0.2155, 0.1845, 0.2155, 0.081)
IIWA_FLANGE_Z = 0.045
# Joint axes in the zero configuration (J2, J4, J6 pitch; J1, J3, J5, J7 roll about the link).
IIWA_AXES = ((0, 0, 1), (0, 1, 0), (0, 0, 1), (0, -1, 0), (0, 0, 1), (0, 1, 0), (0, 0, 1))
# Link masses (kg) and principal inertias (kg m^2), close to the identified values that
# KUKA-derived models publish (links 1-7: 25.6 kg).
IIWA_MASS = (5.76, 6.35, 3.5, 3.5, 3.5, 1.8, 1.2)
IIWA_COM_Z = (0.12, 0.042, 0.13, 0.034, 0.076, 0.0004, 0.02)
IIWA_INERTIA = (
    (0.0333, 0.033, 0.0123),
    (0.0305, 0.0304, 0.011),
    (0.025, 0.0238, 0.0076),
    (0.017, 0.0164, 0.006),
    (0.01, 0.0087, 0.00449),
    (0.0049, 0.0047, 0.0036),
    (0.001, 0.001, 0.001),
)
IIWA_LINK_RADIUS = (0.075, 0.075, 0.07, 0.07, 0.065, 0.06, 0.045)
# Table 10.
JOINT_LIMITS = np.array(
    [[-2.967, 2.967], [-2.094, 2.094], [-3.054, 3.054], [-2.094, 2.094],
     [-2.967, 2.967], [-2.094, 2.094], [-3.054, 3.054]]
)
TORQUE_LIMITS = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])
MAX_JOINT_VELOCITY = 1.92  # rad/s (110 deg/s)

# ------------------------------------------------------------------------------ tool
# Robotiq PowerPick-like vacuum tool: adapter + ejector body + bellows cup.
TOOL_BODY_RADIUS = 0.04
TOOL_BODY_LENGTH = 0.08
CUP_RADIUS = 0.035
CUP_LENGTH = 0.03
TOOL_LENGTH = TOOL_BODY_LENGTH + CUP_LENGTH  # flange -> cup lip (the TCP), 0.11 m
TOOL_MASS = 0.6

# ------------------------------------------------------------------------------ wall
WALL_Y = 0.70            # wall face at y = -WALL_Y: clear of every ground placement, even a
                         # 0.6 m panel at y = -0.3 turned 15 deg reaches only y = -0.668
WALL_THICKNESS = 0.14    # depth of the wood buck
BUCK_THICKNESS = 0.02    # lining boards
BUCK_CHAMFER = 0.005     # 45-degree eased entry edge of the lining boards
STOP_DEPTH = 0.10        # back stop strips start this far behind the wall face
PREINSERT_OFFSET = STOP_DEPTH + 0.02  # panel centre this far out from the seat along the wall
                         # normal: the leading face 2 cm in front of the wall face
STOP_LIP = 0.015         # how far the stop strips reach into the opening
OPENING_CENTER_X = 0.35
OPENING_CENTER_Z = 0.60
WALL_HALF_WIDTH = 0.9    # wall extends +-0.9 m in x around the opening centre
WALL_HEIGHT = 1.4

# ----------------------------------------------------------------------------- panel
PANEL_THICKNESS = 0.08   # 80 mm frame depth: deep enough that a tilted panel can wedge
                         # (w cos t + d sin t > w + 2c needs d > sqrt(4 c w) = 63 mm at w = 0.5 m)
PANEL_AREAL_DENSITY = 8.0  # kg/m^2 -> 2.0 kg for 0.5 x 0.5 m (see docs: torque margin)

# ------------------------------------------------------------------------------ rack
RACK_CENTER = np.array([0.72, 0.10])
RACK_TILT_DEG = 15.0     # panel leans back 15 deg from vertical, face toward the robot
RACK_LEDGE_Z = 0.12      # top of the ledge the panel stands on
RACK_GAP = 0.02          # nominal gap panel<->rack: +-5 mm, +-2 deg perturbations never overlap

CUP_PANEL_BIT = 2

# Time. Physics at 1 kHz: a contact solref time constant of 2 ms (the low end of Table 9)
# is unstable at a 2 ms timestep (MuJoCo needs timeconst >= 2 x timestep; measured: a panel
# resting on the floor flew off at 2.0 ms and was still at 2.5 ms). The OSC runs at 500 Hz
# and holds its torque for two physics steps.
TIMESTEP = 0.001
PHYSICS_PER_CONTROL = 2
CONTROL_SUBSTEPS = 50    # OSC updates per 10 Hz policy step


#: The supported clearance per side, metres (SceneConfig refuses others; ``bench eval
#: --clearance`` states it in millimetres).
CLEARANCE_RANGE = (0.0005, 0.02)

#: Where an episode starts: "A" the panel held on the staging rack, "B" the panel on the
#: ground and suction off, "Insert" the panel held square in front of the opening at the
#: pre-insertion pose (the insertion alone).
EXPERIMENTS = ("A", "B", "Insert")


@dataclass(frozen=True)
class SceneConfig:
    """Geometry of one benchmark instance. Every length in metres."""

    experiment: str = "A"                   # see EXPERIMENTS
    panel_width: float = 0.5                # along the wall (x)
    panel_height: float = 0.5               # vertical when seated (z)
    clearance: float = 0.002                # per side
    panel_thickness: float = PANEL_THICKNESS
    panel_mass: float | None = None         # default: areal density x area

    def __post_init__(self):
        if self.experiment not in EXPERIMENTS:
            raise ValueError(f"experiment must be one of {', '.join(map(repr, EXPERIMENTS))}, "
                             f"got {self.experiment!r}")
        # Up to 0.6 m: a larger panel placed at the edge of the ground region (y = -0.3 m,
        # yaw 15 deg) would start inside the wall.
        for name, lo, hi in (("panel_width", 0.3, 0.6), ("panel_height", 0.3, 0.6),
                             ("clearance", *CLEARANCE_RANGE), ("panel_thickness", 0.01, 0.08)):
            v = getattr(self, name)
            if not (lo <= v <= hi):
                raise ValueError(f"{name}={v!r} is outside the supported range [{lo}, {hi}]")
        if self.panel_mass is not None and not (0.2 <= self.panel_mass <= 5.0):
            raise ValueError(f"panel_mass={self.panel_mass!r} is outside [0.2, 5.0] kg")

    @property
    def starts_latched(self) -> bool:
        """The panel starts in the cup, suction latched (Pr(S) = 1 by design)."""
        return self.experiment != "B"

    @property
    def mass(self) -> float:
        if self.panel_mass is not None:
            return self.panel_mass
        return PANEL_AREAL_DENSITY * self.panel_width * self.panel_height

    @property
    def opening(self) -> tuple[float, float]:
        return self.panel_width + 2 * self.clearance, self.panel_height + 2 * self.clearance

    @property
    def seated_center(self) -> np.ndarray:
        """Target panel centre: front face against the back stop."""
        depth = STOP_DEPTH - self.panel_thickness / 2
        return np.array([OPENING_CENTER_X, -WALL_Y - depth, OPENING_CENTER_Z])

    @property
    def seated_depth(self) -> float:
        return STOP_DEPTH - self.panel_thickness / 2


# Panel body frame: z = suction-face normal (out of the face the cup holds), x along the
# width, y along the height. Seated: z -> +y world (toward the robot), x -> +x along the
# wall, y -> -z. This is the panel lying on the ground (z up, x ~ +x) tilted up by a single
# -90 deg turn about x, so picking from the ground never winds the wrist through its limits.
SEATED_PANEL_MAT = np.column_stack([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # cols = body axes
assert np.isclose(np.linalg.det(SEATED_PANEL_MAT), 1.0)
WALL_NORMAL = np.array([0.0, 1.0, 0.0])
INSERTION_AXIS = -WALL_NORMAL


def _quat_from_mat(mat: np.ndarray) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(mat).ravel())
    return q


def rack_panel_pose(cfg: SceneConfig) -> tuple[np.ndarray, np.ndarray]:
    """Staged panel pose on the tilted rack (centre, rotation matrix)."""
    tilt = np.deg2rad(RACK_TILT_DEG)
    # Face normal points toward the robot (-x) and up; the panel leans back onto the rack.
    normal = np.array([-np.cos(tilt), 0.0, np.sin(tilt)])
    up = np.array([np.sin(tilt), 0.0, np.cos(tilt)])     # along the panel, up the rack
    width = np.array([0.0, 1.0, 0.0])
    # Body y points down the rack: the staged frame is the seated frame turned 90 deg about
    # the vertical and leaned back, so the transport is one turn plus the lean.
    mat = np.column_stack([width, -up, normal])
    assert np.allclose(np.cross(width, -up), normal)
    h, t = cfg.panel_height, cfg.panel_thickness
    # Bottom-back edge rests RACK_GAP above the ledge and RACK_GAP in front of the backrest.
    center = np.array([RACK_CENTER[0], RACK_CENTER[1], RACK_LEDGE_Z + RACK_GAP])
    center = center + up * (h / 2) + normal * (t / 2)
    return center, mat


def _add_box(body, name, size, pos, rgba, *, contype=1, conaffinity=1, quat=None, group=0):
    g = body.add_geom()
    g.name = name
    g.type = mujoco.mjtGeom.mjGEOM_BOX
    g.size = size
    g.pos = pos
    if quat is not None:
        g.quat = quat
    g.rgba = rgba
    g.contype = contype
    g.conaffinity = conaffinity
    g.group = group
    return g


WOOD = (0.72, 0.55, 0.36, 1)
WALL_RGBA = (0.82, 0.80, 0.76, 1)
STOP_RGBA = (0.35, 0.35, 0.38, 1)
ROBOT_RGBA = (0.93, 0.45, 0.1, 1)
GLASS = (0.55, 0.75, 0.9, 0.75)

BUCK_GEOMS = ("buck_sill", "buck_head", "buck_jamb_left", "buck_jamb_right",
              "buck_bevel_sill", "buck_bevel_head", "buck_bevel_jamb_left", "buck_bevel_jamb_right")
STOP_GEOMS = ("stop_sill", "stop_head", "stop_left", "stop_right")
WALL_GEOMS = ("wall_below", "wall_above", "wall_left", "wall_right")
RACK_GEOMS = ("rack_ledge", "rack_back")


def _build_arena(spec: mujoco.MjSpec, cfg: SceneConfig) -> None:
    wb = spec.worldbody
    floor = wb.add_geom()
    floor.name = "floor"
    floor.type = mujoco.mjtGeom.mjGEOM_PLANE
    floor.size = [2.5, 2.5, 0.05]
    floor.material = "grid"
    floor.contype, floor.conaffinity = 1, 1

    light = wb.add_light()
    light.pos = [0.4, 0.4, 2.5]
    light.dir = [0, -0.3, -1]
    light.castshadow = False

    ow, oh = cfg.opening
    cx, cz = OPENING_CENTER_X, OPENING_CENTER_Z
    yc = -WALL_Y - WALL_THICKNESS / 2
    ht = WALL_THICKNESS / 2
    b = BUCK_THICKNESS
    wall = wb.add_body()
    wall.name = "wall"
    # Wall around the opening (outside the buck lining).
    x_in_l, x_in_r = cx - ow / 2 - b, cx + ow / 2 + b
    z_in_b, z_in_t = cz - oh / 2 - b, cz + oh / 2 + b
    xl, xr = cx - WALL_HALF_WIDTH, cx + WALL_HALF_WIDTH
    _add_box(wall, "wall_below", [WALL_HALF_WIDTH, ht, z_in_b / 2], [cx, yc, z_in_b / 2], WALL_RGBA)
    top_h = WALL_HEIGHT - z_in_t
    _add_box(wall, "wall_above", [WALL_HALF_WIDTH, ht, top_h / 2], [cx, yc, z_in_t + top_h / 2], WALL_RGBA)
    lw = (x_in_l - xl) / 2
    _add_box(wall, "wall_left", [lw, ht, (z_in_t - z_in_b) / 2], [xl + lw, yc, (z_in_b + z_in_t) / 2], WALL_RGBA)
    rw = (xr - x_in_r) / 2
    _add_box(wall, "wall_right", [rw, ht, (z_in_t - z_in_b) / 2], [x_in_r + rw, yc, (z_in_b + z_in_t) / 2], WALL_RGBA)
    # Wood buck lining: its inner faces bound the opening with `clearance` per side; the
    # boards stop BUCK_CHAMFER short of the wall face where a 45-degree bevel eases the edge.
    ch = BUCK_CHAMFER
    bd = (WALL_THICKNESS - ch) / 2
    yb = -WALL_Y - ch - bd
    boards = (  # name, centre, half sizes, inward normal, long axis, half length, face point
        ("buck_sill", [cx, yb, cz - oh / 2 - b / 2], [ow / 2 + b, bd, b / 2], [0, 0, 1.0], [1.0, 0, 0], ow / 2 + b, [cx, 0, cz - oh / 2]),
        ("buck_head", [cx, yb, cz + oh / 2 + b / 2], [ow / 2 + b, bd, b / 2], [0, 0, -1.0], [1.0, 0, 0], ow / 2 + b, [cx, 0, cz + oh / 2]),
        ("buck_jamb_left", [cx - ow / 2 - b / 2, yb, cz], [b / 2, bd, oh / 2], [1.0, 0, 0], [0, 0, 1.0], oh / 2, [cx - ow / 2, 0, cz]),
        ("buck_jamb_right", [cx + ow / 2 + b / 2, yb, cz], [b / 2, bd, oh / 2], [-1.0, 0, 0], [0, 0, 1.0], oh / 2, [cx + ow / 2, 0, cz]),
    )
    bevel_half = 0.004
    for gname, center, half, n_in, axis, half_len, face in boards:
        _add_box(wall, gname, half, center, WOOD)
        n_in, axis, face = np.array(n_in), np.array(axis), np.array(face, float)
        n_out = (n_in + WALL_NORMAL) / np.sqrt(2)
        p1 = face - ch * n_in + np.array([0, -WALL_Y, 0])
        p2 = face + np.array([0, -WALL_Y - ch, 0])
        c = (p1 + p2) / 2 - bevel_half * n_out
        rot = np.column_stack([axis, np.cross(n_out, axis), n_out])
        _add_box(wall, gname.replace("buck_", "buck_bevel_"), [half_len, ch / np.sqrt(2), bevel_half],
                 c, WOOD, quat=_quat_from_mat(rot))
    # Back stop: strips behind STOP_DEPTH that narrow the opening by STOP_LIP.
    sd = (WALL_THICKNESS - STOP_DEPTH) / 2
    ys = -WALL_Y - STOP_DEPTH - sd
    s = STOP_LIP
    _add_box(wall, "stop_sill", [ow / 2, sd, s / 2], [cx, ys, cz - oh / 2 + s / 2], STOP_RGBA)
    _add_box(wall, "stop_head", [ow / 2, sd, s / 2], [cx, ys, cz + oh / 2 - s / 2], STOP_RGBA)
    _add_box(wall, "stop_left", [s / 2, sd, oh / 2 - s], [cx - ow / 2 + s / 2, ys, cz], STOP_RGBA)
    _add_box(wall, "stop_right", [s / 2, sd, oh / 2 - s], [cx + ow / 2 - s / 2, ys, cz], STOP_RGBA)
    # Seated target marker (visual only).
    site = wb.add_site()
    site.name = "seated_target"
    site.pos = cfg.seated_center
    site.quat = _quat_from_mat(SEATED_PANEL_MAT)
    site.size = [0.01, 0.01, 0.01]
    site.rgba = [0, 1, 0, 0.0]

    if cfg.experiment == "A":
        rack = wb.add_body()
        rack.name = "rack"
        rx, ry = RACK_CENTER
        half_w = cfg.panel_width / 2 + 0.05
        _add_box(rack, "rack_ledge", [0.06, half_w, RACK_LEDGE_Z / 2], [rx + 0.03, ry, RACK_LEDGE_Z / 2], STOP_RGBA)
        # Backrest: a board parallel to the staged panel, behind it.
        center, mat = rack_panel_pose(cfg)
        normal = mat[:, 2]
        back_c = center - normal * (cfg.panel_thickness / 2 + RACK_GAP + 0.01)
        back_c = back_c - mat[:, 1] * 0.05
        _add_box(rack, "rack_back", [half_w, cfg.panel_height / 2 - 0.03, 0.01], back_c, WOOD,
                 quat=_quat_from_mat(mat))


def _build_robot(spec: mujoco.MjSpec, cfg: SceneConfig) -> None:
    parent = spec.worldbody
    base = parent.add_body()
    base.name = "robot0_base"
    _add_box(base, "robot0_base_geom", [0.1, 0.1, 0.02], [0, 0, 0.02], (0.2, 0.2, 0.2, 1))
    parent = base
    for i in range(7):
        body = parent.add_body()
        body.name = f"robot0_link{i + 1}"
        body.pos = [0, 0, IIWA_JOINT_Z[i]]
        body.mass = IIWA_MASS[i]
        body.ipos = [0, 0, IIWA_COM_Z[i]]
        body.inertia = list(IIWA_INERTIA[i])
        body.explicitinertial = True
        j = body.add_joint()
        j.name = f"robot0_joint{i + 1}"
        j.type = mujoco.mjtJoint.mjJNT_HINGE
        j.axis = list(IIWA_AXES[i])
        j.range = list(JOINT_LIMITS[i])
        j.limited = mujoco.mjtLimited.mjLIMITED_TRUE
        j.armature = 0.1 if i < 4 else 0.02   # reflected rotor inertia
        j.damping = [0.5 if i < 4 else 0.1, 0, 0]
        length = IIWA_JOINT_Z[i + 1] if i < 6 else IIWA_FLANGE_Z
        g = body.add_geom()
        g.name = f"robot0_link{i + 1}_collision"
        g.type = mujoco.mjtGeom.mjGEOM_CAPSULE
        r = IIWA_LINK_RADIUS[i]
        g.fromto = [0, 0, 0, 0, 0, length]
        g.size = [r * 0.8 if i == 6 else r, 0, 0]
        g.rgba = ROBOT_RGBA if i % 2 == 0 else (0.85, 0.85, 0.85, 1)
        g.contype, g.conaffinity = 0, 1   # collides with the world, never with itself
        g.mass = 0
        g.density = 0
        a = spec.add_actuator()
        a.name = f"robot0_torque{i + 1}"
        a.target = j.name
        a.trntype = mujoco.mjtTrn.mjTRN_JOINT
        a.ctrlrange = [-TORQUE_LIMITS[i], TORQUE_LIMITS[i]]
        a.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        a.forcerange = [-TORQUE_LIMITS[i], TORQUE_LIMITS[i]]
        a.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        parent = body
    # Tool: flange -> ejector body -> bellows cup. The TCP is the cup lip centre, z along the tool.
    tool = parent.add_body()
    tool.name = "robot0_vacuum_tool"
    tool.pos = [0, 0, IIWA_FLANGE_Z]
    tool.mass = TOOL_MASS
    tool.ipos = [0, 0, TOOL_BODY_LENGTH / 2]
    tool.inertia = [0.0008, 0.0008, 0.0005]
    tool.explicitinertial = True
    g = tool.add_geom()
    g.name = "robot0_vacuum_body"
    g.type = mujoco.mjtGeom.mjGEOM_CYLINDER
    g.size = [TOOL_BODY_RADIUS, TOOL_BODY_LENGTH / 2, 0]
    g.pos = [0, 0, TOOL_BODY_LENGTH / 2]
    g.rgba = (0.25, 0.25, 0.28, 1)
    g.contype, g.conaffinity = 0, 1
    g.priority = 1
    g.density = 0
    cup = tool.add_geom()
    cup.name = "robot0_vacuum_cup"
    cup.type = mujoco.mjtGeom.mjGEOM_CYLINDER
    cup.size = [CUP_RADIUS, CUP_LENGTH / 2, 0]
    cup.pos = [0, 0, TOOL_BODY_LENGTH + CUP_LENGTH / 2]
    cup.rgba = (0.1, 0.1, 0.1, 1)
    cup.contype, cup.conaffinity = CUP_PANEL_BIT, 1  # bit 2: the panel
    cup.priority = 1
    cup.density = 0
    tcp = tool.add_site()
    tcp.name = "robot0_tcp"
    tcp.pos = [0, 0, TOOL_LENGTH]
    tcp.size = [0.006, 0, 0]
    tcp.rgba = [1, 0, 0, 0.6]
    cam = tool.add_camera()
    cam.name = "robot0_wrist"
    cam.pos = [0.0, -0.09, 0.02]
    # MuJoCo cameras look along their -z: view along the tool axis (+z of the tool), then
    # tilted 17 deg toward the axis so the cup lip and the face it holds are in view.
    look = np.column_stack([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
    tilt = np.deg2rad(-17.0)
    rx = np.array([[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]])
    cam.quat = _quat_from_mat(rx @ look)
    cam.fovy = 75


def _build_panel(spec: mujoco.MjSpec, cfg: SceneConfig) -> None:
    panel = spec.worldbody.add_body()
    panel.name = "window"
    fj = panel.add_freejoint()
    fj.name = "window_free"
    w, h, t = cfg.panel_width, cfg.panel_height, cfg.panel_thickness
    m = cfg.mass
    panel.mass = m
    panel.ipos = [0, 0, 0]
    panel.inertia = [m * (h**2 + t**2) / 12, m * (w**2 + t**2) / 12, m * (w**2 + h**2) / 12]
    panel.explicitinertial = True
    # Collision box (bit 2 only: the cup; everything else through explicit pairs).
    _add_box(panel, "window_box", [w / 2, h / 2, t / 2], [0, 0, 0], GLASS, contype=0, conaffinity=2)
    frame_w = 0.03
    for k, (sx, sy, px, py) in enumerate(
        ((w / 2, frame_w / 2, 0, h / 2 - frame_w / 2), (w / 2, frame_w / 2, 0, -h / 2 + frame_w / 2),
         (frame_w / 2, h / 2, w / 2 - frame_w / 2, 0), (frame_w / 2, h / 2, -w / 2 + frame_w / 2, 0))):
        _add_box(panel, f"window_frame_visual{k}", [sx, sy, t / 2 + 0.0005], [px, py, 0],
                 (0.95, 0.95, 0.95, 1), contype=0, conaffinity=0, group=2)
    face = panel.add_site()
    face.name = "window_suction_face"
    face.pos = [0, 0, t / 2]
    face.size = [0.01, 0, 0]
    face.rgba = [0, 0, 1, 0.0]


def _add_pairs(spec: mujoco.MjSpec, cfg: SceneConfig) -> dict[str, list[str]]:
    groups = {
        "buck": list(BUCK_GEOMS),
        "window": list(STOP_GEOMS) + list(WALL_GEOMS) + ["floor"]
        + (list(RACK_GEOMS) if cfg.experiment == "A" else []),
    }
    for group, geoms in groups.items():
        for gname in geoms:
            p = spec.add_pair()
            p.name = f"pair_{group}_{gname}"
            p.geomname1 = "window_box"
            p.geomname2 = gname
            p.condim = 3
            p.friction = [0.75, 0.75, 0.005, 0.0001, 0.0001]
            p.solref = [0.003, 1.0]
            p.solimp = [0.95, 0.99, 0.001, 0.5, 2]
    return groups


#: The seat cameras: name and which corner of the opening (sign of x, sign of z).
SEAT_CAMERAS = (("seat_top_right", 1.0, 1.0), ("seat_bottom_left", -1.0, -1.0))
SEAT_CAMERA_OFFSET = np.array([0.118, 0.25, 0.118])  # out from its corner (x, along the wall normal, z), in m; x and z signed by the corner
SEAT_CAMERA_FOVY = 25.0


def _add_cameras(spec: mujoco.MjSpec, cfg: SceneConfig) -> None:
    wb = spec.worldbody
    # A marker body at the opening centre for cameras to track (the wall body sits at the
    # origin, its geoms carry world coordinates).
    opening = wb.add_body()
    opening.name = "opening"
    opening.pos = [OPENING_CENTER_X, -WALL_Y, OPENING_CENTER_Z]
    side = wb.add_camera()
    side.name = "side"
    # In front of the robot (+x), on the side away from the wall, looking at the opening:
    # the buck, the back stop and the panel on its way in.
    side.mode = mujoco.mjtCamLight.mjCAMLIGHT_TARGETBODY
    side.targetbody = "opening"
    side.pos = [1.05, 0.25, 1.25]
    side.fovy = 55
    overview = wb.add_camera()
    overview.name = "overview"
    overview.mode = mujoco.mjtCamLight.mjCAMLIGHT_TARGETBODY
    overview.targetbody = "robot0_link2"
    overview.pos = [1.9, 1.5, 1.6]
    overview.fovy = 50
    # Two fixed seat cameras for the pixel track's "seat" camera set (window_bench.pixels.
    # cameras); the env's own views (wrist, side) never render them. Each sits
    # SEAT_CAMERA_OFFSET out from a corner of the opening (diagonally outward, clear of the
    # panel's path, and in front of the wall) and looks at that corner, so the gap between
    # the panel and the buck fills its view.
    half_w, half_h = cfg.opening[0] / 2, cfg.opening[1] / 2
    for name, sx, sz in SEAT_CAMERAS:
        corner = np.array([OPENING_CENTER_X + sx * half_w, -WALL_Y, OPENING_CENTER_Z + sz * half_h])
        pos = corner + np.array([sx, 1.0, sz]) * SEAT_CAMERA_OFFSET
        cam = wb.add_camera()
        cam.name = name
        cam.pos = pos
        cam.quat = _quat_from_mat(_look_at(corner - pos))
        cam.fovy = SEAT_CAMERA_FOVY


def _look_at(forward: np.ndarray) -> np.ndarray:
    """Rotation (columns: the camera's x, y, z in world) of a camera looking along
    ``forward`` with the world's z up in its image (MuJoCo cameras look along their -z)."""
    f = forward / np.linalg.norm(forward)
    x = np.cross(f, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(-f, x), -f])


def build_spec(cfg: SceneConfig) -> mujoco.MjSpec:
    """Compose arena, objects, robot and tool into one spec."""
    spec = mujoco.MjSpec()
    spec.modelname = f"window_install_{cfg.experiment}"
    spec.compiler.degree = False  # every angle in this file is in radians
    spec.option.timestep = TIMESTEP
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 5
    # Constraint Jacobian left at "auto", which MuJoCo resolves to dense up to 60 dofs (we
    # have 13): the same trajectories, bit for bit, as the explicit dense setting that worked
    # around mujoco 4.0.0's sparse-Cholesky bug, and faster here than sparse
    # (benchmarks/physics_compare.py, docs/speed.md).
    spec.option.noslip_iterations = 0
    # MuJoCo clamps solref time constants below 2 x timestep unless this flag is off. At a
    # 1 ms timestep the clamp (2 ms) sits exactly at Table 9's lower bound; we turn it off so
    # that no sampled value is ever silently replaced (tests/test_physics.py checks that the
    # sampled time constant changes contact penetration).
    spec.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_REFSAFE
    spec.visual.global_.offwidth = 640
    spec.visual.global_.offheight = 480
    spec.stat.center = [0.4, -0.2, 0.5]
    spec.stat.extent = 1.5
    tex = spec.add_texture()
    tex.name = "grid"
    tex.type = mujoco.mjtTexture.mjTEXTURE_2D
    tex.builtin = mujoco.mjtBuiltin.mjBUILTIN_CHECKER
    tex.rgb1 = [0.32, 0.34, 0.36]
    tex.rgb2 = [0.28, 0.3, 0.32]
    tex.width = tex.height = 256
    mat = spec.add_material()
    mat.name = "grid"
    mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "grid"
    mat.texrepeat = [8, 8]
    _build_arena(spec, cfg)
    _build_robot(spec, cfg)
    _build_panel(spec, cfg)
    _add_pairs(spec, cfg)
    _add_cameras(spec, cfg)
    # The suction weld: inactive until the validity check latches it.
    eq = spec.add_equality()
    eq.name = "suction"
    eq.type = mujoco.mjtEq.mjEQ_WELD
    eq.objtype = mujoco.mjtObj.mjOBJ_BODY
    eq.name1 = "robot0_vacuum_tool"
    eq.name2 = "window"
    eq.active = False
    eq.solref = [0.004, 1.0]
    eq.solimp = [0.95, 0.99, 0.001, 0.5, 2]
    return spec


@dataclass
class Scene:
    """A compiled scene plus the ids the env and the controller need."""

    cfg: SceneConfig
    model: mujoco.MjModel = field(init=False)

    def __getstate__(self) -> dict:
        # MjSpec does not pickle; the compiled model does (with any run-time edits, such as
        # the randomized frictions), and the spec is rebuilt from the config on load.
        state = self.__dict__.copy()
        del state["spec"]
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.spec = build_spec(self.cfg)

    def __post_init__(self):
        self.spec = build_spec(self.cfg)
        self.model = self.spec.compile()
        m = self.model
        name = lambda t, n: mujoco.mj_name2id(m, t, n)  # noqa: E731
        self.joint_ids = np.array([name(mujoco.mjtObj.mjOBJ_JOINT, f"robot0_joint{i + 1}") for i in range(7)])
        self.qpos_adr = m.jnt_qposadr[self.joint_ids]
        self.dof_adr = m.jnt_dofadr[self.joint_ids]
        assert np.array_equal(self.qpos_adr, np.arange(7)) and np.array_equal(self.dof_adr, np.arange(7))
        self.tcp_site = name(mujoco.mjtObj.mjOBJ_SITE, "robot0_tcp")
        self.tool_body = name(mujoco.mjtObj.mjOBJ_BODY, "robot0_vacuum_tool")
        self.panel_body = name(mujoco.mjtObj.mjOBJ_BODY, "window")
        self.panel_geom = name(mujoco.mjtObj.mjOBJ_GEOM, "window_box")
        self.cup_geom = name(mujoco.mjtObj.mjOBJ_GEOM, "robot0_vacuum_cup")
        self.tool_geoms = np.array([name(mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("robot0_vacuum_body", "robot0_vacuum_cup")])
        self.suction_eq = name(mujoco.mjtObj.mjOBJ_EQUALITY, "suction")
        jnt = m.body_jntadr[self.panel_body]
        self.panel_qpos_adr = m.jnt_qposadr[jnt]
        self.panel_dof_adr = m.jnt_dofadr[jnt]
        self.pairs = {"buck": [], "window": []}
        for i in range(m.npair):
            pname = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_PAIR, i)
            self.pairs[pname.split("_")[1]].append(i)
        self.pairs = {k: np.array(v) for k, v in self.pairs.items()}
        self.buck_geoms = np.array([name(mujoco.mjtObj.mjOBJ_GEOM, n) for n in BUCK_GEOMS])
        self.stop_geoms = np.array([name(mujoco.mjtObj.mjOBJ_GEOM, n) for n in STOP_GEOMS])
        self.wall_geoms = np.array([name(mujoco.mjtObj.mjOBJ_GEOM, n) for n in WALL_GEOMS])
        self.robot_geoms = np.array([
            g for g in range(m.ngeom)
            if m.geom_bodyid[g] != self.panel_body and m.body_rootid[m.geom_bodyid[g]] == name(mujoco.mjtObj.mjOBJ_BODY, "robot0_base")
        ])
