#!/usr/bin/env python3
"""procl against its PyTorch twin on the same machine, in one run: the training step of the
point-mass and reacher presets (2 threads) and their control steps (1 thread).

Runs each pair in turn, `--rounds` times, alternating procl and PyTorch so both see the same
machine state, and prints each figure (median over rounds of each run's median) and the ratio
PyTorch time / procl time (above 1: procl is faster).

  pip install torch numpy
  python3 benches/twin/compare.py [--rounds 3]
"""

import argparse
import json
import os
import re
import statistics
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))

# (label, cargo bench target, criterion filter, twin arguments)
PAIRS = [
    ("train step, point mass, batch 128, 2 threads", "train", "train_step/point-mass_procl",
     ["--preset", "point-mass", "--what", "train", "--threads", "2"]),
    ("train step, reacher, batch 128, 2 threads", "train", "train_step/reacher_procl",
     ["--preset", "reacher", "--what", "train", "--threads", "2"]),
    ("control step, point mass, 1 thread", "control", "control_step_1thread/procl_pointmass_pd",
     ["--preset", "point-mass", "--what", "control", "--threads", "1"]),
    ("control step, reacher, 1 thread", "control", "control_step_1thread/procl_reacher_pd",
     ["--preset", "reacher", "--what", "control", "--threads", "1"]),
]

UNITS = {"ns": 1e-6, "µs": 1e-3, "us": 1e-3, "ms": 1.0, "s": 1e3}


def procl_ms(target, name):
    """The median of criterion's estimate for one benchmark, in ms."""
    out = subprocess.run(
        ["cargo", "bench", "--bench", target, "--", "--warm-up-time", "2",
         "--measurement-time", "10", "--exact", name],
        cwd=ROOT, capture_output=True, text=True, check=True).stdout
    match = re.search(re.escape(name) + r"\s+time:\s+\[\S+ \S+ (\S+) (\S+) \S+ \S+\]", out)
    if not match:
        sys.exit(f"no criterion estimate for {name} in:\n{out}")
    return float(match.group(1)) * UNITS[match.group(2)]


def twin_ms(args):
    out = subprocess.run([sys.executable, os.path.join(HERE, "twin.py"), *args],
                         capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])["median_ms"]


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    subprocess.run(["cargo", "bench", "--no-run"], cwd=ROOT, check=True,
                   capture_output=True)
    print(f"{'what':<48} {'procl ms':>10} {'PyTorch ms':>11} {'PyTorch/procl':>14}")
    for label, target, name, twin_args in PAIRS:
        procl, torch = [], []
        for _ in range(args.rounds):
            procl.append(procl_ms(target, name))
            torch.append(twin_ms(twin_args))
        p, t = statistics.median(procl), statistics.median(torch)
        print(f"{label:<48} {p:>10.3f} {t:>11.3f} {t / p:>14.2f}", flush=True)


if __name__ == "__main__":
    main()
