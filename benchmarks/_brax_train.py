"""`python -m benchmarks brax-train`: what the reporting Brax wrapper costs inside Brax's
own trainer (`ppo.train`).

`python -m benchmarks brax-train --env ant --num-envs 4096 --timesteps 10000000
--variants brax,report_full,report_mean --runs 2 --call overhead --commit $(git rev-parse HEAD)
--out F.json --summary docs/benchmarks/h100_brax_ppo_train.json`

Runs `brax.training.agents.ppo.train` on `brax.envs.get_environment(env, backend="mjx")`
with Brax's tuned PPO settings for `ant` (Brax's README), the same seed for every variant:

- `brax`: Brax's own wrapper (no `wrap_env_fn`).
- `report_full`: `jaxmetrics.brax.wrap` with a `Logger` (TensorBoard), reporting by itself
  from inside the trainer; 11 terms for `ant` (episode return and length, and every
  `State.metrics` entry but `forward_reward`, which duplicates `reward_forward`) with the
  benchmarks' "full" statistics (`_workload.pattern_stats`: mean/std/min/max/sum/count, EMA,
  window(100) with percentiles, histograms), default `report_every`.
- `report_mean`: the same terms, mean + count only.
- `report_all` (not run by default): every statistic on every term.
- `fold_full`, `fold_mean`: `jaxmetrics.brax.wrap` with the same specs and no logger: the
  wrapper folds on every step and never reports (the cost of the fold alone).
- `report_full_mem`: `report_full` with a `jm.MemoryWriter` in place of the TensorBoard
  writer (what the report costs without event files).
- `report_full_rare`: `report_full` with `report_every=RARE_REPORT_EVERY` (5M env steps:
  one or two reports per 10M-step run instead of 28): the per-step reporting machinery
  without the per-report cost.
- `report_full_often`: `report_full` with `report_every=OFTEN_REPORT_EVERY` (10x the
  reports: 288 per 10M-step run), where the per-report cost stands above the noise.

Per run: the steady-state env steps per second between consecutive `progress_fn` calls
(each interval includes Brax's evaluation; every interval in which a backend compile
ended is left out: on JAX 0.11 the first two, as the training epoch compiles twice),
Brax's own `training/sps` (the training epoch alone, over the same epochs), the wall time
of `ppo.train`, and for the reporting variants each record's arrival time relative to the
start of training. Results are written after every run, so a run cut short keeps the
finished ones. Every run is tagged with `--call`, the device call it ran in, and compared
only with the `brax` runs of the same call (`_brax_results`). `--out` keeps every run
(progress calls, arrivals: not for the repository); `--summary` writes the summary that
docs/benchmarks.md renders; `--merge A.json B.json` joins the runs and calls of several
`--out` files.
"""

import argparse
import functools
import json
import os
import platform
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

import jaxmetrics as jm
import jaxmetrics.brax as jmb

from ._brax_results import call_tables, summarize, summary_doc, summary_table
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
) -> dict:
    """Env steps per second between progress calls (the initial eval at step 0, then one
    per training epoch + eval), over the intervals in which nothing compiled.

    Brax compiles its training epoch in the first interval and, on this JAX, once more in
    the second (the first epoch's outputs come back with other types or layouts than
    the inputs it was traced with): `steady_sps` leaves out every interval in which a
    backend compile ended; `steady_sps_excl_first` leaves out the first interval only."""
    out: dict[str, Any] = {"intervals_sps": [], "compiling_intervals": []}
    for i, (a, b) in enumerate(zip(progress, progress[1:])):
        out["intervals_sps"].append((b["step"] - a["step"]) / (b["t_s"] - a["t_s"]))
        n = sum(a["t_s"] < t <= b["t_s"] for t, _ in compiles)
        if n:
            out["compiling_intervals"].append(i)
    if compiles and progress:
        out["compiles_after_last_progress"] = sum(t > progress[-1]["t_s"] for t, _ in compiles)
    skip = set(out["compiling_intervals"])
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
    t0 = time.time()
    counter.start(t0)
    if mode == "report":
        writer = ArrivalWriter(t0)
        main_writer = jm.MemoryWriter() if sink == "memory" else jm.TensorBoardWriter(logdir)
        logger = jm.Logger(metrics, [main_writer, writer])
        result["writer"] = type(main_writer).__name__
        result["report_channel"] = logger.report_channel._asdict()
        extra["wrap_env_fn"] = functools.partial(
            jmb.wrap, metrics=metrics, logger=logger, report_every=report_every
        )
    elif mode == "fold":
        extra["wrap_env_fn"] = functools.partial(jmb.wrap, metrics=metrics)

    def progress_fn(step: int, m: dict[str, Any]) -> None:
        record_progress(progress, f"{variant} run {run}", t0, step, m)

    try:
        ppo.train(environment=env, progress_fn=progress_fn, **settings, **extra)
        t_train = time.time() - t0
    finally:
        counter.active = False
        if logger is not None:
            result["logger_close_s"] = closed(logger)
    result.update(
        **run_times(t_train, counter, progress),
        compile_events=[(round(t, 2), round(d, 2)) for t, d in counter.events],
        **_steady(progress, counter.events),
    )
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


def restore_device_put_replicated() -> None:
    """What docs/brax.md tells users to run before Brax's `ppo.train`: Brax 0.14.2's
    `ppo.train` calls `jax.device_put_replicated`, which JAX 0.10 removed from its public
    namespace (the function is still in `jax._src.api`, in JAX 0.11.2 too), so the name is
    restored. With a Brax that no longer calls it, or a JAX that still has it, it does
    nothing."""
    if not hasattr(jax, "device_put_replicated"):
        from jax._src.api import device_put_replicated

        jax.device_put_replicated = device_put_replicated


def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks brax-train",
        description="What the reporting Brax wrapper costs inside Brax's ppo.train.",
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
    p.add_argument("--out", default=None, help="every run (progress calls, record arrivals)")
    p.add_argument(
        "--summary",
        default=None,
        help="where to write the summary docs/benchmarks.md renders "
        "(docs/benchmarks/<kind>_brax_ppo_train.json)",
    )
    p.add_argument("--explain-cache-misses", action="store_true", help="log why JAX recompiles")
    p.add_argument(
        "--merge",
        nargs="+",
        default=None,
        help="run nothing: join these --out files' runs and calls into --out and --summary",
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
    for t in [*call_tables(doc), summary_table(doc)]:
        print(t.to_markdown(), flush=True)


def _write_outputs(args: argparse.Namespace, doc: dict[str, Any]) -> None:
    if args.out:
        _write(args.out, doc)
    if args.summary and doc["runs"]:
        _write(args.summary, summary_doc(doc))


def main(argv: Sequence[str] | None = None) -> None:
    args = _parse(argv)
    if args.merge:
        docs = []
        for path in args.merge:
            with open(path) as fh:
                docs.append(json.load(fh))
        doc = merge(docs)
        _print_tables(doc)
        _write_outputs(args, doc)
        return
    variants = [v for v in args.variants.split(",") if v]
    for v in variants:
        if v not in VARIANTS:
            sys.exit(f"unknown variant {v!r}; choose from {', '.join(VARIANTS)}")
    restore_device_put_replicated()
    if args.explain_cache_misses:
        jax.config.update("jax_explain_cache_misses", True)
    counter = CompileCounter()
    command = " ".join(
        ["python", "-m", "benchmarks", "brax-train"]
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
            _write_outputs(args, doc)
    _print_tables(doc)
