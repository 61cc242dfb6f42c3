"""A curriculum driven by live statistics, inside Brax's own PPO trainer.

`python -m jaxmetrics.examples.curriculum` trains `inverted_pendulum` with
`brax.training.agents.ppo.train` while disturbances grow with each env's level. Envs are
in two groups: "jitter" (noise on every action) and "kick" (random shoves). A group's
envs move to the next level when the group's success rate over its last `--window`
finished episodes at its current level reaches `--threshold` (success: the pole stays up
to the time limit). The rule runs in-graph, in the env's `on_reset`, on the statistics
jaxmetrics keeps anyway: no host sync, and it survives Brax's env resets and `pmap`.
TensorBoard (`tensorboard --logdir runs/curriculum`) shows `Episode_Metrics/level/<group>`
and `Episode_Metrics/success_rate/<group>_l<level>/window_mean`.
"""

import argparse
import functools
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp

import jaxmetrics as jm
import jaxmetrics.brax as jmb

with jmb.quiet_upstream():  # MuJoCo's warp lines, where warp is not installed
    from brax import envs
    from brax.envs.base import Env, State, Wrapper
    from brax.training.agents.ppo import train as ppo

from .brax_ppo import _brax_on_this_jax

GROUPS = ("jitter", "kick")
LEVELS = 4
JITTER_STD = 0.35  # action noise per level (inverted_pendulum's actions are in [-3, 3])
KICK = 1.2  # shove per level, on 5% of the steps


class Disturbed(Wrapper):
    """`inverted_pendulum` with disturbances that grow with `info["level"]`.

    Each env draws its group at reset (`info["group"]`: 0 jitter, 1 kick) and starts at
    level 0; the level is in `info`, which Brax's auto-reset keeps, so whatever
    `on_reset` sets there holds for the env's next episode.
    """

    def reset(self, rng: jax.Array) -> State:
        rng, draw = jax.random.split(rng)
        state = self.env.reset(rng)
        info = {
            **state.info,
            "group": jax.random.bernoulli(draw).astype(jnp.int32),
            "level": jnp.zeros((), jnp.int32),
            "disturbance_key": draw,
        }
        return state.replace(info=info)  # pyright: ignore[reportAttributeAccessIssue]

    def step(self, state: State, action: jax.Array) -> State:
        key, noise_key, kick_key, sign_key = jax.random.split(state.info["disturbance_key"], 4)
        level = state.info["level"].astype(jnp.float32)
        noise = JITTER_STD * level * jax.random.normal(noise_key, action.shape)
        sign = jnp.where(jax.random.bernoulli(sign_key), 1.0, -1.0)
        kick = KICK * level * sign * jax.random.bernoulli(kick_key, 0.05)
        disturbance = jnp.where(state.info["group"] == 0, noise, kick)
        state = state.replace(info={**state.info, "disturbance_key": key})  # pyright: ignore[reportAttributeAccessIssue]
        return self.env.step(state, action + disturbance)


def group_level(t: jmb.Transition) -> jax.Array:
    """Each env's (group, level) as one group index: `group * LEVELS + level`."""
    return t.state.info["group"] * LEVELS + t.state.info["level"]


def metrics_spec(window: int) -> jm.Metrics:
    """Success per (group, level) over the last `window` episodes, level per group, return."""
    by_group_level = jm.groups(group_level, [f"{g}_l{k}" for g in GROUPS for k in range(LEVELS)])
    by_group = jm.groups(lambda t: t.state.info["group"], GROUPS)
    return jm.Metrics(
        terms={
            # Success: the pole stayed up to the time limit.
            "success_rate": jm.success_rate(
                lambda t: t.truncation, window_size=window, groups=by_group_level
            ),
            "level": jm.Term(
                lambda t: t.state.info["level"], reduce="last", stats=("mean",), groups=by_group
            ),
            "episode_return": jmb.episode_return(stats=("mean", "count", jm.window(100))),
        }
    )


def curriculum(window: int, threshold: float) -> Callable[[Callable[..., jax.Array], State], State]:
    """The `on_reset` rule: an env begins its next episode at its group's level, the
    first level whose success rate over the last `window` episodes is below `threshold`
    (or has fewer than `window` episodes yet); the last level is the highest."""

    def on_reset(read: Callable[..., jax.Array], state: State) -> State:
        rate = read("success_rate", "window_mean", by_group=True).reshape(len(GROUPS), LEVELS)
        count = read("success_rate", "window_count", by_group=True).reshape(len(GROUPS), LEVELS)
        mastered = (count >= window) & (rate >= threshold)  # NaN (no episodes): not mastered
        first_open = jnp.argmin(mastered, axis=1)  # the first False (0 if all are True)
        level = jnp.where(jnp.all(mastered, axis=1), LEVELS - 1, first_open).astype(jnp.int32)
        return state.replace(info={**state.info, "level": level[state.info["group"]]})  # pyright: ignore[reportAttributeAccessIssue]

    return on_reset


def make_env(backend: str) -> Env:
    with jmb.quiet_upstream():  # Brax's "not actively maintained" warning
        return Disturbed(envs.get_environment("inverted_pendulum", backend=backend))


def main(argv: Sequence[str] | None = None) -> int:
    """Trains with Brax's PPO under the curriculum; returns the exit status."""
    assert __doc__ is not None
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--timesteps", type=int, default=300_000, help="env steps to train for")
    p.add_argument("--num-envs", type=int, default=128, help="envs stepped together")
    p.add_argument("--batch-size", type=int, default=128, help="PPO's batch_size")
    p.add_argument("--minibatches", type=int, default=4, help="PPO's num_minibatches")
    p.add_argument("--unroll", type=int, default=16, help="PPO's unroll_length")
    p.add_argument("--updates", type=int, default=2, help="PPO's num_updates_per_batch")
    p.add_argument("--backend", default="spring", help="Brax physics: spring (CPU), mjx (GPU)")
    p.add_argument("--window", type=int, default=20, help="episodes per success window")
    p.add_argument("--threshold", type=float, default=0.8, help="success rate to level up")
    p.add_argument("--report-every", type=int, default=None, help="env steps per record")
    p.add_argument("--log-dir", default="runs/curriculum", help="TensorBoard files go here")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    _brax_on_this_jax()

    metrics = metrics_spec(args.window)
    report_every = args.report_every or args.timesteps // 20
    start = time.time()
    memory = jm.MemoryWriter()
    with jm.Logger(metrics, [jm.TensorBoardWriter(args.log_dir), memory]) as logger:

        def progress(step: int, brax_metrics: Mapping[str, Any]) -> None:
            ret = brax_metrics.get("eval/episode_reward")
            shown = "" if ret is None else f"  eval return {float(ret):7.2f}"
            print(f"{time.time() - start:6.1f} s  step {int(step):>8}{shown}", flush=True)

        with jmb.default_promotion():
            ppo.train(
                environment=make_env(args.backend),
                num_timesteps=args.timesteps,
                episode_length=100,
                num_envs=args.num_envs,
                batch_size=args.batch_size,
                num_minibatches=args.minibatches,
                unroll_length=args.unroll,
                num_updates_per_batch=args.updates,
                num_evals=5,
                num_eval_envs=32,
                learning_rate=3e-4,
                entropy_cost=1e-3,
                normalize_observations=True,
                wrap_env_fn=functools.partial(
                    jmb.wrap,
                    metrics=metrics,
                    logger=logger,
                    report_every=report_every,
                    on_reset=curriculum(args.window, args.threshold),
                ),
                progress_fn=progress,
                seed=args.seed,
            )
    if memory.records:
        last = memory.records[-1]
        levels = ", ".join(
            f"{g} {last.scalars.get(f'Episode_Metrics/level/{g}', float('nan')):.2f}"
            for g in GROUPS
        )
        print(f"mean level of the last period's episodes: {levels}")
    print(f"TensorBoard logs in {args.log_dir}; {time.time() - start:.0f} s in all.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
