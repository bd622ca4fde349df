#!/usr/bin/env python3
"""The k-step action-response criterion on a dataset's true states (docs/method.md, stop 18).

For the true configuration q, and for the same angles curled into a ring (radius 2 + q1,
angle q0) standing in for a curled latent, prints the share of the k-step response that one
linear map leaves unexplained (1 - R^2, centred least squares over random samples), in the two
forms of `loss.action_response_velocity`:
  extrapolated: q_{t+k} - q_t - k (q_t - q_{t-1})  ~  sum_j (k - j) u_{t+j}
  velocity fit: q_{t+k} - q_t  ~  (q_t - q_{t-1}, sum_j (k - j) u_{t+j})
Standard library only (no numpy):
  python3 tools/k_step_response.py reacher.npz [--samples 4000] [--seed 0]
"""

import argparse
import ast
import math
import random
import struct
import zipfile


def load_f32(archive, name):
    """A little-endian float32 array from an .npz member: (shape, flat values)."""
    raw = archive.read(name + ".npy")
    header_len = struct.unpack("<H", raw[8:10])[0]
    header = ast.literal_eval(raw[10 : 10 + header_len].decode())
    if header["descr"] != "<f4" or header["fortran_order"]:
        raise SystemExit(f"{name}: expected C-ordered <f4, got {header}")
    data = raw[10 + header_len :]
    return header["shape"], struct.unpack(f"<{len(data) // 4}f", data)


def solve(gram, cross):
    """gram^-1 cross by Gauss-Jordan elimination with partial pivoting."""
    p, d = len(gram), len(cross[0])
    rows = [gram[i][:] + cross[i][:] for i in range(p)]
    for c in range(p):
        pivot = max(range(c, p), key=lambda r: abs(rows[r][c]))
        rows[c], rows[pivot] = rows[pivot], rows[c]
        rows[c] = [v / rows[c][c] for v in rows[c]]
        for r in range(p):
            if r != c and rows[r][c] != 0.0:
                f = rows[r][c]
                rows[r] = [a - f * b for a, b in zip(rows[r], rows[c])]
    return [row[p:] for row in rows]


def unexplained(pairs):
    """1 - R^2 of the centred least-squares fit response ~ regressors over `pairs`."""
    m, p, d = len(pairs), len(pairs[0][1]), len(pairs[0][0])
    mean_a = [sum(a[i] for a, _ in pairs) / m for i in range(d)]
    mean_x = [sum(x[i] for _, x in pairs) / m for i in range(p)]
    a = [[v - mu for v, mu in zip(row, mean_a)] for row, _ in pairs]
    x = [[v - mu for v, mu in zip(row, mean_x)] for _, row in pairs]
    gram = [[sum(r[i] * r[j] for r in x) for j in range(p)] for i in range(p)]
    cross = [[sum(xr[i] * ar[j] for xr, ar in zip(x, a)) for j in range(d)] for i in range(p)]
    coefficients = solve(gram, cross)
    explained = sum(coefficients[i][j] * cross[i][j] for i in range(p) for j in range(d))
    total = sum(v * v for row in a for v in row)
    return 1.0 - explained / total


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data")
    parser.add_argument("--samples", type=int, default=4000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    with zipfile.ZipFile(args.data) as archive:
        (episodes, frames, ds), states = load_f32(archive, "states")
        (_, steps, du), actions = load_f32(archive, "actions")
    dq = ds // 2

    def q(e, t):
        return [states[(e * frames + t) * ds + i] for i in range(dq)]

    def u(e, t):
        return [actions[(e * steps + t) * du + i] for i in range(du)]

    def ring(c):
        return [(2.0 + c[1]) * math.cos(c[0]), (2.0 + c[1]) * math.sin(c[0])]

    print("k  extrapolated q  ring  |  velocity fit q  ring")
    for k in [1, 3, 5, 10]:
        rng = random.Random(args.seed)
        samples = [
            (rng.randrange(episodes), rng.randrange(1, steps + 1 - k))
            for _ in range(args.samples)
        ]
        shares = []
        for velocity in [False, True]:
            for chart in [lambda c: c, ring]:
                pairs = []
                for e, t in samples:
                    prev, now, ahead = chart(q(e, t - 1)), chart(q(e, t)), chart(q(e, t + k))
                    step = [b - a for a, b in zip(prev, now)]
                    drive = [
                        sum((k - j) * u(e, t + j)[i] for j in range(k)) for i in range(du)
                    ]
                    moved = [b - a for a, b in zip(now, ahead)]
                    if velocity:
                        pairs.append((moved, step + drive))
                    else:
                        pairs.append(([m - k * s for m, s in zip(moved, step)], drive))
                shares.append(unexplained(pairs))
        print(f"{k:<2} {shares[0]:14.3f} {shares[1]:5.3f}  | {shares[2]:15.3f} {shares[3]:5.3f}")


if __name__ == "__main__":
    main()
