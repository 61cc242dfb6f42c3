"""A jitted PPO on a Brax environment (MJX backend) or a MuJoCo Playground environment,
every metric through jaxmetrics.

One `MetricsState` holds everything: it lives in the env state (`jaxmetrics.brax.wrap`,
or `jaxmetrics.playground.wrap` for a Playground env name such as `CartpoleBalance`), the
env folds episode terms into it on every step (return, length, the env's reward
components, joint velocity, control effort), and the learner logs its values into the
same state with `Metrics.log` after each update.

In host mode the run checkpoints its whole carry with orbax-checkpoint, and a killed run
continues with `--resume`, writing exactly the records of an uninterrupted run (see
`train`).

Run `python -m jaxmetrics.examples.ppo --help`.

The modules, one job each: `_config` (`PPOConfig`), `_networks` (the actor-critic and its
Gaussian), `_obs_stats` (observation normalization), `_algorithm` (GAE, the loss, the pure
`init`/`iteration`: `make_ppo`), `_metrics` (the metrics spec), `_envs` (finding, wrapping
and sharding the env), `_loop` (the three modes), `_checkpoints` (orbax, resume), `_board`
(the console progress bars), `_train` (`train`: a whole run) and `_cli` (`main`).
"""

from ._algorithm import gae as gae
from ._algorithm import make_ppo as make_ppo
from ._cli import main as main
from ._config import PPOConfig as PPOConfig
from ._metrics import LEARNER_METRICS as LEARNER_METRICS
from ._metrics import make_metrics as make_metrics
from ._obs_stats import init_obs_stats as init_obs_stats
from ._obs_stats import normalize_obs as normalize_obs
from ._obs_stats import update_obs_stats as update_obs_stats
from ._train import train as train

__all__ = [
    "LEARNER_METRICS",
    "PPOConfig",
    "gae",
    "init_obs_stats",
    "main",
    "make_metrics",
    "make_ppo",
    "normalize_obs",
    "train",
    "update_obs_stats",
]
