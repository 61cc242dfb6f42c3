"""The fused kernel's inputs and outputs by name (`KernelIn`, `KernelOut`), read by both
its caller (`_kernel.fold`) and its programs (`_program`).

`pl.pallas_call` takes its inputs and outputs as positional lists, and hands a program its
refs in one flat list, inputs then outputs. Both sides here describe them as one structure
of named fields instead, and flatten it in the same order (`jax.tree`): the caller builds
each field as an `Operand` (its array and its block), the program unflattens its refs with
the same tree structure (`Layout`) and reads them by name. An optional input is None where
absent, which flattening skips; a per-ring or per-histogram input is a tuple of them.

A field that the kernel updates in place is the same `Operand` in the inputs and the
outputs: the input-output aliases are found from that (`Layout.aliases`), never counted
by hand, so that adding an input is one field, and a reordering cannot alias the wrong
buffer.
"""

import dataclasses
from typing import Any, Generic, NamedTuple, TypeVar

import jax
from jax.experimental import pallas as pl

T = TypeVar("T")


@dataclasses.dataclass(frozen=True, eq=False)
class Operand:
    """One input or output of the kernel: its array (an output's shape and dtype; for
    an output written in place, the input's array) and its block (`pl.BlockSpec`).
    Not a pytree: each is one leaf of `KernelIn` and `KernelOut`, and compared by
    identity."""

    value: jax.Array | jax.ShapeDtypeStruct
    spec: pl.BlockSpec


class Words(NamedTuple, Generic[T]):
    """A count's high and low words (`_count.Count`'s order)."""

    hi: T
    lo: T


class RingOf(NamedTuple, Generic[T]):
    """A ring (`_kernel.RingIn`): its `data` (`[rows, size, 2]` uint32, written in place)
    and its rows' next slots `pos` (whole, or with `FieldsIn` each row's own, `[R, 1]`,
    which the update advances in place)."""

    data: T
    pos: T


class HistOf(NamedTuple, Generic[T]):
    """A histogram (`_hists.HistIn`): the step's counts and the low and high words,
    each updated in place."""

    counted: T
    lo: T
    hi: T


class FieldsIn(NamedTuple, Generic[T]):
    """The state's per-row fields that the kernel updates (`_update.InKernel`) besides
    those it reads anyway (`KernelIn.shift` is the mean, `steps`, `ema_w`, `ema_off`, the
    rings' `pos`): `[R, 1]` each, the counted rows' `counts` `[packs, R]` (None without
    counted rows), and `listed_sums`, the counted rows' chunk sums from the listing
    (`[C, n]`; None where they are not read from the lists), the only one not updated."""

    count: Words[T]  # the field shadows tuple.count  # pyright: ignore[reportIncompatibleMethodOverride]
    nonfinite: Words[T]
    m2: T
    m2_c: T
    sum: T
    sum_c: T
    min: T
    max: T
    ema: T | None
    ema_n: T | None
    filled: tuple[T, ...]
    counts: Words[T] | None
    listed_sums: T | None


class FieldsOut(NamedTuple, Generic[T]):
    """The per-row fields the kernel writes (`_update.update`'s), each in place of its
    input; the EMA's None without EMA rows."""

    count: Words[T]  # the field shadows tuple.count  # pyright: ignore[reportIncompatibleMethodOverride]
    nonfinite: Words[T]
    mean: T
    m2: T
    m2_c: T
    sum: T
    sum_c: T
    min: T
    max: T
    steps: T
    ema: T | None
    ema_off: T | None
    ema_w: T | None
    ema_n: T | None
    pos: tuple[T, ...]
    filled: tuple[T, ...]
    counts: Words[T] | None


class KernelIn(NamedTuple, Generic[T]):
    """The kernel's inputs, in `pl.pallas_call`'s order (see `_kernel.fold`).

    Always: the batch's source rows (`ok`, `values`, `bad`: `[S, B]`, whole), the rows'
    `shift` (`[R, 1]` float32) and arrival `steps` (`[R, 1]` uint32), and their static
    ints (`table`, `[R, n]` int32, `Table`). Then, where present: the group index (`ids`,
    `[K, B]`, with group rows); the lists of reached entries (`listed`, `reached`, and
    `flags` without group rows: `_reached.Reached`); the pairs' table (`_hists.Pairs`);
    the chunks' masked-in counts (`chunk_counts`, `_chunks.reads_counts`); the counted
    rows (`counted`, read with the batch); the EMA's `ema_w` and `ema_off` (`[R, 1]`); each
    ring; each histogram; and the fields the kernel updates (`update`)."""

    ok: T
    values: T
    bad: T
    shift: T
    steps: T
    table: T
    ids: T | None
    listed: T | None
    reached: T | None
    flags: T | None
    pairs: T | None
    chunk_counts: T | None
    counted: T | None
    ema_w: T | None
    ema_off: T | None
    rings: tuple[RingOf[T], ...]
    hists: tuple[HistOf[T], ...]
    update: FieldsIn[T] | None


class KernelOut(NamedTuple, Generic[T]):
    """The kernel's outputs: per program its statistics (`floats`, 8 a program, and
    `ints`, a power of two a program: count, non-finite flags, counted sums), each ring's
    data, each histogram, and the per-row fields it updates (`update`, or None)."""

    floats: T
    ints: T
    rings: tuple[T, ...]
    hists: tuple[HistOf[T], ...]
    update: FieldsOut[T] | None


@dataclasses.dataclass(frozen=True)
class Layout:
    """The tree structures of `KernelIn` and `KernelOut` that a call's operands have: what
    flattens them into `pl.pallas_call`'s lists, and what rebuilds a program's refs into
    them (`refs`). Hashable, so that a program takes it as a static argument."""

    ins: Any  # jax.tree_util.PyTreeDef
    outs: Any  # jax.tree_util.PyTreeDef

    @classmethod
    def of(cls, ins: KernelIn[Operand], outs: KernelOut[Operand]) -> "Layout":
        return cls(jax.tree.structure(ins), jax.tree.structure(outs))

    def refs(self, refs: tuple[Any, ...]) -> tuple[KernelIn[Any], KernelOut[Any]]:
        """A program's refs (inputs, then outputs) by name."""
        n = self.ins.num_leaves
        return jax.tree.unflatten(self.ins, refs[:n]), jax.tree.unflatten(self.outs, refs[n:])


def operands(tree: KernelIn[Operand] | KernelOut[Operand]) -> list[Operand]:
    """The operands of `tree` in `pl.pallas_call`'s order."""
    return jax.tree.leaves(tree)


def aliases(ins: KernelIn[Operand], outs: KernelOut[Operand]) -> dict[int, int]:
    """The input-output aliases: each output that is an input's `Operand` (updated in
    place), by their positions in the flattened inputs and outputs."""
    at = {id(o): i for i, o in enumerate(operands(outs))}
    return {i: at[id(o)] for i, o in enumerate(operands(ins)) if id(o) in at}


class Table:
    """The columns of a batch row's static ints (`KernelIn.table`, `[R, n]` int32): the
    EMA coefficient's float32 bits, the row's source row, grouping (-1: none) and group
    (`Selected`), then each ring's `row` and `pos_row` (`_kernel.RingIn`), then each
    histogram's row and the float32 bits of its range where the kernel counts them
    (`_hists.HistRows`)."""

    COEFF, SRC, KIND, GROUP = range(4)

    @staticmethod
    def ring(i: int) -> int:
        """The column of ring `i`'s `row` (its `pos_row` follows)."""
        return Table.GROUP + 1 + 2 * i

    @staticmethod
    def hist(rings: int, i: int) -> int:
        """The column of histogram `i`'s row (its `lo` and `hi` bits follow)."""
        return Table.ring(rings) + 3 * i
