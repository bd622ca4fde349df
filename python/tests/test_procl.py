"""The procl Python package: gymnasium environments, the controller, collect / train, errors."""

from __future__ import annotations

import json
import re
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import procl

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("env_id", list(procl.ENV_IDS))
def test_environments_pass_gymnasiums_checker(env_id):
    check_env(procl.make(env_id, render_mode="rgb_array"), skip_render_check=False)
    env = gymnasium.make(f"procl/{env_id}", render_mode="rgb_array")
    check_env(env.unwrapped, skip_render_check=False)
    obs, info = env.reset(seed=0)
    assert obs.shape == (64, 64, 3) and obs.dtype == np.uint8
    assert info["goal_frame"].shape == (64, 64, 3)
    assert env.render().shape == (64, 64, 3)


def test_reset_seed_determines_start_goal_and_frames():
    env = procl.make("Reacher-v0")
    first, info1 = env.reset(seed=7)
    again, info2 = env.reset(seed=7)
    assert np.array_equal(first, again)
    assert np.array_equal(info1["goal_frame"], info2["goal_frame"])
    assert np.array_equal(info1["goal_q"], info2["goal_q"])
    other, info3 = env.reset(seed=8)
    assert not np.array_equal(info1["goal_q"], info3["goal_q"])
    # Same seed and actions, same trajectory, bit for bit.
    actions = np.random.default_rng(0).uniform(-1, 1, (20, 2)).astype(np.float32)
    runs = []
    for _ in range(2):
        env.reset(seed=7)
        runs.append([env.step(a)[0] for a in actions])
    assert all(np.array_equal(a, b) for a, b in zip(*runs))
    # Options place the start and the goal.
    _, info = env.reset(seed=1, options={"start_q": [0.5, -0.5], "goal_q": [0.0, 0.0]})
    assert np.allclose(info["q"], [0.5, -0.5]) and np.allclose(info["goal_q"], [0.0, 0.0])
    assert info["distance"] > 0


def test_reward_is_minus_the_distance_and_success_terminates():
    env = procl.make("PointMass-v0")
    _, info = env.reset(seed=0, options={"start_q": [0.1, 0.1], "goal_q": [0.1, 0.1]})
    _, reward, terminated, truncated, info = env.step(np.zeros(2, np.float32))
    assert reward == -info["distance"]
    assert terminated and info["is_success"] and not truncated
    env = procl.make("PointMass-v0", horizon=3)
    env.reset(seed=0, options={"start_q": [-0.2, -0.2], "goal_q": [0.2, 0.2]})
    outcomes = [env.step(np.zeros(2))[2:4] for _ in range(3)]
    assert outcomes == [(False, False), (False, False), (False, True)]


def test_shipped_point_mass_controller_reaches_goals():
    controller = procl.Controller.load(procl.pretrained("point-mass"))
    assert controller.label == "ProCL + PD" and controller.env == "point-mass"
    env = procl.make("PointMass-v0")
    reached = 0
    for seed in range(5):
        obs, info = env.reset(seed=seed)
        controller.reset(info["goal_frame"])
        for _ in range(env.horizon):
            obs, _, terminated, truncated, info = env.step(controller.act(obs))
            if terminated or truncated:
                break
        reached += terminated
    assert reached == 5
    # encode: one frame or a batch, the latent the controller acts on.
    h = controller.encode(np.stack([obs, info["goal_frame"]]))
    assert h.shape == (2, 2) and h.dtype == np.float32
    assert np.allclose(h[1], controller.goal_latent, atol=1e-5)
    assert controller.encode(obs).shape == (1, 2)


def test_vector_env_steps_every_copy_and_autoresets_next_step():
    envs = procl.make_vec("PointMass-v0", 3, horizon=2)
    obs, info = envs.reset(seed=4)
    assert obs.shape == (3, 64, 64, 3) and info["goal_q"].shape == (3, 2)
    assert info["_distance"].all()
    zeros = np.zeros((3, 2), np.float32)
    envs.step(zeros)
    _, rewards, terminated, truncated, _ = envs.step(zeros)
    assert truncated.all() and (rewards < 0).all()
    # The next step resets every copy: reward 0, neither flag, a new task.
    _, rewards, terminated, truncated, info = envs.step(zeros)
    assert (rewards == 0).all() and not terminated.any() and not truncated.any()
    # Seeding is reproducible; copy i of reset(seed=s) is the same task each time.
    again = procl.make_vec("PointMass-v0", 3)
    first, _ = again.reset(seed=4)
    assert np.array_equal(first, obs)


def write_custom_dataset(path: Path, episodes=4, steps=10, seed=0):
    """Frames and actions from a rollout, saved with numpy alone (no states, no meta)."""
    env = procl.make("PointMass-v0")
    rng = np.random.default_rng(seed)
    obs = np.zeros((episodes, steps + 1, 64, 64, 3), np.uint8)
    actions = rng.uniform(-1, 1, (episodes, steps, 2)).astype(np.float32)
    for e in range(episodes):
        obs[e, 0], _ = env.reset(seed=e)
        for t in range(steps):
            obs[e, t + 1] = env.step(actions[e, t])[0]
    np.savez(path, obs=obs, actions=actions, control_dt_s=np.float64(env.control_dt_s))


def test_custom_dataset_from_numpy_trains_and_controls(tmp_path):
    data = tmp_path / "camera.npz"
    write_custom_dataset(data)
    info = procl.info(data)
    assert info["env"] == "custom" and info["config_dim"] is None
    assert (info["episodes"], info["steps"], info["action_dim"]) == (4, 10, 2)
    summary = procl.train(data, tmp_path / "run", steps=2, config={"batch_size": 8})
    assert summary["steps"] == 2
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["env"] == "custom" and config["batch_size"] == 8
    controller = procl.Controller.load(tmp_path / "run")
    assert controller.env == "custom" and controller.control_dt_s == pytest.approx(0.02)
    frames = np.load(data)["obs"][0]
    controller.reset(frames[-1])
    action = controller.act(frames[0])
    assert action.shape == (2,) and action.dtype == np.float32
    assert np.all(np.abs(action) <= 1)


def test_collect_and_a_newtonian_vae_run_with_pid(tmp_path):
    summary = procl.collect("point-mass", tmp_path / "pm.npz", transitions=40, episode_len=10)
    assert (summary["env"], summary["transitions"], summary["config_dim"]) == ("point-mass", 40, 2)
    procl.train(tmp_path / "pm.npz", tmp_path / "nvae", method="nvae", steps=1,
                config={"batch_size": 4})
    controller = procl.Controller.load(tmp_path / "nvae")
    assert controller.label == "NewtonianVAE + PID"
    env = procl.make("PointMass-v0")
    obs, info = env.reset(seed=0)
    controller.reset(info["goal_frame"])
    assert controller.act(obs).shape == (2,)


def test_a_variant_collected_as_custom_records_its_simulator(tmp_path):
    data = tmp_path / "variant.npz"
    summary = procl.collect("reacher", data, transitions=400, episode_len=10,
                            variant={"base_m": [0.035, -0.025]}, as_custom=True)
    assert summary["env"] == "custom" and summary["config_dim"] == 2
    recorded = json.loads(summary["env_config_json"])
    assert recorded["reacher"]["base_m"] == [0.035, -0.025]
    meta = json.loads(bytes(np.load(data)["meta"]))
    assert meta["env"] == "custom" and meta["env_config"] == recorded
    # The frames turn about the moved shoulder, at pixel (35.6, 34.6).
    hub = procl.info(data)["hub"]
    assert hub["accepted"] and np.allclose(hub["pixel"], [35.6, 34.6], atol=1.0), hub
    assert 0.0 <= hub["cut_deg"] < 360.0, hub
    plain = procl.collect("reacher", tmp_path / "plain.npz", transitions=400, episode_len=10)
    assert plain["env_config_json"] is None
    assert not np.array_equal(np.load(data)["obs"], np.load(tmp_path / "plain.npz")["obs"])


def test_a_variant_runs_as_a_gymnasium_environment():
    # The shoulder moved 0.035 m right and 0.025 m towards the bottom of the image: at the same
    # configuration the arm's pixels move by 3.6 and 2.6 px (103 px per metre).
    def arm_centroid(frame):
        rows, cols = np.nonzero(frame[..., 0].astype(int) > frame[..., 2].astype(int) + 40)
        return np.array([cols.mean(), rows.mean()])

    options = {"start_q": [0.5, 1.0], "goal_q": [0.0, 0.0]}
    variant = {"base_m": [0.035, -0.025]}
    plain, _ = procl.make("Reacher-v0").reset(seed=0, options=options)
    moved, info = procl.make("Reacher-v0", variant=variant).reset(seed=0, options=options)
    shift = arm_centroid(moved) - arm_centroid(plain)
    assert np.allclose(shift, [3.6, 2.6], atol=0.6), shift
    assert np.array_equal(info["q"], [0.5, 1.0])
    envs = procl.make_vec("Reacher-v0", 2, variant={"base_m": np.array([0.035, -0.025])})
    frames, _ = envs.reset(seed=0)
    assert frames.shape == (2, 64, 64, 3)
    with pytest.raises(procl.ProclError, match="link1_length_m"):
        procl.make("Reacher-v0", variant={"link1_length_m": -1.0})


def test_bad_input_raises_one_line_errors(tmp_path):
    def raises(fn, needle):
        with pytest.raises(procl.ProclError) as caught:
            fn()
        message = str(caught.value)
        assert needle in message and "\n" not in message, message

    raises(lambda: procl.make("CartPole-v1"), "unknown environment")
    raises(lambda: procl.Controller.load(tmp_path / "missing"), str(tmp_path / "missing"))
    env = procl.make("Fetch-v0")
    env.reset(seed=0)
    raises(lambda: env.step(np.zeros(2)), "3")
    controller = procl.Controller.load(procl.pretrained("point-mass"))
    frame = np.zeros((64, 64, 3), np.uint8)
    raises(lambda: controller.act(frame), "reset(goal_frame)")
    raises(lambda: controller.reset(np.zeros((32, 32, 3), np.uint8)), "[64, 64, 3]")
    raises(lambda: controller.encode(np.zeros((2, 48, 64, 3), np.uint8)), "`frames` has shape")
    raises(lambda: procl.pretrained("cartpole"), "point-mass")
    raises(lambda: procl.collect("reacher", tmp_path / "v.npz", variant={"base": 1}), "base")
    raises(lambda: procl.collect("reacher", tmp_path / "v.npz", variant={"base_m": [0.2, 0.0]}),
           "reacher.base_m")
    bad = tmp_path / "bad.npz"
    np.savez(bad, obs=np.zeros((1, 3, 64, 64, 3), np.uint8),
             actions=np.full((1, 2, 2), 2.0, np.float32), control_dt_s=np.float64(0.1))
    raises(lambda: procl.info(bad), "[-1, 1]")
    raises(lambda: procl.train(bad, tmp_path / "r"), str(bad))
    good = tmp_path / "good.npz"
    write_custom_dataset(good, episodes=2, steps=4)
    raises(lambda: procl.train(good, tmp_path / "r2", config={"steps": -1}), "steps")
    raises(lambda: procl.train(good, tmp_path / "r3", method="ppo"), "method")


def test_readme_python_quickstart_runs_as_written(tmp_path, monkeypatch):
    readme = (REPO / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", readme, re.S)
    assert blocks, "README has no Python quickstart"
    monkeypatch.chdir(tmp_path)
    exec(compile(blocks[0], "README.md", "exec"), {})


def test_ctrl_c_stops_training_and_resume_continues(tmp_path):
    import os
    import signal
    import threading

    data = tmp_path / "camera.npz"
    write_custom_dataset(data, episodes=4, steps=10)
    config = {"batch_size": 8, "checkpoint_every": 5, "orientation_search_every": 5}
    # A process started in the background by a non-interactive shell (as CI may be) inherits
    # SIGINT ignored, and Python then installs no handler: install the usual one.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    timer = threading.Timer(1.0, lambda: os.kill(os.getpid(), signal.SIGINT))
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt) as caught:
            # A budget the signal cuts short; should it be missed, the test fails in a minute.
            procl.train(data, tmp_path / "run", steps=3_000, config=config)
    finally:
        timer.cancel()
        signal.signal(signal.SIGINT, previous)
    assert "training stopped after step" in str(caught.value)
    # It stopped within a step or two of the signal, not at the end of the budget; resuming
    # from the kept checkpoint is tested in Rust (tests/integration/faults.rs).
    steps = len((tmp_path / "run" / "metrics.csv").read_text().splitlines()) - 1
    assert 0 < steps < 1_000, steps
