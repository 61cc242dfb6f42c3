"""The fused kernel's operands by name (`_stream._layout`) against what `pl.pallas_call` is
given. The caller and the programs read the same `KernelIn` and `KernelOut` by name, and the
input-output aliases come from that description: here every alias must join an input and
an output of the same field, of the same shape, dtype and block, and every field must hold
an array of its kind, so that a reordered or miswired field fails here rather than
folding one buffer into another on a GPU."""

import functools
import re

import jax
import jax.numpy as jnp
import pytest
from jax.experimental import pallas as pl
from test_kernel_lowering import _spec as full_spec

# An input's field and the output field it is updated in place as, where their names
# differ: the mean is the batch's shift, a ring's `pos` the update's.
RENAMED = {".shift": ".update.mean", ".steps": ".update.steps"}
RENAMED |= {".ema_w": ".update.ema_w", ".ema_off": ".update.ema_off"}


def _out_field(path: str) -> str:
    """The output field that input field `path` is updated in place as."""
    ring = re.fullmatch(r"\.rings\[(\d+)\]\.(data|pos)", path)
    if ring:
        return f".rings[{ring[1]}]" if ring[2] == "data" else f".update.pos[{ring[1]}]"
    return RENAMED.get(path, path)


@pytest.mark.parametrize(
    ("num_envs", "groups", "history", "own"),
    [
        (256, 0, False, True),  # one program per row, which updates the row's fields
        (300, 3, False, True),  # group rows from the lists, histograms counted in the kernel
        (24576, 0, False, True),  # rows from the lists, histogram pairs in programs of their own
        (3000, 0, False, False),  # chunks that count the row's mask themselves
        (256, 0, True, False),  # the EMAs' rings too, which XLA advances
    ],
)
def test_kernel_aliases_join_each_field_to_itself(monkeypatch, num_envs, groups, history, own):
    from jaxmetrics._core import _fresh, _stream
    from jaxmetrics._core._stream import _program

    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    fold = _stream.add_with_counts
    monkeypatch.setattr(_stream, "add_with_counts", functools.partial(fold, interpret=True))
    calls = []
    pallas_call = pl.pallas_call

    def spy(kernel, **kw):
        call = pallas_call(kernel, **kw)

        def run(*args):
            if getattr(kernel, "func", None) is _program.program:
                calls.append((kernel.keywords["layout"], kw, args))
            return call(*args)

        return run

    monkeypatch.setattr(pl, "pallas_call", spy)
    metrics = full_spec("full", groups)  # EMAs, windows, two histograms, counted rows
    x = jnp.zeros((4, num_envs), jnp.float32)
    state = metrics.init(num_envs)
    if history:
        state = _fresh.fresh(metrics._rows, num_envs, 1, ema_history=True)
    jax.make_jaxpr(metrics.update)(state, x, jnp.zeros(num_envs, bool))
    assert calls
    for layout, kw, args in calls:
        ins = jax.tree.unflatten(layout.ins, args)
        outs = jax.tree.unflatten(layout.outs, kw["out_shape"])
        assert (ins.update is not None) == (outs.update is not None) == own
        # Each field holds what its name says.
        assert (ins.ok.dtype, ins.values.dtype, ins.table.dtype) == (
            jnp.bool_,
            jnp.float32,
            jnp.int32,
        )
        assert (ins.shift.dtype, ins.steps.dtype) == (jnp.float32, jnp.uint32)
        assert ins.ema_w is not None and ins.ema_w.dtype == ins.ema_off.dtype == jnp.float32
        # The two window sizes' rings, and the two EMAs' with their history.
        assert len(ins.rings) == (4 if history else 2) and len(ins.hists) == 2
        assert all(r.data.dtype == jnp.uint32 and r.data.shape[2] == 2 for r in ins.rings)
        assert all(h.counted.dtype == jnp.int32 for h in ins.hists)
        assert all(h.lo.dtype == h.hi.dtype == jnp.uint32 for h in ins.hists)
        assert (ins.ids is not None) == bool(groups)
        in_paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_leaves_with_path(ins)]
        out_paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_leaves_with_path(outs)]
        aliases = dict(kw["input_output_aliases"])
        for i, o in aliases.items():
            assert _out_field(in_paths[i]) == out_paths[o], (in_paths[i], out_paths[o])
            a, b = args[i], kw["out_shape"][o]
            assert (a.shape, a.dtype) == (b.shape, b.dtype), in_paths[i]
            assert kw["in_specs"][i].block_shape == kw["out_specs"][o].block_shape, in_paths[i]
        # Every output but the programs' statistics is an input updated in place.
        assert sorted(aliases.values()) == list(range(2, len(out_paths)))
        assert out_paths[:2] == [".floats", ".ints"]
        if own:
            # The counted rows' counts, and their chunk sums where read from the lists.
            assert ins.update.counts is not None
            assert (ins.update.listed_sums is not None) == (ins.listed is not None)
