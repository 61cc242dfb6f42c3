"""What XLA made of a jitted scan: the ops left in the loop body after optimization.

On a GPU each fusion, custom call, sort or scatter left in the body of the scan's
`while` is (about) one kernel launch per step; that count, more than bytes or flops,
is what small per-step updates cost. Read off `compiled.as_text()`.
"""

import collections
import re
from collections.abc import Iterator

# Ops that move no data and launch nothing.
_FREE = frozenset(
    {
        "parameter",
        "get-tuple-element",
        "tuple",
        "constant",
        "bitcast",
        "after-all",
        "opt-barrier",
        "partition-id",
        "replica-id",
    }
)
# Ops that only hold other computations; their bodies are counted instead.
_CONTAINERS = frozenset({"while", "call", "conditional", "async-start", "async-done"})

_BODY = re.compile(r"\bbody=%?([\w.\-]+)")
_CALLS = re.compile(r"\b(?:to_apply|calls|branch_computations)=\{?%?([\w.\-, %]+)\}?")


def _split_computations(text: str) -> tuple[dict[str, list[str]], str | None]:
    comps: dict[str, list[str]] = {}
    name = entry = None
    for line in text.splitlines():
        s = line.strip()
        if s.endswith("{") and " = " not in s.split("(")[0] and not s.startswith("HloModule"):
            head = s.split()[1] if s.startswith("ENTRY") else s.split()[0]
            name = head.lstrip("%")
            entry = name if s.startswith("ENTRY") else entry
            comps[name] = []
        elif s == "}":
            name = None
        elif name is not None and " = " in s:
            comps[name].append(s)
    return comps, entry


def _opcode(instr: str) -> str:
    rhs = instr.split(" = ", 1)[1].lstrip()
    if rhs.startswith("("):  # tuple-shaped result: skip to the matching paren
        depth = 0
        for i, ch in enumerate(rhs):
            depth += ch == "("
            depth -= ch == ")"
            if depth == 0:
                rhs = rhs[i + 1 :].lstrip()
                break
    else:
        rhs = rhs.split(" ", 1)[1] if " " in rhs else rhs
    return rhs.split("(", 1)[0].strip()


def _ops(comps: dict[str, list[str]], name: str, seen: set[str]) -> Iterator[str]:
    if name in seen or name not in comps:
        return
    seen.add(name)
    for instr in comps[name]:
        op = _opcode(instr)
        if op in _CONTAINERS:
            for m in _BODY.finditer(instr):
                yield from _ops(comps, m.group(1), seen)
            for m in _CALLS.finditer(instr):
                for callee in m.group(1).replace("%", "").split(","):
                    yield from _ops(comps, callee.strip(), seen)
            if op == "while":
                yield "while"
            continue
        if op not in _FREE:
            yield op


def loop_body_ops(hlo_text: str) -> dict[str, int]:
    """Op counts in the body of the outermost `while` (the scan) of compiled HLO text.

    Fusions are counted as one op (their insides are not looked at); nested loops and
    called computations are looked into. Returns {} when there is no loop.
    """
    comps, entry = _split_computations(hlo_text)
    body = _first_loop(comps, entry, set()) if entry else None
    if body is None:
        return {}
    return dict(collections.Counter(_ops(comps, body, set())).most_common())


def program_ops(hlo_text: str) -> dict[str, int]:
    """Op counts of a whole compiled program (the entry computation and what it calls),
    counted as `loop_body_ops` counts a loop body's."""
    comps, entry = _split_computations(hlo_text)
    if entry is None:
        return {}
    return dict(collections.Counter(_ops(comps, entry, set())).most_common())


def _first_loop(comps: dict[str, list[str]], name: str, seen: set[str]) -> str | None:
    # Breadth-first from the entry computation, so the outermost loop wins.
    queue = [name]
    while queue:
        name = queue.pop(0)
        if name in seen or name not in comps:
            continue
        seen.add(name)
        for instr in comps[name]:
            op = _opcode(instr)
            if op == "while":
                m = _BODY.search(instr)
                if m:
                    return m.group(1)
            if op in _CONTAINERS:
                for m in _CALLS.finditer(instr):
                    queue += [c.strip() for c in m.group(1).replace("%", "").split(",")]
    return None


COLLECTIVES = ("all-reduce", "all-gather", "all-to-all", "collective-permute", "reduce-scatter")
"""Opcode prefixes of the ops that move data between devices (sync and async forms)."""


def top_level_loops(hlo_text: str) -> list[dict[str, int]]:
    """Op counts of each `while` of the entry computation, in program order."""
    comps, entry = _split_computations(hlo_text)
    out = []
    for instr in comps.get(entry, []) if entry else []:
        m = _BODY.search(instr)
        if _opcode(instr) == "while" and m:
            out.append(dict(collections.Counter(_ops(comps, m.group(1), set())).most_common()))
    return out


def collectives(ops: dict[str, int]) -> dict[str, int]:
    """The cross-device ops among `ops` (an asynchronous one as its `-start` op alone)."""
    return {
        op: n for op, n in ops.items() if op.startswith(COLLECTIVES) and not op.endswith("-done")
    }
