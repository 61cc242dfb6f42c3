"""The command line: `python -m jaxmetrics.examples.ppo` and the `jaxmetrics-ppo` script."""

import argparse
import dataclasses
import os
import sys
import time
from collections.abc import Sequence

from ._board import HEADLINE
from ._config import PPOConfig
from ._envs import brax_env_names
from ._loop import MODES
from ._train import GRAPH_CHECKPOINTS, train

CHECKPOINT_EVERY = 50
"""The command line's default for `--checkpoint-every` (host mode), in iterations."""

# The flags that set a PPOConfig field have the field's name as their dest (`config_flag`).
_CONFIG_FIELDS = frozenset(f.name for f in dataclasses.fields(PPOConfig))


def _prog() -> str:
    # Run as `python -m jaxmetrics.examples.ppo`, argv[0] is the package's `__main__.py`;
    # run as the installed `jaxmetrics-ppo` script, it is that script.
    name = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else ""
    return "python -m jaxmetrics.examples.ppo" if name in ("", "__main__.py", "-c") else name


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=_prog(),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description=(
            "Train PPO on a Brax environment (MJX backend) or a MuJoCo Playground one "
            "(e.g. --env CartpoleBalance) with every metric logged "
            "through jaxmetrics to TensorBoard. The defaults train inverted_pendulum to "
            "the maximum return (1,000) in under a minute on a 2-core laptop CPU, "
            "compilation included."
        ),
    )
    defaults = PPOConfig()

    def config_flag(flag: str, field: str, text: str) -> None:
        default = getattr(defaults, field)
        metavar = flag.removeprefix("--").upper().replace("-", "_")
        p.add_argument(
            flag, dest=field, metavar=metavar, type=type(default), default=default, help=text
        )

    config_flag("--env", "env_name", "Brax or MuJoCo Playground env name")
    config_flag("--backend", "backend", "Brax physics backend")
    config_flag("--num-envs", "num_envs", "envs per seed")
    config_flag("--steps", "total_steps", "env steps per seed")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="one run per seed")
    p.add_argument(
        "--mode",
        choices=MODES,
        default="host",
        help="host loop, one jit streaming through emit, or one jit keeping a report history",
    )
    p.add_argument("--log-dir", default="runs/ppo/<env>-<time>", help="run dirs go here")
    config_flag("--episode-length", "episode_length", "time limit")
    config_flag("--unroll-length", "unroll_length", "steps per iteration")
    config_flag("--epochs", "update_epochs", "passes per batch")
    config_flag("--minibatches", "num_minibatches", "per pass")
    config_flag("--learning-rate", "learning_rate", "Adam, annealed")
    config_flag("--entropy-coef", "entropy_coef", "entropy bonus")
    config_flag("--devices", "devices", "local devices, envs split over them")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--jsonl", action="store_true", help="also write <run dir>/metrics.jsonl")
    p.add_argument(
        "--checkpoint-every",
        type=int,
        default=argparse.SUPPRESS,  # unset: the mode's default, below
        help=f"iterations between checkpoints, 0: none (default: {CHECKPOINT_EVERY} in host "
        "mode; graph mode cannot checkpoint)",
    )
    p.add_argument("--checkpoint-dir", default="<log-dir>/checkpoints", help="where checkpoints go")
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in --log-dir from its newest checkpoint (host mode)",
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """The command line: trains, then prints where the event files and checkpoints are.

    Args:
      argv: arguments (default: `sys.argv[1:]`).

    Returns:
      The exit status.
    """
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        config = PPOConfig(**{k: v for k, v in vars(args).items() if k in _CONFIG_FIELDS})
    except ValueError as e:
        parser.error(str(e))
    if args.resume and "<time>" in args.log_dir:
        parser.error("--resume needs the --log-dir of the run to resume.")
    every = getattr(args, "checkpoint_every", CHECKPOINT_EVERY if args.mode == "host" else 0)
    if args.mode != "host" and (args.resume or every):
        parser.error(GRAPH_CHECKPOINTS)
    if every < 0:
        parser.error(f"--checkpoint-every must be >= 0, got {every}.")
    log_dir = args.log_dir.replace("<env>", config.env_name).replace(
        "<time>", time.strftime("%Y%m%d-%H%M%S")
    )
    checkpoint_dir = args.checkpoint_dir.replace("<log-dir>", log_dir)
    result = train(
        config,
        log_dir,
        seeds=args.seeds,
        mode=args.mode,
        progress=not args.no_progress,
        jsonl=args.jsonl,
        checkpoint_every=every,
        checkpoint_dir=checkpoint_dir,
        resume=args.resume,
    )
    steps = config.num_iterations * config.steps_per_iteration
    brax_env = config.env_name in brax_env_names()
    where = config.backend if brax_env else "MuJoCo Playground, MJX"
    print(
        f"\nTrained {config.env_name} ({where}) for {steps:,} env steps per seed, "
        f"{len(args.seeds)} seed(s), {args.mode} mode, in {result.seconds:.0f} s "
        "(compilation included)."
    )
    for seed, last in zip(args.seeds, result.last):
        ret = last.get(HEADLINE[0][1])
        shown = "no finished episode" if ret is None else f"{ret:.1f}"
        print(f"  seed {seed}: episode return, mean of the last 100 episodes: {shown}")
    print("TensorBoard event files:")
    for d in result.run_dirs:
        print(f"  {d}")
    if len(result.run_dirs) > 1:
        print(f"  {os.path.join(log_dir, 'seeds_summary')} (mean, IQM, 95% interval across seeds)")
    print(f"Open them with:\n  tensorboard --logdir {log_dir}")
    if every:
        print(
            f"Checkpoints: {checkpoint_dir}; a killed run continues with the same command "
            f"and --resume --log-dir {log_dir}"
        )
    return 0
