"""`python -m benchmarks playground-train`: MuJoCo Playground's standard training of
`CartpoleBalance` (Brax's `ppo.train`) with the reporting Playground wrapper against
Playground's own, for MJX's Warp and JAX physics.

`python -m benchmarks playground-train --runs warp:jaxmetrics,warp:playground,
jax:jaxmetrics,jax:playground --commit $(git rev-parse HEAD) --out F.json`

Each run is what Playground's `learning/train_jax_ppo.py` does for a DM Control suite env:
`registry.load` with the env's default config (`impl` set per run), Playground's tuned
`dm_control_suite_params.brax_ppo_config` (num_envs, batch size, unroll, minibatches, ...),
seed 1, a separately loaded `eval_env`, and Playground's XLA flags; then
`ppo.train(..., wrap_env_fn=W)` with W one of Playground's `wrapper.wrap_for_brax_training`
(`playground`), the one-line change `functools.partial(jmp.wrap, metrics=metrics,
logger=logger, report_every=...)` (`jaxmetrics`; `jaxmetrics_io` the same with
`report_channel="io_callback"`), or `jmp.wrap` with the same metrics and no logger (`fold`:
it folds on every step and never reports). The metrics: episode return and
length and every reward component, each with mean, std, min, max, count and a window(100).
What differs from Playground's config:

- `num_timesteps` and `num_evals` (a few million steps in several intervals, instead of
  60M in 9);
- `num_resets_per_eval` (Playground's 10; default here 0, Brax's default): Brax resets the
  training envs after every epoch when it is positive, and an epoch of this config is
  `unroll_length * batch_size * num_minibatches / num_envs` = 480 steps per env unless
  `num_timesteps` asks for more than one training step per epoch (at Playground's 60M it does
  not), so with 10 resets no training episode (1000 steps) ever ends: the wrapper reports
  records of 0 episodes. `--runs warp:jaxmetrics:10` runs that setting (with the same
  `num_timesteps`, 10 times the steps: Brax runs at least one training step per epoch). Brax's
  `training/sps` is then 10 times too high: it divides the steps of every reset's epoch by
  the time of one.

A run spec is `impl:wrap[:num_resets_per_eval]`. Per run: env steps per second between
consecutive progress calls over the intervals in which no backend compile ended
(`_brax_train._steady`), Brax's `training/sps`, the wall time of `ppo.train`, and for the
reporting wrapper each record's arrival time at the writer thread relative to the start of
training, how many arrived before `ppo.train` returned, the records read back from the event
files by TensorBoard's `event_accumulator` (per record: step, episode count, mean return and
length), and the episode counts expected per record: the episodes have a fixed length (the
time limit; CartpoleBalance never terminates early) and start together, so every env ends
one at each multiple of `episode_length` of its steps since its last reset.
`--merge A.json B.json --out C.json` joins the runs of several outputs.
"""

import argparse
import functools
import json
import math
import os
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence
from typing import Any

import jax

import jaxmetrics as jm
import jaxmetrics.playground as jmp

from ._brax_train import (
    ArrivalWriter,
    CompileCounter,
    _steady,
    _version,
    _write,
    closed,
    record_progress,
    restore_device_put_replicated,
    run_times,
)
from ._brax_train import environment as brax_environment

ENV = "CartpoleBalance"
WRAPS = ("jaxmetrics", "jaxmetrics_io", "fold", "playground")
IMPLS = ("warp", "jax")
STATS = ("mean", "std", "min", "max", "count", jm.window(100))
REPORTS_PER_EPOCH = 5
"""Records per training epoch by default (every 96 env-batch steps of Playground's 480)."""
RETURN = "Episode_Metrics/episode_return"
LENGTH = "Episode_Metrics/episode_length"


def parse_run(spec: str) -> tuple[str, str, int | None]:
    """`(impl, wrap, num_resets_per_eval or None for --num-resets-per-eval)` of a spec."""
    impl, wrap, *rest = spec.split(":")
    if impl not in IMPLS or wrap not in WRAPS or len(rest) > 1:
        raise ValueError(f"bad run {spec!r}: impl:wrap[:num_resets_per_eval], impl in "
                         f"{IMPLS}, wrap in {WRAPS}")  # fmt: skip
    return impl, wrap, int(rest[0]) if rest else None


def ppo_settings(args: argparse.Namespace, resets: int | None) -> dict[str, Any]:
    """Playground's tuned PPO settings for `ENV` with this bench's overrides."""
    from mujoco_playground.config import dm_control_suite_params

    settings = dict(dm_control_suite_params.brax_ppo_config(ENV))
    settings.setdefault("num_eval_envs", 128)  # train_jax_ppo.py's default
    settings.update(
        num_timesteps=args.timesteps,
        num_evals=args.num_evals,
        num_resets_per_eval=args.num_resets_per_eval if resets is None else resets,
    )
    for item in args.set:
        key, value = item.split("=", 1)
        if key not in settings:
            raise ValueError(f"--set {item!r}: no PPO setting {key!r} in {sorted(settings)}")
        settings[key] = type(settings[key])(value)
    return settings


def epoch_env_steps(settings: dict[str, Any]) -> int:
    """Env steps of one Brax training epoch (`ppo.train`'s own arithmetic)."""
    per_training_step = (
        settings["batch_size"]
        * settings["unroll_length"]
        * settings["num_minibatches"]
        * settings["action_repeat"]
    )
    evals_after_init = max(settings["num_evals"] - 1, 1)
    resets = max(settings["num_resets_per_eval"], 1)
    steps_per_epoch = math.ceil(
        settings["num_timesteps"] / (evals_after_init * per_training_step * resets)
    )
    return steps_per_epoch * per_training_step


def expected_counts(steps: Sequence[int], settings: dict[str, Any]) -> list[int]:
    """Training episodes ended in each record's period, for records at `steps` (env steps
    over all envs): every env ends one at each multiple of `episode_length` sub-steps
    since its last reset (Brax's reset after each epoch when `num_resets_per_eval > 0`)."""
    num_envs, length = settings["num_envs"], settings["episode_length"]
    epoch = epoch_env_steps(settings) // num_envs if settings["num_resets_per_eval"] else None

    def ended(per_env: int) -> int:
        if epoch is None:
            return per_env // length
        return (per_env // epoch) * (epoch // length) + (per_env % epoch) // length

    out, before = [], 0
    for s in steps:
        now = ended(s // num_envs)
        out.append(num_envs * (now - before))
        before = now
    return out


def build_terms(env: Any) -> dict[str, jm.Term]:
    """Episode return and length and every reward component of the env's `State.metrics`."""
    shapes = jax.eval_shape(env.reset, jax.ShapeDtypeStruct((2,), jax.numpy.uint32))
    return {
        "episode_return": jmp.episode_return(stats=STATS),
        "episode_length": jmp.episode_length(stats=STATS),
        **jmp.state_metrics(sorted(shapes.metrics), stats=STATS),
    }


def read_events(logdir: str) -> dict[str, list[tuple[int, float]]]:
    """Every scalar tag of the event files under `logdir`: (step, value) in file order."""
    from tensorboard.backend.event_processing import event_accumulator

    acc = event_accumulator.EventAccumulator(logdir, size_guidance={event_accumulator.SCALARS: 0})
    acc.Reload()
    return {t: [(e.step, e.value) for e in acc.Scalars(t)] for t in acc.Tags()["scalars"]}


def _finite(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def records_summary(tb: dict[str, list[tuple[int, float]]], settings: dict[str, Any]) -> dict:
    """Per record read back: step, episodes, mean return and length; against the counts
    expected from the episodes' fixed length."""
    steps = [s for s, _ in tb.get("Counters/env_steps", [])]
    by_tag = {t: dict(tb.get(t, [])) for t in (f"{RETURN}/count", RETURN, LENGTH)}
    rows = [
        {
            "step": s,
            "episodes": int(by_tag[f"{RETURN}/count"].get(s, 0)),
            "episode_return": _finite(by_tag[RETURN].get(s)),
            "episode_length": _finite(by_tag[LENGTH].get(s)),
        }
        for s in steps
    ]
    want = expected_counts(steps, settings)
    episodes = sum(r["episodes"] for r in rows)
    weighted = sum(r["episodes"] * r["episode_return"] for r in rows if r["episodes"])
    return {
        "records_read": len(rows),
        "tags": len(tb),
        "steps_in_order_once": steps == sorted(set(steps)),
        "episodes": episodes,
        "episodes_expected": sum(want),
        "counts_as_expected": [r["episodes"] for r in rows] == want,
        "mean_return_over_records": weighted / episodes if episodes else None,
        "lengths": sorted({r["episode_length"] for r in rows if r["episodes"]}),
        "per_record": rows,
    }


def run_one(spec: str, args: argparse.Namespace, counter: CompileCounter) -> dict[str, Any]:
    """One `ppo.train` of a run spec; its timings and, with the reporting wrapper, records."""
    from brax.training.agents.ppo import networks as ppo_networks
    from brax.training.agents.ppo import train as ppo
    from mujoco_playground import registry, wrapper

    impl, wrap, resets = parse_run(spec)
    config = registry.get_default_config(ENV)
    config.impl = impl
    env = registry.load(ENV, config=config)
    eval_env = registry.load(ENV, config=config)
    settings = ppo_settings(args, resets)
    num_eval_envs = settings.pop("num_eval_envs")
    network_factory = settings.pop("network_factory", None)
    extra: dict[str, Any] = {
        "network_factory": ppo_networks.make_ppo_networks
        if network_factory is None
        else functools.partial(ppo_networks.make_ppo_networks, **network_factory),
        "num_eval_envs": num_eval_envs,
        "seed": args.seed,
        "eval_env": eval_env,
    }
    epoch = epoch_env_steps(settings)
    report_every = args.report_every or epoch // args.reports_per_epoch
    if epoch % report_every or report_every % settings["num_envs"]:
        # Records at whole env-batch steps dividing the epoch: none is cut by Brax's reset.
        raise ValueError(f"report_every {report_every} must divide the epoch's {epoch} env "
                         f"steps and be a multiple of num_envs {settings['num_envs']}")  # fmt: skip
    result: dict[str, Any] = {
        "run": spec, "impl": impl, "wrap": wrap,
        "settings": settings | {"num_eval_envs": num_eval_envs, "seed": args.seed,
                                "epoch_env_steps": epoch},
    }  # fmt: skip
    progress: list[dict[str, Any]] = []
    logger = writer = logdir = None
    t0 = time.time()
    if wrap in ("jaxmetrics", "jaxmetrics_io"):
        terms = build_terms(env)
        metrics = jm.Metrics(terms=terms)
        result["terms"] = list(terms)
        result["settings"]["report_every"] = report_every
        logdir = tempfile.mkdtemp(prefix=f"playground_{impl}_")
        writer = ArrivalWriter(t0)
        channel = "io_callback" if wrap == "jaxmetrics_io" else "auto"
        logger = jm.Logger(metrics, [jm.TensorBoardWriter(logdir), writer], report_channel=channel)
        result["report_channel"] = logger.report_channel._asdict()
        extra["wrap_env_fn"] = functools.partial(
            jmp.wrap, metrics=metrics, logger=logger, report_every=report_every
        )
    elif wrap == "fold":
        extra["wrap_env_fn"] = functools.partial(
            jmp.wrap, metrics=jm.Metrics(terms=build_terms(env))
        )
    else:
        extra["wrap_env_fn"] = wrapper.wrap_for_brax_training

    def progress_fn(step: int, m: dict[str, Any]) -> None:
        record_progress(progress, spec, t0, step, m)

    counter.start(t0)
    try:
        ppo.train(environment=env, progress_fn=progress_fn, **settings, **extra)
        t_train = time.time() - t0
    finally:
        counter.active = False
        if logger is not None:
            result["logger_close_s"] = closed(logger)
    result.update(
        **run_times(t_train, counter, progress),
        first_progress_s=progress[0]["t_s"] if progress else None,
        **_steady(progress, counter.events),
    )
    if writer is not None and logger is not None and logdir is not None:
        arr = [a | {"episode_return": _finite(a["episode_return"])} for a in writer.arrivals]
        result.update(
            records=len(arr),
            logger_emit_calls=logger.emit_calls,
            first_record_s=arr[0]["written_s"] if arr else None,
            last_record_s=arr[-1]["written_s"] if arr else None,
            records_before_train_end=sum(a["written_s"] <= t_train for a in arr),
            arrivals=arr,
            events=records_summary(read_events(logdir), settings),
        )
        shutil.rmtree(logdir, ignore_errors=True)
    return result


def environment(commit: str | None) -> dict[str, Any]:
    """`_brax_train.environment` with Playground's, Warp's and XLA's settings."""
    return {
        **brax_environment(commit),
        "playground": _version("playground"),
        "warp_lang": _version("warp-lang"),
        "xla_flags": os.environ.get("XLA_FLAGS"),
    }


def summarize(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Per impl (and `num_resets_per_eval` other than 0) and wrap: the runs' mean steady
    steps/s, Brax's training/sps and wall time; per wrap but Playground's, its cost against
    Playground's wrap (time per step, %)."""
    groups: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for r in runs:
        if "error" in r:
            continue
        resets = r["settings"]["num_resets_per_eval"]
        key = r["impl"] if resets == 0 else f"{r['impl']}_resets{resets}"
        wrap, every = r["wrap"], r["settings"].get("report_every")
        if every and every != r["settings"]["epoch_env_steps"] // REPORTS_PER_EPOCH:
            wrap += f"_{r['settings']['epoch_env_steps'] // every}_per_epoch"
        groups.setdefault(key, {}).setdefault(wrap, []).append(r)
    out: dict[str, Any] = {}
    for key, by_wrap in groups.items():
        row = out[key] = {}
        for wrap, rs in by_wrap.items():
            row[wrap] = {"runs": len(rs)} | {
                k: statistics.mean(r[k] for r in rs)
                for k in ("steady_sps", "brax_training_sps", "wall_s")
            }
        theirs = row.get("playground")
        for wrap, ours in row.items():
            if theirs and wrap != "playground":
                for k in ("steady_sps", "brax_training_sps"):
                    ours[f"overhead_{k}_pct"] = 100.0 * (theirs[k] / ours[k] - 1.0)
    return out


def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks playground-train",
        description="Playground's CartpoleBalance training with the reporting wrapper against "
        "Playground's own.",
    )
    p.add_argument(
        "--runs",
        default="warp:jaxmetrics,warp:playground,jax:jaxmetrics,jax:playground",
        help="comma-separated impl:wrap[:num_resets_per_eval], run in this order",
    )
    p.add_argument("--impl", choices=IMPLS, default=None, help="only the runs of this impl")
    p.add_argument("--timesteps", type=int, default=7_864_320, help="8 epochs of 983,040")
    p.add_argument("--num-evals", type=int, default=9, help="progress calls (Playground's 10)")
    p.add_argument("--num-resets-per-eval", type=int, default=0, help="Playground's 10")
    p.add_argument("--reports-per-epoch", type=int, default=REPORTS_PER_EPOCH)
    p.add_argument("--report-every", type=int, default=None, help="default: see above")
    p.add_argument("--seed", type=int, default=1, help="train_jax_ppo.py's default")
    p.add_argument(
        "--set", action="append", default=[], help="KEY=VALUE: another PPO setting (tiny runs)"
    )
    p.add_argument("--commit", default=None, help="git commit of the tree (`git rev-parse HEAD`)")
    p.add_argument("--out", default=None)
    p.add_argument("--merge", nargs="+", default=None, help="join these outputs' runs into --out")
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> None:
    args = _parse(argv)
    if args.merge:
        docs = [json.load(open(p)) for p in args.merge]
        doc = dict(docs[0])
        doc["runs"] = [r | {"from": os.path.basename(p)} for p, d in zip(args.merge, docs)
                       for r in d["runs"]]  # fmt: skip
        doc["merged_from"] = [{"file": os.path.basename(p), "environment": d["environment"],
                               "args": d["args"]} for p, d in zip(args.merge, docs)]  # fmt: skip
        doc["summary"] = summarize(doc["runs"])
        print(json.dumps(doc["summary"], indent=1))
        if args.out:
            _write(args.out, doc)
        return
    # Playground's training script sets these before JAX starts its backend.
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + " --xla_gpu_triton_gemm_any=True"
    ).strip()
    os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    os.environ.setdefault("MUJOCO_GL", "disable")
    restore_device_put_replicated()
    specs = [s for s in args.runs.split(",") if s]
    specs = [s for s in specs if args.impl is None or parse_run(s)[0] == args.impl]
    counter = CompileCounter()
    doc: dict[str, Any] = {
        "benchmark": "playground_ppo_train",
        "description": __doc__,
        "environment": environment(args.commit),
        "args": vars(args),
        "runs": [],
    }
    print(json.dumps(doc["environment"]), flush=True)
    for spec in specs:
        print(f"== {spec}", flush=True)
        t = time.time()
        try:
            r = run_one(spec, args, counter)
        except Exception as e:  # noqa: BLE001  (a failed impl is a result; the next run goes on)
            impl, wrap, _ = parse_run(spec)
            r = {"run": spec, "impl": impl, "wrap": wrap, "error": f"{type(e).__name__}: {e}",
                 "failed_after_s": round(time.time() - t, 2)}  # fmt: skip
            print(f"== {spec} FAILED: {r['error']}", flush=True)
        doc["runs"].append(r)
        doc["summary"] = summarize(doc["runs"])
        if "error" not in r:
            ev = r.get("events", {})
            print(
                f"== {spec}: wall {r['wall_s']:.1f}s steady {r['steady_sps']} "
                f"brax {r['brax_training_sps']} compiles {r['compiles']} records "
                f"{r.get('records')} (before end {r.get('records_before_train_end')}) episodes "
                f"{ev.get('episodes')}/{ev.get('episodes_expected')} return "
                f"{ev.get('mean_return_over_records')}",
                flush=True,
            )
        if args.out:
            _write(args.out, doc)
    print(json.dumps(doc.get("summary"), indent=1), flush=True)
    if any("error" in r for r in doc["runs"]):
        sys.exit(1)
