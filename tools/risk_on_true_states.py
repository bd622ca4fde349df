#!/usr/bin/env python3
"""The Lyapunov risk of procl's loss evaluated on latents made from a dataset's true states
(docs/method.md, reacher, stop 20).

The latent is h = A s(q), where s standardises each joint angle over the dataset and A is a
2x2 mixing matrix (the identity: the joint angles themselves; a second row mostly along the
first joint: a latent with a faint second joint). As in `loss.risk_latent_std = 1`, h is
standardised per coordinate over the batch, v is the finite difference (h_t - h_{t-1}) / dt,
v* is v permuted across the batch and h* = h + (u - Kd (v* - v)) / Kp (paper eq. 9). Prints
mean max(0, V(z_{t+1} - z*) - V(z_t - z*)) / dt for each velocity weight q_v.
Standard library only (no numpy):
  python3 tools/risk_on_true_states.py reacher.npz [--mix "1,0;0,1"] [--kp 1] [--kd 0.2]
"""

import argparse
import ast
import json
import random
import struct
import zipfile

from k_step_response import load_f32


def load_u8(archive, name):
    """The bytes of a uint8 .npz member."""
    raw = archive.read(name + ".npy")
    header_len = struct.unpack("<H", raw[8:10])[0]
    header = ast.literal_eval(raw[10 : 10 + header_len].decode())
    if header["descr"] != "|u1":
        raise SystemExit(f"{name}: expected |u1, got {header}")
    return raw[10 + header_len :]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("--mix", default="1,0;0,1", help="rows of A, e.g. '1,0;0.9,0.44'")
    parser.add_argument("--kp", type=float, default=1.0)
    parser.add_argument("--kd", type=float, default=0.2)
    parser.add_argument("--q-v", default="0.1,0.01,0", help="velocity weights to compare")
    parser.add_argument("--samples", type=int, default=4000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    with zipfile.ZipFile(args.dataset) as archive:
        (episodes, frames, width), states = load_f32(archive, "states")
        _, actions = load_f32(archive, "actions")
        meta = json.loads(bytes(load_u8(archive, "meta")).decode())
    dt, steps, dq = meta["control_dt_s"], frames - 1, width // 2
    mix = [[float(x) for x in row.split(",")] for row in args.mix.split(";")]
    if len(mix) != dq or any(len(row) != dq for row in mix):
        raise SystemExit(f"--mix must be {dq}x{dq}")

    def q(e, t, i):
        return states[(e * frames + t) * width + i]

    count = episodes * frames
    mean = [sum(q(e, t, i) for e in range(episodes) for t in range(frames)) / count for i in range(dq)]
    std = [
        (sum((q(e, t, i) - mean[i]) ** 2 for e in range(episodes) for t in range(frames)) / count)
        ** 0.5
        for i in range(dq)
    ]

    def latent(e, t):
        s = [(q(e, t, i) - mean[i]) / std[i] for i in range(dq)]
        return [sum(row[i] * s[i] for i in range(dq)) for row in mix]

    rng = random.Random(args.seed)
    batch = [(rng.randrange(episodes), rng.randrange(1, steps)) for _ in range(args.samples)]
    h_prev, h_now, h_next = ([latent(e, t + d) for e, t in batch] for d in (-1, 0, 1))
    # The batch standardisation of `risk_latent_std = 1` (one scale for every latent of a sample).
    n = len(batch)
    centre = [sum(h[j] for h in h_now) / n for j in range(dq)]
    scale = [(sum((h[j] - centre[j]) ** 2 for h in h_now) / n) ** 0.5 for j in range(dq)]
    h_prev, h_now, h_next = ([[h[j] / scale[j] for j in range(dq)] for h in hs] for hs in (h_prev, h_now, h_next))
    v_now = [[(a[j] - b[j]) / dt for j in range(dq)] for a, b in zip(h_now, h_prev)]
    v_next = [[(a[j] - b[j]) / dt for j in range(dq)] for a, b in zip(h_next, h_now)]
    permutation = list(range(n))
    rng.shuffle(permutation)

    print(f"mix {mix}, Kp {args.kp}, Kd {args.kd}, {n} samples, dt {dt}")
    for q_v in (float(x) for x in args.q_v.split(",")):
        total = 0.0
        for k, (e, t) in enumerate(batch):
            u = [actions[(e * steps + t) * dq + j] for j in range(dq)]
            v_star = v_now[permutation[k]]
            h_star = [h_now[k][j] + (u[j] - args.kd * (v_star[j] - v_now[k][j])) / args.kp for j in range(dq)]

            def value(h, v):
                return sum((h[j] - h_star[j]) ** 2 for j in range(dq)) + q_v * sum(
                    (v[j] - v_star[j]) ** 2 for j in range(dq)
                )

            total += max(0.0, (value(h_next[k], v_next[k]) - value(h_now[k], v_now[k])) / dt)
        print(f"q_v {q_v}: risk {total / n:.3f}")


if __name__ == "__main__":
    main()
