r"""What happens when the held panel first touches the opening? Roll a frozen state-track
policy, or an operator profile of the scripted installer, on development seeds and report per
episode: where the cup holds the panel (the TCP in the panel frame at the first latch), the
panel's depth, lateral offset and orientation error at the first step the held panel touches
the buck or the wall, how far it then backs off (the demonstrator's retract-and-realign) and
how many steps it takes to reach 60 mm from the seat, the largest peel moment on the cup
over the 10 steps after that contact, and every grip break (the holding limit of
``WindowInstallEnv``: the cup lets go) with its depth and wrench. ``--unbreakable-grip``
lifts the cup's holding limits (a counterfactual: does the grip break fail the episode, or
the wedge that comes before it?); ``--centre-grip`` moves the panel under the cup at every
latch so that the cup holds it at the centre of its face, as the demonstrator picks (a
counterfactual: is the off-centre pick what fails the insertion?); ``--no-peel-cue`` takes
from the operator the one cue it acts on that no policy observes (it backs off when the
cup's peel moment passes 30 % of the holding limit).

    python experiments/sanity/entry_contact.py --policy POLICY --env WindowInstall-B-v0 \
        --episodes 20 --out experiments/sanity/results/entry_contact_qcfql_offline_fine_B_s2.json
    python experiments/sanity/entry_contact.py --operator attentive --env WindowInstall-B-v0 \
        --episodes 20 --out experiments/sanity/results/entry_contact_attentive_B.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from rollout_args import env_errors, episodes_errors, load_policy_or_exit, out_errors  # noqa: E402

#: Grip breaks this far in front of the seat count as breaks at the entry (the leading face
#: meets the wall face about 90-100 mm out).
ENTRY_MM = (-120.0, -40.0)
DEEP_MM = -60.0
EDGE_MM = -80.0   # a first contact farther out than this is at the entry edge


def _actor(args, parser, env):
    """``(reset(seed), act(obs) -> (7,))`` of the policy (its chunks executed open loop, as the
    harness evaluates it) or of the operator."""
    if args.policy:
        cls, state, _ = load_policy_or_exit(parser, args.policy)
        if getattr(cls, "track", "state") != "state":
            parser.error(f"{args.policy} is not a state-track policy")
        agent = cls.from_policy_state_dict(state)
        queue: list = []

        def reset(seed):
            agent.reset()
            queue.clear()

        def act(obs):
            if not queue:
                queue.extend(agent.act(obs, deterministic=True))
            return queue.pop(0)
        return reset, act
    from window_bench.installer.operators import HumanlikeInstaller

    if args.no_peel_cue:
        import window_bench.installer.scripted as scripted   # read by its insert and seat phases

        scripted.VACUUM_HOLD_MOMENT = float("inf")
    installer = HumanlikeInstaller(env, args.operator, seed=0)
    return installer.reset, installer.act


def episode(env, reset, act, seed: int) -> dict:
    from window_bench.envs import scene as S
    from window_bench.envs.env import mat_to_rotvec

    u = env.unwrapped
    obs, _ = env.reset(seed=seed)
    reset(seed)
    sc, d = u.scene, u.data
    grasp, contact, breaks, rows = None, None, [], []
    done, term, t = False, False, 0
    while not done:
        obs, _, term, trunc, _ = env.step(act(obs))
        done, t = term or trunc, t + 1
        rel = d.xpos[sc.panel_body] - u._target_pos
        depth = float(rel @ S.INSERTION_AXIS) * 1000
        wrench = u.osc.weld_force_mean   # the last step's, kept after a break
        moment = float(np.linalg.norm(wrench[3:]))
        if u._suction_failures > len(breaks):
            axis = d.site_xmat[sc.tcp_site].reshape(3, 3)[:, 2]
            pull = float(wrench[:3] @ axis)
            breaks.append({"step": t, "depth_mm": round(depth, 1), "moment_Nm": round(moment, 1),
                           "pull_N": round(pull, 1),
                           "shear_N": round(float(np.linalg.norm(wrench[:3] - pull * axis)), 1)})
        if u._latched and grasp is None:
            pm = d.xmat[sc.panel_body].reshape(3, 3)
            grasp = (pm.T @ (d.site_xpos[sc.tcp_site] - d.xpos[sc.panel_body]) * 1000).round(1)
        rows.append((t, depth, moment))
        if contact is None and u._latched and u._buck_contact():
            lateral = (rel - (rel @ S.INSERTION_AXIS) * S.INSERTION_AXIS) * 1000
            rot = np.rad2deg(mat_to_rotvec(u._target_mat.T @ d.xmat[sc.panel_body].reshape(3, 3)))
            contact = {"step": t, "depth_mm": round(depth, 1),
                       "lateral_mm": lateral.round(1).tolist(), "rot_deg": rot.round(2).tolist()}
    rec = {"seed": seed, "success": bool(term), "steps": t,
           "grasp_mm": None if grasp is None else grasp.tolist(), "first_contact": contact,
           "grip_breaks": breaks}
    if contact is not None:
        c = contact["step"]
        contact["max_moment_10_Nm"] = round(max(m for s, _, m in rows if c <= s < c + 10), 1)
        contact["steps_to_60mm"] = next((s - c for s, dep, _ in rows if s >= c and dep > DEEP_MM),
                                        None)
        # How far it backs off before it gets in (or within 60 steps): a retract-and-realign.
        end = c + (contact["steps_to_60mm"] if contact["steps_to_60mm"] is not None else 60)
        contact["backoff_mm"] = round(contact["depth_mm"] - min(dep for s, dep, _ in rows
                                                                if c <= s <= end), 1)
    return rec


def follows_grasp(touched: list[dict]) -> dict:
    """How the panel's offset at the first contact follows where the cup holds it: per axis,
    the least-squares slope and Pearson r of the contact offset (mm) on the cup's offset from
    the panel's centre (mm) - across the opening (panel x, world x) and vertically (panel y,
    world z). Slope -1: the tool goes where it would for a centred grip (the offset is carried
    to the opening); 0: the grip is corrected for."""
    out = {}
    for name, g, c in (("across", 0, 0), ("vertical", 1, 2)):
        xy = np.array([(e["grasp_mm"][g], e["first_contact"]["lateral_mm"][c])
                       for e in touched if e["grasp_mm"] is not None])
        if len(xy) < 3 or np.ptp(xy[:, 0]) == 0 or np.ptp(xy[:, 1]) == 0:
            out[name] = None
            continue
        out[name] = {"slope": round(float(np.polyfit(xy[:, 0], xy[:, 1], 1)[0]), 2),
                     "r": round(float(np.corrcoef(xy[:, 0], xy[:, 1])[0, 1]), 2),
                     "grasp_std_mm": round(float(xy[:, 0].std()), 1), "n": len(xy)}
    return out


def summary(eps: list[dict]) -> dict:
    touched = [e for e in eps if e["first_contact"]]
    at_entry = [e for e in eps
                if any(ENTRY_MM[0] <= b["depth_mm"] <= ENTRY_MM[1] for b in e["grip_breaks"])]

    def med(vals):
        return round(float(np.median(vals)), 2) if vals else None
    lat = np.array([np.abs(e["first_contact"]["lateral_mm"]) for e in touched]).reshape(-1, 3)
    rot = [float(np.max(np.abs(e["first_contact"]["rot_deg"]))) for e in touched]
    passed = [e["first_contact"]["steps_to_60mm"] for e in touched
              if e["first_contact"]["steps_to_60mm"] is not None]
    return {"episodes": len(eps), "seated": sum(e["success"] for e in eps),
            "touched_held": len(touched),
            "median_abs_lateral_mm_at_contact": [med(list(lat[:, i])) for i in range(3)],
            "median_max_abs_rot_deg_at_contact": med(rot),
            "max_moment_10_Nm_median": med([e["first_contact"]["max_moment_10_Nm"]
                                            for e in touched]),
            "backed_off_5mm": sum(e["first_contact"]["backoff_mm"] >= 5 for e in touched),
            "stalled_at_edge": sum(e["first_contact"]["depth_mm"] < EDGE_MM
                                   and e["first_contact"]["steps_to_60mm"] is None
                                   for e in touched),
            "reached_60mm": len(passed), "median_steps_to_60mm": med(passed),
            "contact_offset_follows_grasp": follows_grasp(touched),
            "episodes_with_grip_break": sum(bool(e["grip_breaks"]) for e in eps),
            "episodes_with_grip_break_at_entry": len(at_entry),
            "failures_with_grip_break_at_entry": sum(not e["success"] for e in at_entry)}


def _centre_grip_at_latch() -> None:
    """Patch ``WindowInstallEnv._set_latch``: before the weld is made, slide the panel in
    its face plane so the TCP sits over the face's centre (gap and orientation kept)."""
    import mujoco

    from window_bench.envs.env import WindowInstallEnv

    latch = WindowInstallEnv._set_latch

    def centred(self, on: bool) -> None:
        if on:
            d, sc = self.data, self.scene
            pm = d.xmat[sc.panel_body].reshape(3, 3).copy()
            across, vertical, _ = self.tcp_on_face()
            self._set_panel_pose(d.xpos[sc.panel_body] + pm @ np.array([across, vertical, 0.0]), pm)
            mujoco.mj_forward(self.model, d)
        latch(self, on)

    WindowInstallEnv._set_latch = centred


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    who = p.add_mutually_exclusive_group(required=True)
    who.add_argument("--policy", help="a policies/step_*.safetensors file (state track)")
    who.add_argument("--operator", help="an operator profile of the scripted installer")
    p.add_argument("--env", default="WindowInstall-B-v0")
    p.add_argument("--episodes", type=int, default=20,
                   help="development seeds from the first one (as `bench eval` takes them)")
    p.add_argument("--unbreakable-grip", action="store_true",
                   help="lift the cup's holding limits (pull, shear, peel moment)")
    p.add_argument("--centre-grip", action="store_true",
                   help="at every latch, slide the panel so the cup holds its face's centre")
    p.add_argument("--no-peel-cue", action="store_true",
                   help="with --operator: it does not back off on the cup's peel moment")
    p.add_argument("--out", required=True, help="JSON file to write (not overwritten)")
    args = p.parse_args(argv)
    from window_bench.installer.operators import OPERATORS

    errs = env_errors(args.env) + episodes_errors(args.episodes) + out_errors(args.out)
    if args.operator is not None and args.operator not in OPERATORS:
        errs.append(f"--operator {args.operator!r}; allowed: {', '.join(sorted(OPERATORS))}")
    if args.no_peel_cue and not args.operator:
        errs.append("--no-peel-cue needs --operator")
    if errs:
        p.error("; ".join(errs))

    import gymnasium as gym

    from window_bench.harness.evaluation import provenance
    from window_bench.harness.seeds import DEV_SEED0

    torch.set_num_threads(1)
    if args.unbreakable_grip:
        import window_bench.envs.env as env_module   # the step reads these module constants

        env_module.VACUUM_HOLD_FORCE = env_module.VACUUM_HOLD_MOMENT = float("inf")
    if args.centre_grip:
        _centre_grip_at_latch()
    env = gym.make(args.env, obs_mode="flat")
    reset, act = _actor(args, p, env)
    eps = []
    for seed in range(DEV_SEED0, DEV_SEED0 + args.episodes):
        eps.append(episode(env, reset, act, seed))
        print(json.dumps({k: eps[-1][k] for k in ("seed", "success", "grip_breaks")}), flush=True)
    env.close()
    out = {"actor": {"policy": args.policy} if args.policy else {"operator": args.operator},
           "env_id": args.env, "unbreakable_grip": args.unbreakable_grip,
           "centre_grip": args.centre_grip,
           "no_peel_cue": args.no_peel_cue,
           "entry_mm": list(ENTRY_MM), "summary": summary(eps),
           "episodes": eps, "provenance": provenance()}
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out["summary"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
