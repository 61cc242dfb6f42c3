"""Results: one `Table` per scenario, printed as Markdown and written as JSON with the
machine, device, versions and date they were measured on."""

import dataclasses
import datetime
import importlib.metadata
import json
import os
import platform
import re
import subprocess
import sys
from collections.abc import Sequence
from typing import Any

import jax

PACKAGES = ("jax", "jaxlib", "numpy", "brax", "mujoco", "mujoco-mjx", "flax", "jaxmetrics")


@dataclasses.dataclass
class Table:
    """One scenario's results: rows of cells under named columns, plus notes and raw data."""

    name: str
    title: str
    columns: Sequence[str]
    rows: list[list[Any]] = dataclasses.field(default_factory=list)
    notes: list[str] = dataclasses.field(default_factory=list)
    data: dict[str, Any] = dataclasses.field(default_factory=dict)
    scenario: str = ""  # the `--scenarios` name that made it ("" for the targets)

    @classmethod
    def from_dict(cls, name: str, d: dict[str, Any]) -> "Table":
        """The table `to_dict` wrote (as read back from a results JSON)."""
        return cls(name, d["title"], d["columns"], d["rows"], d["notes"], d["data"])

    def add(self, *cells: Any) -> None:
        if len(cells) != len(self.columns):
            raise ValueError(f"{self.name}: {len(cells)} cells for columns {list(self.columns)}")
        self.rows.append(list(cells))

    def to_markdown(self, heading: str | None = "###") -> str:
        """The table under its title as a heading of this level (none: no title), then
        its notes as a list."""
        lines = [] if heading is None else [f"{heading} {self.title}", ""]
        lines.append("| " + " | ".join(self.columns) + " |")
        lines.append("|" + "---|" * len(self.columns))
        lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in self.rows]
        lines += [""] + [f"- {n}" for n in self.notes]
        return "\n".join(lines).rstrip() + "\n"

    def to_dict(self) -> dict[str, Any]:
        return {
            "title": self.title,
            "columns": list(self.columns),
            "rows": self.rows,
            "notes": self.notes,
            "data": self.data,
        }


def _cell(c: Any) -> str:
    if c is None:
        return "-"
    if isinstance(c, bool):
        return "yes" if c else "no"
    if isinstance(c, float):
        if c != c:
            return "nan"
        a = abs(c)
        if a == 0 or 0.01 <= a < 1e5:
            return f"{c:.3g}" if a < 10 else f"{c:,.1f}" if a < 1000 else f"{c:,.0f}"
        return f"{c:.2e}"
    if isinstance(c, int):
        return f"{c:,}"
    return str(c)


def _version(name: str) -> str | None:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def _git_commit() -> str | None:
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=10
        )
    except (OSError, subprocess.SubprocessError):
        return None
    commit = out.stdout.strip()
    return commit if out.returncode == 0 and len(commit) == 40 else None


def environment(commit: str | None = None) -> dict[str, Any]:
    """Machine, device, versions and date of this run; `commit` names the tree measured
    where the checkout's own `git rev-parse HEAD` would not (a copy with a stale `.git`)."""
    import jaxmetrics

    dev = jax.devices()[0]
    versions = {name: _version(name) for name in PACKAGES}
    versions["jaxmetrics"] = jaxmetrics.__version__
    versions["python"] = platform.python_version()
    return {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": {
            "hostname": platform.node(),
            "platform": platform.platform(),
            "processor": platform.machine(),
            "cpu_count": os.cpu_count(),
        },
        "device": {
            "backend": jax.default_backend(),
            "kind": dev.device_kind,
            "count": jax.device_count(),
        },
        "versions": versions,
        "git_commit": commit or _git_commit(),
        "xla_flags": os.environ.get("XLA_FLAGS"),
        "command": " ".join([os.path.basename(sys.executable), "-m", "benchmarks"] + sys.argv[1:]),
    }


def device_label(env: dict[str, Any]) -> str:
    """The device kind in a results file's name, from an `environment()`'s device: `cpu`;
    else the model, the first word of the kind after NVIDIA's name (`tpuv4` for a TPU), with
    the count where there are several devices (`h200x2`).

    >>> device_label({"device": {"backend": "gpu", "kind": "NVIDIA H100 80GB HBM3", "count": 1}})
    'h100'
    >>> device_label({"device": {"backend": "gpu", "kind": "NVIDIA H200", "count": 2}})
    'h200x2'
    """
    dev = env["device"]
    if dev["backend"] == "cpu":
        return "cpu"
    words = [w for w in re.findall(r"[a-z0-9]+", dev["kind"].lower()) if w != "nvidia"]
    name = "".join(words[:2]) if words[:1] == ["tpu"] else words[0]
    return name if dev["count"] == 1 else f"{name}x{dev['count']}"


def write_json(path: str, env: dict[str, Any], config: dict[str, Any], tables: Sequence[Table]):
    doc = {"environment": env, "config": config, "scenarios": {t.name: t.to_dict() for t in tables}}
    with open(path, "w") as f:
        json.dump(doc, f, indent=1, default=_jsonable)
        f.write("\n")


def _jsonable(x: Any) -> Any:
    if hasattr(x, "item"):
        return x.item()
    if hasattr(x, "tolist"):
        return x.tolist()
    raise TypeError(f"not JSON serializable: {type(x).__name__}")
