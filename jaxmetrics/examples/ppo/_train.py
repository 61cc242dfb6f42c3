"""`train`: a whole run, from its checks to its last record: the writers, the console
board, the loop of the chosen mode, and checkpoints."""

import os
import time
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import jaxmetrics as jm

from ._algorithm import TrainState, make_ppo
from ._board import HEADLINE, ProgressBoard, ProgressWriter
from ._checkpoints import Checkpoints
from ._config import PPOConfig, config_values, is_int
from ._loop import MODES, init_states, train_graph, train_graph_history, train_host

GRAPH_CHECKPOINTS = (
    "train(mode='graph' or 'graph-history') cannot checkpoint or resume: the whole run is "
    "one jitted scan, whose carry never reaches the host before the end. Use mode='host' "
    "(--mode host), which writes the same values and checkpoints at period ends."
)


class RunResult(NamedTuple):
    """What `train` returns.

    Attributes:
      state: the final `TrainState` (with a leading `[seeds]` axis for several seeds).
      run_dirs: each seed's TensorBoard run directory, in seed order.
      last: each seed's last headline values (tag -> value), in seed order.
      seconds: wall time of the whole run, compilation included.
    """

    state: TrainState
    run_dirs: tuple[str, ...]
    last: tuple[dict[str, float | int], ...]
    seconds: float


def _hparams(config: PPOConfig, seed: int, mode: str) -> dict[str, bool | int | float | str]:
    return {"seed": seed, "mode": mode, **config_values(config)}


def _check_run(
    config: PPOConfig,
    seeds: tuple[int, ...],
    mode: str,
    n: int,
    checkpoint_every: int,
    resume: bool,
) -> None:
    """Raises for the arguments of `train` that cannot run, before anything is built."""
    if mode not in MODES:
        raise ValueError(f"train(mode={mode!r}): use one of {MODES}.")
    if not seeds or not all(is_int(s) and 0 <= s < 2**32 for s in seeds):
        raise ValueError(
            f"train(seeds=...) must be a non-empty list of ints in [0, 2**32), got {seeds!r}."
        )
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"train(seeds=...) has repeated seeds: {seeds!r}.")
    if not (is_int(n) and 1 <= n <= config.num_iterations):
        raise ValueError(f"train(iterations={n!r}) must be an int in [1, {config.num_iterations}].")
    if not is_int(checkpoint_every):
        raise ValueError(f"train(checkpoint_every=...) must be an int, got {checkpoint_every!r}.")
    if checkpoint_every < 0:
        raise ValueError(f"train(checkpoint_every=...) must be >= 0, got {checkpoint_every}.")
    if mode != "host" and (checkpoint_every or resume):
        raise ValueError(GRAPH_CHECKPOINTS)
    spi = config.steps_per_iteration
    if mode != "host" and n * spi >= 2**31:
        raise ValueError(
            f"train(mode={mode!r}): {n * spi:,} env steps overflow the int32 step of the "
            "in-graph emit; use mode='host' or fewer steps."
        )


def train(
    config: PPOConfig,
    log_dir: str,
    *,
    seeds: Sequence[int] = (0,),
    mode: str = "host",
    iterations: int | None = None,
    progress: bool = True,
    jsonl: bool = False,
    checkpoint_every: int = 0,
    checkpoint_dir: str | None = None,
    resume: bool = False,
) -> RunResult:
    """Trains one PPO per seed, writing each seed's metrics to `log_dir/seed_<seed>`.

    Every iteration ends a flush period: one TensorBoard record per iteration per seed,
    at step = env steps so far (per seed). All modes write the same tags and, for the
    same seed, the same values (up to float round-off between differently fused
    programs).

    Checkpoints (host mode): every `checkpoint_every` iterations and after the last one,
    the whole training carry of all seeds (parameters, optimizer state, observation
    statistics, env states, PRNG keys, the MetricsState as `flush` returned it, the
    iteration) goes to `checkpoint_dir/<step>` with orbax-checkpoint (the 2 newest are
    kept), once the records up to that step are written (`Logger.wait`): a checkpoint
    never exists without its records. `resume=True` restores the newest checkpoint of
    the same config and seeds and carries on: the writers drop the records a killed run
    wrote after it (`purge_step`), `Logger.resume` continues the counters' rates, and the
    run writes exactly the records an uninterrupted run writes (same values, bit for bit
    on CPU; `tests/examples/test_ppo_resume.py` kills a run and compares).

    Args:
      config: the configuration.
      log_dir: parent directory of the run directories.
      seeds: one run per seed; several seeds are `vmap`-ed in one program.
      mode: "host": one jitted call per iteration and a `Logger.flush` between calls;
        "graph": the whole run is one jitted `lax.scan` whose reports are streamed by
        `Logger.emit`; "graph-history": the same scan keeps each iteration's report in
        an in-graph history (`Logger.record`, no host callback), written after the call
        (`Logger.write_history`).
      iterations: stop after this many iterations (default: `config.num_iterations`);
        the learning-rate schedule still spans `config.total_steps`.
      progress: show a progress bar.
      jsonl: also write each seed's records to `<run dir>/metrics.jsonl`.
      checkpoint_every: iterations between checkpoints (host mode); 0: none.
      checkpoint_dir: where checkpoints go (default: `log_dir/checkpoints`).
      resume: continue from the newest checkpoint in `checkpoint_dir` (host mode).

    Returns:
      A `RunResult`.

    Raises:
      ValueError: for an unknown mode, repeated or negative seeds, a bad `iterations` or
        `checkpoint_every`, (graph mode) a run past 2^31 env steps, whose step would
        overflow int32, or checkpoints asked for in graph mode; with `resume`, when
        there is no checkpoint or it was taken with another config or other seeds.
    """
    seeds = tuple(seeds)
    n = config.num_iterations if iterations is None else iterations
    _check_run(config, seeds, mode, n, checkpoint_every, resume)
    spi = config.steps_per_iteration
    start = time.perf_counter()
    ppo = make_ppo(config)
    runs = len(seeds)
    run_dirs = tuple(os.path.join(log_dir, f"seed_{s}") for s in seeds)
    keys = jax.vmap(jax.random.key)(jnp.asarray(seeds, jnp.uint32))
    checkpoints = None
    if checkpoint_every or resume:
        checkpoints = Checkpoints(
            checkpoint_dir or os.path.join(log_dir, "checkpoints"), config, seeds
        )
    try:
        restored, done = None, 0
        if checkpoints is not None and resume:
            step = checkpoints.newest()
            restored = checkpoints.restore(step, init_states(ppo, keys, runs))
            done = int(np.max(jax.device_get(restored.iteration)))
        # A resumed run's first record is at `(done + 1) * spi`: the writers drop what a
        # killed run wrote from there on, so that those steps are not drawn twice.
        purge = (done + 1) * spi if resume else None
        board = ProgressBoard(n * spi, enabled=progress)
        bars = [ProgressWriter(board, r, f"seed {s}") for r, s in enumerate(seeds)]

        def writers(run: int) -> list[jm.Writer]:
            tb = jm.TensorBoardWriter(
                run_dirs[run],
                hparams=_hparams(config, seeds[run], mode),
                hparam_metrics=[HEADLINE[0][1], HEADLINE[1][1]],
                purge_step=purge,
            )
            out: list[jm.Writer] = [tb, bars[run]]
            if jsonl:
                path = os.path.join(run_dirs[run], "metrics.jsonl")
                out.append(jm.JsonlWriter(path, purge_step=purge))
            return out

        try:
            summary = None
            if runs > 1:
                summary = [
                    jm.TensorBoardWriter(os.path.join(log_dir, "seeds_summary"), purge_step=purge)
                ]
            with jm.Logger(ppo.metrics, writers, runs=runs, seeds_summary=summary) as logger:
                if mode == "graph":
                    state = train_graph(ppo, logger, keys, n)
                elif mode == "graph-history":
                    state = train_graph_history(ppo, logger, keys, n)
                else:
                    if restored is None:
                        state = init_states(ppo, keys, runs)
                    else:
                        state = restored
                        logger.resume(state.metrics_state(), done * spi)
                    state = train_host(ppo, logger, state, done, n, checkpoints, checkpoint_every)
        finally:
            board.stop()
    finally:
        if checkpoints is not None:
            checkpoints.close()
    return RunResult(state, run_dirs, tuple(b.last for b in bars), time.perf_counter() - start)
