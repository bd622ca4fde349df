#!/usr/bin/env python3
"""PyTorch twin of procl's shipped training step and control step, for a side-by-side timing.

Same layers, shapes, batch, losses, optimiser and thread count as procl's presets (see
src/model/, src/losses/ and src/train/config.rs); random frames stand in for a dataset, since
the cost does not depend on what the frames show. Prints one JSON line with the median and
the quartiles of the step time in milliseconds.

  pip install torch numpy
  python3 benches/twin/twin.py --preset point-mass --what train --threads 2
  python3 benches/twin/twin.py --preset point-mass --what control --threads 1
"""

import argparse
import bisect
import json
import math
import statistics
import time

import torch
import torch.nn as nn
import torch.nn.functional as F

DT = 0.02
FADE_RADIUS = 0.05


def hub_fade(r2):
    """How much an angle about the hub counts at squared distance `r2`: 0 at the hub."""
    return r2 / (r2 + FADE_RADIUS**2)


def pixel_grid(rows, cols):
    xs = (2.0 * torch.arange(cols, dtype=torch.float32) + 1.0) / cols - 1.0
    ys = (2.0 * torch.arange(rows, dtype=torch.float32) + 1.0) / rows - 1.0
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    return grid_x.reshape(1, 1, -1), grid_y.reshape(1, 1, -1)


class Encoder(nn.Module):
    """procl's soft-argmax encoder: two convs, 1x1 feature maps, per-keypoint sharpness,
    Cartesian or polar keypoints (with the angles between them), a linear or tanh head."""

    def __init__(self, du, second_stride, polar, pairwise, hidden, falloff=0.0, moving_cut=False,
                 keypoints=16):
        super().__init__()
        self.conv1 = nn.Conv2d(3, 16, 4, stride=2, padding=1)
        self.conv2 = nn.Conv2d(16, 32, 3, stride=second_stride, padding=1)
        self.features = nn.Conv2d(32, keypoints, 1)
        self.log_sharpness = nn.Parameter(torch.full((keypoints,), math.log(30.0)))
        self.polar, self.pairwise, self.k = polar, pairwise, keypoints
        width = 2 * keypoints + (keypoints * (keypoints - 1) // 2 if pairwise else 0)
        self.hidden = nn.Linear(width, hidden) if hidden else None
        self.out = nn.Linear(hidden or width, du)
        side = 32 // second_stride
        gx, gy = pixel_grid(side, side)
        self.register_buffer("grid_x", gx)
        self.register_buffer("grid_y", gy)
        self.register_buffer("transform", torch.eye(du))
        r2 = gx**2 + gy**2
        cell_angle, cell_fade = torch.atan2(gy, gx), hub_fade(r2)
        # The outer cells' angles count less (model.encoder.polar_angle_falloff).
        cell_weight = 1 / (1 + r2 / falloff**2) if falloff > 0 else torch.ones_like(r2)
        self.register_buffer("angle", cell_angle * cell_fade * cell_weight)
        self.register_buffer("radius", r2.sqrt())
        self.moving_cut = moving_cut
        if moving_cut:
            # Each frame's cut opposite its direction from the still background
            # (model.encoder.polar_moving_cut): the cells' raw angles, fades and weights, and
            # each pixel's faded unit direction. The random frames have no still background,
            # so a blank one and the axis at 0 stand in: the cost is the same.
            self.register_buffer("cell_angle", cell_angle)
            self.register_buffer("cell_fade", cell_fade)
            self.register_buffer("cell_weight", cell_weight)
            px, py = pixel_grid(64, 64)
            pixel_fade, pixel_angle = hub_fade(px**2 + py**2), torch.atan2(py, px)
            self.register_buffer("pixel_cos", (pixel_fade * pixel_angle.cos()).reshape(1, 64, 64))
            self.register_buffer("pixel_sin", (pixel_fade * pixel_angle.sin()).reshape(1, 64, 64))
            self.register_buffer("background", torch.zeros(1, 3, 64, 64))
            self.axis = 0.0
        pairs = torch.triu_indices(keypoints, keypoints, 1)
        self.register_buffer("upper", pairs[0] * keypoints + pairs[1])

    def forward(self, frames):
        x = F.relu(self.conv1(frames))
        x = F.relu(self.conv2(x))
        maps = self.features(x)
        n, k = maps.shape[:2]
        logits = maps.reshape(n, k, -1) * self.log_sharpness.exp().reshape(1, k, 1)
        attention = torch.softmax(logits, dim=2)

        def expected(grid):
            return (attention * grid).sum(dim=2, keepdim=True)

        if self.polar and self.moving_cut:
            coords = [expected(self.frame_angles(frames)), expected(self.radius)]
        elif self.polar:
            coords = [expected(self.angle), expected(self.radius)]
        else:
            coords = [expected(self.grid_x), expected(self.grid_y)]
        feats = torch.cat(coords, dim=1).reshape(n, -1)
        if self.pairwise:
            x_k, y_k = expected(self.grid_x), expected(self.grid_y)
            x_j, y_j = x_k.reshape(n, 1, k), y_k.reshape(n, 1, k)
            cross = x_k * y_j - y_k * x_j
            dot = x_k * x_j + y_k * y_j
            r2 = x_k**2 + y_k**2
            fade = hub_fade(r2)
            angle = torch.atan2(cross, dot + 1e-12) * (fade * fade.reshape(n, 1, k))
            feats = torch.cat([feats, angle.reshape(n, k * k)[:, self.upper]], dim=1)
        if self.hidden is not None:
            feats = torch.tanh(self.hidden(feats))
        return self.out(feats) @ self.transform.T

    def frame_angles(self, frames):
        """Each frame's cells' angles, `[n, 1, cells]`, measured from its own direction."""
        with torch.no_grad():
            d = (frames - self.background).abs().sum(1)
            psi = torch.atan2((d * self.pixel_sin).sum((1, 2)), (d * self.pixel_cos).sum((1, 2)))

            def wrap(a):
                return torch.remainder(a + math.pi, 2 * math.pi) - math.pi

            big_psi = wrap(psi - self.axis).reshape(-1, 1, 1)
            offset = wrap(self.cell_angle - psi.reshape(-1, 1, 1))
            before_cut = ((math.pi - offset.abs()) / (math.pi / 4)).clamp(max=1.0)
            return (big_psi + self.cell_fade * offset * before_cut) * self.cell_weight


class Dynamics(nn.Module):
    """`v' = v + dt a(h, dt v, u)`, `h' = h + dt v'`, a 2x64 ReLU MLP, diagonal log std."""

    def __init__(self, du, hidden=64):
        super().__init__()
        self.fc1, self.fc2 = nn.Linear(3 * du, hidden), nn.Linear(hidden, hidden)
        self.fc3 = nn.Linear(hidden, du)
        self.log_std = nn.Parameter(torch.full((2 * du,), math.log(0.1)))

    def forward(self, h, v, u):
        accel = self.fc3(F.relu(self.fc2(F.relu(self.fc1(torch.cat([h, v * DT, u], 1))))))
        v_next = v + accel * DT
        return h + v_next * DT, v_next

    def jvp(self, h, v, u, th, tv, tu):
        x = torch.cat([h, v * DT, u], 1)
        tx = torch.cat([th, tv * DT, tu], 1)
        pre1 = self.fc1(x)
        t1 = (tx @ self.fc1.weight.T) * (pre1 > 0).float()
        pre2 = self.fc2(F.relu(pre1))
        t2 = (t1 @ self.fc2.weight.T) * (pre2 > 0).float()
        accel = self.fc3(F.relu(pre2))
        t_accel = t2 @ self.fc3.weight.T
        v_next = v + accel * DT
        t_v = tv + t_accel * DT
        return (h + v_next * DT, v_next), (th + t_v * DT, t_v)


def least_squares(a, x):
    """Coefficients of `a ~ x B + c` with `(x^T x)^-1` held fixed (procl's sign term)."""
    a, x = a - a.mean(0), x - x.mean(0)
    inverse = torch.linalg.inv((x.T @ x).detach().double()).float()
    return inverse @ (x.T @ a)


def sign_term(response, regressors, h, regions, floor):
    n, p = regressors.shape
    d = response.shape[1]
    mask = torch.zeros(p, d)
    for i in range(d):
        mask[p - d + i, i] = 1.0
    whole = least_squares(response, regressors)
    scale = whole[p - d :].detach().pow(2).mean().sqrt().item()
    centred = (h - h.mean(0)).detach().double()
    _, vectors = torch.linalg.eigh(centred.T @ centred)
    order = torch.argsort(centred @ vectors[:, -1], stable=True)
    total = torch.zeros(())
    for r in range(regions):
        rows = order[r * n // regions : (r + 1) * n // regions]
        local = least_squares(response[rows], regressors[rows])
        total = total + F.relu(-(local * mask)).sum()
        drive = local[p - d :]
        u, s, vt = torch.linalg.svd(drive.detach().double())
        outer = (u[:, -1:] @ vt[-1:, :]).float()
        total = total + F.relu(floor * scale - (drive * outer).sum())
    return total / (regions * scale)


PRESETS = {
    # point mass: Cartesian keypoints over 16x16 cells, tanh head, paper gains.
    "point-mass": dict(second_stride=2, polar=False, pairwise=False, hidden=32, kp=10.0,
                       kd=2.0, q_v=0.1, lambda_r=10.0, ahead=0, std_c=None),
    # reacher: polar keypoints with their pairwise angles over 32x32 cells, the cells' angles
    # falling off beyond 0.4 and cut opposite each frame's arm, tanh head, the standardised risk
    # and the sign term (5 steps ahead, 6 groups).
    "reacher": dict(second_stride=1, polar=True, pairwise=True, hidden=32, falloff=0.4,
                    moving_cut=True, kp=1.0, kd=0.2, q_v=0.0, lambda_r=1.0, ahead=5, std_c=1.0),
}


def clip_to_percentile(params, norms, percentile=10.0):
    """Scales the gradient down to the `percentile` of the run's global gradient norms so far
    (`norms`, ascending, this step's included), as procl's trainer does (AutoClip)."""
    grads = [p.grad for p in params if p.grad is not None]
    norm = float(torch.linalg.vector_norm(torch.stack([g.norm() for g in grads])))
    bisect.insort(norms, norm)
    threshold = norms[int(percentile / 100 * (len(norms) - 1) + 0.5)]
    if norm > threshold:
        for g in grads:
            g.mul_(threshold / norm)


def train_step(enc, dyn, opt, norms, frames, u, drive, cfg, n, du):
    h = enc(frames)
    h_prev, h_now, h_next = h[:n], h[n : 2 * n], h[2 * n : 3 * n]
    v_now = (h_now - h_prev) / DT
    h_noisy = h_next + torch.randn(n, du) * 0.01
    v_noisy = (h_noisy - h_now) / DT
    h_pred, v_pred = dyn(h_now, v_now, u)
    z_next = torch.cat([h_noisy, v_noisy * DT], 1)
    z_pred = torch.cat([h_pred, v_pred * DT], 1)
    d = 2 * du
    diff = (z_next.unsqueeze(1) - z_pred.unsqueeze(0)) * torch.exp(-dyn.log_std)
    log_density = -0.5 * diff.pow(2).sum(2) - (dyn.log_std.sum() + 0.5 * d * math.log(2 * math.pi))
    log_density = log_density + du * math.log(DT)
    cpc = -torch.log_softmax(log_density, 1).diagonal().mean()
    cons = -log_density.diagonal().mean()
    eta = [torch.randn(n, du) * 0.1 for _ in range(3)]
    (hb, vb), (th, tv) = dyn.jvp(h_now, v_now, u, *eta)
    hp, vp = dyn(h_now + eta[0], v_now + eta[1], u + eta[2])
    curv = (torch.cat([hp - hb - th, vp - vb - tv], 1)).pow(2).sum(1).mean()
    # The Lyapunov risk on clean encodings, with hindsight targets.
    h_after, v_after = h_next, (h_next - h_now) / DT
    h_r, v_r = h_now, v_now
    if cfg["std_c"]:
        scale = cfg["std_c"] / (h_now.var(0, unbiased=False) + 1e-12).sqrt()
        h_r, v_r, h_after, v_after = h_r * scale, v_r * scale, h_after * scale, v_after * scale
    perm = torch.randperm(n)
    v_star = v_r[perm]
    h_star = h_r + (u - (v_star - v_r) * cfg["kd"]) / cfg["kp"]

    def lyap(hh, vv):
        return (hh - h_star).pow(2).sum(1) + cfg["q_v"] * (vv - v_star).pow(2).sum(1)

    risk = F.relu((lyap(h_after, v_after) - lyap(h_r, v_r)) / DT).mean()
    total = cpc + cons + 10.0 * curv + cfg["lambda_r"] * risk
    if cfg["ahead"]:
        h_ahead = h[3 * n :]
        response = h_ahead - h_now
        regressors = torch.cat([h_now - h_prev, drive], 1)
        total = total + 3.0 * sign_term(response, regressors, h_now, 6, 0.25)
    opt.zero_grad(set_to_none=True)
    total.backward()
    clip_to_percentile([p for group in opt.param_groups for p in group["params"]], norms)
    opt.step()


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--preset", choices=sorted(PRESETS), default="point-mass")
    parser.add_argument("--what", choices=["train", "control"], default="train")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--batch", type=int, default=128)
    parser.add_argument("--iters", type=int, default=30)
    parser.add_argument("--warmup", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    cfg = PRESETS[args.preset]
    du, n = 2, args.batch
    enc = Encoder(du, cfg["second_stride"], cfg["polar"], cfg["pairwise"], cfg["hidden"],
                  cfg.get("falloff", 0.0), cfg.get("moving_cut", False))
    dyn = Dynamics(du)
    times = []
    if args.what == "train":
        opt = torch.optim.Adam(list(enc.parameters()) + list(dyn.parameters()), lr=1e-3)
        frames_per_sample = 4 if cfg["ahead"] else 3
        raw = torch.randint(0, 256, (frames_per_sample * n, 64, 64, 3), dtype=torch.uint8)
        u = torch.rand(n, du) * 2 - 1
        drive = torch.rand(n, du) * 2 - 1
        norms = []
        for i in range(args.warmup + args.iters):
            start = time.perf_counter()
            # As procl does each step: u8 HWC frames to a [-0.5, 0.5] CHW batch.
            frames = raw.permute(0, 3, 1, 2).float() / 255.0 - 0.5
            train_step(enc, dyn, opt, norms, frames, u, drive, cfg, n, du)
            if i >= args.warmup:
                times.append(time.perf_counter() - start)
    else:
        raw = torch.randint(0, 256, (64, 64, 3), dtype=torch.uint8)
        h_goal = torch.zeros(1, du)
        h_last = torch.zeros(1, du)
        with torch.inference_mode():
            for i in range(args.warmup + 20 * args.iters):
                start = time.perf_counter()
                frame = raw.permute(2, 0, 1).unsqueeze(0).float() / 255.0 - 0.5
                h = enc(frame)
                v = (h - h_last) / DT
                action = (cfg["kp"] * (h_goal - h) + cfg["kd"] * (0 - v)).clamp(-1, 1)
                action.numpy()
                h_last = h
                if i >= args.warmup:
                    times.append(time.perf_counter() - start)
    q = statistics.quantiles([1e3 * t for t in times], n=4)
    print(json.dumps({"impl": "pytorch", "preset": args.preset, "what": args.what,
                      "threads": args.threads, "median_ms": q[1], "q1_ms": q[0], "q3_ms": q[2],
                      "torch": torch.__version__}))


if __name__ == "__main__":
    main()
