"""What a `brax-train` output says, as numbers and tables (no Brax needed).

An output holds runs of `ppo.train` from one or more device calls (`calls`: the tree, the
commands). Runs are compared only with the Brax wrapper's runs of their own call: from
one machine start to the next, Brax's own sps moves by about 1%, as much as what is
measured. `summary_doc` keeps what docs/benchmarks.md shows (per call and variant, the
means and the costs), without the runs' progress calls and record arrivals.
"""

import statistics
from collections.abc import Sequence
from typing import Any

from ._report import Table


def _mean(xs: Sequence[float]) -> float | None:
    return statistics.mean(xs) if xs else None


def _over(base: float | None, sps: float | None) -> float | None:
    """Time per step above `base`'s, in %, from steps per second."""
    return 100.0 * (base / sps - 1.0) if base and sps else None


def _clean_intervals(run: dict[str, Any]) -> list[tuple[dict, dict, int]]:
    """The progress intervals the steady figures keep: `(start, end, index)`."""
    skip = set(run["compiling_intervals"]) | set(run.get("traced_intervals", ()))
    progress = run["progress"]
    return [(a, b, i) for i, (a, b) in enumerate(zip(progress, progress[1:])) if i not in skip]


MIN_REPORTS = 100
"""Fewest reports a per-report cost is read from: with the default period's 28 (22 in
the intervals kept), the ~1% spread of sps between runs is more per report than a
report costs."""


def report_cost(
    run: dict[str, Any], brax: dict[str, float | None]
) -> tuple[float | None, float | None]:
    """Milliseconds per report above the Brax wrapper's time for the same steps, over the
    intervals the steady figures keep: `(steady, training epochs)`; `(None, None)` where
    the run made fewer than `MIN_REPORTS` there or its call has no Brax run.

    Steady time is wall time between progress calls; a training epoch's time is its
    steps over Brax's `training/sps` for it."""
    clean = _clean_intervals(run)
    reports = sum(
        any(a["step"] < x["step"] <= b["step"] for a, b, _ in clean)
        for x in run.get("arrivals", ())
    )
    if reports < MIN_REPORTS or not brax["steady"] or not brax["training"]:
        return None, None
    steps = sum(b["step"] - a["step"] for a, b, _ in clean)
    steady_s = sum(b["t_s"] - a["t_s"] for a, b, _ in clean) - steps / brax["steady"]
    # Progress call i (i >= 1) brings Brax's training/sps of the epoch in interval i - 1.
    epoch_sps = {i - 1: p["training_sps"] for i, p in enumerate(run["progress"]) if i}
    training_s = sum(
        (b["step"] - a["step"]) * (1.0 / epoch_sps[i] - 1.0 / brax["training"]) for a, b, i in clean
    )
    return 1e3 * steady_s / reports, 1e3 * training_s / reports


def _brax_rates(runs: Sequence[dict[str, Any]]) -> dict[str, float | None]:
    base = [r for r in runs if r["variant"] == "brax"]
    return {
        "steady": _mean([r["steady_sps"] for r in base if r["steady_sps"]]),
        "training": _mean([r["brax_training_sps"] for r in base if r["brax_training_sps"]]),
    }


def summarize(runs: Sequence[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per call, per variant: the mean steady and Brax sps over its runs, and each one's
    overhead against the call's `brax` runs in % (time per step); for the reporting
    variants the reports per run and, where `report_cost` reads one, the ms per report."""
    out: dict[str, dict[str, Any]] = {}
    for call in dict.fromkeys(r["call"] for r in runs):
        in_call = [r for r in runs if r["call"] == call]
        brax = _brax_rates(in_call)
        out[call] = {}
        for v in dict.fromkeys(r["variant"] for r in in_call):
            rs = [r for r in in_call if r["variant"] == v]
            steady = _mean([r["steady_sps"] for r in rs if r["steady_sps"]])
            training = _mean([r["brax_training_sps"] for r in rs if r["brax_training_sps"]])
            costs = [report_cost(r, brax) for r in rs]
            out[call][v] = {
                "runs": len(rs),
                "steady_sps_mean": steady,
                "brax_training_sps_mean": training,
                "overhead_steady_pct": _over(brax["steady"], steady),
                "overhead_brax_sps_pct": _over(brax["training"], training),
                "reports_mean": _mean([r["records"] for r in rs if "records" in r]),
                "ms_per_report_steady": _mean([c[0] for c in costs if c[0] is not None]),
                "ms_per_report_training": _mean([c[1] for c in costs if c[1] is not None]),
            }
    return out


def _tree(commit: str | None) -> str:
    """`369e972+edits` for `369e9724860e...+edits`."""
    if not commit:
        return "-"
    head, plus, rest = commit.partition("+")
    return head[:7] + plus + rest


def _sps(x: float | None) -> int | None:
    return None if x is None else round(x)


def call_table(call: str, meta: dict[str, Any], runs: Sequence[dict[str, Any]]) -> Table:
    """One call's runs against the Brax wrapper's runs of that call, and the mean of each
    variant that ran more than once."""
    s = runs[0]["settings"]
    t = Table(
        f"call_{call}",
        f"Call `{call}`, tree `{_tree(meta['commit'])}`: {s['num_envs']:,} envs, "
        f"{s['num_timesteps'] / 1e6:g}M steps",
        [
            "variant",
            "run",
            "reports",
            "steady sps",
            "Brax training/sps",
            "steady vs Brax %",
            "training vs Brax %",
            "ms per report, steady",
            "ms per report, training",
        ],
    )
    brax = _brax_rates(runs)
    for v in dict.fromkeys(r["variant"] for r in runs):
        rs = [r for r in runs if r["variant"] == v]
        for r in rs:
            steady, training = r["steady_sps"], r["brax_training_sps"]
            t.add(
                v,
                r["run"],
                r.get("records"),
                _sps(steady),
                _sps(training),
                _over(brax["steady"], steady),
                _over(brax["training"], training),
                *report_cost(r, brax),
            )
        if len(rs) > 1:
            steady = _mean([r["steady_sps"] for r in rs])
            training = _mean([r["brax_training_sps"] for r in rs])
            t.add(
                v,
                f"mean of {len(rs)}",
                None,
                _sps(steady),
                _sps(training),
                _over(brax["steady"], steady),
                _over(brax["training"], training),
                None,
                None,
            )
    t.notes.append("Commands: " + "; ".join(f"`{c}`" for c in meta["commands"]) + ".")
    return t


def call_tables(doc: dict[str, Any]) -> list[Table]:
    """One `call_table` per call of an output (its runs one by one)."""
    return [
        call_table(call, meta, [r for r in doc["runs"] if r["call"] == call])
        for call, meta in doc["calls"].items()
        if any(r["call"] == call for r in doc["runs"])
    ]


def summary_doc(doc: dict[str, Any]) -> dict[str, Any]:
    """The summary of an output (or of a merge of outputs): its environment, calls and
    `summarize`d runs, with each call's envs and steps; not the runs themselves."""
    env = {k: v for k, v in doc["environment"].items() if k != "host"}
    calls = {}
    for call, meta in doc["calls"].items():
        runs = [r for r in doc["runs"] if r["call"] == call]
        if runs:
            s = runs[0]["settings"]
            calls[call] = {
                "commit": meta["commit"],
                "commands": meta["commands"],
                "notes": meta["notes"],
                "num_envs": s["num_envs"],
                "num_timesteps": s["num_timesteps"],
            }
    return {
        "benchmark": "brax_ppo_train",
        "environment": env,
        "calls": calls,
        "summary": summarize(doc["runs"]),
        "notes": list(doc.get("notes", [])),
    }


def summary_table(doc: dict[str, Any]) -> Table:
    """Per call and variant of a summary (or an output): the means of its runs against
    the call's `brax` runs, and the ms per report where enough reports were made."""
    t = Table(
        "brax_ppo_train",
        "Inside Brax's `ppo.train`: per device call, means of the runs",
        [
            "call",
            "tree",
            "envs, steps",
            "variant",
            "runs",
            "reports",
            "steady sps",
            "Brax training/sps",
            "steady vs Brax %",
            "training vs Brax %",
            "ms per report, steady",
            "ms per report, training",
        ],
        notes=list(doc.get("notes", [])),
    )
    for call, variants in doc["summary"].items():
        meta = doc["calls"][call]
        size = meta.get("num_envs"), meta.get("num_timesteps")
        if size[0] is None:  # an output: the sizes are in its runs
            run = next(r for r in doc["runs"] if r["call"] == call)
            size = run["settings"]["num_envs"], run["settings"]["num_timesteps"]
        for v, m in variants.items():
            base = v == "brax"
            t.add(
                call,
                _tree(meta["commit"]),
                f"{size[0]:,}, {size[1] / 1e6:g}M",
                v,
                m["runs"],
                None if m.get("reports_mean") is None else round(m["reports_mean"]),
                _sps(m["steady_sps_mean"]),
                _sps(m["brax_training_sps_mean"]),
                None if base else m["overhead_steady_pct"],
                None if base else m["overhead_brax_sps_pct"],
                m.get("ms_per_report_steady"),
                m.get("ms_per_report_training"),
            )
    return t
