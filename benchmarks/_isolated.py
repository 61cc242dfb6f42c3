"""Scenarios on random inputs, without physics: the isolated update cost against the
floor (with an ablation by feature and the ops XLA leaves in the loop), scaling in
num_envs / number of terms / window size / number of groups, and the state size."""

import os

import jax
import jax.numpy as jnp

from . import _profile
from . import _workload as wl
from ._hlo import loop_body_ops
from ._report import Table
from ._timing import Variant, blocking, compile_jit, measure, tree_bytes

DONE_PROB = 0.01  # episodes of 100 steps on average


def inputs(num_envs: int, steps: int, seed: int = 0) -> tuple[jax.Array, jax.Array]:
    """Random step inputs `[steps, 10, num_envs]` in [0, 1) and dones `[steps, num_envs]`."""
    kx, kd = jax.random.split(jax.random.key(seed))
    xs = jax.random.uniform(kx, (steps, 10, num_envs), jnp.float32)
    dones = jax.random.bernoulli(kd, DONE_PROB, (steps, num_envs))
    return jax.block_until_ready((xs, dones))


def _metrics_scan(metrics):
    def run(state, xs, dones):
        def body(s, inp):
            return metrics.update(s, inp[0], inp[1]), None

        return jax.lax.scan(body, state, (xs, dones))[0]

    return run


def _floor_scan(num_terms: int, update=wl.floor_update):
    """A scan of a hand-written floor's `update` (`wl.floor_update`, or the layout
    floor's) over the step inputs."""

    def run(state, xs, dones):
        def body(s, inp):
            return update(s, wl.random_values(inp[0], num_terms), inp[1]), None

        return jax.lax.scan(body, state, (xs, dones))[0]

    return run


def _prepare(name: str, fn, state, xs, dones, hlo_dir: str | None) -> tuple[Variant, dict]:
    compiled, compile_s = compile_jit(fn, state, xs, dones)
    text = compiled.as_text()
    if hlo_dir:
        os.makedirs(hlo_dir, exist_ok=True)
        with open(os.path.join(hlo_dir, f"{name}.hlo.txt"), "w") as f:
            f.write(text)
    info = {
        "hlo": text,
        "compile_s": compile_s,
        "loop_ops": loop_body_ops(text),
        "state_bytes": tree_bytes(state),
    }
    return Variant(name, blocking(compiled, state, xs, dones), compile_s), info


def _kernels(ops: dict[str, int]) -> int:
    return sum(ops.values())


ABLATION = (
    ("sum", "jaxmetrics: 10 sum terms, mean+sum+count"),
    ("simple", "jaxmetrics: mixed reductions, simple stats"),
    ("ema", "  + EMA (2 terms)"),
    ("window", "  + window(100) (2 terms)"),
    ("histogram", "  + histogram(20) (2 terms)"),
    ("discounted_quantiles", "  2 sums -> discounted(0.99), + quantiles(1%) (2 terms)"),
    ("full", "jaxmetrics: full 10-term spec"),
)


def isolated(
    num_envs: int, steps: int, repeats: int, hlo_dir: str | None = None, profile: bool = False
) -> list[Table]:
    """Scenario 1: `update` of the 10-term spec under a scan, against the floor; with
    `profile`, also the device time of each kernel of the floor, the simple-statistics
    spec and the full spec."""
    t = Table(
        "isolated",
        f"Isolated update: {num_envs} envs x 10 terms, {steps}-step scan of random inputs",
        ["variant", "us/step", "x floor", "compile s", "ops in loop", "state bytes"],
    )
    xs, dones = inputs(num_envs, steps)
    variants, infos = [], {}
    fstate = wl.floor_init(10, num_envs)
    v, infos["floor"] = _prepare("floor", _floor_scan(10), fstate, xs, dones, hlo_dir)
    variants.append(v)
    specs = {}
    for feat, _ in ABLATION:
        specs[feat] = wl.random_spec(10, 100, feat)
        v, infos[feat] = _prepare(
            feat, _metrics_scan(specs[feat]), specs[feat].init(num_envs), xs, dones, hlo_dir
        )
        variants.append(v)
    timings, last = measure(variants, repeats)
    floor_us = timings["floor"].median_s / steps * 1e6
    labels = {"floor": "floor: hand-written sum+count", **dict(ABLATION)}
    for name, label in labels.items():
        us = timings[name].median_s / steps * 1e6
        i = infos[name]
        t.add(label, us, us / floor_us, i["compile_s"], _kernels(i["loop_ops"]), i["state_bytes"])
    full = specs["full"]
    check = wl.compare_with_floor(full, full.to_host(full.compute(last["full"])), last["floor"])
    t.data = {
        "timings": {k: vars(v) for k, v in timings.items()},
        "loop_ops": {k: i["loop_ops"] for k, i in infos.items()},
        "check": check,
        "num_envs": num_envs,
        "steps": steps,
        "done_prob": DONE_PROB,
    }
    t.notes.append(
        f"Check, same inputs: episodes {check['episodes']}, every /count equals the floor's: "
        f"{check['counts_equal']}; max relative difference of the {check['sum_metrics']} "
        f"sum-reduced /sum against the floor's total: {check['max_rel_diff_sum']:.1e}."
    )
    t.notes.append(
        "ops in loop: operations XLA left in the scan's loop body after optimization "
        "(fusions, scatters, sorts, custom calls...); on a GPU each is about one kernel "
        "launch per step. Breakdown in the JSON (`data.loop_ops`)."
    )
    t.notes.append(
        f"Median of {repeats} interleaved repeats after one warm-up; spread (max-min)/median "
        "in the JSON. Ablation rows add one feature at a time to the simple-stats spec."
    )
    if not profile:
        return [t]
    by_name = {v.name: v for v in variants}
    profiled = {k: (by_name[k], infos[k], timings[k].median_s / steps * 1e6) for k in PROFILED}
    return [t, _kernel_table(num_envs, steps, profiled)]


PROFILED = ("floor", "simple", "full")


def _kernel_table(num_envs: int, steps: int, profiled: dict, name: str = "kernels") -> Table:
    """The kernels of each `profiled` variant (name -> its `Variant`, `_prepare`'s info
    and its timed wall us/step) in one profiled call each, and how much of the step's
    wall time no kernel ran."""
    t = Table(
        name,
        f"Device time per kernel and step: {num_envs} envs, {steps}-step scan (one profiled call)",
        ["variant", "kernel", "us/step", "launches/step", "shape", "fuses"],
    )
    totals, busy, wall = {}, {}, {}
    for name, (variant, info, wall_us) in profiled.items():
        p = _profile.profile(variant.run, info["hlo"], steps)
        totals[name] = sum(k.us_per_step for k in p.kernels)
        busy[name], wall[name] = p.busy_us_per_step, wall_us
        for k in p.kernels:
            t.add(name, k.name, k.us_per_step, k.launches_per_step, k.shape, k.ops)
    t.data = {"total_us_per_step": totals, "busy_us_per_step": busy, "wall_us_per_step": wall}
    t.notes.append(
        "Summed device events per name over one call, divided by the steps (on a GPU the "
        "kernels of its streams, on the CPU the thunks of XLA's client threads); `fuses` "
        "lists the opcodes inside a fusion, most frequent first. Totals per step: "
        + ", ".join(f"{k} {v:.1f} us" for k, v in totals.items())
        + "."
    )
    t.notes.append(
        "Time per step in which some kernel ran (the union of their intervals), against the "
        "timed wall time per step; the rest the device ran none (launches between kernels "
        "and between steps): "
        + ", ".join(f"{k} {busy[k]:.1f} of {wall[k]:.1f} us" for k in profiled)
        + ". On a CPU the profiler slows the call past the timed one."
    )
    return t


def scaling(
    env_list: list[int],
    term_list: list[int],
    window_list: list[int],
    base_envs: int,
    steps: int,
    repeats: int,
) -> list[Table]:
    """Scenario 5 (+ state size): per-step cost against num_envs, terms and window size."""
    envs = Table(
        "scaling_envs",
        f"Scaling with num_envs (10 terms, {steps}-step scan)",
        [
            "num_envs",
            "floor us/step",
            "jaxmetrics us/step",
            "x floor",
            "simple stats us/step",
            "simple x floor",
            "ns/env/step",
            "state bytes",
            "floor state bytes",
            "layout floor us/step",
            "layout x floor",
        ],
    )
    for n in env_list:
        xs, dones = inputs(n, steps)
        full, simple = wl.random_spec(10), wl.random_spec(10, features="simple")
        vf, _ = _prepare("floor", _floor_scan(10), wl.floor_init(10, n), xs, dones, None)
        layout = _floor_scan(10, wl.layout_floor_update)
        vl, _ = _prepare("layout", layout, wl.layout_floor_init(10, n), xs, dones, None)
        vj, ij = _prepare("jaxmetrics", _metrics_scan(full), full.init(n), xs, dones, None)
        vs, _ = _prepare("simple", _metrics_scan(simple), simple.init(n), xs, dones, None)
        tm, _ = measure([vf, vl, vj, vs], repeats)
        f_us, l_us, j_us, s_us = (
            tm[k].median_s / steps * 1e6 for k in ("floor", "layout", "jaxmetrics", "simple")
        )
        envs.add(
            n,
            f_us,
            j_us,
            j_us / f_us,
            s_us,
            s_us / f_us,
            j_us * 1e3 / n,
            ij["state_bytes"],
            tree_bytes(wl.floor_init(10, n)),
            l_us,
            l_us / f_us,
        )
        del xs, dones
    envs.notes.append(
        "jaxmetrics: the full 10-term spec; simple stats: the same terms with their period "
        "statistics only (count, mean, sum, std, min, max), no EMA, window or histogram."
    )
    envs.notes.append(
        "layout floor: the floor over jaxmetrics' running-episode layout, three [10, envs] "
        "accumulators (a step count and two float slots) updated per step, here a Welford "
        "mean and M2, and the finished episodes' means summed: what the state's layout costs "
        "with no statistic folded beyond the floor's."
    )

    terms = Table(
        "scaling_terms",
        f"Scaling with the number of terms ({base_envs} envs, {steps}-step scan)",
        [
            "terms",
            "floor us/step",
            "jaxmetrics us/step",
            "x floor",
            "us/term/step",
            "ops in loop",
            "state bytes",
        ],
    )
    xs, dones = inputs(base_envs, steps)
    for m in term_list:
        spec = wl.random_spec(m)
        vf, _ = _prepare("floor", _floor_scan(m), wl.floor_init(m, base_envs), xs, dones, None)
        vj, ij = _prepare("jaxmetrics", _metrics_scan(spec), spec.init(base_envs), xs, dones, None)
        tm, _ = measure([vf, vj], repeats)
        f_us, j_us = (tm[k].median_s / steps * 1e6 for k in ("floor", "jaxmetrics"))
        terms.add(m, f_us, j_us, j_us / f_us, j_us / m, _kernels(ij["loop_ops"]), ij["state_bytes"])

    windows = Table(
        "scaling_window",
        f"Scaling with the window size ({base_envs} envs, 10 terms of which 2 windowed, "
        f"{steps}-step scan)",
        ["window", "jaxmetrics us/step", "x smallest window", "state bytes"],
    )
    variants, infos = [], {}
    for w in window_list:
        spec = wl.random_spec(10, window=w)
        v, infos[w] = _prepare(f"w{w}", _metrics_scan(spec), spec.init(base_envs), xs, dones, None)
        variants.append(v)
    tm, _ = measure(variants, repeats)
    first = tm[f"w{window_list[0]}"].median_s
    for w in window_list:
        windows.add(
            w,
            tm[f"w{w}"].median_s / steps * 1e6,
            tm[f"w{w}"].median_s / first,
            infos[w]["state_bytes"],
        )
    windows.notes.append(
        "A window is a ring buffer written by one bounded scatter of the finished episodes "
        "per step: its per-step cost should not grow with its size (only the state does)."
    )
    return [envs, terms, windows]


GROUP_SPECS = (
    ("full", "full"),
    ("simple", "period stats"),
)
"""The specs of the per-group table: the bench's `random_spec` features, and their label."""


def groups(
    group_list: list[int], num_envs: int, steps: int, repeats: int, profile: bool = False
) -> list[Table]:
    """Per-group statistics: the full 10-term spec and its period statistics alone (every
    group row a segment row), kept per group, each against itself without groups; with
    `profile`, also the device time of each kernel of both specs at the most groups."""
    t = Table(
        "groups",
        f"Per-group statistics ({num_envs} envs, 10 terms, {steps}-step scan)",
        ["spec", "groups", "us/step", "x no groups", "compile s", "ops in loop", "state bytes"],
    )
    xs, dones = inputs(num_envs, steps)
    variants, infos, specs = [], {}, {}
    counts = [0, *group_list]
    for features, _ in GROUP_SPECS:
        for g in counts:
            name = f"{features}_g{g}"
            specs[name] = wl.random_spec(10, features=features, groups=g)
            v, infos[name] = _prepare(
                name, _metrics_scan(specs[name]), specs[name].init(num_envs), xs, dones, None
            )
            variants.append(v)
    tm, last = measure(variants, repeats)
    for features, label in GROUP_SPECS:
        base = tm[f"{features}_g0"].median_s
        for g in counts:
            name = f"{features}_g{g}"
            i = infos[name]
            t.add(
                label,
                g,
                tm[name].median_s / steps * 1e6,
                tm[name].median_s / base,
                i["compile_s"],
                _kernels(i["loop_ops"]),
                i["state_bytes"],
            )
    most = max(group_list)
    prefix = specs[f"full_g{most}"].prefixes["episode"]
    split = True
    for features, _ in GROUP_SPECS:
        m = specs[f"{features}_g{most}"]
        host = m.to_host(m.compute(last[f"{features}_g{most}"]))
        split = split and all(
            sum(host[f"{prefix}/m{i}/g{k}/count"] for k in range(most))
            == host[f"{prefix}/m{i}/count"]
            for i in range(10)
        )
    t.data = {
        "timings": {k: vars(v) for k, v in tm.items()},
        "loop_ops": {k: i["loop_ops"] for k, i in infos.items()},
        "check": {"groups": most, "group_counts_sum_to_total": split},
    }
    t.notes.append(
        f"Each env is in a random group on every step. Check: with {most} groups every "
        f"metric's group /counts sum to its overall /count (both specs): {split}."
    )
    t.notes.append(
        "The group rows of a metric with period statistics only (count, sum, mean, std, "
        "min, max) are segment reductions over the group index, one pass over the envs; "
        "a metric with an EMA, a window, a histogram or quantiles keeps one row per group, "
        "whose per-step work grows with rows x envs. 'period stats' is the spec with "
        "simple statistics only (mixed reductions)."
    )
    if not profile:
        return [t]
    by_name = {v.name: v for v in variants}
    profiled = {
        f"{features}, {most} groups": (
            by_name[f"{features}_g{most}"],
            infos[f"{features}_g{most}"],
            tm[f"{features}_g{most}"].median_s / steps * 1e6,
        )
        for features, _ in GROUP_SPECS
    }
    return [t, _kernel_table(num_envs, steps, profiled, "group_kernels")]
