"""What the reporting Brax wrapper costs inside Brax's own trainer (`ppo.train`).

`python -m jaxmetrics.bench._brax_train --env ant --num-envs 4096 --timesteps 10000000
--variants brax,report_full,report_mean --runs 2 --call overhead --commit $(git rev-parse HEAD)
--out F.json`

Runs `brax.training.agents.ppo.train` on `brax.envs.get_environment(env, backend="mjx")`
with Brax's tuned PPO settings for `ant` (Brax's README), the same seed for every variant:

- `brax`: Brax's own wrapper (no `wrap_env_fn`).
- `report_full`: `jaxmetrics.brax.wrap` with a `Logger` (TensorBoard), reporting by itself
  from inside the trainer; 11 terms for `ant` (episode return and length, and every
  `State.metrics` entry but `forward_reward`, which duplicates `reward_forward`) with the
  bench's "full" statistics (`_workload.pattern_stats`: mean/std/min/max/sum/count, EMA,
  window(100) with percentiles, histograms), default `report_every`.
- `report_mean`: the same terms, mean + count only.
- `report_all` (not run by default): every statistic on every term.
- `fold_full`, `fold_mean`: `jaxmetrics.brax.wrap` with the same specs and no logger: the
  wrapper folds on every step and never reports (the cost of the fold alone).
- `report_full_mem`: `report_full` with a `jm.MemoryWriter` in place of the TensorBoard
  writer (what the report costs without event files).
- `report_full_rare`: `report_full` with `report_every=RARE_REPORT_EVERY` (5M env steps:
  one or two reports per 10M-step run instead of 28): the per-step reporting machinery
  (the int32 clock, the `lax.cond` on its predicate, the EMA history kept under `pmap`)
  without the per-report cost (`all_gather`, compute, `io_callback`, writers).
- `report_full_often`: `report_full` with `report_every=OFTEN_REPORT_EVERY` (10x the
  reports: 288 per 10M-step run), where the per-report cost stands above the noise.

Per run: the steady-state env steps per second between consecutive `progress_fn` calls
(each interval includes Brax's evaluation; every interval in which a backend compile
ended is left out: on this JAX the first two, as the training epoch compiles twice),
Brax's own `training/sps` (the training epoch alone, over the same epochs), the wall time
of `ppo.train`, and for the reporting variants each record's arrival time relative to the
start of training (it shows reports arriving while training runs). Results are written
after every run, so a run cut short keeps the finished ones. Every run is tagged with
`--call`, the device call it ran in, and compared only with the `brax` runs of the same
call (`_brax_results`); `--merge A.json B.json --out C.json` joins the runs and calls of
several outputs.

`--time-callbacks` times the host side of every report of the reporting variants
(`callback_times`, perf_counter): JAX's own host function around ours (`io_callback_impl`:
the operands put on the CPU device, then our function), `Logger._on_emit` (numpy copies,
queueing the job), the writer thread's job per record (`RunWriters.write_run`: unpack,
`Record`, every writer) and the main writer's `write`; each with its start.
`--callback-probe` measures, in a small jitted device loop (no Brax), what one ordered
`io_callback` under `lax.cond` costs: the loop's time with a callback every k iterations
against none.

`--trace VARIANTS` takes a `jax.profiler` trace of the last interval of those variants'
runs (left out of the steady figures) and stores a summary of it in the run's result
(`trace_summary`: events per device/host line, the most frequent names, and every
memcpy/sync/callback/conditional name); `hlo_summary` summarizes an optimized HLO dump
(`XLA_FLAGS=--xla_dump_to=D --xla_dump_hlo_module_re=_fun`).
"""

import argparse
import collections
import functools
import glob
import json
import os
import platform
import re
import shlex
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence
from importlib import metadata
from typing import Any

import jax
import jax._src.api

import jaxmetrics as jm
import jaxmetrics.brax as jmb  # before Brax (quiet imports)

from ._brax_results import summarize, tables
from ._hlo import _BODY, _CALLS, _CONTAINERS, _opcode, _ops, _split_computations
from ._workload import pattern_stats

VARIANTS = (
    "brax", "report_full", "report_mean", "report_all", "fold_full", "fold_mean",
    "report_full_rare", "report_full_often", "report_full_mem",
)  # fmt: skip

RARE_REPORT_EVERY = 5_000_000
"""`report_every` of the `*_rare` variants: one or two reports in a 10M-step run."""

OFTEN_REPORT_EVERY = 40_960
"""`report_every` of the `*_often` variants: 288 reports in a 10M-step run (10x the
default's 28)."""

# Brax's tuned PPO settings for ant (brax README, "ant"); num_timesteps comes from the CLI.
ANT_PPO = {
    "num_evals": 10,
    "reward_scaling": 10,
    "episode_length": 1000,
    "normalize_observations": True,
    "action_repeat": 1,
    "unroll_length": 5,
    "num_minibatches": 32,
    "num_updates_per_batch": 4,
    "discounting": 0.97,
    "learning_rate": 3e-4,
    "entropy_cost": 1e-2,
    "num_envs": 4096,
    "batch_size": 2048,
    "seed": 1,
}

# Duplicates of another State.metrics entry (Brax's ant: forward_reward == reward_forward).
DUPLICATES = {"forward_reward": "reward_forward"}

# Histogram ranges of the terms the pattern gives a histogram (others: (0, 1)).
HIST_RANGES = {
    "episode_return": (-1000.0, 8000.0),
    "reward_ctrl": (-4000.0, 0.0),
    "x_velocity": (-5.0, 5.0),
    "y_velocity": (-5.0, 5.0),
}


def _reduction(name: str) -> str:
    """The episode reduction of a `State.metrics` entry, from its name."""
    if "reward" in name or "cost" in name:
        return "sum"
    if "position" in name or "distance" in name:
        return "last"
    return "mean"


def state_metric_names(env: Any) -> list[str]:
    """The env's `State.metrics` names (from shapes alone), duplicates left out."""
    shapes = jax.eval_shape(env.reset, jax.ShapeDtypeStruct((2,), jax.numpy.uint32))
    names = list(shapes.metrics)
    return [n for n in names if not (n in DUPLICATES and DUPLICATES[n] in names)]


def build_spec(env: Any, features: str) -> tuple[jm.Metrics, dict[str, Any]]:
    """The spec of a reporting variant and a description of it (term -> reduce, stats)."""
    names = ["episode_return", "episode_length", *state_metric_names(env)]
    terms: dict[str, jm.Term] = {}
    desc: dict[str, Any] = {}
    for i, name in enumerate(names):
        hist = HIST_RANGES.get(name, (0.0, 1.0))
        if features == "mean":
            stats: tuple[Any, ...] = ("mean", "count")
        elif features == "full":
            stats = pattern_stats(i, 100, hist)
        elif features == "all":
            stats = (
                "mean", "std", "min", "max", "sum", "count", jm.ema(0.01),
                jm.window(100, percentiles=(50, 90)), jm.histogram(20, hist),
            )  # fmt: skip
        else:
            raise ValueError(f"unknown features {features!r}")
        if name == "episode_return":
            term = jmb.episode_return(stats=stats)
        elif name == "episode_length":
            term = jmb.episode_length(stats=stats)
        else:
            term = jmb.state_metrics({name: _reduction(name)}, stats=stats)[name]
        terms[name] = term
        desc[name] = {"reduce": term.reduce, "stats": [repr(s) for s in stats]}
    return jm.Metrics(terms=terms), desc


class ArrivalWriter:
    """A writer that notes when each record reaches the writer thread (and its step)."""

    def __init__(self, t0: float):
        self.t0 = t0
        self.arrivals: list[dict[str, Any]] = []

    def open(self, tags: Sequence[Any]) -> None:
        pass

    def write(self, record: Any) -> None:
        now = time.time()
        ret = {
            k: v
            for k, v in record.scalars.items()
            if k.startswith("Episode_Metrics/episode_return")
        }
        self.arrivals.append(
            {
                "step": int(record.step),
                "emitted_s": round(record.wall_time - self.t0, 3),  # the callback ran
                "written_s": round(now - self.t0, 3),  # the writer thread got it
                "episodes": int(ret.get("Episode_Metrics/episode_return/count", 0)),
                "episode_return": ret.get("Episode_Metrics/episode_return"),
            }
        )

    def close(self) -> None:
        pass


class CompileCounter:
    """Backend compiles seen while it is active: when each ended (seconds after `t0`) and
    how long it took."""

    EVENT = "/jax/core/compile/backend_compile_duration"

    def __init__(self):
        self.active = False
        self.t0 = 0.0
        self.events: list[tuple[float, float]] = []
        jax.monitoring.register_event_duration_secs_listener(self._on)

    def start(self, t0: float) -> None:
        self.t0, self.events, self.active = t0, [], True

    def _on(self, event: str, duration: float, **_: Any) -> None:
        if self.active and event == self.EVENT:
            self.events.append((time.time() - self.t0, float(duration)))


def parse_variant(variant: str) -> tuple[str, str | None, int | None, str]:
    """`(mode, features, report_every, sink)` of a variant name: mode "brax", "fold" or
    "report"; `report_every` that of `*_rare` or `*_often` (None: the command line's);
    sink "tensorboard", or "memory" for `*_mem` (a `MemoryWriter` instead)."""
    if variant == "brax":
        return "brax", None, None, "tensorboard"
    mode, features, *rest = variant.split("_")
    tag = "_".join(rest)
    if mode not in ("fold", "report") or tag not in ("", "mem", "rare", "often"):
        raise ValueError(f"unknown variant {variant!r}")
    every = {"rare": RARE_REPORT_EVERY, "often": OFTEN_REPORT_EVERY}.get(tag)
    return mode, features, every, "memory" if tag == "mem" else "tensorboard"


def _ms_stats(xs: Sequence[float]) -> dict[str, Any]:
    """Count, mean, median, p90, max and sum of durations in seconds, in ms."""
    if not xs:
        return {"n": 0}
    ms = sorted(1e3 * x for x in xs)
    return {
        "n": len(ms),
        "mean_ms": round(statistics.mean(ms), 4),
        "median_ms": round(statistics.median(ms), 4),
        "p90_ms": round(ms[min(len(ms) - 1, int(0.9 * len(ms)))], 4),
        "max_ms": round(ms[-1], 4),
        "sum_ms": round(sum(ms), 3),
    }


class CallbackTimes:
    """Host-side timings of a reporting variant's reports (`--time-callbacks`).

    - `jax_callback`: JAX's own host function of an `io_callback` (`io_callback_impl`:
      the operands `device_put` on the CPU device, then ours), wrapped in the module for
      the run (it is looked up there at every call);
    - `on_emit`: `Logger._on_emit` (a `Logger` subclass: the logger binds it when built);
    - `writer_job`: the writer thread's job per record (`RunWriters.write_run`: unpack,
      build the `Record`, every writer);
    - `write`: the main writer's `write` (its instance attribute, wrapped).

    Each entry: (start in s after `t0`, duration in s)."""

    def __init__(self, t0: float):
        self.t0 = t0
        self.times: dict[str, list[tuple[float, float]]] = {
            "jax_callback": [], "on_emit": [], "writer_job": [], "write": [],
        }  # fmt: skip
        self.arg_types: list[str] | None = None
        self._jax_module: Any = None
        self._jax_impl: Any = None

    def _note(self, key: str, start: float) -> None:
        self.times[key].append((start - self.t0, time.perf_counter() - start))

    def logger_class(self) -> type:
        times = self

        class TimedLogger(jm.Logger):
            def _on_emit(self, packed: Any, step: Any, when: Any, run: Any) -> None:
                t = time.perf_counter()
                if times.arg_types is None:
                    times.arg_types = [type(a).__name__ for a in (*packed, when)]
                try:
                    return super()._on_emit(packed, step, when, run)
                finally:
                    times._note("on_emit", t)

            def __init__(self, *args: Any, **kwargs: Any) -> None:
                super().__init__(*args, **kwargs)
                write_run = self._runs.write_run

                def timed_write_run(*args: Any, **kwargs: Any) -> None:
                    t = time.perf_counter()
                    try:
                        return write_run(*args, **kwargs)
                    finally:
                        times._note("writer_job", t)

                self._runs.write_run = timed_write_run

        return TimedLogger

    def wrap_writer(self, writer: Any) -> None:
        write = writer.write

        def timed_write(record: Any) -> None:
            t = time.perf_counter()
            try:
                write(record)
            finally:
                self._note("write", t)

        writer.write = timed_write

    def patch_jax(self) -> bool:
        """Wraps JAX's `io_callback_impl` (False where this JAX has none)."""
        try:
            from jax._src import callback as module
        except ImportError:
            return False
        impl = getattr(module, "io_callback_impl", None)
        if impl is None:
            return False

        def timed_impl(*args: Any, **kwargs: Any) -> Any:
            t = time.perf_counter()
            try:
                return impl(*args, **kwargs)
            finally:
                self._note("jax_callback", t)

        self._jax_module, self._jax_impl = module, impl
        module.io_callback_impl = timed_impl
        return True

    def unpatch_jax(self) -> None:
        if self._jax_module is not None:
            self._jax_module.io_callback_impl = self._jax_impl
            self._jax_module = None

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {k: _ms_stats([d for _, d in v]) for k, v in self.times.items()}
        starts = [s for s, _ in self.times["on_emit"]]
        gaps = [b - a for a, b in zip(starts, starts[1:])]
        out["on_emit_interval"] = _ms_stats(gaps) if gaps else {"n": 0}
        out["arg_types"] = self.arg_types
        out["switch_interval_ms"] = 1e3 * sys.getswitchinterval()
        out["raw"] = {
            k: [(round(s, 4), round(1e3 * d, 4)) for s, d in v] for k, v in self.times.items()
        }
        return out


def _dir_bytes(path: str) -> int:
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(path) for f in fs)


def record_progress(
    progress: list[dict[str, Any]], label: str, t0: float, step: int, m: dict[str, Any]
) -> None:
    """Appends a Brax progress call (time since `t0`, training/sps, eval return) to
    `progress` and prints it under `label`."""
    now = time.time() - t0
    sps, ret = m.get("training/sps"), m.get("eval/episode_reward")
    progress.append(
        {
            "step": int(step),
            "t_s": round(now, 3),
            "training_sps": None if sps is None else float(sps),
            "eval_episode_reward": None if ret is None else float(ret),
        }
    )
    print(
        f"  [{label}] t={now:7.1f}s step={int(step):>10}"
        + ("" if sps is None else f" training/sps={float(sps):,.0f}")
        + ("" if ret is None else f" eval_return={float(ret):.1f}"),
        flush=True,
    )


def closed(logger: Any) -> float:
    """Closes `logger`; the seconds it took (what is pending is written then)."""
    t = time.time()
    logger.close()
    return round(time.time() - t, 3)


def run_times(t_train: float, counter: "CompileCounter", progress: list) -> dict[str, Any]:
    """A training run's wall time, its compiles and its progress calls."""
    return {
        "wall_s": round(t_train, 3),
        "compiles": len(counter.events),
        "compile_s": round(sum(d for _, d in counter.events), 2),
        "progress": progress,
    }


def _steady(
    progress: list[dict[str, Any]],
    compiles: list[tuple[float, float]],
    traced: Sequence[int] = (),
) -> dict:
    """Env steps per second between progress calls (the initial eval at step 0, then one
    per training epoch + eval), over the intervals in which nothing compiled.

    Brax compiles its training epoch in the first interval and, on this JAX, once more in
    the second (the first epoch's outputs come back with other types or layouts than
    the inputs it was traced with): `steady_sps` leaves out every interval in which a
    backend compile ended, and the `traced` ones (profiled); `steady_sps_excl_first`
    leaves out the first interval only."""
    out: dict[str, Any] = {"intervals_sps": [], "compiling_intervals": []}
    if traced:
        out["traced_intervals"] = list(traced)
    for i, (a, b) in enumerate(zip(progress, progress[1:])):
        out["intervals_sps"].append((b["step"] - a["step"]) / (b["t_s"] - a["t_s"]))
        n = sum(a["t_s"] < t <= b["t_s"] for t, _ in compiles)
        if n:
            out["compiling_intervals"].append(i)
    if compiles and progress:
        out["compiles_after_last_progress"] = sum(t > progress[-1]["t_s"] for t, _ in compiles)
    skip = set(out["compiling_intervals"]) | set(traced)
    clean = [(a, b) for i, (a, b) in enumerate(zip(progress, progress[1:])) if i not in skip]
    out["steady_intervals"] = len(clean)
    out["steady_sps"] = (
        sum(b["step"] - a["step"] for a, b in clean) / sum(b["t_s"] - a["t_s"] for a, b in clean)
        if clean
        else None
    )
    later = progress[1:]
    out["steady_sps_excl_first"] = (
        (later[-1]["step"] - later[0]["step"]) / (later[-1]["t_s"] - later[0]["t_s"])
        if len(later) >= 2
        else None
    )
    # Brax's training/sps of epoch k comes with progress call k (k >= 1): interval k-1.
    epochs = [
        (i - 1, p["training_sps"])
        for i, p in enumerate(progress)
        if p.get("training_sps") is not None
    ]
    out["brax_training_sps_all"] = [sps for _, sps in epochs]
    kept = [sps for i, sps in epochs if i not in skip]
    if kept:
        # Steps per epoch are equal: the steady rate is the harmonic mean of the epochs'.
        out["brax_training_sps"] = len(kept) / sum(1.0 / x for x in kept)
        out["brax_training_sps_median"] = statistics.median(kept)
    else:
        out["brax_training_sps"] = out["brax_training_sps_median"] = None
    return out


def run_one(variant: str, run: int, args: argparse.Namespace, counter: CompileCounter) -> dict:
    """One `ppo.train` of `variant`; its timings and records."""
    from brax import envs
    from brax.training.agents.ppo import train as ppo

    env = envs.get_environment(args.env, backend=args.backend)
    settings = dict(ANT_PPO)
    for key in ("num_envs", "batch_size", "num_minibatches", "episode_length", "num_evals"):
        if getattr(args, key) is not None:
            settings[key] = getattr(args, key)
    settings["num_timesteps"] = args.timesteps
    extra: dict[str, Any] = {"num_eval_envs": args.num_eval_envs}
    result: dict[str, Any] = {"variant": variant, "run": run, "call": args.call}
    logger = writer = logdir = None
    progress: list[dict[str, Any]] = []
    mode, features, every, sink = parse_variant(variant)
    report_every = every or args.report_every

    if mode != "brax":
        metrics, desc = build_spec(env, features)
        result["terms"] = len(desc)
        result["spec"] = desc
    if mode == "report":
        logdir = tempfile.mkdtemp(prefix=f"brax_train_{variant}_")
    # A trace of the last interval: from the next-to-last progress call to the last
    # (Brax calls progress_fn num_evals times: at step 0, then after each epoch + eval).
    trace_at = settings["num_evals"] - 1 if variant in (args.trace or "").split(",") else None
    trace: dict[str, Any] = {}
    t0, t0_perf = time.time(), time.perf_counter()
    counter.start(t0)
    times = None
    if mode == "report":
        writer = ArrivalWriter(t0)
        main_writer = jm.MemoryWriter() if sink == "memory" else jm.TensorBoardWriter(logdir)
        logger_class: Any = jm.Logger
        if args.time_callbacks:
            times = CallbackTimes(t0_perf)
            logger_class = times.logger_class()
            times.wrap_writer(main_writer)
            result["jax_callback_timed"] = times.patch_jax()
        logger = logger_class(metrics, [main_writer, writer])
        result["writer"] = type(main_writer).__name__
        extra["wrap_env_fn"] = functools.partial(
            jmb.wrap, metrics=metrics, logger=logger, report_every=report_every
        )
    elif mode == "fold":
        extra["wrap_env_fn"] = functools.partial(jmb.wrap, metrics=metrics)

    def progress_fn(step: int, m: dict[str, Any]) -> None:
        record_progress(progress, f"{variant} run {run}", t0, step, m)
        if trace_at is not None and len(progress) in (trace_at, trace_at + 1):
            _trace_toggle(trace, len(progress) == trace_at, args.trace_dir, variant, run)

    try:
        ppo.train(environment=env, progress_fn=progress_fn, **settings, **extra)
        t_train = time.time() - t0
    finally:
        counter.active = False
        if times is not None:
            times.unpatch_jax()
        if trace.get("active"):
            _trace_toggle(trace, False, args.trace_dir, variant, run)
        if logger is not None:
            result["logger_close_s"] = closed(logger)
    result.update(
        **run_times(t_train, counter, progress),
        compile_events=[(round(t, 2), round(d, 2)) for t, d in counter.events],
        **_steady(progress, counter.events, [trace_at - 1] if trace.get("dir") else []),
    )
    if trace:
        trace.pop("active", None)
        result["trace"] = trace
    if times is not None:
        result["callback_times"] = times.summary()
    if writer is not None:
        arr = writer.arrivals
        result.update(
            records=len(arr),
            logger_emit_calls=logger.emit_calls,
            first_record_s=arr[0]["written_s"] if arr else None,
            last_record_s=arr[-1]["written_s"] if arr else None,
            records_before_train_end=sum(a["written_s"] <= t_train for a in arr),
            arrivals=arr,
            tensorboard_bytes=_dir_bytes(logdir),
        )
        shutil.rmtree(logdir, ignore_errors=True)
    result["settings"] = {k: v for k, v in settings.items()} | {
        "num_eval_envs": args.num_eval_envs,
        "report_every": report_every if mode == "report" else None,
    }
    return result


def callback_probe(
    iters: int = 3000, periods: Sequence[int] = (0, 300, 100, 30), repeats: int = 5
) -> dict[str, Any]:
    """What one ordered `io_callback` under `lax.cond` costs in a device loop like Brax's.

    A jitted `fori_loop` of `iters` steps (8 small matmul + tanh kernels each, on a
    4096 x 256 array) with a `lax.cond` per step that fires an ordered `io_callback` of a
    1,452-byte operand (the size of a report) and the step every `period` steps (never
    for 0: the cond, no callback). Per period: the median seconds of `repeats` calls after
    a warm-up (one compile: the period is an argument), the callbacks made, the cost per
    callback (`(t - t_0) / callbacks`), and the host function's own time."""
    import numpy as np
    from jax.experimental import io_callback

    jnp = jax.numpy
    host_s: list[float] = []
    times = CallbackTimes(time.perf_counter())
    patched = times.patch_jax()

    def host(x: Any, i: Any) -> None:
        t = time.perf_counter()
        np.asarray(x).sum()
        int(i)
        host_s.append(time.perf_counter() - t)

    def loop(x: Any, w: Any, period: Any) -> Any:
        def body(i: Any, x: Any) -> Any:
            for _ in range(8):
                x = jnp.tanh(x @ w)

            def fire(x: Any) -> Any:
                io_callback(host, None, x[:2].reshape(-1)[:363], i, ordered=True)
                return x

            due = (period > 0) & (i % jnp.maximum(period, 1) == 0)
            return jax.lax.cond(due, fire, lambda x: x, x)

        return jax.lax.fori_loop(0, iters, body, x)

    f = jax.jit(loop)
    x = jnp.ones((4096, 256), jnp.float32)
    w = jnp.eye(256, dtype=jnp.float32) * 0.5
    out: dict[str, Any] = {"iters": iters, "repeats": repeats, "jax_callback_timed": patched}
    try:
        t = time.perf_counter()
        f(x, w, 0).block_until_ready()
        out["first_call_s"] = round(time.perf_counter() - t, 3)
        rows = []
        for period in periods:
            f(x, w, period).block_until_ready()
            host_s.clear()
            for v in times.times.values():
                v.clear()
            ts = []
            for _ in range(repeats):
                t = time.perf_counter()
                f(x, w, period).block_until_ready()
                ts.append(time.perf_counter() - t)
            calls = -(-iters // period) if period else 0
            rows.append(
                {
                    "period": period,
                    "callbacks_per_call": calls,
                    "median_s": statistics.median(ts),
                    "all_s": ts,
                    "host_fn": _ms_stats(host_s),
                    "jax_callback": _ms_stats([d for _, d in times.times["jax_callback"]]),
                }
            )
        base = rows[0]["median_s"]
        for r in rows[1:]:
            r["ms_per_callback"] = 1e3 * (r["median_s"] - base) / r["callbacks_per_call"]
        out["rows"] = rows
    finally:
        times.unpatch_jax()
    return out


def _trace_toggle(
    trace: dict[str, Any], start: bool, trace_dir: str | None, variant: str, run: int
) -> None:
    """Starts or stops (and summarizes) a `jax.profiler` trace; errors are noted in
    `trace["error"]`, never raised (a profile is a side show of the timing)."""
    try:
        if start:
            d = tempfile.mkdtemp(prefix=f"trace_{variant}_{run}_", dir=trace_dir)
            trace.update(dir=d, active=True)
            jax.profiler.start_trace(d)
            return
        if not trace.get("active"):
            return
        t = time.time()
        trace["active"] = False
        jax.profiler.stop_trace()
        trace["stop_s"] = round(time.time() - t, 2)
        (path,) = glob.glob(os.path.join(trace["dir"], "**", "*.xplane.pb"), recursive=True)
        trace["bytes"] = os.path.getsize(path)
        t = time.time()
        trace["summary"] = trace_summary(path)
        trace["summarize_s"] = round(time.time() - t, 2)
        if trace_dir is None:
            shutil.rmtree(trace["dir"], ignore_errors=True)
    except Exception as e:  # noqa: BLE001
        trace["error"] = f"{type(e).__name__}: {e}"


_NOTABLE = re.compile(r"memcpy|memset|sync|callback|conditional|cond\b|while|host", re.I)


def trace_summary(path: str, top: int = 25) -> dict[str, Any]:
    """Per line of every plane but the host CPU's (device streams, XLA ops/modules, CUDA
    API calls): the number of events, their total time, the `top` most frequent names,
    and every name that looks like a copy, a sync, a callback, a loop or a conditional."""
    data = jax.profiler.ProfileData.from_file(path)
    out: dict[str, Any] = {}
    for plane in data.planes:
        if plane.name == "/host:CPU":
            continue
        lines: dict[str, Any] = {}
        for line in plane.lines:
            count: collections.Counter[str] = collections.Counter()
            ns: collections.Counter[str] = collections.Counter()
            for e in line.events:
                count[e.name] += 1
                ns[e.name] += e.duration_ns
            if not count:
                continue
            lines[line.name] = {
                "events": sum(count.values()),
                "total_ms": round(sum(ns.values()) / 1e6, 3),
                "names": len(count),
                "top": [[n, c, round(ns[n] / 1e3, 1)] for n, c in count.most_common(top)],
                "notable": [
                    [n, c, round(ns[n] / 1e3, 1)]
                    for n, c in count.most_common()
                    if _NOTABLE.search(n)
                ][:100],
            }
        if lines:
            out[plane.name] = lines
    return out


def hlo_summary(text: str) -> dict[str, Any]:
    """What an optimized HLO module (`compiled.as_text()` or an XLA dump's
    `*after_optimizations.txt`) holds: its ops (fusions counted as one; each loop body
    once), custom-call targets, loops with and without a known trip count, and where
    every `conditional` sits (the trip counts of the loops around it, outermost first)."""
    comps, entry = _split_computations(text)
    parent: dict[str, tuple[str, str, str | None]] = {}  # callee -> (caller, opcode, trips)
    whiles = {"known_trip_count": 0, "unknown_trip_count": 0}
    targets: collections.Counter[str] = collections.Counter()
    conds: list[str] = []
    for name, instrs in comps.items():
        for instr in instrs:
            op = _opcode(instr)
            if op == "custom-call":
                m = re.search(r'custom_call_target="([^"]+)"', instr)
                targets[m.group(1) if m else "?"] += 1
            if op not in _CONTAINERS:
                continue
            trips = None
            if op == "while":
                m = re.search(r'"known_trip_count":\{"n":"(\d+)"', instr)
                trips = m.group(1) if m else "?"
                whiles["known_trip_count" if m else "unknown_trip_count"] += 1
            if op == "conditional":
                conds.append(name)
            callees = [m.group(1) for m in _BODY.finditer(instr)]
            callees += re.findall(r"\b(?:true|false)_computation=%?([\w.\-]+)", instr)
            for m in _CALLS.finditer(instr):
                callees += [c.strip() for c in m.group(1).replace("%", "").split(",")]
            for c in callees:
                parent.setdefault(c, (name, op, trips))

    def enclosing(name: str) -> list[str]:
        trips: list[str] = []
        seen: set[str] = set()
        while name in parent and name not in seen:
            seen.add(name)
            name, op, n = parent[name]
            if op == "while":
                trips.append(n or "?")
        return trips[::-1]

    ops = collections.Counter(_ops(comps, entry, set())) if entry else collections.Counter()
    return {
        "ops": dict(ops.most_common()),
        "custom_call_targets": dict(targets.most_common()),
        "whiles": whiles,
        "conditionals": [
            {"in": c, "loop_trip_counts": enclosing(c)} for c in conds if not c.startswith("fused")
        ],
        "bytes": len(text),
    }


def hlo_dump_summary(directory: str, largest: int = 4) -> list[dict[str, Any]]:
    """`hlo_summary` of the `largest` `*after_optimizations.txt` files of an XLA dump
    (Brax's training epoch, a `pmap`, is named `jit__fun` by JAX's own `pmap`)."""
    paths = glob.glob(os.path.join(directory, "*after_optimizations.txt"))
    out = []
    for path in sorted(paths, key=os.path.getsize, reverse=True)[:largest]:
        with open(path) as fh:
            out.append({"file": os.path.basename(path), **hlo_summary(fh.read())})
    return out


def _version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def environment(commit: str | None) -> dict[str, Any]:
    dev = jax.devices()[0]
    return {
        "device": getattr(dev, "device_kind", str(dev)),
        "platform": dev.platform,
        "device_count": jax.device_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "jaxlib": _version("jaxlib"),
        "brax": _version("brax"),
        "mujoco": _version("mujoco"),
        "mujoco_mjx": _version("mujoco-mjx"),
        "commit": commit,
        "host": platform.node(),
    }


def _write(path: str, doc: dict[str, Any]) -> None:
    tmp = path + ".tmp"
    with open(tmp, "w") as fh:
        json.dump(doc, fh, indent=1, default=float)
    os.replace(tmp, path)


def _device_put_replicated(x: Any, devices: Sequence[Any]) -> Any:
    """`jax.device_put_replicated` where JAX no longer has it: a leading axis of one copy
    per device, split over the devices (what `pmap` takes)."""
    import numpy as np

    sharding = jax.sharding.NamedSharding(
        jax.sharding.Mesh(np.array(devices), ("d",)), jax.sharding.PartitionSpec("d")
    )

    def put(a: Any) -> jax.Array:
        a = jax.numpy.asarray(a)
        return jax.device_put(jax.numpy.broadcast_to(a, (len(devices), *a.shape)), sharding)

    return jax.tree.map(put, x)


def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="python -m jaxmetrics.bench._brax_train", description=__doc__.split("\n")[0]
    )
    p.add_argument("--env", default="ant")
    p.add_argument("--backend", default="mjx")
    p.add_argument("--num-envs", type=int, default=None, help="default 4096 (Brax's ant)")
    p.add_argument("--timesteps", type=int, default=10_000_000)
    p.add_argument("--batch-size", type=int, default=None, help="default 2048")
    p.add_argument("--num-minibatches", type=int, default=None, help="default 32")
    p.add_argument("--episode-length", type=int, default=None, help="default 1000")
    p.add_argument("--num-evals", type=int, default=None, help="default 10")
    p.add_argument("--num-eval-envs", type=int, default=128, help="Brax's default 128")
    p.add_argument("--report-every", type=int, default=None, help="default: the wrapper's")
    p.add_argument("--variants", default="brax,report_full,report_mean")
    p.add_argument("--runs", type=int, default=1)
    p.add_argument(
        "--first-run", type=int, default=1, help="number of the first run (when split over calls)"
    )
    p.add_argument("--commit", default=None, help="git commit of the tree (`git rev-parse HEAD`)")
    p.add_argument(
        "--call",
        default="1",
        help="name of this device call: runs are compared with the brax runs of the same call",
    )
    p.add_argument("--note", default=None, help="free text stored with the call")
    p.add_argument("--out", default=None)
    p.add_argument("--explain-cache-misses", action="store_true", help="log why JAX recompiles")
    p.add_argument(
        "--trace", default=None, help="variants whose last interval to profile (comma-separated)"
    )
    p.add_argument("--trace-dir", default=None, help="keep the raw traces here (default: drop)")
    p.add_argument("--time-callbacks", action="store_true", help="time each report's host side")
    p.add_argument(
        "--callback-probe", action="store_true", help="what one io_callback costs (no Brax)"
    )
    p.add_argument(
        "--merge", nargs="+", default=None, help="join these outputs' runs and calls into --out"
    )
    return p.parse_args(argv)


def merge(docs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """One results file of several outputs: their runs, and their calls joined by name
    (commands and notes one after the other; a call's tree must be the same in each)."""
    calls: dict[str, dict[str, Any]] = {}
    for d in docs:
        for name, meta in d["calls"].items():
            seen = calls.setdefault(name, {**meta, "commands": [], "notes": []})
            if seen["commit"] != meta["commit"]:
                raise ValueError(
                    f"call {name!r} measured tree {seen['commit']} in one output and "
                    f"{meta['commit']} in another; give each tree its own --call"
                )
            seen.update({k: v for k, v in meta.items() if k not in ("commands", "notes")})
            seen["commands"] += meta["commands"]
            seen["notes"] += meta["notes"]
    runs = [r for d in docs for r in d["runs"]]
    return {
        **docs[0],
        "calls": calls,
        "runs": runs,
        "summary": summarize(runs),
        "specs": {k: v for d in docs for k, v in d.get("specs", {}).items()},
    }


def _print_tables(doc: dict[str, Any]) -> None:
    for t in tables(doc):
        print(t.to_markdown(), flush=True)


def main(argv: Sequence[str] | None = None) -> None:
    args = _parse(argv)
    if args.merge:
        docs = []
        for path in args.merge:
            with open(path) as fh:
                docs.append(json.load(fh))
        doc = merge(docs)
        _print_tables(doc)
        if args.out:
            _write(args.out, doc)
        return
    variants = [v for v in args.variants.split(",") if v]
    for v in variants:
        if v not in VARIANTS:
            sys.exit(f"unknown variant {v!r}; choose from {', '.join(VARIANTS)}")
    # Brax 0.14.2's ppo.train calls jax.device_put_replicated, gone from JAX 0.10's namespace.
    if not hasattr(jax, "device_put_replicated"):
        jax.device_put_replicated = getattr(
            jax._src.api, "device_put_replicated", _device_put_replicated
        )
    if args.explain_cache_misses:
        jax.config.update("jax_explain_cache_misses", True)
    counter = CompileCounter()
    command = " ".join(
        ["python", "-m", "jaxmetrics.bench._brax_train"]
        + [shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv)]
    )
    call: dict[str, Any] = {
        "commit": args.commit,
        "commands": [command],
        "notes": [args.note] if args.note else [],
    }
    doc: dict[str, Any] = {
        "benchmark": "brax_ppo_train",
        "description": __doc__,
        "environment": environment(args.commit),
        "args": vars(args),
        "calls": {args.call: call},
        "runs": [],
    }
    print(json.dumps(doc["environment"]), flush=True)
    if args.callback_probe:
        call["callback_probe"] = callback_probe()
        for r in call["callback_probe"]["rows"]:
            print({k: v for k, v in r.items() if k != "all_s"}, flush=True)
        if args.out:
            _write(args.out, doc)
    # Runs interleave the variants (run 1 of each, then run 2 of each) against drift.
    for run in range(args.first_run, args.first_run + args.runs):
        for v in variants:
            print(f"== {v} run {run}", flush=True)
            r = run_one(v, run, args, counter)
            doc["runs"].append(r)
            if "spec" in r:
                doc.setdefault("specs", {})[v] = r.pop("spec")
            doc["summary"] = summarize(doc["runs"])
            print(
                f"== {v} run {run}: wall {r['wall_s']:.1f}s steady {r['steady_sps']} "
                f"brax {r['brax_training_sps']} compiles {r['compiles']} "
                f"records {r.get('records')}",
                flush=True,
            )
            if args.out:
                _write(args.out, doc)
    _print_tables(doc)


if __name__ == "__main__":
    main()
