"""Type hints of procl's Rust core (``procl._procl``)."""

from os import PathLike
from typing import Any, Optional, Sequence, Union

import numpy as np
import numpy.typing as npt

_Path = Union[str, PathLike[str]]

FRAME_PX: int
ENV_NAMES: list[str]

class ProclError(Exception):
    """Bad input, a missing or broken file, an invalid configuration; the message is the
    command line's one-line error."""

class ReachEnv:
    """One environment as a reach task (the core of ``procl.ReachEnv``)."""

    def __init__(
        self, env: str, horizon: Optional[int] = None, variant_json: Optional[str] = None
    ) -> None: ...
    def reset(
        self, seed: Optional[int] = None, options: Optional[dict[str, Any]] = None
    ) -> tuple[npt.NDArray[np.uint8], dict[str, Any]]: ...
    def step(
        self, action: npt.NDArray[np.float64]
    ) -> tuple[npt.NDArray[np.uint8], float, bool, bool, dict[str, Any]]: ...
    def render(self) -> npt.NDArray[np.uint8]: ...
    @property
    def action_dim(self) -> int: ...
    @property
    def config_dim(self) -> int: ...
    @property
    def control_dt_s(self) -> float: ...
    @property
    def horizon(self) -> int: ...
    @property
    def success_threshold(self) -> float: ...
    @property
    def name(self) -> str: ...

class ReachVecEnv:
    """``n`` copies stepped together with next-step autoreset (the core of
    ``procl.ReachVectorEnv``)."""

    def __init__(
        self,
        env: str,
        n: int,
        horizon: Optional[int] = None,
        variant_json: Optional[str] = None,
    ) -> None: ...
    def reset(
        self, seeds: Sequence[int]
    ) -> tuple[npt.NDArray[np.uint8], dict[str, npt.NDArray[Any]]]: ...
    def step(
        self, actions: npt.NDArray[np.float64]
    ) -> tuple[
        npt.NDArray[np.uint8],
        npt.NDArray[np.float64],
        npt.NDArray[np.bool_],
        npt.NDArray[np.bool_],
        dict[str, npt.NDArray[Any]],
    ]: ...
    def render(self) -> npt.NDArray[np.uint8]: ...
    @property
    def num_envs(self) -> int: ...
    @property
    def action_dim(self) -> int: ...
    @property
    def horizon(self) -> int: ...

class Controller:
    """A trained run's controller: latent PD (ProCL, PC3) or PID (NewtonianVAE) on 64x64 RGB
    frames from any source, with the latent velocity estimate kept inside."""

    @staticmethod
    def load(run_dir: _Path) -> Controller:
        """Loads the run folder written by ``procl train``."""
    def reset(self, goal_frame: npt.NDArray[np.uint8]) -> None:
        """Sets the goal image ``[64, 64, 3]`` and forgets the previous frame."""
    def act(self, frame: npt.NDArray[np.uint8]) -> npt.NDArray[np.float32]:
        """The action ``[du]`` in [-1, 1] for the newest frame ``[64, 64, 3]``."""
    def encode(self, frames: npt.NDArray[np.uint8]) -> npt.NDArray[np.float32]:
        """Latents ``[n, du]`` of frames ``[n, 64, 64, 3]`` (or one ``[64, 64, 3]``)."""
    @property
    def latent(self) -> npt.NDArray[np.float64]: ...
    @property
    def goal_latent(self) -> npt.NDArray[np.float64]: ...
    @property
    def label(self) -> str: ...
    @property
    def env(self) -> str: ...
    @property
    def control_dt_s(self) -> float: ...
    @property
    def action_dim(self) -> int: ...

def collect(
    env: str,
    out: _Path,
    seed: int = 0,
    transitions: Optional[int] = None,
    episode_len: Optional[int] = None,
    force: bool = False,
    variant_json: Optional[str] = None,
    as_custom: bool = False,
) -> dict[str, Any]: ...
def info(data: _Path) -> dict[str, Any]: ...
def train(
    data: _Path,
    out: _Path,
    method: Optional[str] = None,
    config_path: Optional[_Path] = None,
    overrides_json: Optional[str] = None,
    preset_env: Optional[str] = None,
    resume: bool = False,
) -> dict[str, Any]: ...
