"""The env a run trains on: a Brax or MuJoCo Playground env found by name, wrapped so that
it folds the run's metrics, and split over the devices."""

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P

import jaxmetrics as jm
import jaxmetrics.brax as jmb

from ._config import PPOConfig
from ._metrics import make_metrics

with jmb.quiet_upstream():  # MuJoCo's warp lines, where warp is not installed
    from brax import envs


class WrappedEnv(NamedTuple):
    """A batched env that folds the metrics of `metrics`, and what a PPO needs of it."""

    env: Any  # `jaxmetrics.brax.wrap` or `jaxmetrics.playground.wrap` of the named env
    metrics: jm.Metrics  # the run's spec (`make_metrics`)
    obs_size: int
    action_size: int
    sharding: NamedSharding | None  # the env axis over the devices; None for one device


def brax_env_names() -> list[str]:
    """The names Brax's registry knows (it keeps them in a private dict)."""
    return sorted(getattr(envs, "_envs", {}))


def _playground_env(name: str) -> tuple[Any, Callable[..., Any]]:
    """MuJoCo Playground's env `name` (MJX's JAX implementation: Warp's is for NVIDIA
    GPUs) and its wrap, or a ValueError naming the Brax and Playground envs there are."""
    known = f"known: {brax_env_names()}"
    try:
        from mujoco_playground import registry

        import jaxmetrics.playground as jmp
    except ImportError:
        raise ValueError(
            f"unknown Brax env {name!r}; {known}. For MuJoCo Playground envs, pip install "
            "'jaxmetrics[playground]'."
        ) from None
    if name not in registry.ALL_ENVS:
        raise ValueError(
            f"unknown Brax env {name!r}, nor a MuJoCo Playground env; {known}; Playground's: "
            f"{sorted(registry.ALL_ENVS)}."
        )
    env_config = registry.get_default_config(name)
    env_config.impl = "jax"
    return registry.load(name, config=env_config), jmp.wrap


def _env_sharding(devices: int) -> NamedSharding | None:
    """The env axis split over the first `devices` local devices (None for one)."""
    if devices == 1:
        return None
    local = jax.local_devices()
    if devices > len(local):
        raise ValueError(
            f"PPOConfig(devices={devices}): only {len(local)} local device(s) "
            f"({local[0].platform}). On a CPU, XLA_FLAGS="
            f"--xla_force_host_platform_device_count={devices} makes that many."
        )
    mesh = jax.make_mesh((devices,), ("env",), axis_types=(AxisType.Auto,), devices=local[:devices])
    return NamedSharding(mesh, P("env"))


def make_env(config: PPOConfig) -> WrappedEnv:
    """Finds `config.env_name` (Brax's registry first, then Playground's), builds the
    metrics spec from its `State.metrics`, and wraps it (time limit, action repeat, metrics,
    the env axis split over `config.devices`).

    Raises:
      ValueError: for an unknown env name, an env whose observation is not a flat array,
        or more `devices` than there are local devices.
    """
    with jmb.quiet_upstream():  # Brax's "not actively maintained" warning, on every build
        try:
            raw_env = envs.get_environment(config.env_name, backend=config.backend)
            wrap = jmb.wrap
        except KeyError:
            raw_env, wrap = _playground_env(config.env_name)
    # Brax and MJX run under JAX's default promotion whatever the user's config; the
    # example's own code stays strict.
    with jmb.default_promotion():
        shape = jax.eval_shape(raw_env.reset, jax.random.key_data(jax.random.key(0)))
    if not isinstance(shape.obs, jax.ShapeDtypeStruct) or len(shape.obs.shape) != 1:
        raise ValueError(
            f"env {config.env_name!r} has observation {shape.obs!r}; this PPO needs a flat "
            "array observation."
        )
    obs_size, action_size = shape.obs.shape[0], raw_env.action_size
    names = sorted(shape.metrics)
    metrics = make_metrics(
        reward_components=[n for n in names if n.startswith("reward")],
        other_state_metrics=[n for n in names if not n.startswith("reward")],
        action_size=action_size,
        episode_length=config.episode_length,
    )
    sharding = _env_sharding(config.devices)
    env = wrap(raw_env, metrics, config.episode_length, config.action_repeat, sharding=sharding)
    return WrappedEnv(env, metrics, obs_size, action_size, sharding)
