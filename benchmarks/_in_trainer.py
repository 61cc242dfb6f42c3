"""`python -m benchmarks in-trainer`: reporting inside a trainer the user does not own, one
summary file of steady env steps/s per wrapper, from the `--out` files of `playground-train`
(Playground's CartpoleBalance) and `brax-train` (Brax's `ant`), both Brax's `ppo.train`.

`python -m benchmarks in-trainer --playground A.json [B.json] --brax C.json
--commit <tree> --out docs/benchmarks/<kind>_in_trainer.json`

Per case (env, physics, num_envs): the steady env steps/s of every run, in run order, per
wrapper: `own` (the trainer's own wrapper: Playground's `wrap_for_brax_training`, or Brax's
when none is given), `jaxmetrics` (the reporting wrapper, `report_channel="auto"`),
`jaxmetrics_io_callback` (the same, `report_channel="io_callback"`) and `fold` (the wrapper
with no logger: it folds every step and never reports).
"""

import argparse
import json
import statistics
from collections.abc import Sequence
from typing import Any

from ._report import Table

# The runs' wrapper names in each bench, as this file names them.
_PLAYGROUND = {
    "playground": "own",
    "jaxmetrics": "jaxmetrics",
    "jaxmetrics_io": "jaxmetrics_io_callback",
    "fold": "fold",
}
_BRAX = {"brax": "own", "report_full": "jaxmetrics", "fold_full": "fold"}


def _add(cases: dict[tuple, dict[str, Any]], key: tuple, wrap: str, sps: float) -> None:
    env, impl, num_envs = key
    case = cases.setdefault(key, {"env": env, "impl": impl, "num_envs": num_envs, "runs": {}})
    case["runs"].setdefault(wrap, []).append(round(float(sps), 1))


def summarize(
    playground: Sequence[dict[str, Any]], brax: Sequence[dict[str, Any]], commit: str | None
) -> dict[str, Any]:
    """The summary file's content (see the module docstring)."""
    cases: dict[tuple, dict[str, Any]] = {}
    env: dict[str, Any] = {}
    for doc in playground:
        env = env or doc["environment"]
        for r in doc["runs"]:
            if "error" not in r and r["wrap"] in _PLAYGROUND:
                key = ("CartpoleBalance", r["impl"], r["settings"]["num_envs"])
                _add(cases, key, _PLAYGROUND[r["wrap"]], r["steady_sps"])
    for doc in brax:
        env = env or doc["environment"]
        for r in doc["runs"]:
            if "error" not in r and r.get("variant") in _BRAX:
                key = (doc["args"]["env"], doc["args"]["backend"], r["settings"]["num_envs"])
                _add(cases, key, _BRAX[r["variant"]], r["steady_sps"])
    return {
        "benchmark": "in_trainer",
        "cases": list(cases.values()),
        "device": env.get("device"),
        "jax": env.get("jax"),
        "commit": commit,
    }


def table(doc: dict[str, Any]) -> Table:
    """Mean steady steps/s per case and wrapper, and each wrapper's cost against `own`."""
    t = Table(
        "in_trainer",
        "Inside Brax's `ppo.train`: steady env steps/s, mean of the runs",
        ["env", "physics", "num_envs", "wrapper", "runs", "steady steps/s", "cost vs own %"],
    )
    for case in doc["cases"]:
        runs = case["runs"]
        own = statistics.mean(runs["own"]) if runs.get("own") else None
        for wrap, values in runs.items():
            mean = statistics.mean(values)
            cost = "" if own is None or wrap == "own" else round(100.0 * (own / mean - 1.0), 1)
            t.add(case["env"], case["impl"], case["num_envs"], wrap, len(values), round(mean), cost)
    return t


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks in-trainer",
        description="One summary of steady env steps/s per wrapper inside ppo.train, from "
        "playground-train and brax-train outputs.",
    )
    p.add_argument("--playground", nargs="*", default=[])
    p.add_argument("--brax", nargs="*", default=[])
    p.add_argument("--commit", default=None)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    load = lambda paths: [json.load(open(f)) for f in paths]  # noqa: E731
    doc = summarize(load(args.playground), load(args.brax), args.commit)
    with open(args.out, "w") as f:
        json.dump(doc, f, indent=1)
        f.write("\n")
    print(table(doc).to_markdown("####"))
