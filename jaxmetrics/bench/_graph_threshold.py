"""The isolated rows with XLA's CUDA-graph threshold at its default and lowered.

XLA captures a loop body into a CUDA graph only from `--xla_gpu_graph_min_graph_size`
kernels on (default 5). The isolated scan of an update of fewer kernels launches each from
the host and waits on the host for the loop condition on every step, which a rollout's loop
body, hundreds of kernels, never does. This bench times the isolated floor and variants
(`_loaded.rows`) once per `--xla-flags` setting, each in a fresh process (XLA reads its flags
once): where lowering the threshold brings a row near the floor, its isolated figure is the
threshold's, not the update's.

`python -m jaxmetrics.bench._graph_threshold --xla-flags=--xla_gpu_graph_min_graph_size=1`
"""

import argparse
import json
import sys

from . import _loaded
from ._timing import in_fresh_process

SIZES = ("num_envs", "features", "terms", "envs", "steps", "repeats")


def measure(
    num_envs: int,
    features: list[str],
    terms: list[int],
    envs: list[int],
    steps: int,
    repeats: int,
) -> list[dict]:
    """Per row of `_loaded.rows`: its size, the floor's and its isolated us/step and the
    ops in their loops, in this process."""
    from ._isolated import _kernels

    todo = _loaded.rows(num_envs, features, terms, envs)
    sizes: dict[tuple[int, int], list[str]] = {}
    for r in todo:
        sizes.setdefault((r.num_envs, r.terms), []).append(r.features)
    measured = {
        size: _loaded.measure_size(*size, feats, steps, repeats, kernels=0)
        for size, feats in sizes.items()
    }
    out = []
    for r in todo:
        us, infos, _, _ = measured[r.num_envs, r.terms]
        out.append(
            {
                **r._asdict(),
                "floor_us": us["floor"],
                "us": us[r.features],
                "floor_ops": _kernels(infos["floor"]["loop_ops"]),
                "ops": _kernels(infos[r.features]["loop_ops"]),
            }
        )
    return out


def _ints(s: str) -> list[int]:
    return [int(x) for x in s.split(",") if x]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--num-envs", type=int, default=4096)
    p.add_argument("--features", default=",".join(f for f, _ in _loaded.ABLATION))
    p.add_argument("--terms", type=_ints, default=[1, 3])
    p.add_argument("--envs", type=_ints, default=[16384])
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument(
        "--xla-flags",
        action="append",
        help="XLA_FLAGS to add, one process per use (write --xla-flags=--xla_...); the "
        "default flags always run first",
    )
    p.add_argument("--out", help="write the results here as JSON")
    p.add_argument("--commit", help="the tree measured, stored with the results")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    a.features = [f for f in a.features.split(",") if f]
    sizes = {k: getattr(a, k) for k in SIZES}
    if a.child:
        print(json.dumps(measure(**sizes)))
        return 0
    runs = []
    for flags in ["", *(a.xla_flags or ())]:
        args = [
            f"--num-envs={a.num_envs}",
            f"--features={','.join(a.features)}",
            f"--terms={','.join(map(str, a.terms))}",
            f"--envs={','.join(map(str, a.envs))}",
            f"--steps={a.steps}",
            f"--repeats={a.repeats}",
        ]
        rows = in_fresh_process("jaxmetrics.bench._graph_threshold", args, flags)
        runs.append({"xla_flags": flags, "rows": rows})
        for r in rows:
            print(
                f"{flags or '(default flags)'}: {r['label'].strip()}, {r['num_envs']} envs x "
                f"{r['terms']}: floor {r['floor_us']:.1f}, ours {r['us']:.1f} us/step",
                flush=True,
            )
    if a.out:
        import jax

        doc = {
            "benchmark": "graph_threshold",
            "device": str(jax.devices()[0].device_kind),
            "jax": jax.__version__,
            "commit": a.commit,
            "sizes": sizes,
            "runs": runs,
        }
        with open(a.out, "w") as f:
            json.dump(doc, f, indent=1)
            f.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
