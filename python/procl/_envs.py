"""procl's environments as gymnasium environments: goal-reaching tasks stepped in Rust.

Each episode draws a start and a goal configuration (both at rest) from the reset seed; the
observation is the camera's 64x64 RGB frame, the goal is an image in ``info["goal_frame"]``,
the reward is minus the distance to the goal (metres; the reacher's in joint-space radians),
an episode terminates when that distance falls below the evaluation protocol's threshold and
is truncated at its horizon (500 steps; Fetch 250).
"""

from __future__ import annotations

import json
from typing import Any, Mapping, Optional, Sequence, Union

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from . import _procl

#: gymnasium ids (also registered as ``procl/<id>``) and the environments they name.
ENV_IDS = {"PointMass-v0": "point-mass", "Reacher-v0": "reacher", "Fetch-v0": "fetch"}

FRAME_SPACE = spaces.Box(0, 255, (_procl.FRAME_PX, _procl.FRAME_PX, 3), np.uint8)


def _env_name(name: str) -> str:
    name = name.removeprefix("procl/")
    if name in ENV_IDS:
        return ENV_IDS[name]
    if name in ENV_IDS.values():
        return name
    raise _procl.ProclError(
        f"unknown environment `{name}` (expected {', '.join(ENV_IDS)}, or {', '.join(ENV_IDS.values())})"
    )


def _variant_json(variant: Optional[Mapping[str, Any]]) -> Optional[str]:
    """A variant's fields as the JSON object the Rust core reads; numpy values become lists
    and numbers."""
    if variant is None:
        return None
    return json.dumps(dict(variant), default=lambda value: np.asarray(value).tolist())


def _action_space(action_dim: int) -> spaces.Box:
    return spaces.Box(-1.0, 1.0, (action_dim,), np.float32)


class ReachEnv(gymnasium.Env):
    """One procl environment as a goal-reaching task (see the module docstring).

    ``variant`` changes fields of the environment's configuration, as ``procl collect
    --env-config`` does (for the reacher e.g. ``{"base_m": [0.035, -0.025]}``), so that a
    controller trained on a variant's data runs in that variant.
    ``reset(options={"start_q": [...], "goal_q": [...]})`` sets the start or goal
    configuration instead of drawing it. ``info`` holds the true state ``q``, ``qd``, the goal
    ``goal_q``, ``goal_frame``, ``distance`` and ``is_success``.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 25}

    def __init__(
        self,
        env: str = "point-mass",
        render_mode: Optional[str] = None,
        horizon: Optional[int] = None,
        variant: Optional[Mapping[str, Any]] = None,
    ):
        if render_mode not in (None, "rgb_array"):
            raise _procl.ProclError(f"render_mode `{render_mode}`: procl renders rgb_array only")
        self._core = _procl.ReachEnv(_env_name(env), horizon, _variant_json(variant))
        self.observation_space = FRAME_SPACE
        self.action_space = _action_space(self._core.action_dim)
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": round(1.0 / self._core.control_dt_s)}

    @property
    def control_dt_s(self) -> float:
        """Seconds per step."""
        return self._core.control_dt_s

    @property
    def horizon(self) -> int:
        """Steps after which an episode is truncated."""
        return self._core.horizon

    @property
    def success_threshold(self) -> float:
        """Distance to the goal below which an episode terminates as a success."""
        return self._core.success_threshold

    def reset(
        self, *, seed: Optional[int] = None, options: Optional[dict] = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        task_seed = int(self.np_random.integers(0, 2**63))
        return self._core.reset(task_seed, options)

    def step(self, action) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        action = np.ascontiguousarray(action, dtype=np.float64).reshape(-1)
        return self._core.step(action)

    def render(self) -> Optional[np.ndarray]:
        if self.render_mode == "rgb_array":
            return self._core.render()
        return None


class ReachVectorEnv(VectorEnv):
    """``num_envs`` copies of one environment stepped together in Rust, with next-step
    autoreset: the step after a copy's episode ends resets it (its action is ignored, its
    reward 0). ``reset(seed=s)`` seeds copy ``i`` with ``s + i``; each copy draws its later
    tasks from its own stream. Infos are arrays with a leading copy axis.
    """

    metadata = {"render_modes": ["rgb_array"], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        env: str = "point-mass",
        num_envs: int = 1,
        render_mode: Optional[str] = None,
        horizon: Optional[int] = None,
        variant: Optional[Mapping[str, Any]] = None,
    ):
        self._core = _procl.ReachVecEnv(_env_name(env), num_envs, horizon, _variant_json(variant))
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.single_observation_space = FRAME_SPACE
        self.single_action_space = _action_space(self._core.action_dim)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)

    @staticmethod
    def _with_masks(info: dict) -> dict:
        # gymnasium's vector infos pair each key with a `_key` mask of the copies that set it.
        for key in list(info):
            info["_" + key] = np.ones(len(info[key]), dtype=bool)
        return info

    def reset(
        self,
        *,
        seed: Union[None, int, Sequence[int]] = None,
        options: Optional[dict] = None,
    ) -> tuple[np.ndarray, dict[str, Any]]:
        if seed is None:
            seeds = np.random.SeedSequence().generate_state(self.num_envs, dtype=np.uint64)
        elif isinstance(seed, (int, np.integer)):
            seeds = [int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
        obs, info = self._core.reset([int(s) for s in seeds])
        return obs, self._with_masks(info)

    def step(self, actions):
        actions = np.ascontiguousarray(actions, dtype=np.float64).reshape(self.num_envs, -1)
        obs, rewards, terminated, truncated, info = self._core.step(actions)
        return obs, rewards, terminated, truncated, self._with_masks(info)

    def render(self) -> Optional[tuple[np.ndarray, ...]]:
        if self.render_mode == "rgb_array":
            return tuple(self._core.render())
        return None


def make(name: str, **kwargs: Any) -> ReachEnv:
    """The environment ``name`` ("PointMass-v0", "Reacher-v0", "Fetch-v0", or procl's
    names "point-mass", ...) as a ``gymnasium.Env``; keyword arguments go to ``ReachEnv``."""
    return ReachEnv(_env_name(name), **kwargs)


def make_vec(name: str, num_envs: int, **kwargs: Any) -> ReachVectorEnv:
    """``num_envs`` copies of ``name`` as a ``gymnasium.vector.VectorEnv`` stepped in Rust."""
    return ReachVectorEnv(_env_name(name), num_envs, **kwargs)


for _id, _name in ENV_IDS.items():
    if f"procl/{_id}" not in gymnasium.registry:
        gymnasium.register(
            id=f"procl/{_id}",
            entry_point="procl._envs:ReachEnv",
            kwargs={"env": _name},
            vector_entry_point="procl._envs:ReachVectorEnv",
        )
