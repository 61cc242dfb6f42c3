"""Scenarios on a Brax rollout: end to end (bare vs jaxmetrics, the empty spec, the
floor, compile time, state size) and the alternatives (Brax's own episode metrics,
per-step host callbacks, a Python loop with a per-step copy to the host).

The rollout is a hand-written jitted `lax.scan` over `env.step` of a Brax env wrapped
by `brax.envs.training.wrap` (VmapWrapper + EpisodeWrapper + AutoResetWrapper), with
pseudo-random actions drawn in-graph; every variant runs the same rollout.
"""

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

import jaxmetrics as jm

from . import _live
from . import _workload as wl
from ._report import Table
from ._timing import Variant, blocking, compile_jit, measure, tree_bytes


def _brax_promotion():
    # Imported here: the other scenarios of the bench run without Brax installed.
    from jaxmetrics.brax import default_promotion

    return default_promotion()


class Rollout:
    """A wrapped, batched Brax env and the builder of scanned rollouts over it."""

    def __init__(
        self,
        env_name: str,
        backend: str,
        num_envs: int,
        episode_length: int = 1000,
        metrics: jm.Metrics | None = None,
        sharding: jax.sharding.NamedSharding | None = None,
        leveled: bool = False,
        on_reset: Callable[..., Any] | None = None,
    ):
        from jaxmetrics import brax as jmb

        from brax import envs  # isort: skip
        from brax.envs.wrappers import training  # isort: skip

        with _brax_promotion():
            base = envs.get_environment(env_name, backend=backend)
            if leveled:
                base = _leveled(base)
            if metrics is None:
                self.env = training.wrap(base, episode_length=episode_length)
            else:
                self.env = jmb.wrap(base, metrics, episode_length=episode_length, on_reset=on_reset)
            keys = jax.random.split(jax.random.PRNGKey(0), num_envs)
            if sharding is not None:  # the env batch follows its keys' layout
                keys = jax.device_put(keys, sharding)
            self.state0 = jax.block_until_ready(jax.jit(self.env.reset)(keys))
        self.num_envs = num_envs
        self.action_key = jax.random.PRNGKey(1)

    def _actions(self, t: jax.Array) -> jax.Array:
        key = jax.random.fold_in(self.action_key, t)
        shape = (self.num_envs, self.env.action_size)
        return jax.random.uniform(key, shape, jnp.float32, -1.0, 1.0)

    def step(self, s: Any, t: jax.Array) -> Any:
        a = self._actions(t)
        with _brax_promotion():
            return self.env.step(s, a)

    def scan(self, steps: int, per_step: Callable[[Any, Any], tuple[Any, Any]]):
        """`rollout(env_state, carry) -> (env_state, carry, ys)`, calling
        `per_step(carry, state) -> (carry, y)` after every env step."""

        def rollout(env_state, carry):
            def body(c, t):
                s, extra = c
                s = self.step(s, t)
                extra, y = per_step(extra, s)
                return (s, extra), y

            ts = jnp.arange(steps, dtype=jnp.int32)
            (s, extra), ys = jax.lax.scan(body, (env_state, carry), ts)
            return s, extra, ys

        return rollout


def _bare(c, s):
    return c, None


LEVELS = 4


def _leveled(env: Any) -> Any:
    """`env` with a curriculum level per env in `info["level"]` (0 at reset) that its step
    reads: actions are scaled by `1 - 0.05 * level`, a stand-in for a harder setting."""
    from brax.envs.base import Wrapper

    class Leveled(Wrapper):
        def reset(self, rng):
            s = self.env.reset(rng)
            return s.replace(info={**s.info, "level": jnp.zeros((), jnp.int32)})

        def step(self, state, action):
            scale = 1.0 - 0.05 * state.info["level"].astype(jnp.float32)
            return self.env.step(state, action * scale)

    return Leveled(env)


def curriculum_spec() -> jm.Metrics:
    """The wrapper's 10 terms plus a success rate per level (the episode ran to its time
    limit), window of 100 and EMA: what a curriculum reads."""
    by_level = jm.groups(lambda t: t.state.info["level"], [f"l{k}" for k in range(LEVELS)])
    success = jm.success_rate(lambda t: t.truncation, groups=by_level)
    return jm.Metrics(terms={**wl.rollout_terms(transition=True), "success_rate": success})


def promote(read: Callable[..., jax.Array], state: Any) -> Any:
    """The curriculum rule of `docs/curriculum.md`'s example, one group: an episode that
    begins runs at the first level whose window success rate is under 0.8 (or has fewer
    than 100 episodes)."""
    rate = read("success_rate", "window_mean", by_group=True)
    count = read("success_rate", "window_count", by_group=True)
    mastered = (count >= 100) & (rate >= 0.8)
    level = jnp.where(jnp.all(mastered), LEVELS - 1, jnp.argmin(mastered)).astype(jnp.int32)
    return state.replace(info={**state.info, "level": jnp.full_like(state.info["level"], level)})


def _with_metrics(metrics: jm.Metrics):
    def per_step(ms, s):
        return metrics.update(ms, s, s.done.astype(bool)), None

    return per_step


def _with_floor(fs, s):
    return wl.floor_update(fs, wl.rollout_values(s), s.done), None


def _with_both(metrics: jm.Metrics):
    def per_step(c, s):
        ms, fs = c
        return (
            metrics.update(ms, s, s.done.astype(bool)),
            wl.floor_update(fs, wl.rollout_values(s), s.done),
        ), None

    return per_step


def _brax_episode_metrics(c, s):
    return c, (s.info["episode_metrics"], s.info["episode_done"])


def _with_callback(logger):
    def per_step(c, s):
        jax.debug.callback(logger.update, wl.rollout_values(s), s.done)
        return c, None

    return per_step


class _Fresh:
    """The logger a callback was traced with: forwards to a fresh logger on every run."""

    def __init__(self, make: Callable[[], Any]):
        self.make, self.current = make, make()

    def update(self, values: Any, done: Any) -> None:
        self.current.update(values, done)

    def run(self, run: Callable[[], Any]) -> Any:
        self.current = self.make()
        run()
        return self.current


def _jitted(name: str, ro: Rollout, steps: int, per_step, carry) -> Variant:
    compiled, compile_s = compile_jit(ro.scan(steps, per_step), ro.state0, carry)
    return Variant(name, blocking(compiled, ro.state0, carry), compile_s)


# Every variant but the two the others are measured against ("bare", "jaxmetrics").
VARIANTS = (
    "empty",
    "floor",
    "lean",
    "wrapper",
    "brax",
    "callback_numpy",
    "callback_dict",
    "device_get_loop",
    "live",
)
LABELS = {
    "bare": "bare rollout",
    "empty": "jaxmetrics, empty spec",
    "floor": "hand-written in-graph sum+count of 10 metrics (floor)",
    "jaxmetrics": "jaxmetrics, 10 terms",
    "lean": "jaxmetrics, same 10 terms, simple stats only (no EMA/window/histogram)",
    "wrapper": "jaxmetrics.brax.wrap (MetricsWrapper), same 10 terms",
    "brax": "Brax episode_metrics (sums) stacked over the scan, one copy per rollout into "
    "brax.training.logger.EpisodeMetricsLogger",
    "callback_numpy": "per-step jax.debug.callback -> numpy per-episode logger",
    "callback_dict": "per-step jax.debug.callback -> per-env Python-dict logger",
    "device_get_loop": "Python loop: jitted step + device_get per step -> numpy logger",
    "live_base": "jaxmetrics.brax.wrap, 10 terms + success rate per level, env with levels",
    "live": "the same + on_reset: a curriculum reads the success window per level every step",
}
LIVE_AGAIN = "live_base_again"
"""The live read's control: the program without the read, loaded a second time."""
E2E_ROWS = ("bare", "empty", "floor", "jaxmetrics", "lean", "wrapper", "live_base", "live")
ALT_ROWS = ("jaxmetrics", "floor", "brax", "callback_numpy", "callback_dict", "device_get_loop")


def _brax_logger(ro: Rollout, steps: int) -> Variant:
    compiled, compile_s = compile_jit(ro.scan(steps, _brax_episode_metrics), ro.state0, None)

    def run():
        from brax.training.logger import EpisodeMetricsLogger

        _, _, (ep_metrics, ep_done) = compiled(ro.state0, None)
        ep_metrics, ep_done = jax.device_get((ep_metrics, ep_done))
        logger = EpisodeMetricsLogger(steps_between_logging=float("inf"))
        with _brax_promotion():
            logger.update_episode_metrics(ep_metrics, ep_done, {})
        return int(ep_done.sum())

    return Variant("brax", run, compile_s)


def _host_variants(ro: Rollout, steps: int, variants: tuple[str, ...]) -> list[Variant]:
    """Per-step host logging; each `run` returns the logger it fed."""
    n = ro.num_envs
    names = [name for name, _, _ in wl.ROLLOUT_TERMS]
    make = {
        "callback_numpy": lambda: wl.NumpyEpisodeLogger(wl.PATTERN, n),
        "callback_dict": lambda: wl.DictEpisodeLogger(names, wl.PATTERN, n),
    }
    out = []
    for name in ("callback_numpy", "callback_dict"):
        if name in variants:
            fresh = _Fresh(make[name])
            rollout = ro.scan(steps, _with_callback(fresh))
            compiled, compile_s = compile_jit(rollout, ro.state0, None)
            run = blocking(compiled, ro.state0, None)
            out.append(Variant(name, lambda f=fresh, r=run: f.run(r), compile_s))
    if "device_get_loop" in variants:

        def one_step(s, t):
            s = ro.step(s, t)
            return s, wl.rollout_values(s), s.done

        step, compile_s = compile_jit(one_step, ro.state0, jnp.int32(0))

        def loop_run():
            logger = wl.NumpyEpisodeLogger(wl.PATTERN, n)
            s = ro.state0
            for t in range(steps):
                s, v, d = step(s, jnp.int32(t))
                logger.update(*jax.device_get((v, d)))
            jax.block_until_ready(s)
            return logger

        out.append(Variant("device_get_loop", loop_run, compile_s))
    return out


def end_to_end(
    env_name: str,
    backend: str,
    num_envs: int,
    steps: int,
    repeats: int,
    host_steps: int,
    host_repeats: int,
    variants: tuple[str, ...] = VARIANTS,
    live_rounds: int = 8,
) -> list[Table]:
    """Scenarios 2, 3, 6 and 7 on one rollout set-up, in one process.

    "bare" and "jaxmetrics" always run; `variants` picks the others (see `VARIANTS`).
    """
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        raise ValueError(f"unknown end-to-end variants {unknown}; choose from {list(VARIANTS)}")
    ro = Rollout(env_name, backend, num_envs)
    spec = wl.rollout_spec()
    specs = {"empty": jm.Metrics(), "jaxmetrics": spec, "lean": wl.rollout_spec(features="simple")}
    carries: dict[str, Any] = {k: m.init(num_envs) for k, m in specs.items()}
    carries["floor"] = wl.floor_init(10, num_envs)

    # ------------------------------------------------------------ in-graph, full length
    built = [_jitted("bare", ro, steps, _bare, None)]
    for k in ("empty", "floor", "jaxmetrics", "lean"):
        if k == "jaxmetrics" or k in variants:
            per_step = _with_floor if k == "floor" else _with_metrics(specs[k])
            built.append(_jitted(k, ro, steps, per_step, carries[k]))
    if "wrapper" in variants:
        wro = Rollout(env_name, backend, num_envs, metrics=wl.rollout_spec(transition=True))
        built.append(_jitted("wrapper", wro, steps, _bare, None))
    live_hlo: dict[str, str] = {}
    trio: list[Variant] = []
    if "live" in variants:
        # The cost of reading live statistics: the same env, spec and wrapper with and
        # without the curriculum's on_reset; and, as `live_read`'s control, the program
        # without it loaded a second time (timed there only).
        live = curriculum_spec()
        for name, hook in (("live_base", None), (LIVE_AGAIN, None), ("live", promote)):
            lro = Rollout(env_name, backend, num_envs, metrics=live, leveled=True, on_reset=hook)
            compiled, compile_s = compile_jit(lro.scan(steps, _bare), lro.state0, None)
            trio.append(Variant(name, blocking(compiled, lro.state0, None), compile_s))
            live_hlo[name] = compiled.as_text()
        built += [v for v in trio if v.name != LIVE_AGAIN]
    if "brax" in variants:
        built.append(_brax_logger(ro, steps))
    timings, last = measure(built, repeats)
    compile_s = {v.name: v.compile_s for v in built}

    # An empty spec should add nothing at all: is its rollout the bare program?
    if "empty" in variants:
        bare_ir = jax.jit(ro.scan(steps, _bare)).lower(ro.state0, None).as_text()
        empty_ir = jax.jit(ro.scan(steps, _with_metrics(specs["empty"])))
        check_empty = bare_ir == empty_ir.lower(ro.state0, carries["empty"]).as_text()
    # Same rollout carrying both jaxmetrics and the floor: do they report the same?
    both = jax.jit(ro.scan(steps, _with_both(spec)))
    _, (ms, fs), _ = both(ro.state0, (spec.init(num_envs), wl.floor_init(10, num_envs)))
    check = wl.compare_with_floor(spec, spec.to_host(spec.compute(ms)), jax.device_get(fs))

    # ------------------------------------------------------------ host loggers, shorter
    hosts = _host_variants(ro, host_steps, variants)
    host_timings, host_last = measure(hosts, host_repeats) if hosts else ({}, {})
    compile_s.update({v.name: v.compile_s for v in hosts})

    # ------------------------------------------------------------ tables
    bare_step = timings["bare"].median_s / steps
    noise_step = (timings["bare"].max_s - timings["bare"].min_s) / steps
    where = f"{env_name} ({backend}), {num_envs} envs"
    e2e = Table(
        "end_to_end",
        f"End to end: {where}, {steps}-step jitted scan with auto-reset",
        ["variant", "ms/step", "x bare", "overhead %", "compile s", "metrics state bytes"],
    )
    state_bytes = {k: tree_bytes(c) for k, c in carries.items()}
    state_bytes.update(bare=0, wrapper=state_bytes["jaxmetrics"])
    if "live" in variants:
        live_bytes = tree_bytes(curriculum_spec().init(num_envs))
        state_bytes.update(live_base=live_bytes, live=live_bytes)
    for k in E2E_ROWS:
        if k in timings:
            x = timings[k].median_s / steps / bare_step
            e2e.add(LABELS[k], x * bare_step * 1e3, x, (x - 1) * 100, compile_s[k], state_bytes[k])
    e2e.notes += [
        f"Median of {repeats} interleaved repeats after one warm-up; the bare rollout's "
        f"repeats spread over {noise_step * 1e3:.4f} ms/step (max-min), the resolution of "
        "the overhead column.",
        "Compile s: lowering + XLA compile of the whole rollout, reported apart from the run.",
        f"Check, same rollout carrying both: {check['episodes']} episodes, every /count "
        f"equals the floor's: {check['counts_equal']}; sum-reduced metrics' max relative "
        f"difference to the floor: {check['max_rel_diff_sum']:.1e}.",
    ]
    if "empty" in variants:
        check["empty_lowers_to_bare"] = check_empty
        e2e.notes.append(
            f"The empty spec's rollout lowers to the same program text as the bare rollout: "
            f"{check_empty} (so any difference in its row is measurement noise)."
        )
    e2e.data = {
        "timings": {k: vars(v) for k, v in timings.items()},
        "check": check,
        "env": env_name,
        "backend": backend,
        "num_envs": num_envs,
        "steps": steps,
    }

    alt = Table(
        "alternatives",
        f"Versus the alternatives: {where}; overhead = ms/step above the bare rollout",
        [
            "variant",
            "steps timed",
            "ms/step",
            "overhead ms/step",
            "x jaxmetrics overhead",
            "episodes logged",
        ],
    )
    jm_over = timings["jaxmetrics"].median_s / steps - bare_step
    episodes = {
        "jaxmetrics": check["episodes"],
        "floor": int(last["floor"][1].episodes) if "floor" in last else None,
        "brax": last.get("brax"),
    }
    episodes.update({k: logger.episodes for k, logger in host_last.items()})
    ratios = {}
    for k in ALT_ROWS:
        if k in timings:
            n, sec = steps, timings[k].median_s
        elif k in host_timings:
            n, sec = host_steps, host_timings[k].median_s
        else:
            continue
        over = sec / n - bare_step
        ratios[k] = over / jm_over if jm_over > 0 and over > 0 else None
        alt.add(LABELS[k], n, sec / n * 1e3, over * 1e3, ratios[k], episodes[k])
    alt.notes += [
        f"Overheads are against the bare rollout's {bare_step * 1e3:.3f} ms/step measured in "
        f"the same process ({steps}-step scan). Host loggers ran {host_steps}-step rollouts "
        f"(median of {host_repeats}); their ms/step is that rollout's time / {host_steps}.",
        "x jaxmetrics overhead: the row's overhead divided by jaxmetrics' overhead (10 terms); "
        "how many times more each logger costs per step than jaxmetrics does ('-' where an "
        "overhead is not above zero).",
        "episodes logged: finished episodes the logger saw in its last run.",
    ]
    alt.data = {
        "host_timings": {k: vars(v) for k, v in host_timings.items()},
        "compile_s": compile_s,
        "ratios_to_jaxmetrics": ratios,
        "jaxmetrics_overhead_ms_per_step": jm_over * 1e3,
        "host_steps": host_steps,
    }
    if "callback_numpy" in host_last:
        alt.data["host_numpy_totals"] = host_last["callback_numpy"].totals()
    if "live" not in variants:
        return [e2e, alt]
    return [e2e, alt, _live.live_read(trio, live_hlo, steps, live_rounds)]
