"""The tables of docs/benchmarks.md, made from the results files beside it.

The document is prose around generated blocks. A block

    <!-- bench: h100_isolated.json -->
    ...
    <!-- /bench -->

holds where and how `docs/benchmarks/h100_isolated.json` was measured and its tables; the
block `<!-- bench: targets -->` the project's targets judged on every accelerator's file.
`render` rewrites the blocks and keeps the prose, and refuses a file no block shows or a
block naming no file, so that a table cannot be left out or outlive its data; a test
checks that the committed document is what `render` makes of the committed files.
"""

import json
import os
import re
from collections.abc import Mapping
from typing import Any

from . import _brax_results, _in_trainer
from ._report import Table
from ._targets import NOTE, order, targets

DOC = "docs/benchmarks.md"
TARGETS = "targets"
BLOCK = re.compile(r"(<!-- bench: (\S+) -->\n)(.*?)(<!-- /bench -->)", re.S)


def results_dir(doc_path: str) -> str:
    """The folder of a document's results files: `docs/benchmarks/` for
    `docs/benchmarks.md`."""
    return os.path.splitext(doc_path)[0]


def load(directory: str) -> dict[str, dict[str, Any]]:
    """Every results file in `directory`, by file name."""
    docs = {}
    for name in sorted(os.listdir(directory)):
        if name.endswith(".json"):
            with open(os.path.join(directory, name)) as f:
                docs[name] = json.load(f)
    return docs


def tables(doc: dict[str, Any]) -> list[Table]:
    """The tables of one results file: a bench run's scenarios (its stored targets left
    out: `render` judges the targets again), or a `_brax_train` file's calls."""
    if doc.get("benchmark") == "brax_ppo_train":
        return _brax_results.tables(doc)
    if doc.get("benchmark") == "playground_ppo_train":
        return [_playground_table(doc)]
    if doc.get("benchmark") == "cond_sync":
        return [_cond_sync_table(doc)]
    if doc.get("benchmark") == "graph_threshold":
        return [_graph_threshold_table(doc)]
    if doc.get("benchmark") == "env_sync":
        return [_env_sync_table(doc)]
    if doc.get("benchmark") == "in_trainer":
        return [_in_trainer.table(doc)]
    return [Table.from_dict(n, d) for n, d in doc["scenarios"].items() if n != TARGETS]


def _playground_table(doc: dict[str, Any]) -> Table:
    """Steady training steps/s per physics and wrapper, against Playground's own wrap."""
    t = Table(
        "playground_ppo_train",
        "Playground's CartpoleBalance training (Brax `ppo.train`)",
        ["physics", "wrapper", "runs", "steady steps/s", "cost %"],
    )
    for impl, variants in doc["summary"].items():
        base = variants.get("playground")
        for wrap, v in variants.items():
            cost = "" if base is None or wrap == "playground" else v["overhead_steady_sps_pct"]
            t.add(impl, wrap, v["runs"], round(v["steady_sps"]), cost)
    return t


def _cond_sync_table(doc: dict[str, Any]) -> Table:
    """Microseconds per step of a scanned step of small kernels, per XLA_FLAGS setting."""
    from ._cond_sync import VARIANTS

    n = doc["sizes"]
    t = Table(
        "cond_sync",
        f"A step of {n['kernels']} small kernels over {n['envs']:,} floats, us/step",
        ["XLA_FLAGS", *VARIANTS],
        notes=[doc["note"]] if doc.get("note") else [],
    )
    for row in doc["rows"]:
        t.add(
            f"`{row['xla_flags']}`" if row["xla_flags"] else "(default)",
            *(row["us_per_step"].get(v, "") for v in VARIANTS),
        )
    return t


def _graph_threshold_table(doc: dict[str, Any]) -> Table:
    """The isolated rows' us/step, the floor's and ours, per XLA_FLAGS setting."""
    runs = doc["runs"]
    tags = [r["xla_flags"].removeprefix("--xla_gpu_") or "default" for r in runs]
    n = doc["sizes"]
    t = Table(
        "graph_threshold",
        f"Isolated update per XLA_FLAGS setting: {n['steps']}-step scan, us/step",
        [
            "variant",
            "envs",
            "terms",
            "ops in loop (floor, ours)",
            *(f"{c} ({tag})" for tag in tags for c in ("floor", "ours", "x floor")),
        ],
        notes=[
            "Each setting in a fresh process: "
            + "; ".join(
                f"{tag}: `XLA_FLAGS={r['xla_flags']}`" if r["xla_flags"] else f"{tag}: none set"
                for tag, r in zip(tags, runs)
            )
            + ". Median of interleaved repeats, the floor and every variant of a size in "
            "one timing."
        ],
    )
    for k, row in enumerate(runs[0]["rows"]):
        cells = []
        for r in runs:
            other = r["rows"][k]
            cells += [other["floor_us"], other["us"], other["us"] / other["floor_us"]]
        t.add(
            row["label"], row["num_envs"], row["terms"], f"{row['floor_ops']}, {row['ops']}", *cells
        )
    return t


def _env_sync_table(doc: dict[str, Any]) -> Table:
    """Per case and variant: ms per step against Playground's wrap of the same case, and
    what one profiled call ran per step."""
    n = doc["sizes"]
    t = Table(
        "env_sync",
        f"Playground's CartpoleBalance, {n['envs']:,} envs, pmapped {n['steps']}-step scan, "
        "ms/step",
        [
            "physics",
            "XLA_FLAGS",
            "variant",
            "ms/step",
            "vs playground %",
            "graph launches",
            "device events",
            "D2H copy on the stream",
            "GPU busy us",
        ],  # fmt: skip
        notes=[
            "Per step of the profiled call: graph launches: CUDA graphs the host launched "
            "(XLA's command buffers, Warp's own graph); device events: kernels, memsets "
            "and copies the GPU ran; D2H copy: whether a device-to-host copy ran on the "
            "stream (a conditional run from the host copies its predicate there each step); "
            "GPU busy: the device events' summed time.",
            *([doc["note"]] if doc.get("note") else []),
        ],
    )
    for case in doc["cases"]:
        rows = {r["variant"]: r for r in case["rows"]}
        base = rows.get("playground")
        flags = f"`{case['xla_flags']}`" if case["xla_flags"] else "(default)"
        if "error" in case and not rows:
            t.add(case["impl"], flags, "failed: " + case["error"], *[""] * 6)
        for v, r in rows.items():
            tc = r["trace_counts"]
            t.add(
                case["impl"],
                flags,
                v,
                round(r["ms_per_step"], 3),
                "" if base is None or v == "playground"
                else round(100 * (r["ms_per_step"] / base["ms_per_step"] - 1), 1),
                tc["graph_launches_per_step"],
                round(sum(tc["device_events_per_step"].values()), 1),
                "yes" if any("MemcpyD2H" in k for k in tc["device_events_per_step"]) else "no",
                round(tc["gpu_busy_us_per_step"]),
            )  # fmt: skip
    return t


def _versions(v: Mapping[str, Any]) -> str:
    names = ("jax", "jaxlib", "brax", "mujoco-mjx", "mujoco_mjx", "playground", "warp_lang")
    return ", ".join(f"{n.replace('_', '-')} {v[n]}" for n in names if v.get(n))


def source(name: str, doc: dict[str, Any]) -> str:
    """Where and how a results file was measured, in one paragraph."""
    if doc.get("benchmark") == "graph_threshold":
        n = doc["sizes"]
        tree = f", tree `{doc['commit'][:7]}`" if doc.get("commit") else ""
        return (
            f"`{name}`: {doc['device']}{tree}; jax {doc['jax']}; median of {n['repeats']} "
            f"calls per variant."
        )
    if doc.get("benchmark") == "cond_sync":
        n = doc["sizes"]
        return (
            f"`{name}`: {doc['device']}; jax {doc['jax']}; median of {n['repeats']} calls "
            f"of a {n['steps']}-step scan."
        )
    if doc.get("benchmark") == "env_sync":
        e, n = doc["environment"], doc["sizes"]
        return (
            f"`{name}`: {e['device']}; jax {e['jax']}, mujoco-mjx {e['mujoco_mjx']}, playground "
            f"{e['playground']}, warp-lang {e['warp_lang']}; median of {n['repeats']} calls per "
            "variant, each case (physics, XLA_FLAGS) in a fresh process."
        )
    if doc.get("benchmark") == "in_trainer":
        return (
            f"`{name}`: {doc['device']}, tree `{doc['commit']}`; jax {doc['jax']}. Runs of "
            "the wrappers alternate in one process on one machine; steady env steps/s leave "
            "out the intervals in which a compile ended; the cost is the steady steps/s lost "
            "against the trainer's own wrapper, in %."
        )
    env = doc["environment"]
    if doc.get("benchmark") == "playground_ppo_train":
        return (
            f"`{name}`: {env['device']} x{env['device_count']}; {_versions(env)}. Means over "
            "runs; the cost is the steady steps/s lost against Playground's own wrap of the "
            "same physics, in %."
        )
    if doc.get("benchmark") == "brax_ppo_train":
        device = f"{env['device']} x{env['device_count']}"
        return (
            f"`{name}`: {device}; {_versions(env)}. One table per device call (each names "
            "the tree it measured); runs are compared with the `brax` runs of their own call."
        )
    dev = env["device"]
    device = dev["kind"] + (f" x{dev['count']}" if dev["count"] > 1 else "")
    tree = f", tree `{env['git_commit'][:7]}`" if env.get("git_commit") else ""
    flags = f" (`XLA_FLAGS={env['xla_flags']}`)" if env.get("xla_flags") else ""
    return (
        f"`{name}`: {device}, {env['date'][:10]}{tree}; {_versions(env['versions'])}; "
        f"`{env['command']}`{flags}."
    )


def file_markdown(name: str, doc: dict[str, Any]) -> str:
    """The block of one results file: its source, then each table with its notes."""
    parts = [source(name, doc) + "\n"] + [t.to_markdown("####") for t in tables(doc)]
    return "\n".join(parts)


def targets_markdown(docs: Mapping[str, dict[str, Any]]) -> str:
    """The targets, each judged on the accelerator file that measures it."""
    t = Table("targets", "", ["target", "measured", "met", "measured in"], notes=[NOTE])
    runs = [
        (name, doc, tables(doc))
        for name, doc in docs.items()
        if "scenarios" in doc and doc["environment"]["device"]["backend"] != "cpu"
    ]
    for name, doc, its in sorted(runs, key=lambda r: order(r[2])):
        env = doc["environment"]
        for row in targets(its, env["device"]["backend"]).rows:
            t.add(*row, f"`{name}`, {env['date'][:10]}")
    return t.to_markdown(heading=None)


def render(text: str, docs: Mapping[str, dict[str, Any]]) -> str:
    """`text` with every generated block made anew from `docs` (file name -> contents).

    Raises:
        ValueError: a block names no file of `docs`, or a file has no block.
    """
    shown: set[str] = set()

    def block(m: re.Match[str]) -> str:
        name = m.group(2)
        if name == TARGETS:
            body = targets_markdown(docs)
        elif name in docs:
            body = file_markdown(name, docs[name])
            shown.add(name)
        else:
            raise ValueError(
                f"the block '<!-- bench: {name} -->' names no results file; there are "
                f"{sorted(docs)}"
            )
        return m.group(1) + body + m.group(4)

    out = BLOCK.sub(block, text)
    hidden = sorted(set(docs) - shown)
    if hidden:
        raise ValueError(
            f"no block shows {hidden}: add '<!-- bench: NAME -->' and '<!-- /bench -->' "
            "lines where its tables belong, or delete the file"
        )
    return out


def render_file(doc_path: str = DOC) -> None:
    """Rewrites the generated blocks of `doc_path` from the files in `results_dir`."""
    with open(doc_path) as f:
        text = f.read()
    out = render(text, load(results_dir(doc_path)))
    with open(doc_path, "w") as f:
        f.write(out)
