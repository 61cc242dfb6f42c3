"""The isolated update measured in a loop that also steps an env: what a rollout pays.

On a GPU, XLA captures a loop body into a CUDA graph only from `--xla_gpu_graph_min_graph_size`
kernels on (default 5); a smaller body launches each kernel from the host and waits on the
host for the loop condition on every step. The isolated scan of a 4-kernel update is such a
body, a rollout's never is: there the update's kernels run in the graph of the env step's.
So each variant here runs twice: alone in a scan (the isolated figure), and after a
synthetic env step in the same scan body, timed against the env step alone.

The env step is a chain of `step_kernels` dependent elementwise kernels on a `[64, num_envs]`
float32 state, every 8th also reducing over the 64 features (a per-env sum, as physics
does); an `optimization_barrier` after each keeps it a kernel of its own, neither fused with
the next nor with the metrics, as a launch-bound env step's kernels are. The step's action
is the isolated scan's random input, added to the state's first 10 rows; those rows, after
the chain, are the step's metric values (in [0, 1]), so the update waits for the step as it
does in a rollout. Dones are the isolated scan's.
"""

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from . import _workload as wl
from ._isolated import ABLATION, _floor_scan, _kernels, _metrics_scan, _prepare, inputs
from ._report import Table
from ._timing import measure

FEATURES = 64  # rows of the env state: a small robot's qpos, qvel and contacts
VALUES = 10  # rows read as the step's metric values (the isolated inputs' rows)
REDUCE_EVERY = 8  # every 8th kernel of the step also reduces over the features


class Row(NamedTuple):
    """One variant: a spec trimmed to `features` (see `random_spec`), at a size."""

    label: str
    num_envs: int
    terms: int
    features: str


def rows(
    num_envs: int, features: Sequence[str], terms: Sequence[int], envs: Sequence[int]
) -> list[Row]:
    """The ablation's `features` at `num_envs` with 10 terms, then the full spec with each
    number of `terms` at `num_envs`, then with 10 terms at each of `envs`."""
    out = [Row(label, num_envs, 10, f) for f, label in ABLATION if f in features]
    out += [
        Row(f"jaxmetrics: full spec, {m} term{'s' if m > 1 else ''}", num_envs, m, "full")
        for m in terms
        if m != 10
    ]
    out += [Row("jaxmetrics: full 10-term spec", n, 10, "full") for n in envs if n != num_envs]
    return out


def env_init(num_envs: int) -> jax.Array:
    return jnp.full((FEATURES, num_envs), 0.5, jnp.float32)


def env_step(x: jax.Array, action: jax.Array, kernels: int) -> jax.Array:
    """`kernels` dependent kernels on the env state `[FEATURES, num_envs]`, `action`
    `[VALUES, num_envs]` added to its first rows; every value of the result is in [0, 1]."""
    x = x.at[:VALUES].add(action)
    for i in range(kernels):
        if i % REDUCE_EVERY == REDUCE_EVERY - 1:
            y = x - jnp.mean(x, axis=0, keepdims=True)
        else:
            y = x * jnp.float32(3.0) + jnp.float32(i)
        x = jax.lax.optimization_barrier(jnp.float32(0.5) + jnp.float32(0.5) * jnp.sin(y))
    return x


def _stepped(kernels: int, update: Callable[[Any, jax.Array, jax.Array], Any] | None):
    """A scan of the env step, then `update(state, values, done)` on its values (none:
    the env step alone)."""

    def run(carry, xs, dones):
        def body(c, inp):
            x, s = c
            x = env_step(x, inp[0], kernels)
            if update is not None:
                s = update(s, x[:VALUES], inp[1])
            return (x, s), None

        return jax.lax.scan(body, carry, (xs, dones))[0]

    return run


def _floor_update(num_terms: int):
    def update(s, values, done):
        return wl.floor_update(s, wl.random_values(values, num_terms), done)

    return update


def measure_size(
    num_envs: int, terms: int, features: Sequence[str], steps: int, repeats: int, kernels: int
) -> tuple[dict[str, float], dict[str, dict], dict[str, Any], dict[str, Any]]:
    """The floor and each of `features` at one size, alone and (unless `kernels` is 0)
    after an env step of `kernels` kernels, interleaved in one timing.

    Returns us/step and `_prepare`'s info by variant (`floor`, `step`, `step+floor`, each
    feature `f` and `step+f`), the last outputs, and the specs by feature.
    """
    xs, dones = inputs(num_envs, steps)
    variants, infos, specs = [], {}, {}

    def add(name: str, fn, state) -> None:
        v, infos[name] = _prepare(name, fn, state, xs, dones, None)
        infos[name].pop("hlo")
        variants.append(v)

    add("floor", _floor_scan(terms), wl.floor_init(terms, num_envs))
    x0 = env_init(num_envs)
    if kernels:
        add("step", _stepped(kernels, None), (x0, ()))
        add(
            "step+floor",
            _stepped(kernels, _floor_update(terms)),
            (x0, wl.floor_init(terms, num_envs)),
        )
    for f in features:
        specs[f] = wl.random_spec(terms, 100, f)
        add(f, _metrics_scan(specs[f]), specs[f].init(num_envs))
        if kernels:
            add(f"step+{f}", _stepped(kernels, specs[f].update), (x0, specs[f].init(num_envs)))
    timings, last = measure(variants, repeats)
    us = {k: t.median_s / steps * 1e6 for k, t in timings.items()}
    return us, infos, last, specs


def loaded(
    num_envs: int,
    features: Sequence[str],
    terms: Sequence[int],
    envs: Sequence[int],
    steps: int,
    repeats: int,
    kernels: int,
) -> Table:
    """The isolated rows `rows(...)` alone and in a loop with an env step of `kernels`
    kernels: the overheads over the env step alone, ours against the floor's."""
    t = Table(
        "loaded",
        f"In a loop with an env step of {kernels} kernels: {steps}-step scan, us/step",
        [
            "variant",
            "envs",
            "terms",
            "isolated floor",
            "isolated",
            "isolated x floor",
            "ops in loop",
            "step",
            "step + floor",
            "step + ours",
            "floor overhead",
            "our overhead",
            "x floor overhead",
            "% of step",
        ],
    )
    todo = rows(num_envs, features, terms, envs)
    sizes: dict[tuple[int, int], list[str]] = {}
    for r in todo:
        sizes.setdefault((r.num_envs, r.terms), []).append(r.features)
    measured, data = {}, {}
    check = None
    for (n, m), feats in sizes.items():
        us, infos, last, specs = measure_size(n, m, feats, steps, repeats, kernels)
        measured[n, m] = (us, infos)
        data[f"{n}x{m}"] = {
            "us_per_step": us,
            "loop_ops": {k: i["loop_ops"] for k, i in infos.items()},
            "compile_s": {k: i["compile_s"] for k, i in infos.items()},
        }
        if check is None and "full" in specs:
            full = specs["full"]
            _, state = last["step+full"]
            report = full.to_host(full.compute(state))
            check = wl.compare_with_floor(full, report, last["step+floor"][1])
    for r in todo:
        us, infos = measured[r.num_envs, r.terms]
        step, f = us["step"], r.features
        floor_over = us["step+floor"] - step
        over = us[f"step+{f}"] - step
        t.add(
            r.label,
            r.num_envs,
            r.terms,
            us["floor"],
            us[f],
            us[f] / us["floor"],
            _kernels(infos[f]["loop_ops"]),
            step,
            us["step+floor"],
            us[f"step+{f}"],
            floor_over,
            over,
            over / floor_over if floor_over > 0 else None,
            100 * over / step,
        )
    step_ops = {k: _kernels(v["loop_ops"]["step"]) for k, v in data.items()}
    t.data = {"sizes": data, "check": check, "step_kernels": kernels, "steps": steps}
    t.notes.append(
        f"The env step: {kernels} dependent kernels on a [{FEATURES}, envs] float32 state "
        f"(ops in its loop alone, by envs x terms: "
        + ", ".join(f"{k} {v}" for k, v in step_ops.items())
        + "); its first 10 rows are the metrics' values, the isolated scan's random "
        "inputs added to them first, the dones the isolated scan's."
    )
    t.notes.append(
        "isolated: the update alone in the scan (us/step; ops in loop: ours); step: the env "
        "step alone; overheads: us/step above the env step alone, x floor overhead = ours / "
        "the floor's, % of step = ours / the env step alone. Median of "
        f"{repeats} interleaved repeats per size, every variant of a size in one timing."
    )
    if check is not None:
        t.notes.append(
            f"Check, env step + full spec against env step + floor: episodes "
            f"{check['episodes']}, every /count equals the floor's: {check['counts_equal']}; "
            f"max relative difference of the {check['sum_metrics']} sum-reduced /sum: "
            f"{check['max_rel_diff_sum']:.1e}."
        )
    return t
