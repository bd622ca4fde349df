#!/usr/bin/env python3
"""Where a reacher run's goal-reaching failures are (docs/research/reacher.md).

Reads an eval.json written by `procl eval` (it needs the per-episode `goal_configs` and
`final_configs`) and, for the first method in it, counts the failed episodes (final distance
>= the protocol's success threshold):
  - by goal: fingertip angle q0 + q1/2 past 150 or below -130 degrees ("near the cut"), else
    wrist past 120 degrees ("folded"), else "rest";
  - by goal shoulder angle: below -110, -110..110, above 110 degrees;
  - by where the arm stopped: within 5 degrees of a joint limit (shoulder +-160, wrist 0 or 160)
    or in free space, with how many of each ended more than 0.3 rad from the goal;
  - where the eval.json has them, by the latent: whether the arm still moved
    (joint speed > 0.05 rad/s after the last step), and how far its last latent was from the
    goal's as a share of the first's (< 1%: PD had reached h*, so the latent folds two
    configurations onto one h), and how many end in a valley: the last latent less than 0.02
    units from h* per radian of remaining joint error;
  - the failures' remaining joint error (0.1-0.3 rad: near misses, or further), and the goals
    with the wrist under 0.6 rad (the straight wrist).
Standard library only:
  python3 tools/reach_failures.py runs/R/eval.json
"""

import json
import math
import sys

LIMIT = math.radians(160)
NEAR_LIMIT = math.radians(5)
STRAIGHT_WRIST = 0.6
# A failure ends in a valley when its last latent is this close to h* per radian of joint error
# left (the reacher's latent moves 1-2 units per radian of shoulder).
VALLEY_SLOPE = 0.02


def main():
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    try:
        with open(sys.argv[1]) as f:
            report = json.load(f)
    except (OSError, json.JSONDecodeError) as e:
        raise SystemExit(f"{sys.argv[1]}: {e}")
    method = report["methods"][0]
    threshold = report["protocol"]["success_threshold"]
    if not method.get("final_configs"):
        raise SystemExit(f"{sys.argv[1]}: no per-episode configurations (evaluate again)")
    by_goal, by_shoulder, by_stop = {}, {}, {}

    def count(table, key, failed):
        total = table.setdefault(key, [0, 0])
        total[0] += failed
        total[1] += 1

    for distance, goal, final in zip(
        method["final_distances"], method["goal_configs"], method["final_configs"]
    ):
        failed = distance >= threshold
        q0, q1 = (math.degrees(a) for a in goal)
        tip = q0 + q1 / 2
        near_cut = tip > 150 or tip < -130
        count(by_goal, "near the cut" if near_cut else "folded" if q1 > 120 else "rest", failed)
        count(by_shoulder, "below -110" if q0 < -110 else "above 110" if q0 > 110 else
              "-110..110", failed)
        if failed:
            at = []
            if abs(final[0]) > LIMIT - NEAR_LIMIT:
                at.append("shoulder limit")
            if final[1] > LIMIT - NEAR_LIMIT:
                at.append("wrist folded")
            if final[1] < NEAR_LIMIT:
                at.append("wrist straight")
            stop = by_stop.setdefault(" + ".join(at) or "free space", [0, 0])
            stop[0] += 1
            stop[1] += distance > 0.3
    print(f"{method['method']}: success {method['success_rate']:.1%} of {len(method['final_distances'])}")
    # by_stop's second column already counts the failures past 0.3 rad.
    failed = sum(n for n, _ in by_stop.values())
    further = sum(far for _, far in by_stop.values())
    print(f"failures {threshold}-0.3 rad from the goal: {failed - further}, further: {further}")
    straight = [d for d, goal in zip(method["final_distances"], method["goal_configs"])
                if goal[1] < STRAIGHT_WRIST]
    reached = sum(d < threshold for d in straight)
    print(f"goals with the wrist under {STRAIGHT_WRIST} rad: {reached} of {len(straight)} reached")
    for name, table in [("goal", by_goal), ("goal shoulder", by_shoulder)]:
        print(f"failed by {name}:")
        for key, (failed, total) in table.items():
            print(f"  {key}: {failed} of {total}")
    print("failures by where the arm stopped (of them > 0.3 rad from the goal):")
    for key, (failed, far) in sorted(by_stop.items(), key=lambda kv: -kv[1][0]):
        print(f"  {key}: {failed} ({far})")
    print_latent_gaps(method, threshold)


def print_latent_gaps(method, threshold):
    """Failures by motion and by the latent's remaining share of its start gap to h*."""
    columns = ["final_velocities", "goal_latents", "start_latents", "final_latents"]
    if not all(method.get(c) for c in columns):
        return
    rows = []
    valleys = 0
    for distance, q_goal, q_final, qd, goal, start, final in zip(
        method["final_distances"], method["goal_configs"], method["final_configs"],
        *(method[c] for c in columns)
    ):
        if distance < threshold:
            continue
        gap = math.dist(final, goal) / max(math.dist(start, goal), 1e-12)
        speed = math.hypot(*qd)
        rows.append((gap, speed))
        valleys += math.dist(final, goal) < VALLEY_SLOPE * math.dist(q_final, q_goal)
    if not rows:
        return
    moving = sum(speed > 0.05 for _, speed in rows)
    print(f"failures still moving (> 0.05 rad/s): {moving} of {len(rows)}")
    print("failures by the last latent's gap to h* (share of the first's):")
    for low, high in [(0, 0.01), (0.01, 0.2), (0.2, math.inf)]:
        n = sum(low <= gap < high for gap, _ in rows)
        print(f"  {low:.0%}..{'' if high == math.inf else f'{high:.0%}'}: {n}")
    print(f"failures in a valley (|h - h*| < {VALLEY_SLOPE} |q - q*|): {valleys} of {len(rows)}")


if __name__ == "__main__":
    main()
