"""What the reporting wrapper's per-step work costs a rollout of a cheap Playground env, and
why: a `pmap`ped (axis "i", as Brax's trainers) `lax.scan` of `--steps` steps of MuJoCo
Playground's `CartpoleBalance` in Playground's training stack, random actions, no PPO.

Variants (each compiled and timed in one process per case):

- `playground`: Playground's own `wrapper.wrap_for_brax_training`;
- `fold`: `jaxmetrics.playground.wrap` without a logger;
- `report`: the same with a Logger (the reporting wrapper: an int32 clock and, per step, a
  `lax.cond` whose branch gathers the state over the axis and makes the ordered
  `io_callback`), reporting once per call;
- ablations, the same wrapper with its per-step work replaced: `clock` (the clock alone, no
  conditional), `cond_pure` (a `lax.cond` whose branch resets the period: no callback, no
  gather), `cond_callback` (the emit's `cond` and ordered `io_callback`, no gather), `where`
  (the reset selected with `jnp.where`: no conditional).

A case is `impl;variants;xla_flags` and runs in a fresh process (XLA reads its flags
once): `impl` is `jax`, `warp` (MJX's Warp physics in its default graph mode on a GPU,
`GraphMode.WARP`: Warp captures and launches its own CUDA graph in each FFI call) or
`warp_jaxgraph` (`GraphMode.JAX`: XLA may capture Warp's FFI calls in its command buffers);
`variants` comma-separated, empty for all. Per variant: median ms per step over `--repeats`
calls, compile seconds, the conditionals, loops and custom calls of the compiled program
(`hlo_summary`), and with `--profile` one call under `jax.profiler.trace` counted per step
(`trace_counts`): CUDA graph launches from the host (XLA's command buffers and Warp's own
graphs; the profiler records no single-kernel launches of the host), device-to-host copies
on the GPU's streams (a conditional that XLA runs from the host copies its predicate there
and waits for it), device events per stream (a stream's name lists the kinds of work it
ran), the host's CUDA calls by name, each line's most frequent events, and the GPU's busy
time.

`python -m jaxmetrics.bench._env_sync --case "warp;;" --case "jax;;" --profile --out F.json`
"""

import argparse
import collections
import contextlib
import glob
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from typing import Any

VARIANTS = ("playground", "fold", "report", "clock", "cond_pure", "cond_callback", "where")
IMPLS = ("jax", "warp", "warp_jaxgraph")
ENV = "CartpoleBalance"
BASE_FLAGS = "--xla_gpu_triton_gemm_any=True"  # Playground's training script sets it
_API = re.compile(r"^cu|^cuda", re.I)


def parse_case(spec: str) -> tuple[str, tuple[str, ...], str]:
    """`(impl, variants, xla_flags)` of `impl;variants;xla_flags`."""
    impl, names, flags = (spec.split(";", 2) + ["", ""])[:3]
    variants = tuple(v for v in names.split(",") if v) or VARIANTS
    bad = [v for v in variants if v not in VARIANTS]
    if impl not in IMPLS or bad:
        raise ValueError(f"bad case {spec!r}: impl in {IMPLS}, variants in {VARIANTS}")
    return impl, variants, flags


# --------------------------------------------------------------------------- the compiled HLO


def hlo_summary(text: str) -> dict[str, int]:
    """Conditionals, loops and custom calls (by target) of an optimized module. Which of
    them XLA runs inside a command buffer is decided after the HLO, on its thunks: the
    trace shows it (`command_buffer_*` thunks, one `cuGraphLaunch` each per execution)."""
    from ._hlo import _opcode, _split_computations

    comps, _ = _split_computations(text)
    count: collections.Counter[str] = collections.Counter()
    for instrs in comps.values():
        for instr in instrs:
            op = _opcode(instr)
            if op in ("conditional", "while", "custom-call"):
                target = re.search(r'custom_call_target="([^"]+)"', instr)
                count[op if target is None else f"custom-call:{target.group(1)}"] += 1
    return dict(sorted(count.items()))


# --------------------------------------------------------------------------- the trace


def trace_counts(path: str, steps: int) -> dict[str, Any]:
    """Per step of one profiled call: device events per stream line, the host's CUDA API
    calls by name, and the GPU's busy time against the call's span."""
    import jax

    data = jax.profiler.ProfileData.from_file(path)
    device: collections.Counter[str] = collections.Counter()
    api: collections.Counter[str] = collections.Counter()
    top: dict[str, collections.Counter[str]] = {}
    busy_ns = d2h = 0
    lo, hi = float("inf"), 0.0
    for p in data.planes:
        for ln in p.lines:
            key = f"{p.name} | {ln.name}"
            names = collections.Counter(e.name for e in ln.events)
            top[key] = names
            if p.name.startswith("/device:") and ln.name.startswith("Stream"):
                device[ln.name] += sum(names.values())
                d2h += names["MemcpyD2H"]
                for e in ln.events:
                    busy_ns += e.duration_ns
                    lo, hi = min(lo, e.start_ns), max(hi, e.start_ns + e.duration_ns)
            elif not p.name.startswith("/device:"):
                for name, n in names.items():
                    if _API.match(name):
                        api[name] += n

    def per_step(c: collections.Counter[str]) -> dict[str, float]:
        return {k: round(v / steps, 3) for k, v in c.most_common()}

    span = hi - lo if hi > lo else 0.0
    return {
        "graph_launches_per_step": round(
            sum(n for k, n in api.items() if k.startswith("cuGraphLaunch")) / steps, 3
        ),
        "memcpy_d2h_per_step": round(d2h / steps, 3),
        "device_events_per_step": per_step(device),
        "host_api_calls_per_step": per_step(api),
        "gpu_busy_us_per_step": round(busy_ns / 1e3 / steps, 3),
        "gpu_span_us_per_step": round(span / 1e3 / steps, 3),
        "lines": {k: dict(v.most_common(12)) for k, v in top.items() if v},
    }


# --------------------------------------------------------------------------- the rollout


def make_env(impl: str) -> Any:
    """Playground's `CartpoleBalance` with its default config and the given physics."""
    from mujoco_playground import registry

    config = registry.get_default_config(ENV)
    config.impl = "jax" if impl == "jax" else "warp"
    env = registry.load(ENV, config=config)
    if impl == "warp_jaxgraph":
        from mujoco import mjx
        from mujoco.mjx import warp as mjxw

        env._mjx_model = mjx.put_model(
            env.mj_model, impl="warp", graph_mode=mjxw.types.GraphMode.JAX
        )
    return env


def _ablation(reporter: Any, kind: str) -> Any:
    """The wrapper's `Reporter` with its per-step work replaced by `kind`'s."""
    import jax
    import jax.numpy as jnp

    from .._reporting import Reporter

    class Ablation(Reporter):
        def __init__(self) -> None:
            self.__dict__.update(reporter.__dict__)

        def __call__(self, state, clock, num_envs, steps_per_call):
            clock = jnp.asarray(clock, jnp.int32) + 1
            when = clock >= self.period_calls(num_envs, steps_per_call)
            clock = jnp.where(when, jnp.zeros_like(clock), clock)
            if kind == "cond_pure":
                state = jax.lax.cond(when, self.metrics.reset_period, lambda s: s, state)
            elif kind == "cond_callback":
                period = self.period_calls(num_envs, steps_per_call) * self.batch_env_steps(
                    num_envs, steps_per_call
                )
                state = self.logger.emit_from_wrapper(state, self._step(state), when, period, self)
            elif kind == "where":
                new = self.metrics.reset_period(state)
                state = jax.tree.map(lambda n, o: jnp.where(when, n, o), new, state)
            return state, clock

    return Ablation()


def build(env: Any, variant: str, num_envs: int, steps: int) -> tuple[Any, Any, Any]:
    """`(wrapped env, logger, its memory writer)` of one variant (no logger: None, None)."""
    from mujoco_playground import wrapper

    import jaxmetrics as jm
    import jaxmetrics.playground as jmp

    from ._playground_train import build_terms

    if variant == "playground":
        return wrapper.wrap_for_brax_training(env, episode_length=1000), None, None
    metrics = jm.Metrics(terms=build_terms(env))
    if variant == "fold":
        return jmp.wrap(env, metrics), None, None
    memory = jm.MemoryWriter()
    logger = jm.Logger(metrics, [memory])
    wrapped = jmp.wrap(env, metrics, logger=logger, report_every=num_envs * steps)
    if variant != "report":
        inner = wrapped.env  # BraxAutoResetWrapper(MetricsWrapper(...))
        inner.reporter = _ablation(inner.reporter, variant)
    return wrapped, logger, memory


def measure(
    impl: str, variants: Sequence[str], num_envs: int, steps: int, repeats: int, profile: bool
) -> list[dict[str, Any]]:
    """Every variant of one case, in this process."""
    import jax
    import jax.numpy as jnp

    env = make_env(impl)
    out = []
    for variant in variants:
        wrapped, logger, memory = build(env, variant, num_envs, steps)

        def rollout(state, key, wrapped=wrapped):
            def body(c, _):
                state, key = c
                key, k = jax.random.split(key)
                action = jax.random.uniform(
                    k, (num_envs, wrapped.action_size), jnp.float32, -1.0, 1.0
                )
                return (wrapped.step(state, action), key), None

            return jax.lax.scan(body, (state, key), None, length=steps)[0]

        keys = jax.random.split(jax.random.PRNGKey(0), num_envs)[None]
        state = jax.pmap(wrapped.reset, axis_name="i")(keys)
        key = jax.random.PRNGKey(1)[None]
        t0 = time.perf_counter()
        compiled = jax.pmap(rollout, axis_name="i").lower(state, key).compile()
        compile_s = time.perf_counter() - t0
        carry = jax.block_until_ready(compiled(state, key))
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            carry = jax.block_until_ready(compiled(*carry))
            times.append(time.perf_counter() - t0)
        row: dict[str, Any] = {
            "impl": impl,
            "variant": variant,
            "ms_per_step": statistics.median(times) / steps * 1e3,
            "ms_per_step_all": [t / steps * 1e3 for t in times],
            "compile_s": compile_s,
            "hlo_summary": hlo_summary(compiled.as_text()),
        }
        if profile:
            options = jax.profiler.ProfileOptions()
            options.python_tracer_level = 0  # Warp's FFI calls run Python on every step
            with tempfile.TemporaryDirectory() as d:
                with jax.profiler.trace(d, profiler_options=options):
                    t0 = time.perf_counter()
                    carry = jax.block_until_ready(compiled(*carry))
                    traced_s = time.perf_counter() - t0
                (path,) = glob.glob(os.path.join(d, "**", "*.xplane.pb"), recursive=True)
                row["trace_counts"] = trace_counts(path, steps)
                row["trace_counts"]["ms_per_step_traced"] = traced_s / steps * 1e3
        if logger is not None:
            logger.close()
            row["records"] = len(memory.records)
        out.append(row)
        print(f"{impl} {variant}: {row['ms_per_step']:.4f} ms/step", file=sys.stderr, flush=True)
    return out


# --------------------------------------------------------------------------- cases


def _child(a: argparse.Namespace) -> None:
    impl, variants, _ = parse_case(a.case[0])
    with open(a.child, "a") as f:
        for v in variants:
            for row in measure(impl, [v], a.envs, a.steps, a.repeats, a.profile):
                f.write(json.dumps(row) + "\n")
                f.flush()


def run_case(spec: str, a: argparse.Namespace) -> dict[str, Any]:
    """One case in a fresh process; its rows (those finished if it failed or timed out)."""
    impl, variants, flags = parse_case(spec)
    env = {**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    env.setdefault("MUJOCO_GL", "disable")
    env["XLA_FLAGS"] = " ".join(filter(None, (os.environ.get("XLA_FLAGS"), BASE_FLAGS, flags)))
    sizes = [f"--envs={a.envs}", f"--steps={a.steps}", f"--repeats={a.repeats}"]
    with tempfile.NamedTemporaryFile("r", suffix=".jsonl") as rows:
        cmd = [sys.executable, "-m", "jaxmetrics.bench._env_sync", "--child", rows.name,
               "--case", spec, *sizes, *(["--profile"] if a.profile else [])]  # fmt: skip
        t0 = time.time()
        error = None
        try:
            done = subprocess.run(
                cmd, env=env, timeout=a.case_timeout, capture_output=True, text=True
            )
            if done.returncode:
                error = done.stderr[-2000:]
        except subprocess.TimeoutExpired:
            error = f"timed out after {a.case_timeout} s"
        found = [json.loads(line) for line in rows.read().splitlines() if line]
    return {"case": spec, "impl": impl, "xla_flags": flags, "wall_s": time.time() - t0,
            "rows": found, **({"error": error} if error else {})}  # fmt: skip


def environment() -> dict[str, Any]:
    """Versions and device of the parent process."""
    from importlib import metadata

    import jax

    def version(name: str) -> str | None:
        with contextlib.suppress(metadata.PackageNotFoundError):
            return metadata.version(name)
        return None

    return {
        "device": str(jax.devices()[0].device_kind),
        "host": platform.node(),
        "jax": jax.__version__,
        "mujoco_mjx": version("mujoco-mjx"),
        "playground": version("playground"),
        "warp_lang": version("warp-lang"),
    }


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--case", action="append", help="impl;variants;xla_flags (repeatable)")
    p.add_argument("--envs", type=int, default=2048)
    p.add_argument("--steps", type=int, default=480, help="a Playground training epoch's")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--profile", action="store_true")
    p.add_argument("--case-timeout", type=float, default=600.0)
    p.add_argument("--commit", default=None)
    p.add_argument("--out")
    p.add_argument("--child", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child:
        _child(a)
        return 0
    doc: dict[str, Any] = {
        "benchmark": "env_sync",
        "environment": environment(),
        "commit": a.commit,
        "sizes": {"envs": a.envs, "steps": a.steps, "repeats": a.repeats},
        "base_xla_flags": BASE_FLAGS,
        "cases": [],
    }
    for spec in a.case or ["warp;;", "jax;;"]:
        case = run_case(spec, a)
        doc["cases"].append(case)
        for r in case["rows"]:
            print(f"{spec}: {r['variant']} {r['ms_per_step']:.4f} ms/step", flush=True)
        if "error" in case:
            print(f"{spec}: ERROR {case['error']}", flush=True)
        if a.out:
            with open(a.out, "w") as f:
                json.dump(doc, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
