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
PROFILES = ("kernels", "group_kernels")
"""Tables the page leaves in the files: `--profile`'s device time per kernel (diagnostics
of where a step goes, a dozen rows of kernel names each)."""
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
    """The tables of one results file that the page shows: a scenario run's tables (its
    stored targets left out: `render` judges the targets again; `PROFILES` too), or a
    trainer benchmark's summary."""
    if doc.get("benchmark") == "brax_ppo_train":
        return [_brax_results.summary_table(doc)]
    if doc.get("benchmark") == "playground_ppo_train":
        return [_playground_table(doc)]
    if doc.get("benchmark") == "in_trainer":
        return [_in_trainer.table(doc)]
    shown = [(n, d) for n, d in doc["scenarios"].items() if n not in (TARGETS, *PROFILES)]
    return [Table.from_dict(n, d) for n, d in shown]


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


def _versions(v: Mapping[str, Any]) -> str:
    names = ("jax", "jaxlib", "brax", "mujoco-mjx", "mujoco_mjx", "playground", "warp_lang")
    return ", ".join(f"{n.replace('_', '-')} {v[n]}" for n in names if v.get(n))


OUTPUT_OPTIONS = ("--json", "--out-dir", "--kind", "--commit", "--note", "--hlo-dir")
"""Options of a recorded command that say where its results went, not what was measured."""


def command(recorded: str) -> str:
    """A recorded command line as it runs now: `python -m benchmarks` (the benchmarks were
    `jaxmetrics.bench` when the older files were recorded) with the options that shape
    the measurement, without `OUTPUT_OPTIONS` (paths of the machine it ran on).

    >>> command("python3 -m jaxmetrics.bench --full --note tree abc --out-dir /root/out/c")
    'python -m benchmarks --full'
    """
    words = recorded.split()
    at = next(i for i, w in enumerate(words) if w == "-m") + 2
    kept, skipping = ["python", "-m", "benchmarks"], False
    for w in words[at:]:
        if w.startswith("--"):
            skipping = w.split("=")[0] in OUTPUT_OPTIONS
        if not skipping:
            kept.append(w)
    return " ".join(kept)


def source(name: str, doc: dict[str, Any]) -> str:
    """Where and how a results file was measured, in one paragraph."""
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
            f"`{name}`: {device}; {_versions(env)}. One row per device call and variant (each "
            "call names the tree it measured); runs are compared with the `brax` runs of their "
            "own call."
        )
    dev = env["device"]
    device = dev["kind"] + (f" x{dev['count']}" if dev["count"] > 1 else "")
    tree = f", tree `{env['git_commit'][:7]}`" if env.get("git_commit") else ""
    flags = f" (`XLA_FLAGS={env['xla_flags']}`)" if env.get("xla_flags") else ""
    return (
        f"`{name}`: {device}, {env['date'][:10]}{tree}; {_versions(env['versions'])}; "
        f"`{command(env['command'])}`{flags}."
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
