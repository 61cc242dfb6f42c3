"""`python -m benchmarks`: run the scenarios, print a table each, write JSON; or one of the
trainer benchmarks (`COMMANDS`), each with its own options."""

import argparse
import dataclasses
import importlib
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import jax

from . import _flush_cost, _isolated, _loaded, _render, _rollout, _sharded
from ._report import Table, device_label, environment, write_json
from ._targets import targets

SCENARIOS = ("isolated", "loaded", "scaling", "groups", "flush", "e2e", "sharded")

COMMANDS = {
    "brax-train": ("_brax_train", "Brax's ppo.train on ant, Brax's wrapper against ours"),
    "playground-train": (
        "_playground_train",
        "Playground's CartpoleBalance training, Playground's wrapper against ours",
    ),
    "in-trainer": ("_in_trainer", "one summary file of the two trainers' outputs"),
    "channel": ("_channel", "the report channels side by side in a jitted loop"),
}
"""`python -m benchmarks COMMAND ...`: the module whose `main(argv)` runs it, and what it
measures."""


@dataclasses.dataclass
class Config:
    """Sizes of every scenario. `QUICK` suits a CPU, `FULL` a GPU."""

    scenarios: tuple[str, ...] = SCENARIOS
    num_envs: int = 4096
    steps: int = 1000
    repeats: int = 10
    step_kernels: int = 64
    loaded_features: tuple[str, ...] = tuple(f for f, _ in _isolated.ABLATION)
    loaded_terms: tuple[int, ...] = (1, 3)
    loaded_envs: tuple[int, ...] = (16384,)
    env: str = "ant"
    backend: str = "mjx"
    e2e_envs: int = 4096
    e2e_steps: int = 1000
    e2e_repeats: int = 5
    host_steps: int = 100
    host_repeats: int = 3
    e2e_variants: tuple[str, ...] = _rollout.VARIANTS
    # Two estimates of 8 rounds each: on an H200 rounds agreed within 0.03%, and the whole
    # e2e scenario should then fit one 10-minute device call (16 rounds of one: 8.9 min).
    e2e_live_rounds: int = 8
    scale_envs: tuple[int, ...] = (256, 1024, 4096, 16384, 65536)
    scale_terms: tuple[int, ...] = (1, 3, 10, 30, 100)
    scale_windows: tuple[int, ...] = (10, 100, 1000, 10000)
    scale_steps: int = 1000
    scale_repeats: int = 5
    group_counts: tuple[int, ...] = (1, 8, 64)
    flush_envs: tuple[int, ...] = (256, 1024, 4096, 16384, 65536)
    flush_repeats: int = 50
    period_envs: int = 4096
    period_ends: int = 50
    period_every: int = 10
    sharded_per_device: int = 4096
    sharded_steps: int = 500
    sharded_repeats: int = 5
    sharded_devices: tuple[int, ...] = (1, 2)
    sharded_processes: int = 2


HELP = {
    "num_envs": "envs of the isolated update (scenario 1)",
    "steps": "scan length of the isolated update",
    "repeats": "timed repeats of the isolated update",
    "step_kernels": "kernels of the synthetic env step of the loaded scenario",
    "loaded_terms": "numbers of terms of the loaded scenario's full-spec rows (at --num-envs)",
    "loaded_envs": "num_envs of the loaded scenario's full-spec rows besides --num-envs",
    "env": "Brax env of the end-to-end scenarios",
    "backend": "Brax backend of the end-to-end scenarios",
    "e2e_envs": "envs of the end-to-end rollouts",
    "e2e_steps": "scan length of the end-to-end rollouts",
    "e2e_repeats": "timed repeats of the end-to-end rollouts",
    "e2e_live_rounds": "paired rounds of each live-read estimate, the read's and its control's",
    "host_steps": "rollout length of the per-step host loggers",
    "host_repeats": "timed repeats of the per-step host loggers",
    "scale_envs": "num_envs values of the scaling table",
    "scale_terms": "numbers of terms of the scaling table",
    "scale_windows": "window sizes of the scaling table",
    "scale_steps": "scan length of the scaling tables",
    "scale_repeats": "timed repeats of the scaling tables",
    "group_counts": "numbers of groups of the per-group table (isolated envs, scaling steps)",
    "flush_envs": "num_envs values of the flush table",
    "flush_repeats": "flushes timed per size",
    "period_envs": "envs of the period-end table (emit vs report history)",
    "period_ends": "period ends per jitted call in the period-end table",
    "period_every": "steps per period in the period-end table",
    "sharded_per_device": "envs per device of the weak-scaling rollouts",
    "sharded_steps": "scan length of the weak-scaling rollouts",
    "sharded_repeats": "timed repeats of the weak-scaling rollouts",
    "sharded_devices": "device counts of the weak-scaling table (those present)",
    "sharded_processes": "processes of the jax.distributed table (0: skip it)",
}

FULL = Config()
QUICK = dataclasses.replace(
    FULL,
    num_envs=256,
    steps=200,
    repeats=5,
    loaded_terms=(1,),
    loaded_envs=(1024,),
    e2e_envs=32,
    e2e_steps=200,
    e2e_repeats=3,
    e2e_live_rounds=4,
    host_steps=50,
    host_repeats=2,
    scale_envs=(256, 1024, 4096),
    scale_terms=(1, 10, 30),
    scale_steps=100,
    scale_repeats=3,
    flush_repeats=20,
    period_envs=256,
    sharded_per_device=32,
    sharded_steps=100,
    sharded_repeats=2,
)


def _scenario_tables(name: str, c: Config, hlo_dir: str | None, profile: bool) -> Iterator[Table]:
    """The tables of scenario `name`, each as soon as it is measured."""
    if name == "isolated":
        yield from _isolated.isolated(c.num_envs, c.steps, c.repeats, hlo_dir, profile)
    elif name == "loaded":
        yield _loaded.loaded(
            c.num_envs,
            c.loaded_features,
            c.loaded_terms,
            c.loaded_envs,
            c.steps,
            c.repeats,
            c.step_kernels,
        )
    elif name == "scaling":
        yield from _isolated.scaling(
            list(c.scale_envs),
            list(c.scale_terms),
            list(c.scale_windows),
            c.num_envs,
            c.scale_steps,
            c.scale_repeats,
        )
    elif name == "groups":
        yield from _isolated.groups(
            list(c.group_counts), c.num_envs, c.scale_steps, c.scale_repeats, profile
        )
    elif name == "flush":
        yield _flush_cost.flush(list(c.flush_envs), c.flush_repeats)
        yield _flush_cost.period_ends(c.period_envs, c.period_ends, c.period_every, c.flush_repeats)
    elif name == "e2e":
        yield from _rollout.end_to_end(
            c.env,
            c.backend,
            c.e2e_envs,
            c.e2e_steps,
            c.e2e_repeats,
            c.host_steps,
            c.host_repeats,
            c.e2e_variants,
            c.e2e_live_rounds,
        )
    elif name == "sharded":
        yield from _sharded.sharded(
            c.env,
            c.backend,
            c.sharded_per_device,
            c.sharded_steps,
            c.sharded_repeats,
            c.sharded_devices,
            c.sharded_processes,
        )


def run(
    config: Config,
    hlo_dir: str | None = None,
    profile: bool = False,
    on_table: Callable[[Table, list[Table]], None] | None = None,
) -> list[Table]:
    """Runs the configured scenarios and returns their tables, the targets table last.

    Each table's `scenario` names the scenario that made it. `on_table(table,
    tables_so_far)` is called as each table is done (to print it, or to save partial
    results).
    """
    tables: list[Table] = []

    def done(t: Table) -> None:
        tables.append(t)
        if on_table is not None:
            on_table(t, tables)

    for name in SCENARIOS:
        if name in config.scenarios:
            for t in _scenario_tables(name, config, hlo_dir, profile):
                t.scenario = name
                done(t)
    done(targets(tables, jax.default_backend()))
    return tables


def _ints(s: str) -> tuple[int, ...]:
    return tuple(int(x) for x in s.split(",") if x)


def parse(argv: Sequence[str] | None = None) -> tuple[Config, argparse.Namespace]:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks",
        description="What jaxmetrics costs, against the bare rollout and the alternatives. "
        "Without a command: run the --scenarios.",
        epilog="commands (python -m benchmarks COMMAND --help for their options):\n"
        + "\n".join(f"  {name:<18}{what}" for name, (_, what) in COMMANDS.items()),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    size = p.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="small sizes (default on CPU)")
    size.add_argument("--full", action="store_true", help="full sizes (default on GPU/TPU)")
    lists = {
        "scenarios": SCENARIOS,
        "loaded_features": Config.loaded_features,
        "e2e_variants": _rollout.VARIANTS,
    }
    for name, choices in lists.items():
        p.add_argument(
            "--" + name.replace("_", "-"),
            default=None,
            help=f"comma list of {','.join(choices)} (default: all)",
        )
    p.add_argument(
        "--json",
        default=None,
        help="where to write every table as one JSON (default: benchmarks_<backend>.json, "
        "unless --out-dir is given)",
    )
    p.add_argument(
        "--out-dir",
        default=None,
        help="also write each scenario's tables to DIR/<kind>_<scenario>.json, the file "
        "docs/benchmarks.md shows (e.g. docs/benchmarks/h100_isolated.json)",
    )
    p.add_argument(
        "--kind",
        default=None,
        help="device kind in --out-dir's file names (default from the devices: cpu, h100, "
        "h200x2, ...)",
    )
    p.add_argument(
        "--commit",
        default=None,
        help="the tree measured, stored as git_commit (default: this checkout's HEAD; pass "
        "it where the checkout is a copy whose .git may be stale)",
    )
    p.add_argument(
        "--render",
        nargs="?",
        const=_render.DOC,
        default=None,
        metavar="DOC",
        help=f"run nothing: rewrite the generated tables of DOC (default {_render.DOC}) from "
        "the JSON files in the folder beside it",
    )
    p.add_argument("--hlo-dir", default=None, help="write the compiled HLO of scenario 1 here")
    p.add_argument(
        "--profile",
        action="store_true",
        help="with the isolated scenario: device time per kernel of the floor and full spec; "
        "with groups, of both group specs at the most groups",
    )
    p.add_argument("--note", default=None, help="free text stored in the JSON (e.g. the tree)")
    for f in dataclasses.fields(Config):
        if f.name in lists:
            continue
        flag = "--" + f.name.replace("_", "-")
        if "tuple" in str(f.type):
            p.add_argument(flag, type=_ints, default=None, metavar="N,N,...", help=HELP[f.name])
        else:
            p.add_argument(flag, type=type(getattr(FULL, f.name)), default=None, help=HELP[f.name])
    a = p.parse_args(argv)
    quick = a.quick or (not a.full and jax.default_backend() == "cpu")
    base = QUICK if quick else FULL
    over: dict[str, Any] = {
        f.name: getattr(a, f.name)
        for f in dataclasses.fields(Config)
        if f.name not in lists and getattr(a, f.name) is not None
    }
    for name, choices in lists.items():
        given = getattr(a, name)
        if given is None:
            continue
        names = tuple(s.strip() for s in given.split(",") if s.strip())
        unknown = sorted(set(names) - set(choices))
        if unknown:
            p.error(f"unknown {name.replace('_', '-')} {unknown}; choose from {list(choices)}")
        over[name] = names
    a.preset = "quick" if quick else "full"
    return dataclasses.replace(base, **over), a


# XLA captures a loop body in a CUDA graph only from this many kernels on (default 5);
# below it the host launches each kernel and waits on the loop condition every step. A
# rollout's body always holds the env step's kernels too, so the update's own scans here
# run with every body captured, as in a rollout (docs/benchmarks.md, "What is
# measured"). Set before the first use of the backend; an XLA_FLAGS that names the
# threshold keeps its own.
GRAPH_FLAG = "--xla_gpu_graph_min_graph_size"


def main(argv: Sequence[str] | None = None) -> list[Table]:
    """Runs what `argv` (default: the command line) asks; the scenarios' tables, or [] for
    `--render` and the commands."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in COMMANDS:
        # Before the graph threshold below: the trainers run with their own flags.
        module = importlib.import_module(f".{COMMANDS[argv[0]][0]}", __package__)
        module.main(argv[1:])
        return []
    flags = os.environ.get("XLA_FLAGS", "")
    if GRAPH_FLAG not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {GRAPH_FLAG}=1".strip()
    config, args = parse(argv)
    if args.render is not None:
        _render.render_file(args.render)
        print(f"rendered {args.render}", file=sys.stderr)
        return []
    print(
        f"benchmarks: preset {args.preset} on {jax.devices()[0].device_kind} "
        f"({jax.default_backend()})",
        flush=True,
    )
    path = args.json or (None if args.out_dir else f"benchmarks_{jax.default_backend()}.json")
    cfg = dataclasses.asdict(config)
    cfg["preset"] = args.preset
    env = environment(args.commit)
    env["note"] = args.note
    kind = args.kind or device_label(env)
    if args.out_dir:
        os.makedirs(args.out_dir, exist_ok=True)
    written = [path] if path else []

    def on_table(table: Table, so_far: list[Table]) -> None:
        print(table.to_markdown(), flush=True)
        # Partial results survive a killed run: every file is rewritten after each table.
        if path:
            write_json(path, env, cfg, so_far)
        if args.out_dir and table.scenario:
            own = os.path.join(args.out_dir, f"{kind}_{table.scenario}.json")
            write_json(own, env, cfg, [t for t in so_far if t.scenario == table.scenario])
            written.append(own)

    tables = run(config, args.hlo_dir, args.profile, on_table)
    print("wrote " + ", ".join(dict.fromkeys(written)), file=sys.stderr)
    return tables
