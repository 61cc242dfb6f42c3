"""What a `_brax_train` results file says, as numbers and tables (no Brax needed).

A file holds runs of `ppo.train` from one or more device calls (`calls`: the tree, the
commands). Runs are compared only with the Brax wrapper's runs of their own call: from
one machine start to the next, Brax's own sps moves by about 1%, as much as what is
measured.
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
    overhead against the call's `brax` runs in % (time per step)."""
    out: dict[str, dict[str, Any]] = {}
    for call in dict.fromkeys(r["call"] for r in runs):
        in_call = [r for r in runs if r["call"] == call]
        brax = _brax_rates(in_call)
        out[call] = {}
        for v in dict.fromkeys(r["variant"] for r in in_call):
            rs = [r for r in in_call if r["variant"] == v]
            steady = _mean([r["steady_sps"] for r in rs if r["steady_sps"]])
            training = _mean([r["brax_training_sps"] for r in rs if r["brax_training_sps"]])
            out[call][v] = {
                "runs": len(rs),
                "steady_sps_mean": steady,
                "brax_training_sps_mean": training,
                "overhead_steady_pct": _over(brax["steady"], steady),
                "overhead_brax_sps_pct": _over(brax["training"], training),
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


def callback_split(times: dict[str, Any]) -> dict[str, list[float]]:
    """Per report, in ms: JAX's host function before our `_on_emit` starts (copying the
    operands to the CPU) and after it ends (the return to XLA, where a writer thread
    holding the GIL makes it wait); from the raw `(start s, duration ms)` pairs."""
    before, after = [], []
    for (js, jd), (os_, od) in zip(times["raw"]["jax_callback"], times["raw"]["on_emit"]):
        before.append(1e3 * (os_ - js))
        after.append(jd - 1e3 * (os_ - js) - od)
    return {"before": before, "after": after}


def callback_table(runs: Sequence[dict[str, Any]]) -> Table:
    """Where a report's host time goes, for the runs timed with `--time-callbacks`."""
    t = Table(
        "callbacks",
        "Host side of a report (`--time-callbacks`), ms per report",
        [
            "call",
            "variant",
            "writer",
            "reports",
            "JAX host function, mean",
            "max",
            "copy to CPU, mean",
            "`_on_emit`, mean",
            "return to XLA, mean",
            "max",
            "writer job, mean",
            "`write`, mean",
        ],
    )
    for r in runs:
        c = r["callback_times"]
        split = callback_split(c)
        t.add(
            r["call"],
            r["variant"],
            r["writer"],
            r["records"],
            c["jax_callback"].get("mean_ms"),
            c["jax_callback"].get("max_ms"),
            _mean(split["before"]),
            c["on_emit"].get("mean_ms"),
            _mean(split["after"]),
            max(split["after"], default=None),
            c["writer_job"].get("mean_ms"),
            c["write"].get("mean_ms"),
        )
    t.notes.append(
        "JAX host function: JAX's own function around ours (`io_callback_impl`); copy to "
        "CPU: its time before `Logger._on_emit` starts; return to XLA: its time after "
        "`_on_emit` ends; writer job: the writer thread's work per record (unpack, "
        "`Record`, every writer), beside training; `write`: the main writer's."
    )
    return t


def probe_table(call: str, probe: dict[str, Any]) -> Table:
    """What one ordered `io_callback` under `lax.cond` costs in a device loop."""
    t = Table(
        f"probe_{call}",
        f"Call `{call}`: one ordered io_callback under lax.cond in a jitted loop of "
        f"{probe['iters']:,} iterations, no Brax (`--callback-probe`)",
        ["callback every", "callbacks per call", "ms per callback", "host function ms"]
        + ["JAX host function ms"],
    )
    for r in probe["rows"]:
        if r["period"]:
            t.add(
                r["period"],
                r["callbacks_per_call"],
                r["ms_per_callback"],
                r["host_fn"].get("mean_ms"),
                r["jax_callback"].get("mean_ms"),
            )
    t.notes.append(
        "ms per callback: the loop's median time above the same loop with no callback "
        "(the cond alone), over the callbacks made; host function: ours alone (a copy "
        "and a sum of 1,452 bytes)."
    )
    return t


def tables(doc: dict[str, Any]) -> list[Table]:
    """Every table of a `_brax_train` results file: one per call, then the host side of
    the timed reports and the callback probes."""
    out = [
        call_table(call, meta, [r for r in doc["runs"] if r["call"] == call])
        for call, meta in doc["calls"].items()
        if any(r["call"] == call for r in doc["runs"])
    ]
    timed = [r for r in doc["runs"] if "callback_times" in r]
    if timed:
        out.append(callback_table(timed))
    out += [
        probe_table(call, meta["callback_probe"])
        for call, meta in doc["calls"].items()
        if "callback_probe" in meta
    ]
    return out
