"""Brax's own PPO trainer, reporting jaxmetrics statistics while it trains.

`python -m jaxmetrics.examples.brax_ppo` trains `inverted_pendulum` with
`brax.training.agents.ppo.train`, changed in one argument: `wrap_env_fn` builds the env
with `jaxmetrics.brax.wrap(..., logger=logger)`, which reports every period by itself
from inside Brax's jitted, pmapped training step. TensorBoard files go to `--log-dir`
(`tensorboard --logdir runs/brax_ppo`); Brax's own progress (`eval/*`) is printed.
"""

import argparse
import functools
import time
from collections.abc import Mapping, Sequence
from typing import Any

import jax

import jaxmetrics as jm
import jaxmetrics.brax as jmb

with jmb.quiet_upstream():  # MuJoCo's warp lines, where warp is not installed
    from brax import envs
    from brax.training.agents.ppo import train as ppo


def _brax_on_this_jax() -> None:
    """Brax 0.14's `ppo.train` calls `jax.device_put_replicated`, which JAX 0.10 moved out
    of its public namespace; the function itself is unchanged."""
    if not hasattr(jax, "device_put_replicated"):
        from jax._src.api import device_put_replicated

        jax.device_put_replicated = device_put_replicated


def metrics_spec() -> jm.Metrics:
    """Return, length, termination rate and joint speed, with every report statistic."""
    stats = ("mean", "std", "min", "max", "count", jm.ema(0.05), jm.window(100, (50, 90)))
    return jm.Metrics(
        terms={
            "episode_return": jmb.episode_return(stats=(*stats, jm.histogram(20, (0, 100)))),
            "episode_length": jmb.episode_length(stats=stats),
            "termination": jmb.termination_rate(),
            "joint_speed": jmb.joint_velocity(),
        }
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Trains with Brax's PPO and the reporting wrapper; returns the exit status."""
    assert __doc__ is not None
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="inverted_pendulum", help="a Brax env name")
    p.add_argument("--timesteps", type=int, default=8192, help="env steps to train for")
    p.add_argument("--num-envs", type=int, default=32, help="envs stepped together")
    p.add_argument("--report-every", type=int, default=1024, help="env steps per record")
    p.add_argument("--log-dir", default="runs/brax_ppo", help="TensorBoard files go here")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    _brax_on_this_jax()

    metrics = metrics_spec()
    start = time.time()
    with jm.Logger(metrics, [jm.TensorBoardWriter(args.log_dir)]) as logger:

        def progress(step: int, brax_metrics: Mapping[str, Any]) -> None:
            ret = brax_metrics.get("eval/episode_reward")
            shown = "" if ret is None else f"  eval return {float(ret):7.2f}"
            print(f"{time.time() - start:6.1f} s  step {int(step):>8}{shown}", flush=True)

        with jmb.quiet_upstream():  # Brax's "not actively maintained" warning
            env = envs.get_environment(args.env, backend="mjx")
        with jmb.default_promotion():
            ppo.train(
                environment=env,
                num_timesteps=args.timesteps,
                episode_length=100,
                num_envs=args.num_envs,
                batch_size=args.num_envs,
                num_minibatches=4,
                unroll_length=16,
                num_updates_per_batch=2,
                num_evals=2,
                num_eval_envs=16,
                learning_rate=1e-3,
                max_devices_per_host=1,
                progress_fn=progress,
                seed=args.seed,
                # The one changed line: Brax builds its envs with the reporting wrapper.
                wrap_env_fn=functools.partial(
                    jmb.wrap, metrics=metrics, logger=logger, report_every=args.report_every
                ),
            )
    print(f"{logger.emit_calls} records in {args.log_dir} ({time.time() - start:.1f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
