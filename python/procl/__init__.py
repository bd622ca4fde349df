"""procl: learn a PD-controllable latent space from pixels, then control with PD.

The environments (``make``, ``make_vec``) are goal-reaching tasks stepped in Rust with 64x64
RGB observations; ``Controller`` runs a trained run's latent PD (or a NewtonianVAE run's PID)
on frames from any source; ``collect``, ``train`` and ``info`` do what the ``procl`` command
line does. Errors raise ``ProclError`` with the command line's one-line message.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Mapping, Optional, Union

from . import _procl
from ._envs import ENV_IDS, ReachEnv, ReachVectorEnv, _variant_json, make, make_vec
from ._procl import Controller, ProclError

__all__ = [
    "ENV_IDS",
    "Controller",
    "ProclError",
    "ReachEnv",
    "ReachVectorEnv",
    "collect",
    "info",
    "make",
    "make_vec",
    "pretrained",
    "train",
]

PathLike = Union[str, "os.PathLike[str]"]

#: Folder of the shipped runs (one per environment), inside the package.
MODELS_DIR = Path(__file__).parent / "models"


def pretrained(env: str) -> Path:
    """The run folder of the shipped ProCL run of ``env`` ("point-mass", "reacher", "fetch")."""
    run = MODELS_DIR / env
    if not (run / "model.safetensors").is_file():
        known = sorted(p.name for p in MODELS_DIR.iterdir()) if MODELS_DIR.is_dir() else []
        raise ProclError(f"no shipped run for `{env}` (shipped: {', '.join(known) or 'none'})")
    return run


def collect(
    env: str,
    out: PathLike,
    *,
    seed: int = 0,
    transitions: Optional[int] = None,
    episode_len: Optional[int] = None,
    force: bool = False,
    variant: Optional[Mapping[str, Any]] = None,
    as_custom: bool = False,
) -> dict:
    """Collects a random-control dataset of ``env`` into the ``.npz`` file ``out``.

    Defaults are the command line's: the paper's dataset size (10,000 transitions; Fetch
    50,000) in the environment's episodes. ``variant`` changes fields of the environment's
    configuration (for the reacher e.g. ``{"base_m": [0.035, -0.025]}``), as ``procl collect
    --env-config`` does; ``as_custom`` records the data as custom, so that ``train`` picks its
    recipe from the frames alone while evaluation runs in the recorded simulator. Returns what
    ``info`` returns.
    """
    variant_json = _variant_json(variant)
    return _procl.collect(env, os.fspath(out), seed, transitions, episode_len, force,
                          variant_json, as_custom)


def info(data: PathLike) -> dict:
    """Validates a dataset and describes it: env (or "custom"), episodes, steps, dims, dt, and
    ``hub``, the point its frames turn about (``pixel`` as column and row, ``radial_r2``,
    ``core_share``, whether it is ``accepted`` as a hub, which picks custom data's recipe,
    and ``cut_deg``, where a polar head about it is cut: the direction the frames change
    least, in degrees, 0 along the columns and 90 down the rows), or None for frames that
    never change."""
    return _procl.info(os.fspath(data))


def train(
    data: PathLike,
    out: PathLike,
    *,
    method: Optional[str] = None,
    config: Union[None, PathLike, Mapping[str, Any]] = None,
    seed: Optional[int] = None,
    steps: Optional[int] = None,
    preset_env: Optional[str] = None,
    resume: bool = False,
) -> dict:
    """Trains on ``data`` into the run folder ``out``, as ``procl train`` does.

    ``method`` is "procl" (default), "pc3" or "nvae". ``config`` is a TOML file or a dict of
    the same keys over the preset (``procl config`` prints them). ``preset_env`` picks the
    recipe for custom data ("generic", "point-mass", "reacher" or "fetch"; by default the
    reacher's when the frames turn about a hub, else the generic one). Returns steps done,
    seconds and the final losses.
    """
    overrides = dict(config) if isinstance(config, Mapping) else {}
    config_path = None if config is None or isinstance(config, Mapping) else os.fspath(config)
    if seed is not None:
        overrides["seed"] = seed
    if steps is not None:
        overrides["steps"] = steps
    return _procl.train(
        os.fspath(data),
        os.fspath(out),
        method,
        config_path,
        json.dumps(overrides),
        preset_env,
        resume,
    )
