"""`PPOConfig`: the static settings of a run, checked when built."""

import dataclasses
import math
from collections.abc import Callable
from typing import Any


def is_int(v: Any) -> bool:
    """A Python int; `True`/`False` are not (bool is an int subclass)."""
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


_POSITIVE_INTS = (
    "devices",
    "num_envs",
    "unroll_length",
    "total_steps",
    "episode_length",
    "action_repeat",
    "update_epochs",
    "num_minibatches",
)


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """Static configuration of a PPO run. Validated when built.

    Env steps are counted as Brax counts them: env steps x `action_repeat`.

    Attributes:
      env_name: a Brax environment name (`brax.envs.get_environment`), or a MuJoCo
        Playground one (`mujoco_playground.registry`, e.g. "CartpoleBalance"; needs the
        `playground` extra), run with MJX's JAX implementation and the env's own
        `ctrl_dt`/`sim_dt`.
      backend: the Brax physics backend (Brax envs only).
      num_envs: parallel envs per seed.
      unroll_length: env steps per env per iteration.
      total_steps: env steps to train for (rounded up to whole iterations).
      episode_length: the time limit, in env steps x `action_repeat`.
      action_repeat: physics sub-steps per env step.
      update_epochs: passes over each iteration's batch.
      num_minibatches: minibatches per pass; must divide each device's batch
        `num_envs / devices * unroll_length`.
      learning_rate: Adam's step size (annealed linearly to 0 when `anneal_lr`).
      anneal_lr: anneal the learning rate linearly to 0 over the run.
      gamma: discount.
      gae_lambda: GAE's lambda.
      clip_eps: the clipping range of the probability ratio.
      entropy_coef: weight of the entropy bonus.
      value_coef: weight of the value loss.
      max_grad_norm: global-norm gradient clipping.
      reward_scaling: rewards are multiplied by this inside the losses (not in metrics).
      hidden_sizes: hidden layers of the policy and the value networks (tanh).
      normalize_observations: running mean/std normalization of observations.
      devices: local devices to train on, data-parallel: each seed's envs are split
        evenly over them (metrics fold shard-locally), parameters are replicated, and
        each minibatch's gradient is the mean over the whole batch (XLA all-reduces it).
        Must divide `num_envs`.
    """

    env_name: str = "inverted_pendulum"
    backend: str = "mjx"
    num_envs: int = 64
    unroll_length: int = 32
    total_steps: int = 600_000
    episode_length: int = 1000
    action_repeat: int = 1
    update_epochs: int = 4
    num_minibatches: int = 4
    learning_rate: float = 1e-3
    anneal_lr: bool = True
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.2
    entropy_coef: float = 0.0
    value_coef: float = 0.5
    max_grad_norm: float = 0.5
    reward_scaling: float = 1.0
    hidden_sizes: tuple[int, ...] = (64, 64)
    normalize_observations: bool = True
    devices: int = 1

    def __post_init__(self):
        self._check(_POSITIVE_INTS, lambda v: is_int(v) and v >= 1, "a positive int")
        if self.num_envs % self.devices:
            raise ValueError(
                f"PPOConfig: devices={self.devices} must divide num_envs={self.num_envs} "
                "(each device steps the same number of envs)."
            )
        batch = self.num_envs // self.devices * self.unroll_length
        if batch % self.num_minibatches:
            raise ValueError(
                f"PPOConfig: num_minibatches={self.num_minibatches} must divide each "
                f"device's batch num_envs / devices * unroll_length = {batch}."
            )
        unit = ("gamma", "gae_lambda")
        self._check(unit, lambda v: _is_number(v) and 0.0 <= v <= 1.0, "in [0, 1]")
        positive = ("clip_eps", "learning_rate", "max_grad_norm")
        self._check(positive, lambda v: _is_number(v) and v > 0, "a number > 0")
        non_negative = ("entropy_coef", "value_coef", "reward_scaling")
        self._check(non_negative, lambda v: _is_number(v) and v >= 0, "a number >= 0")
        sizes = self.hidden_sizes
        if not isinstance(sizes, tuple) or not sizes or not all(is_int(h) and h > 0 for h in sizes):
            raise ValueError(
                f"PPOConfig(hidden_sizes=...) must be a non-empty tuple of positive ints, "
                f"got {sizes!r}."
            )

    def _check(self, names: tuple[str, ...], ok: Callable[[Any], bool], what: str) -> None:
        """Raises for the first of `names` whose value fails `ok`, naming it and `what`
        it must be."""
        for name in names:
            v = getattr(self, name)
            if not ok(v):
                raise ValueError(f"PPOConfig({name}=...) must be {what}, got {v!r}.")

    @property
    def steps_per_iteration(self) -> int:
        """Env steps (x `action_repeat`) collected per iteration, per seed."""
        return self.num_envs * self.unroll_length * self.action_repeat

    @property
    def num_iterations(self) -> int:
        """Iterations needed to reach `total_steps`."""
        return -(-self.total_steps // self.steps_per_iteration)

    @property
    def updates_per_iteration(self) -> int:
        """Gradient steps per iteration: epochs x minibatches."""
        return self.update_epochs * self.num_minibatches


def config_values(config: PPOConfig) -> dict[str, bool | int | float | str]:
    """The fields as JSON/hparam values (a tuple such as `hidden_sizes` as its `str`)."""
    out: dict[str, bool | int | float | str] = {}
    for f in dataclasses.fields(config):
        v = getattr(config, f.name)
        out[f.name] = v if isinstance(v, (bool, int, float, str)) else str(v)
    return out
