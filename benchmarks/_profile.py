"""Where a scanned update's time goes: device time per kernel and step, from a profile.

Counting the ops left in the loop body (`_hlo`) says how many kernels run per step, not
which of them cost: on an H100 one reverse cumsum took 6 us of a 28 us update while
four counter adds took 1 us each. `profile` runs a compiled call once under
`jax.profiler.trace`, sums the duration of every device event by name (on a GPU the
kernels of its streams; on the CPU the thunks XLA's CPU client runs) and divides by the
number of steps; each kernel is described by the ops it fuses, read from the compiled HLO.
It also measures how long per step any kernel ran: a step's wall time less that is time
the device spent launching, which the kernels' sum does not show.
"""

import collections
import dataclasses
import glob
import os
import re
import tempfile
from collections.abc import Callable
from typing import Any

import jax

from ._hlo import _CALLS, _CONTAINERS, _FREE, _opcode, _split_computations


@dataclasses.dataclass(frozen=True)
class Kernel:
    """One kernel's device time in a profiled call, per step of its scan."""

    name: str
    us_per_step: float
    launches_per_step: float
    shape: str  # the HLO instruction's result shape ("" when not found in the HLO)
    ops: str  # what it computes: the opcodes it fuses, most frequent first


def _key(name: str) -> str:
    # Kernel names spell the HLO instruction's name with '_' for '.' and '-'.
    return re.sub(r"[^0-9A-Za-z]", "_", name)


def describe(hlo_text: str) -> dict[str, tuple[str, str]]:
    """Per HLO instruction (by `_key` of its name): its result shape and fused opcodes."""
    comps, _ = _split_computations(hlo_text)
    out: dict[str, tuple[str, str]] = {}
    for instrs in comps.values():
        for instr in instrs:
            lhs, rhs = instr.split(" = ", 1)
            name = lhs.replace("ROOT", "").strip().lstrip("%")
            op = _opcode(instr)
            cut = rhs.find(f" {op}(")
            shape = re.sub(r"\{[^{}]*\}|/\*.*?\*/", "", rhs[:cut]).strip() if cut >= 0 else ""
            m = _CALLS.search(instr)
            callee = m.group(1).replace("%", "").split(",")[0].strip() if m else None
            if op == "fusion" and callee in comps:
                inner = collections.Counter(
                    o for o in map(_opcode, comps[callee]) if o not in _FREE
                )
                what = ", ".join(f"{o}x{n}" if n > 1 else o for o, n in inner.most_common(6))
            else:
                what = op
            out[_key(name)] = (shape, what)
    return out


def _device_lines(planes: list[Any]) -> list[Any]:
    # An accelerator: one line per stream holds its kernels (other lines summarize them).
    streams = [
        ln
        for p in planes
        if p.name.startswith("/device:")
        for ln in p.lines
        if ln.name.startswith("Stream")
    ]
    if streams:
        return streams
    # The CPU: XLA's client threads run the thunks; the "python" line is the caller.
    return [ln for p in planes if p.name == "/host:CPU" for ln in p.lines if ln.name != "python"]


@dataclasses.dataclass(frozen=True)
class Profile:
    """A profiled call's kernels (most expensive first) and, per step, the time at least
    one of them ran (`busy_us_per_step`, the union of their intervals: kernels that
    overlap count once). The step's wall time less `busy_us_per_step` is the time the
    device ran no kernel: launch gaps between kernels and between the loop's steps."""

    kernels: list[Kernel]
    busy_us_per_step: float


def _union_ns(intervals: list[tuple[int, int]]) -> int:
    """Total length of the union of `(start, end)` intervals."""
    total, end = 0, None
    for a, b in sorted(intervals):
        if end is None or a > end:
            total, end = total + b - a, b
        elif b > end:
            total, end = total + b - end, b
    return total


def profile(run: Callable[[], Any], hlo_text: str, steps: int) -> Profile:
    """Profiles one `run()` (a whole, blocking call of a program scanning `steps` steps)."""
    total: collections.Counter[str] = collections.Counter()
    launches: collections.Counter[str] = collections.Counter()
    intervals: list[tuple[str, int, int]] = []
    with tempfile.TemporaryDirectory() as d:
        with jax.profiler.trace(d):
            run()
        (path,) = glob.glob(os.path.join(d, "**", "*.xplane.pb"), recursive=True)
        data = jax.profiler.ProfileData.from_file(path)
        for line in _device_lines(list(data.planes)):
            for e in line.events:
                # Skip the CPU runtime's own frames (`ThunkExecutor::Execute`, ...).
                if e.name.startswith("end: ") or "::" in e.name:
                    continue
                total[e.name] += e.duration_ns
                launches[e.name] += 1
                intervals.append((e.name, e.start_ns, e.start_ns + e.duration_ns))
    known = describe(hlo_text)
    kernels = []
    for name, ns in total.most_common():
        shape, ops = known.get(_key(name), ("", ""))
        if ops in _CONTAINERS:  # a loop's own event spans the kernels it runs
            continue
        kernels.append(Kernel(name, ns / 1e3 / steps, launches[name] / steps, shape, ops))
    ran = {k.name for k in kernels}
    busy = _union_ns([(a, b) for name, a, b in intervals if name in ran])
    return Profile(kernels, busy / 1e3 / steps)
