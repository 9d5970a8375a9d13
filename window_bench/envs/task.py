"""Task semantics read from named physical quantities: acceptance, stages, failure modes.

Following dm_control's Physics/Task split, nothing here steps the simulator, so the
acceptance test and the failure taxonomy are unit-testable on constructed situations.

Acceptance (paper, Appendix "Success criteria"): panel centre within 2 mm of the seated
target, cos(n_window, n_wall) > 0.95, panel speed < 1 cm/s.

Failure taxonomy (one label per episode that does not end in acceptance):

=====================  =====================================================================
``never_acquired``     suction never latched (Experiment B).
``suction_lost``       suction latched at some point but is not latched at the end (a grip
                       peeled off by a panel binding in the opening is labelled by where it
                       bound: entry_wedging, mid_depth_jamming or unstable_seating).
``approach_failed``    held, but the panel never entered the opening.
``entry_wedging``      entered, stalled in contact with the buck at less than 35 % of the
                       seating depth (binding/wedging at the entry edge).
``mid_depth_jamming``  entered, stalled in contact deeper than 35 % but short of the stop.
``unstable_seating``   reached the seating depth but never met all three acceptance criteria.
``timeout``            entered or approached without a contact stall, horizon ran out.
``sim_unstable``       physics diverged; the episode was truncated.
=====================  =====================================================================

On every step the env reports in ``info["failure_code"]`` the label the episode would get
if it ended there (``FAILURE_MODE_NAMES[code]``; 0, ``""``, once accepted), so the label is
right whichever wrapper ends the episode; read it on the final step.

The seated target is the centre of the opening. A panel released onto the sill rests the
full clearance (2 mm) low and is therefore *not* accepted: like an installer who shims and
centres a window, the robot must hold the panel centred until acceptance.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

POSITION_TOL = 0.002        # m
NORMAL_COS_MIN = 0.95
SPEED_MAX = 0.01            # m/s
ENTRY_DEPTH = 0.005         # front face this far past the wall face = insertion entered
ENTRY_FRACTION = 0.35       # stalls shallower than this fraction of the seating depth = wedging
SEATING_DEPTH_TOL = 0.004   # centre within this of the seating depth = reached the stop
STALL_STEPS = 8             # contact stalls needed before a wedging/jamming label
STALL_RATIO = 0.3           # realized / commanded translation below this = stalled

FAILURE_MODES = ("never_acquired", "suction_lost", "approach_failed", "entry_wedging",
                 "mid_depth_jamming", "unstable_seating", "timeout", "sim_unstable")
# Integer codes, so that info holds numbers for batched consumers (vector envs,
# TensorDicts): ``info["failure_code"]`` is 0 for no failure, ``FAILURE_MODE_NAMES[code]``
# the label (``info["failure_mode"]`` with ``info_strings=True``), ``FAILURE_CODES`` the
# reverse.
FAILURE_MODE_NAMES = ("", *FAILURE_MODES)
FAILURE_CODES = {name: code for code, name in enumerate(FAILURE_MODE_NAMES)}
# ``info["stage"]``: the furthest stage event reached this episode, as an index here.
STAGES = ("none", "suction_acquired", "insertion_entered", "seated")


@dataclass(frozen=True)
class Acceptance:
    position_error: float
    normal_cos: float
    speed: float

    @property
    def accepted(self) -> bool:
        return (self.position_error < POSITION_TOL and self.normal_cos > NORMAL_COS_MIN
                and self.speed < SPEED_MAX)


def acceptance(panel_pos, panel_normal, panel_linvel, target_pos, wall_normal) -> Acceptance:
    """The three acceptance criteria from named quantities (world frame, metres)."""
    err = float(np.linalg.norm(np.asarray(panel_pos) - np.asarray(target_pos)))
    n = np.asarray(panel_normal, float)
    w = np.asarray(wall_normal, float)
    cos = float(n @ w / (np.linalg.norm(n) * np.linalg.norm(w)))
    return Acceptance(err, cos, float(np.linalg.norm(panel_linvel)))


@dataclass
class StageTracker:
    """Stage events and the contact/motion history that the failure label is derived from."""

    seated_depth: float
    suction_acquired: bool = False
    insertion_entered: bool = False
    seated: bool = False
    latched: bool = False
    max_depth: float = -np.inf
    stall_steps: int = 0
    stall_depths: list = field(default_factory=list)
    bind_loss_depth: float | None = None   # depth at which a binding panel peeled the grip

    def update(self, *, latched: bool, depth: float, front_depth: float, in_opening: bool,
               buck_contact: bool, commanded: float, realized: float, accepted: bool,
               suction_failed: bool = False) -> None:
        """One 10 Hz step. ``depth``/``front_depth``: panel centre / leading face past the
        wall face along the insertion axis (m); ``in_opening``: the panel's centre lies within
        the opening's footprint; ``commanded``/``realized``: TCP translation this step (m)."""
        self.latched = latched
        self.suction_acquired |= latched
        if in_opening and front_depth > ENTRY_DEPTH:
            self.insertion_entered = True
        if self.insertion_entered:
            self.max_depth = max(self.max_depth, depth)
        if buck_contact and commanded > 0.004 and realized < STALL_RATIO * commanded:
            self.stall_steps += 1
            self.stall_depths.append(depth)
        self.seated |= accepted
        if suction_failed and buck_contact and self.insertion_entered:
            self.bind_loss_depth = depth

    @property
    def stage(self) -> int:
        """Index in ``STAGES`` of the furthest stage event reached."""
        return 3 if self.seated else 2 if self.insertion_entered else int(self.suction_acquired)

    def failure_mode(self, sim_unstable: bool = False) -> str | None:
        if self.seated:
            return None
        if sim_unstable:
            return "sim_unstable"
        if not self.suction_acquired:
            return "never_acquired"
        if not self.latched:
            if self.bind_loss_depth is not None:
                # The grip peeled because the panel bound in the opening: the binding is the
                # failure, labelled by where it happened.
                return self._contact_label(self.bind_loss_depth)
            return "suction_lost"
        if not self.insertion_entered:
            return "approach_failed"
        if self.max_depth >= self.seated_depth - SEATING_DEPTH_TOL:
            return "unstable_seating"
        if self.stall_steps >= STALL_STEPS:
            return self._contact_label(float(np.median(self.stall_depths[-STALL_STEPS:])))
        return "timeout"

    def _contact_label(self, depth: float) -> str:
        if depth >= self.seated_depth - SEATING_DEPTH_TOL:
            return "unstable_seating"
        if depth < ENTRY_FRACTION * self.seated_depth:
            return "entry_wedging"
        return "mid_depth_jamming"
