#!/usr/bin/env python3
"""Where a reacher run's goal-reaching failures are (docs/method.md, stops 17-18).

Reads an eval.json written by `procl eval` (it needs the per-episode `goal_configs` and
`final_configs`) and, for the first method in it, counts the failed episodes (final distance
>= the protocol's success threshold):
  - by goal: fingertip angle q0 + q1/2 past 150 or below -130 degrees ("near the cut"), else
    wrist past 120 degrees ("folded"), else "rest";
  - by goal shoulder angle: below -110, -110..110, above 110 degrees;
  - by where the arm stopped: within 5 degrees of a joint limit (shoulder +-160, wrist 0 or 160)
    or in free space, with how many of each ended more than 0.3 rad from the goal.
Standard library only:
  python3 tools/reach_failures.py runs/R/eval.json
"""

import json
import math
import sys

LIMIT = math.radians(160)
NEAR_LIMIT = math.radians(5)


def main():
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    with open(sys.argv[1]) as f:
        report = json.load(f)
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
    for name, table in [("goal", by_goal), ("goal shoulder", by_shoulder)]:
        print(f"failed by {name}:")
        for key, (failed, total) in table.items():
            print(f"  {key}: {failed} of {total}")
    print("failures by where the arm stopped (of them > 0.3 rad from the goal):")
    for key, (failed, far) in sorted(by_stop.items(), key=lambda kv: -kv[1][0]):
        print(f"  {key}: {failed} ({far})")


if __name__ == "__main__":
    main()
