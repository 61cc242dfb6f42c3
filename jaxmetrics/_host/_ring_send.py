"""The ring channel's sending side: the rings and order words of each payload layout
(`Site`, `Orders`) and the primitive a jitted program writes them with (`send_p`).

The primitive is built from JAX internals (`private_jax`); `_channel.self_test` is what
finds out whether they still work. What reads the rings is `_ring`; what chooses the ring
and hands its reports on is `_channel`.
"""

import threading
import weakref
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import _ring


def private_jax() -> Any:
    """The JAX internals the ring's primitive is built from (see `_send_primitive`)."""
    from jax._src import buffer_callback, callback, core, dispatch, ffi
    from jax._src.interpreters import mlir

    return buffer_callback, callback, core, dispatch, ffi, mlir


class Leaf(NamedTuple):
    """How one payload array travels as uint32 words."""

    shape: tuple[int, ...]
    dtype: np.dtype
    words: int

    @staticmethod
    def of(x: Any) -> "Leaf":
        dtype = np.dtype(x.dtype)
        size = int(np.prod(x.shape, dtype=np.int64))
        return Leaf(tuple(x.shape), dtype, size * (2 if dtype.itemsize == 8 else 1))

    def encode(self, x: jax.Array) -> jax.Array:
        if self.dtype.itemsize in (4, 8) and self.dtype != np.bool_:
            return jax.lax.bitcast_convert_type(x, jnp.uint32).reshape(-1)
        wide = jnp.float32 if jnp.issubdtype(x.dtype, jnp.floating) else jnp.int32
        return jax.lax.bitcast_convert_type(x.astype(wide), jnp.uint32).reshape(-1)

    def decode(self, words: np.ndarray) -> np.ndarray:
        if self.dtype.itemsize in (4, 8) and self.dtype != np.bool_:
            return words.view(self.dtype).reshape(self.shape)
        wide = np.float32 if np.issubdtype(self.dtype, np.floating) else np.int32
        return words.view(wide).astype(self.dtype).reshape(self.shape)


class Order:
    """One device's order word (the stamp counter of every ring of the channel that the
    device writes) and the merge of those rings (`_ring.Merge`)."""

    def __init__(self, address: int):
        self.merge = _ring.Merge(address)
        self.lock = threading.Lock()  # held by the host's writers (`Site.write_host`)


class Orders:
    """A channel's order words, one per device that writes its rings ("host": the CPU's
    host function). Held by the channel and by each of its sites, so that the pinned words
    outlive every program that writes them."""

    def __init__(self) -> None:
        self.by_device: dict[Any, Order] = {}
        self._lock = threading.Lock()
        self._host_memory: Any = None

    def host(self) -> Order:
        with self._lock:
            if "host" not in self.by_device:
                self._host_memory = np.zeros(_ring.ORDER_WORDS, np.uint32)
                self.by_device["host"] = Order(self._host_memory.ctypes.data)
            return self.by_device["host"]

    def cuda(self, ordinal: int) -> Order:
        """Device `ordinal`'s word, in pinned memory (allocated at trace time: a stream
        under capture may not)."""
        from . import _cuda

        with self._lock:
            if ordinal not in self.by_device:
                driver = _cuda.driver()
                address = driver.pinned(_ring.ORDER_WORDS * 4)
                self.by_device[ordinal] = Order(address)
                weakref.finalize(self, driver.free_pinned, address).atexit = False
            return self.by_device[ordinal]


class Site:
    """One payload layout (a tree structure and its arrays' shapes and dtypes): its
    rings, one per device that may write it (each holding its reader's place)."""

    def __init__(self, treedef: Any, leaves: tuple[Leaf, ...], slots: int, orders: Orders):
        self.treedef, self.leaves, self.slots = treedef, leaves, slots
        self.words = sum(leaf.words for leaf in leaves)
        self._nbytes = _ring.ring_words(self.words, slots) * 4
        self._orders = orders
        self._host: _ring.Ring | None = None
        self._host_memory: Any = None
        self.rings: dict[Any, _ring.Ring] = {}

    def host_ring(self) -> _ring.Ring:
        if self._host is None:
            self._host_memory = np.zeros(self._nbytes // 4, np.uint32)
            self._host = _ring.Ring(self._host_memory.ctypes.data, self.words, self.slots)
            self.rings["host"] = self._host
        return self._host

    def cuda_rings(self) -> None:
        """Pinned rings and order words for every local CUDA device, and the kernel loaded
        on each (a stream under capture may do none of these)."""
        from . import _cuda

        driver = _cuda.driver()
        for device in jax.local_devices(backend="gpu"):
            ordinal = device.local_hardware_id
            if ordinal in self.rings:
                continue
            driver.prepare(ordinal)
            self._orders.cuda(ordinal)
            address = driver.pinned(self._nbytes)
            self.rings[ordinal] = _ring.Ring(address, self.words, self.slots)
            # Freed with the site: every compiled program that writes this ring holds the
            # site (its host callback does), so once the site is gone nothing writes it.
            # Not at interpreter exit, where the process frees it and CUDA may be gone.
            weakref.finalize(self, driver.free_pinned, address).atexit = False

    def encode(self, leaves: list[jax.Array]) -> jax.Array:
        return jnp.concatenate([leaf.encode(x) for leaf, x in zip(self.leaves, leaves)])

    def decode(self, payload: bytes) -> Any:
        words = np.frombuffer(payload, np.uint32)
        arrays, offset = [], 0
        for leaf in self.leaves:
            arrays.append(leaf.decode(words[offset : offset + leaf.words]))
            offset += leaf.words
        return jax.tree.unflatten(self.treedef, arrays)

    def write_host(self, words: np.ndarray) -> None:
        """Writes one report into the host ring (from any thread: CPU devices run their
        callbacks concurrently), stamped from the host's order word: one lock for all the
        channel's host writers keeps seqs and stamps in one order."""
        order = self._orders.host()
        with order.lock:
            self.host_ring().write(words, order.merge.order)

    def put(self, ctx: Any, words: Any) -> None:
        """The buffer callback: on a GPU it runs once per capture of XLA's command buffer
        (or per execution outside one) and enqueues the ring kernel on XLA's stream; on the
        CPU it runs per execution and writes the ring itself."""
        try:
            src = words.__cuda_array_interface__["data"][0]
        except jax.errors.JaxRuntimeError:  # a CPU buffer: no device address
            self.write_host(np.asarray(words))
            return
        from . import _cuda

        driver = _cuda.driver()
        ordinal = driver.current_device()
        order = self._orders.by_device[ordinal].merge.order
        driver.put(ctx.stream, src, self.rings[ordinal].address, order, self.words, self.slots)


# The custom calls behind `jax.experimental.buffer_callback`; on CUDA, the one XLA records
# into its command buffer (the callback runs once per capture and enqueues the kernel).
_TARGETS = {
    "cpu": "xla_buffer_python_cpu_callback",
    "cuda": "xla_buffer_python_gpu_callback_cmd_buffer",
}


def _send_primitive() -> Any:
    """A primitive lowered as `buffer_callback(..., command_buffer_compatible=True)` is,
    plus the sharding JAX gives its own callbacks: under automatic SPMD partitioning the
    report is sent once, from the first device (as an `io_callback` is), not from every
    device. `buffer_callback` itself sets no sharding, which XLA's partitioner refuses for
    an op with side effects. It has one (unused, unwritten) scalar result, as a host
    callback with a sharding needs one."""
    buffer_callback, callback, core, dispatch, ffi, mlir = private_jax()
    prim = core.Primitive("jaxmetrics_report_send")
    prim.multiple_results = True

    unused = core.ShapedArray((), np.uint32)

    def abstract(words: Any, *, site: Site) -> Any:
        return [unused], {buffer_callback._BufferCallbackEffect}

    def lower(ctx: Any, words: Any, *, site: Site) -> Any:
        platform = ctx.module_context.platforms[0]
        if len(ctx.module_context.platforms) > 1 or platform not in _TARGETS:
            raise ValueError(
                f"report_channel='ring' runs on CUDA GPUs and the CPU, not on "
                f"{ctx.module_context.platforms}; use report_channel='io_callback'."
            )
        axis_context = ctx.module_context.axis_context
        sharding = callback._callback_op_sharding(axis_context, None, ctx.avals_out)
        if sharding is not None:
            # Automatic SPMD partitioning: Shardy keeps the sharding of JAX's own host
            # callbacks only, so the report takes one (run from the host, outside any
            # CUDA graph) that writes the same ring, once, from the first device.
            def write(words: Any) -> tuple[np.ndarray]:
                site.write_host(np.asarray(words))
                return (np.zeros((), np.uint32),)

            results, _, _ = callback.emit_python_callback(
                ctx,
                write,
                None,
                [words],
                ctx.avals_in,
                ctx.avals_out,
                has_side_effect=True,
                returns_token=False,
                sharding=sharding,
            )
            return results

        def put(exec_ctx: Any, words: Any, unused: Any) -> tuple[()]:
            site.put(exec_ctx, words)
            return ()

        ctx.module_context.add_host_callback(put)
        index = np.uint64(len(ctx.module_context.host_callbacks) - 1)
        lowering = ffi.build_ffi_lowering_function(_TARGETS[platform], has_side_effect=True)
        return lowering(ctx, words, index=index).results

    prim.def_effectful_abstract_eval(abstract)
    dispatch.simple_impl(prim)
    mlir.register_lowering(prim, lower)
    return prim


_SEND: list[Any] = []
_SEND_LOCK = threading.Lock()


def send_p() -> Any:
    with _SEND_LOCK:
        if not _SEND:
            _SEND.append(_send_primitive())
        return _SEND[0]
