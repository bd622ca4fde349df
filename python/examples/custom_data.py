"""Bring your own system, end to end: frames and actions saved with numpy alone train with
the recipe procl picks from the frames, and the trained controller runs in a gymnasium loop.

The "system" here is procl's point mass, recorded as any camera would record it (no states,
no metadata), so the result can be checked against the true goal distance:

    python python/examples/custom_data.py --out runs/custom-pm [--episodes 50]

It prints the success rate of the latent PD over the evaluation's goals. The point mass's
frames turn about no hub, so they train with the generic recipe; Reacher-v0's turn about the
shoulder and train with the reacher's.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import procl


def record(env_id: str, episodes: int, steps: int, seed: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Random-action episodes of a gymnasium environment: frames [e, T+1, 64, 64, 3] and
    actions [e, T, du] in [-1, 1]."""
    env = procl.make(env_id)
    rng = np.random.default_rng(seed)
    du = env.action_space.shape[0]
    obs = np.zeros((episodes, steps + 1, 64, 64, 3), np.uint8)
    actions = rng.uniform(-1, 1, (episodes, steps, du)).astype(np.float32)
    for e in range(episodes):
        obs[e, 0], _ = env.reset(seed=seed * 100_000 + e)
        for t in range(steps):
            obs[e, t + 1] = env.step(actions[e, t])[0]
    return obs, actions, env.control_dt_s


def success_rate(run: Path, env_id: str, episodes: int) -> float:
    """Share of goal images the run's controller reaches (gymnasium's terminated flag)."""
    env = procl.make(env_id)
    controller = procl.Controller.load(run)
    reached = 0
    for k in range(episodes):
        obs, info = env.reset(seed=1000 + k)
        controller.reset(info["goal_frame"])
        for _ in range(env.horizon):
            obs, _, terminated, truncated, info = env.step(controller.act(obs))
            if terminated or truncated:
                break
        reached += bool(terminated)
    return reached / episodes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="PointMass-v0")
    parser.add_argument("--out", type=Path, default=Path("runs/custom"))
    parser.add_argument("--transitions", type=int, default=10_000)
    parser.add_argument("--episode-len", type=int, default=100)
    parser.add_argument("--episodes", type=int, default=50, help="evaluation goals")
    parser.add_argument("--steps", type=int, default=None, help="training steps")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    args.out.mkdir(parents=True, exist_ok=True)
    data = args.out / "frames.npz"
    if not data.exists():
        obs, actions, dt = record(
            args.env, args.transitions // args.episode_len, args.episode_len, args.seed
        )
        np.savez(data, obs=obs, actions=actions, control_dt_s=np.float64(dt))
    print(procl.info(data))
    run = args.out / "run"
    if not (run / "model.safetensors").exists():
        print(procl.train(data, run, seed=args.seed, steps=args.steps))
    rate = success_rate(run, args.env, args.episodes)
    print(f"{args.env} as custom data: {100 * rate:.1f}% of {args.episodes} goals")


if __name__ == "__main__":
    main()
