"""`python -m jaxmetrics.bench`: run the scenarios, print a table each, write JSON."""

import argparse
import dataclasses
import sys
from collections.abc import Callable, Sequence
from typing import Any

import jax

from . import _flush_cost, _isolated, _rollout, _sharded
from ._report import Table, environment, write_json

SCENARIOS = ("isolated", "scaling", "groups", "flush", "e2e", "sharded")


@dataclasses.dataclass
class Config:
    """Sizes of every scenario. `QUICK` suits a CPU, `FULL` a GPU."""

    scenarios: tuple[str, ...] = SCENARIOS
    num_envs: int = 4096
    steps: int = 1000
    repeats: int = 10
    env: str = "ant"
    backend: str = "mjx"
    e2e_envs: int = 4096
    e2e_steps: int = 1000
    e2e_repeats: int = 5
    host_steps: int = 100
    host_repeats: int = 3
    e2e_variants: tuple[str, ...] = _rollout.VARIANTS
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
    "env": "Brax env of the end-to-end scenarios",
    "backend": "Brax backend of the end-to-end scenarios",
    "e2e_envs": "envs of the end-to-end rollouts",
    "e2e_steps": "scan length of the end-to-end rollouts",
    "e2e_repeats": "timed repeats of the end-to-end rollouts",
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
    e2e_envs=32,
    e2e_steps=200,
    e2e_repeats=3,
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


def run(
    config: Config,
    hlo_dir: str | None = None,
    profile: bool = False,
    on_table: Callable[[Table, list[Table]], None] | None = None,
) -> list[Table]:
    """Runs the configured scenarios and returns their tables, the targets table last.

    `on_table(table, tables_so_far)` is called as each table is done (to print it, or
    to save partial results).
    """
    tables: list[Table] = []

    def done(*new: Table) -> None:
        for t in new:
            tables.append(t)
            if on_table is not None:
                on_table(t, tables)

    c = config
    if "isolated" in c.scenarios:
        done(*_isolated.isolated(c.num_envs, c.steps, c.repeats, hlo_dir, profile))
    if "scaling" in c.scenarios:
        done(
            *_isolated.scaling(
                list(c.scale_envs),
                list(c.scale_terms),
                list(c.scale_windows),
                c.num_envs,
                c.scale_steps,
                c.scale_repeats,
            )
        )
    if "groups" in c.scenarios:
        done(_isolated.groups(list(c.group_counts), c.num_envs, c.scale_steps, c.scale_repeats))
    if "flush" in c.scenarios:
        done(_flush_cost.flush(list(c.flush_envs), c.flush_repeats))
        done(_flush_cost.period_ends(c.period_envs, c.period_ends, c.period_every, c.flush_repeats))
    if "e2e" in c.scenarios:
        done(
            *_rollout.end_to_end(
                c.env,
                c.backend,
                c.e2e_envs,
                c.e2e_steps,
                c.e2e_repeats,
                c.host_steps,
                c.host_repeats,
                c.e2e_variants,
            )
        )
    if "sharded" in c.scenarios:
        done(
            *_sharded.sharded(
                c.env,
                c.backend,
                c.sharded_per_device,
                c.sharded_steps,
                c.sharded_repeats,
                c.sharded_devices,
                c.sharded_processes,
            )
        )
    done(targets(tables))
    return tables


def _find(tables: Sequence[Table], name: str) -> Table | None:
    return next((t for t in tables if t.name == name), None)


def targets(tables: Sequence[Table]) -> Table:
    """The issue's targets, against what was measured in this run."""
    t = Table("targets", "Targets", ["target", "measured", "met"])
    e2e = _find(tables, "end_to_end")
    if e2e is not None:
        pct = {r[0]: r[3] for r in e2e.rows}
        full = pct[_rollout.LABELS["jaxmetrics"]]
        t.add("end-to-end overhead <= 2% (10 terms)", f"{full:.2f}%", full <= 2.0)
        lean = pct.get(_rollout.LABELS["lean"])
        if lean is not None:
            t.add("(same, 10 terms with simple stats only)", f"{lean:.2f}%", lean <= 2.0)
        empty = pct.get(_rollout.LABELS["empty"])
        if empty is not None:
            same = e2e.data["check"]["empty_lowers_to_bare"]
            t.add(
                "empty spec indistinguishable from bare",
                f"{empty:.2f}%, same program: {same}",
                same,
            )
    iso = _find(tables, "isolated")
    if iso is not None:
        ratio = next(r[2] for r in iso.rows if r[0].startswith("jaxmetrics: full"))
        t.add("isolated update <= 1.5x the floor", f"{ratio:.2f}x", ratio <= 1.5)
    alt = _find(tables, "alternatives")
    if alt is not None:
        for key, label in (
            ("callback_numpy", "callback -> numpy logger"),
            ("callback_dict", "callback -> per-env dict logger"),
            ("device_get_loop", "device_get loop -> numpy logger"),
        ):
            r = alt.data["ratios_to_jaxmetrics"].get(key, "absent")
            if r == "absent":
                continue
            shown = "jaxmetrics overhead not above noise" if r is None else f"{r:,.0f}x"
            t.add(
                f">= 100x less per-step overhead than {label}",
                shown,
                None if r is None else r >= 100,
            )
    sh = _find(tables, "sharded")
    if sh is not None:
        over = {(r[0], r[1]): r[3] for r in sh.rows}
        one = over.get((1, _sharded.SPECS["full"]))
        for (d, label), pct in over.items():
            if d > 1 and label == _sharded.SPECS["full"] and one is not None:
                t.add(
                    f"overhead on {d} devices within 0.5 pp of 1 device's (full spec)",
                    f"{pct:.2f}% vs {one:.2f}%",
                    pct - one <= 0.5,
                )
        left = sum(r[4] for r in sh.rows if r[1] != _sharded.SPECS["unsharded"])
        t.add("no collective in the step loop (sharded state)", f"{left} ops", left == 0)
    fl = _find(tables, "flush")
    if fl is not None:
        col = {c: k for k, c in enumerate(fl.columns)}
        for name, what in (
            ("Logger.flush ms", "Logger.flush call (what the loop waits for)"),
            ("device_get ms", "synchronous compute + device_get of the report"),
        ):
            ms = [r[col[name]] for r in fl.rows]
            t.add(f"flush under 1 ms: {what}", f"{max(ms):.3f} ms at most", max(ms) < 1.0)
            t.add(
                f"flush flat in num_envs: {what}",
                f"max/min over num_envs {max(ms) / min(ms):.2f}",
                None,
            )
        sizes = sorted({r[col["bytes to host"]] for r in fl.rows})
        t.add("bytes to host flat in num_envs", f"{sizes}", len(sizes) == 1)
    t.notes.append("met '-': judged by reading the numbers (noise-limited), not a threshold.")
    return t


def _ints(s: str) -> tuple[int, ...]:
    return tuple(int(x) for x in s.split(",") if x)


def parse(argv: Sequence[str] | None = None) -> tuple[Config, argparse.Namespace]:
    p = argparse.ArgumentParser(
        prog="python -m jaxmetrics.bench",
        description="What jaxmetrics costs, against the bare rollout and the alternatives.",
    )
    size = p.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="small sizes (default on CPU)")
    size.add_argument("--full", action="store_true", help="full sizes (default on GPU/TPU)")
    lists = {"scenarios": SCENARIOS, "e2e_variants": _rollout.VARIANTS}
    for name, choices in lists.items():
        p.add_argument(
            "--" + name.replace("_", "-"),
            default=None,
            help=f"comma list of {','.join(choices)} (default: all)",
        )
    p.add_argument(
        "--json",
        default=None,
        help="where to write the JSON results (default: jaxmetrics_bench_<backend>.json)",
    )
    p.add_argument("--hlo-dir", default=None, help="write the compiled HLO of scenario 1 here")
    p.add_argument(
        "--profile",
        action="store_true",
        help="with the isolated scenario: device time per kernel of the floor and full spec",
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


def main(argv: Sequence[str] | None = None) -> list[Table]:
    config, args = parse(argv)
    print(
        f"jaxmetrics.bench: preset {args.preset} on {jax.devices()[0].device_kind} "
        f"({jax.default_backend()})",
        flush=True,
    )
    path = args.json or f"jaxmetrics_bench_{jax.default_backend()}.json"
    cfg = dataclasses.asdict(config)
    cfg["preset"] = args.preset
    env = environment()
    env["note"] = args.note

    def on_table(table: Table, so_far: list[Table]) -> None:
        print(table.to_markdown(), flush=True)
        write_json(path, env, cfg, so_far)  # partial results survive a killed run

    tables = run(config, args.hlo_dir, args.profile, on_table)
    print(f"wrote {path}", file=sys.stderr)
    return tables
