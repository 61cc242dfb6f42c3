"""A host callback that XLA can keep inside a CUDA graph: a prototype, and what it costs.

`jax.experimental.io_callback` is the custom call `xla_ffi_python_gpu_callback`, which XLA
cannot record into a command buffer: a `lax.cond` whose branch holds one is run from the
host, which reads the predicate back and waits for the GPU on every step. `GraphCallback`
is an XLA FFI custom call registered from Python with ctypes, its CUDA handler declared
command-buffer compatible. Executed, or traced under stream capture when XLA records it into
a command buffer, the handler enqueues on XLA's stream copies of its operands into pinned
host memory, `seq` before and after the arrays, and then

- `host_func`: a host function (`cuLaunchHostFunc`, a ctypes callback) that copies the
  pinned bytes into a queue, emptied by a consumer thread;
- `poll`: nothing more; a host thread watches the trailing `seq` word and takes the
  payload when both words agree (a report overwritten before the thread saw it is lost and
  counted).

On the CPU the handler copies and delivers at once. The bench times a scanned step of
`--kernels` small kernels (as `_cond_sync`), each variant in a fresh process:

- `bare`: the step alone; `cond_pure`: plus a `lax.cond`, true once per `--period` steps,
  with a pure branch; `cond_io_callback`: an ordered `io_callback` in that branch (what
  the reporting wrappers do);
- `cond_graph_*`: a `GraphCallback` in that branch: `poll`, `poll_pure` (results used
  instead of `has_side_effect`), `poll_ring` (a ring of `RING` slots), `host_func`;
- `every_graph_*`: a `GraphCallback` on every step, outside any conditional.

It checks that every callback variant delivered exactly the reports of each call, in order
(`seq` and the step's number exact, the floats against a plain scan's), and with `--profile`
counts per step the graph launches and device-to-host copies of one call.

`python -m jaxmetrics.bench._graph_callback --profile --out F.json`
"""

import argparse
import collections
import ctypes
import enum
import glob
import json
import os
import platform
import queue
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

TARGET = "jaxmetrics_graph_callback"
VARIANTS = (
    "bare",
    "cond_pure",
    "cond_io_callback",
    "cond_graph_poll",
    "cond_graph_poll_pure",
    "cond_graph_poll_ring",
    "cond_graph_host_func",
    "every_graph_poll",
    "every_graph_poll_ring",
    "every_graph_host_func",
)
RING = 8  # slots of the `_ring` variants
_WORD = 4  # bytes of `seq`, an int32

# --------------------------------------------------------------------------- XLA's FFI C API
# The structs of xla/ffi/api/c_api.h that the handler reads, in their declared order.


class _ExtensionBase(ctypes.Structure):
    pass


_ExtensionBase._fields_ = [
    ("struct_size", ctypes.c_size_t),
    ("type", ctypes.c_int),
    ("next", ctypes.POINTER(_ExtensionBase)),
]
_EXTENSION_METADATA = 1
_STAGE_EXECUTE = 3
_TRAITS_COMMAND_BUFFER_COMPATIBLE = 1
_ERROR_INTERNAL = 13


class _ApiVersion(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("extension_start", ctypes.POINTER(_ExtensionBase)),
        ("major_version", ctypes.c_int),
        ("minor_version", ctypes.c_int),
    ]


class _Metadata(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("api_version", _ApiVersion),
        ("traits", ctypes.c_uint32),
    ]


class _MetadataExtension(ctypes.Structure):
    _fields_ = [("extension_base", _ExtensionBase), ("metadata", ctypes.POINTER(_Metadata))]


class _Buffer(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("extension_start", ctypes.POINTER(_ExtensionBase)),
        ("dtype", ctypes.c_int),
        ("data", ctypes.c_void_p),
        ("rank", ctypes.c_int64),
        ("dims", ctypes.POINTER(ctypes.c_int64)),
    ]


class _List(ctypes.Structure):  # XLA_FFI_Args and XLA_FFI_Rets
    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("extension_start", ctypes.POINTER(_ExtensionBase)),
        ("size", ctypes.c_int64),
        ("types", ctypes.POINTER(ctypes.c_int)),
        ("items", ctypes.POINTER(ctypes.c_void_p)),
    ]


class _ByteSpan(ctypes.Structure):
    _fields_ = [("ptr", ctypes.POINTER(ctypes.c_char)), ("len", ctypes.c_size_t)]


class _Scalar(ctypes.Structure):
    _fields_ = [("dtype", ctypes.c_int), ("value", ctypes.c_void_p)]


class _Attrs(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("extension_start", ctypes.POINTER(_ExtensionBase)),
        ("size", ctypes.c_int64),
        ("types", ctypes.POINTER(ctypes.c_int)),
        ("names", ctypes.POINTER(ctypes.POINTER(_ByteSpan))),
        ("attrs", ctypes.POINTER(ctypes.c_void_p)),
    ]


class _ContextGetArgs(ctypes.Structure):  # XLA_FFI_Stream_Get_Args, ..._DeviceOrdinal_Get_Args
    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("extension_start", ctypes.POINTER(_ExtensionBase)),
        ("ctx", ctypes.c_void_p),
        ("out", ctypes.c_void_p),
    ]


class _ErrorCreateArgs(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("extension_start", ctypes.POINTER(_ExtensionBase)),
        ("message", ctypes.c_char_p),
        ("errc", ctypes.c_int),
    ]


_GET = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.POINTER(_ContextGetArgs))
_ERROR_CREATE = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.POINTER(_ErrorCreateArgs))
_API_FIELDS = (
    "Error_GetMessage Error_Destroy Handler_Register Stream_Get TypeId_Register "
    "ExecutionContext_Get State_Set State_Get DeviceMemory_Allocate DeviceMemory_Free "
    "ThreadPool_Schedule ThreadPool_NumThreads Future_Create Future_SetAvailable "
    "Future_SetError RunId_Get DeviceOrdinal_Get"
).split()


class _Api(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("extension_start", ctypes.POINTER(_ExtensionBase)),
        ("api_version", _ApiVersion),
        ("internal_api", ctypes.c_void_p),
        ("Error_Create", _ERROR_CREATE),
        *((f, _GET if f in ("Stream_Get", "DeviceOrdinal_Get") else ctypes.c_void_p)
          for f in _API_FIELDS),
    ]  # fmt: skip


class _CallFrame(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("extension_start", ctypes.POINTER(_ExtensionBase)),
        ("api", ctypes.POINTER(_Api)),
        ("ctx", ctypes.c_void_p),
        ("stage", ctypes.c_int),
        ("args", _List),
        ("rets", _List),
        ("attrs", _Attrs),
        ("future", ctypes.c_void_p),
    ]


_HANDLER = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.POINTER(_CallFrame))


def _attr_int(attrs: _Attrs, name: str) -> int:
    """The integer scalar attribute `name` (an int64 attribute of the custom call)."""
    for i in range(attrs.size):
        span = attrs.names[i].contents
        if ctypes.string_at(span.ptr, span.len).decode() == name:
            scalar = ctypes.cast(attrs.attrs[i], ctypes.POINTER(_Scalar)).contents
            return ctypes.cast(scalar.value, ctypes.POINTER(ctypes.c_int64)).contents.value
    raise KeyError(name)


def _context_get(frame: _CallFrame, field: str) -> int:
    args = _ContextGetArgs(ctypes.sizeof(_ContextGetArgs), None, frame.ctx, None)
    err = getattr(frame.api.contents, field)(ctypes.byref(args))
    if err:
        raise RuntimeError(f"XLA_FFI_{field} failed")
    return args.out or 0


# --------------------------------------------------------------------------- the CUDA driver


class _Cuda:
    """The few driver calls the handler makes (libcuda, present wherever a GPU is)."""

    HOST_FN = ctypes.CFUNCTYPE(None, ctypes.c_void_p)
    _MEMHOSTALLOC_PORTABLE_DEVICEMAP = 0x1 | 0x2

    def __init__(self) -> None:
        lib = ctypes.CDLL("libcuda.so.1")
        self._lib = lib
        p, u, sz = ctypes.c_void_p, ctypes.c_uint, ctypes.c_size_t
        for name, args in {
            "cuInit": [u],
            "cuDeviceGet": [ctypes.POINTER(ctypes.c_int), ctypes.c_int],
            "cuDevicePrimaryCtxRetain": [ctypes.POINTER(p), ctypes.c_int],
            "cuCtxPushCurrent_v2": [p],
            "cuCtxPopCurrent_v2": [ctypes.POINTER(p)],
            "cuCtxGetCurrent": [ctypes.POINTER(p)],
            "cuMemHostAlloc": [ctypes.POINTER(p), sz, u],
            "cuMemcpyDtoHAsync_v2": [p, ctypes.c_uint64, sz, p],
            "cuLaunchHostFunc": [p, self.HOST_FN, p],
            "cuGetErrorName": [ctypes.c_int, ctypes.POINTER(ctypes.c_char_p)],
        }.items():
            fn = getattr(lib, name)
            fn.argtypes, fn.restype = args, ctypes.c_int
        self.check(lib.cuInit(0), "cuInit")
        self._contexts: dict[int, ctypes.c_void_p] = {}

    def check(self, rc: int, what: str) -> None:
        if rc:
            name = ctypes.c_char_p()
            self._lib.cuGetErrorName(rc, ctypes.byref(name))
            raise RuntimeError(f"{what}: CUDA error {rc} {(name.value or b'').decode()}")

    def context(self, ordinal: int) -> ctypes.c_void_p:
        if ordinal not in self._contexts:
            dev, ctx = ctypes.c_int(), ctypes.c_void_p()
            self.check(self._lib.cuDeviceGet(ctypes.byref(dev), ordinal), "cuDeviceGet")
            rc = self._lib.cuDevicePrimaryCtxRetain(ctypes.byref(ctx), dev)
            self.check(rc, "cuDevicePrimaryCtxRetain")
            self._contexts[ordinal] = ctx
        return self._contexts[ordinal]

    def pinned(self, ordinal: int, nbytes: int) -> int:
        """Page-locked host memory, mapped into the device's address space: a graph's memcpy
        nodes may only reach such host memory."""
        ptr = ctypes.c_void_p()
        with self.current(ordinal):
            rc = self._lib.cuMemHostAlloc(
                ctypes.byref(ptr), nbytes, self._MEMHOSTALLOC_PORTABLE_DEVICEMAP
            )
        self.check(rc, "cuMemHostAlloc")
        ctypes.memset(ptr.value, 0, nbytes)
        return int(ptr.value)

    def current(self, ordinal: int) -> "_Current":
        return _Current(self, ordinal)

    def copy_to_host(self, dst: int, src: int, nbytes: int, stream: int) -> None:
        rc = self._lib.cuMemcpyDtoHAsync_v2(dst, src, nbytes, stream)
        self.check(rc, "cuMemcpyDtoHAsync")

    def launch_host_func(self, stream: int, fn: Any, user_data: int) -> None:
        self.check(self._lib.cuLaunchHostFunc(stream, fn, user_data), "cuLaunchHostFunc")


class _Current:
    """Makes the device's primary context current on this thread if none is (XLA's threads
    normally have one)."""

    def __init__(self, cuda: _Cuda, ordinal: int) -> None:
        self.cuda, self.ordinal, self.pushed = cuda, ordinal, False

    def __enter__(self) -> None:
        cur = ctypes.c_void_p()
        self.cuda.check(self.cuda._lib.cuCtxGetCurrent(ctypes.byref(cur)), "cuCtxGetCurrent")
        if not cur.value:
            ctx = self.cuda.context(self.ordinal)
            self.cuda.check(self.cuda._lib.cuCtxPushCurrent_v2(ctx), "cuCtxPushCurrent")
            self.pushed = True

    def __exit__(self, *exc: Any) -> None:
        if self.pushed:
            self.cuda._lib.cuCtxPopCurrent_v2(ctypes.byref(ctypes.c_void_p()))


# --------------------------------------------------------------------------- the callback


class Mode(enum.Enum):
    HOST_FUNC = "host_func"
    POLL = "poll"


class GraphCallback:
    """`cb(seq, *arrays)` in a jitted function hands `(seq, arrays)` to `consumer` on a host
    thread; it returns its operands (aliased: no copy), which a caller that sets
    `has_side_effect=False` must use.

    Args:
      consumer: called on the consumer thread with `(seq: int, arrays: tuple[np.ndarray])`,
        in the order of `seq`.
      shapes: the arrays' `jax.ShapeDtypeStruct`s, fixed (the pinned staging area is
        allocated when the callback is built, as a stream being captured may not allocate).
      mode: `Mode.HOST_FUNC` or `Mode.POLL` (see the module's docstring).
      slots: `POLL` mode: a ring of this many staging slots, report `seq` into slot
        `seq % slots` (a `lax.switch` over one custom call per slot), so the poll thread may
        fall `slots - 1` reports behind before one is lost.
      has_side_effect: whether the custom call is kept when its results are unused.
      poll_interval_s: the poll thread's sleep between looks.

    `seq` is an int32 scalar that starts at 1 and grows by 1 per report (the poll thread
    tells new reports and lost ones by it). `drain()`, after the device has finished, waits
    until every report has reached `consumer`; `reset_sequence()` before work whose `seq`
    starts again; `close()` stops the threads. `lost` counts the reports overwritten before
    the poll thread saw them.
    """

    def __init__(
        self,
        consumer: Callable[[int, tuple[np.ndarray, ...]], None],
        shapes: Sequence[Any],
        mode: Mode = Mode.POLL,
        slots: int = 1,
        has_side_effect: bool = True,
        poll_interval_s: float = 1e-4,
    ) -> None:
        import jax

        if slots < 1 or (slots > 1 and mode is not Mode.POLL):
            raise ValueError("GraphCallback: `slots` > 1 needs Mode.POLL.")
        _register()
        self.mode, self.slots, self.has_side_effect = mode, slots, has_side_effect
        self.poll_interval_s = poll_interval_s
        self._consumer = consumer
        self._shapes = tuple(jax.ShapeDtypeStruct(s.shape, s.dtype) for s in shapes)
        self._sizes = [int(np.prod(s.shape)) * np.dtype(s.dtype).itemsize for s in shapes]
        self.nbytes = _WORD + sum(self._sizes) + _WORD
        self.lost = 0
        self._pinned: dict[tuple[str, int], int] = {}
        self._cpu_buffer = ctypes.create_string_buffer(self.nbytes * slots)
        self._pinned["cpu", 0] = ctypes.addressof(self._cpu_buffer)
        cuda = _cuda()
        if cuda is not None:
            for d in jax.local_devices(backend="gpu"):
                ordinal = d.local_hardware_id
                self._pinned["cuda", ordinal] = cuda.pinned(ordinal, self.nbytes * slots)
        self._queue: queue.Queue[bytes | None] = queue.Queue()
        self._stop = threading.Event()
        self._seen: dict[int, int] = {}
        self._lock = threading.Lock()
        self._threads = [threading.Thread(target=self._consume, daemon=True)]
        if mode is Mode.POLL and cuda is not None:
            self._threads.append(threading.Thread(target=self._poll, daemon=True))
        for t in self._threads:
            t.start()
        with _SITES_LOCK:
            self.site = len(_SITES)
            _SITES.append(self)

    def __call__(self, seq: Any, *arrays: Any) -> tuple[Any, ...]:
        import jax
        import jax.numpy as jnp

        seq = jnp.asarray(seq, jnp.int32).reshape(())
        got = tuple(jax.ShapeDtypeStruct(jnp.shape(a), jnp.result_type(a)) for a in arrays)
        if got != self._shapes:
            raise ValueError(f"GraphCallback: built for {self._shapes}, called with {got}")
        call = jax.ffi.ffi_call(
            TARGET,
            (jax.ShapeDtypeStruct((), jnp.int32), *self._shapes),
            has_side_effect=self.has_side_effect,
            input_output_aliases={i: i for i in range(len(arrays) + 1)},
        )

        def into(slot: int) -> Callable[..., tuple[Any, ...]]:
            return lambda *ops: tuple(call(*ops, site=np.int64(self.site), slot=np.int64(slot)))

        if self.slots == 1:
            return into(0)(seq, *arrays)
        index = jax.lax.rem(seq, jnp.int32(self.slots))
        return jax.lax.switch(index, [into(i) for i in range(self.slots)], seq, *arrays)

    # ----------------------------------------------------------------- the host side

    def _deliver(self, raw: bytes) -> None:
        self._queue.put(raw)

    def _consume(self) -> None:
        while (raw := self._queue.get()) is not None:
            try:
                seq = int(np.frombuffer(raw[:_WORD], np.int32)[0])
                arrays, offset = [], _WORD
                for s, n in zip(self._shapes, self._sizes, strict=True):
                    arrays.append(np.frombuffer(raw[offset : offset + n], s.dtype).reshape(s.shape))
                    offset += n
                self._consumer(seq, tuple(arrays))
            finally:
                self._queue.task_done()
        self._queue.task_done()

    def _take(self, ordinal: int) -> None:
        """POLL mode: the new whole reports in the device's ring, in order of `seq`. The
        device writes a slot's leading `seq`, its arrays, then its trailing `seq`, in stream
        order; a slot whose two words differ is being rewritten with its leading `seq`, and
        the reports from there on wait for the next look."""
        base, last = self._pinned["cuda", ordinal], self._seen.get(ordinal, 0)
        whole, torn = [], []
        for i in range(self.slots):
            ptr = base + i * self.nbytes
            end = ctypes.c_int32.from_address(ptr + self.nbytes - _WORD).value
            raw = ctypes.string_at(ptr, self.nbytes)
            begin = int(np.frombuffer(raw[:_WORD], np.int32)[0])
            if begin != end or ctypes.c_int32.from_address(ptr).value != end:
                torn.append(min(begin, ctypes.c_int32.from_address(ptr).value))
            elif end > last:
                whole.append((end, raw[: self.nbytes - _WORD]))
        for seq, raw in sorted(whole):
            if torn and seq > min(torn):
                break
            self.lost += seq - last - 1
            self._deliver(raw)
            last = seq
        self._seen[ordinal] = last

    def _ordinals(self) -> list[int]:
        return [k[1] for k in self._pinned if k[0] == "cuda"]

    def _poll(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                for ordinal in self._ordinals():
                    self._take(ordinal)
            time.sleep(self.poll_interval_s)

    def drain(self) -> None:
        """Every report of the finished device work handed to the consumer."""
        if self.mode is Mode.POLL:
            with self._lock:
                for ordinal in self._ordinals():
                    self._take(ordinal)
        self._queue.join()

    def reset_sequence(self) -> None:
        """Forget the last `seq` seen (before work whose `seq` starts at 1 again)."""
        with self._lock:
            self._seen.clear()
            for ptr in self._pinned.values():
                ctypes.memset(ptr, 0, self.nbytes * self.slots)

    def close(self) -> None:
        self._stop.set()
        self._queue.put(None)
        for t in self._threads:
            t.join()

    # ----------------------------------------------------------------- the device side

    def enqueue(self, frame: _CallFrame, platform_: str) -> None:
        """The handler's work for this site: copy the operands out, then notify."""
        buffers = [
            ctypes.cast(frame.args.items[i], ctypes.POINTER(_Buffer)).contents
            for i in range(frame.args.size)
        ]
        pieces = [(buffers[0].data, _WORD)]
        pieces += [(b.data, n) for b, n in zip(buffers[1:], self._sizes, strict=True)]
        pieces.append((buffers[0].data, _WORD))
        offset = _attr_int(frame.attrs, "slot") * self.nbytes
        if platform_ == "cpu":
            dst = start = self._pinned["cpu", 0] + offset
            for src, n in pieces:
                ctypes.memmove(dst, src, n)
                dst += n
            self._deliver(ctypes.string_at(start, self.nbytes - _WORD))
            return
        cuda = _cuda()
        assert cuda is not None
        ordinal = _context_get(frame, "DeviceOrdinal_Get")
        stream = _context_get(frame, "Stream_Get")
        dst = self._pinned["cuda", ordinal] + offset
        with cuda.current(ordinal):
            for src, n in pieces:
                cuda.copy_to_host(dst, src, n, stream)
                dst += n
            if self.mode is Mode.HOST_FUNC:
                cuda.launch_host_func(stream, _HOST_FUNC, self.site << 8 | ordinal)


def _on_host(user_data: int | None) -> None:
    """The host function: runs on CUDA's thread between the stream's work, so it only copies
    the staged bytes into the queue (no CUDA call may be made here)."""
    key = user_data or 0
    site = _SITES[key >> 8]
    ptr = site._pinned["cuda", key & 0xFF]
    site._deliver(ctypes.string_at(ptr, site.nbytes - _WORD))


_HOST_FUNC = _Cuda.HOST_FN(_on_host)
_SITES: list[GraphCallback] = []
_SITES_LOCK = threading.Lock()
_STATE: dict[str, Any] = {}
# How often XLA called the handler, by platform and stage: once per report when XLA runs the
# custom call itself, once per trace when it records it into a command buffer.
_CALLS: collections.Counter[str] = collections.Counter()


def _cuda() -> _Cuda | None:
    """The driver, when JAX has a GPU backend."""
    if "cuda" not in _STATE:
        import jax

        try:
            has_gpu = bool(jax.devices("gpu"))
        except RuntimeError:
            has_gpu = False
        _STATE["cuda"] = _Cuda() if has_gpu else None
    return _STATE["cuda"]


def _handler(platform_: str) -> Callable[[Any], int | None]:
    def handle(frame_ptr: Any) -> int | None:
        frame = frame_ptr.contents
        try:
            ext = frame.extension_start
            if ext and ext.contents.type == _EXTENSION_METADATA:
                _CALLS[f"{platform_}:metadata"] += 1
                # XLA's first call asks for the API version and the handler's traits.
                meta = ctypes.cast(ext, ctypes.POINTER(_MetadataExtension)).contents.metadata
                meta.contents.api_version.major_version = 0
                meta.contents.api_version.minor_version = 1
                if platform_ == "cuda":
                    meta.contents.traits = _TRAITS_COMMAND_BUFFER_COMPATIBLE
                return None
            _CALLS[f"{platform_}:stage{frame.stage}"] += 1
            if frame.stage != _STAGE_EXECUTE:
                return None
            _SITES[_attr_int(frame.attrs, "site")].enqueue(frame, platform_)
            return None
        except Exception as e:  # noqa: BLE001 - an exception may not cross into XLA
            args = _ErrorCreateArgs(
                ctypes.sizeof(_ErrorCreateArgs), None, f"{TARGET}: {e!r}".encode(), _ERROR_INTERNAL
            )
            return frame.api.contents.Error_Create(ctypes.byref(args))

    return handle


def _register() -> None:
    """Registers the handler for the CPU and for CUDA, once per process."""
    if "handlers" in _STATE:
        return
    import jax

    handlers = {p: _HANDLER(_handler(p)) for p in ("cpu", "cuda")}
    for p, h in handlers.items():
        capsule = jax.ffi.pycapsule(ctypes.cast(h, ctypes.c_void_p).value)
        jax.ffi.register_ffi_target(TARGET, capsule, platform="CUDA" if p == "cuda" else "cpu")
    _STATE["handlers"] = handlers


# --------------------------------------------------------------------------- the bench


def _payload(x: Any, t: Any, seq: Any) -> tuple[Any, Any]:
    """What a report hands the host, shaped like `_transfer`'s: floats and uint32 words."""
    import jax.numpy as jnp

    words = jnp.stack([t, seq]).astype(jnp.uint32)[:, None]
    return x[:8], words


def measure(
    variant: str, kernels: int, envs: int, steps: int, period: int, repeats: int, profile: bool
) -> dict[str, Any]:
    """One variant, in this process: us per step, and the reports each call delivered
    against those a plain scan computes."""
    import jax
    import jax.numpy as jnp

    from ._env_sync import hlo_summary, trace_counts

    every = variant.startswith("every_")
    got: list[tuple[int, np.ndarray, np.ndarray]] = []

    def receive(seq: int, arrays: tuple[np.ndarray, ...]) -> None:
        got.append((seq, np.array(arrays[0]), np.array(arrays[1])))

    def receive_io(floats: np.ndarray, words: np.ndarray) -> None:
        got.append((int(words[1, 0]), np.array(floats), np.array(words)))

    shapes = (jax.ShapeDtypeStruct((8,), jnp.float32), jax.ShapeDtypeStruct((2, 1), jnp.uint32))
    cb = None
    if "graph" in variant:
        mode = Mode.HOST_FUNC if variant.endswith("host_func") else Mode.POLL
        slots = RING if variant.endswith("_ring") else 1
        pure = variant.endswith("_pure")
        cb = GraphCallback(receive, shapes, mode, slots, has_side_effect=not pure)

    def step(x: Any) -> Any:
        # The barriers keep each operation a kernel of its own, as a launch-bound env is.
        for i in range(kernels):
            x = jax.lax.optimization_barrier(jnp.sin(x) * jnp.float32(0.999) + jnp.float32(i))
        return x

    def report(x: Any) -> Any:
        return jnp.sum(x[:8], dtype=jnp.float32)[None]

    def body(carry: Any, _: Any, check: bool = False) -> Any:
        x, t, acc = carry
        x = step(x)
        t = t + 1
        when = t % period == 0
        seq = t if every else t // period
        if variant == "cond_pure":
            acc = jax.lax.cond(when, lambda: acc + report(x), lambda: acc)
        elif variant == "cond_io_callback":

            def fire():
                floats, words = _payload(x, t, seq)
                jax.experimental.io_callback(receive_io, None, floats, words, ordered=True)
                return acc + report(x)

            acc = jax.lax.cond(when, fire, lambda: acc)
        elif variant.startswith("cond_graph"):

            def fire_graph():
                _, floats, _ = cb(seq, *_payload(x, t, seq))
                return acc + jnp.sum(floats, dtype=jnp.float32)[None]

            acc = jax.lax.cond(when, fire_graph, lambda: acc)
        elif every:
            _, floats, _ = cb(seq, *_payload(x, t, seq))
            acc = acc + jnp.sum(floats, dtype=jnp.float32)[None]
        return (x, t, acc), (x[:8] if check else None)

    carry0 = (jnp.ones((envs,), jnp.float32), jnp.int32(0), jnp.zeros((1,), jnp.float32))
    ref = jax.jit(lambda c: jax.lax.scan(lambda c, _: body(c, _, True), c, None, length=steps))
    t0 = time.perf_counter()
    compiled = jax.jit(lambda c: jax.lax.scan(body, c, None, length=steps)[0]).lower(carry0)
    compiled = compiled.compile()
    compile_s = time.perf_counter() - t0

    expected = []
    if variant not in ("bare", "cond_pure"):
        # The reference scan makes the callbacks too; what they deliver is dropped.
        ys = np.asarray(ref(carry0)[1])
        jax.effects_barrier()
        if cb is not None:
            cb.drain()
        got.clear()
        for t in range(1, steps + 1):
            if every or t % period == 0:
                seq = t if every else t // period
                words = np.array([[t], [seq]], np.uint32)
                expected.append((seq, ys[t - 1], words))

    checks = []

    def one_call() -> float:
        got.clear()
        if cb is not None:
            cb.reset_sequence()
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(carry0))
        elapsed = time.perf_counter() - t0
        jax.effects_barrier()
        if cb is not None:
            cb.drain()
        if expected:
            checks.append(_compare(got, expected))
        return elapsed

    one_call()
    times = [one_call() for _ in range(repeats)]
    row: dict[str, Any] = {
        "variant": variant,
        "us_per_step": float(np.median(times)) / steps * 1e6,
        "us_per_step_all": [t / steps * 1e6 for t in times],
        "compile_s": compile_s,
        "hlo_summary": hlo_summary(compiled.as_text()),
        "reports_per_call": len(expected),
    }
    if profile:
        options = jax.profiler.ProfileOptions()
        options.python_tracer_level = 0
        with tempfile.TemporaryDirectory() as d:
            with jax.profiler.trace(d, profiler_options=options):
                traced_s = one_call()
            (path,) = glob.glob(os.path.join(d, "**", "*.xplane.pb"), recursive=True)
            counts = trace_counts(path, steps)
        counts.pop("lines")
        row["trace_counts"] = {**counts, "us_per_step_traced": traced_s / steps * 1e6}
    row["handler_calls"] = dict(_CALLS)
    if expected:
        row["checks"] = checks
        row["delivered_right"] = all(c == "ok" for c in checks)
        row["lost"] = 0 if cb is None else cb.lost
    if cb is not None:
        cb.close()
    return row


def _compare(got: list, expected: list) -> str:
    """ "ok", or what differs between the delivered reports and the expected ones."""
    if len(got) != len(expected):
        seqs = [g[0] for g in got]
        return f"{len(got)} reports, expected {len(expected)}; seqs {seqs[:10]}..."
    for g, e in zip(got, expected, strict=True):
        if g[0] != e[0] or not np.array_equal(g[2], e[2]) or not np.array_equal(g[1], e[1]):
            return f"report {g[0]} differs: got {g[1]} {g[2].ravel()}, want {e[1]} {e[2].ravel()}"
    return "ok"


def environment() -> dict[str, Any]:
    import jax

    return {
        "device": str(jax.devices()[0].device_kind),
        "host": platform.node(),
        "jax": jax.__version__,
        "jaxlib": getattr(jax.lib, "__version__", None) or jax.__version__,
    }


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--variants", default=",".join(VARIANTS))
    p.add_argument("--kernels", type=int, default=100)
    p.add_argument("--envs", type=int, default=2048)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--period", type=int, default=100)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--profile", action="store_true")
    p.add_argument("--variant-timeout", type=float, default=120.0)
    p.add_argument("--xla-flags", default="")
    p.add_argument("--commit")
    p.add_argument("--out")
    p.add_argument("--child", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    sizes = {k: getattr(a, k) for k in ("kernels", "envs", "steps", "period", "repeats")}
    if a.child:
        print(json.dumps(measure(a.child, **sizes, profile=a.profile)))
        return 0
    doc: dict[str, Any] = {
        "benchmark": "graph_callback",
        "environment": environment(),
        "commit": a.commit,
        "xla_flags": a.xla_flags,
        "sizes": sizes,
        "rows": [],
    }
    env = {**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    env["XLA_FLAGS"] = " ".join(filter(None, (os.environ.get("XLA_FLAGS"), a.xla_flags)))
    for variant in a.variants.split(","):
        flags = [f"--{k}={v}" for k, v in sizes.items()] + (["--profile"] if a.profile else [])
        cmd = [sys.executable, "-m", "jaxmetrics.bench._graph_callback", "--child", variant, *flags]
        t0 = time.time()
        try:
            done = subprocess.run(
                cmd, env=env, timeout=a.variant_timeout, capture_output=True, text=True
            )
            lines = done.stdout.strip().splitlines()
            if done.returncode or not lines:
                row = {"variant": variant, "error": f"rc {done.returncode}: {done.stderr[-3000:]}"}
            else:
                row = json.loads(lines[-1])
        except subprocess.TimeoutExpired as e:
            tail = (e.stderr or b"")[-3000:]
            row = {"variant": variant, "error": f"timed out after {a.variant_timeout} s: {tail!r}"}
        row["wall_s"] = time.time() - t0
        doc["rows"].append(row)
        if "error" in row:
            print(f"{variant}: ERROR {row['error']}", flush=True)
        else:
            tc = row.get("trace_counts", {})
            print(
                f"{variant}: {row['us_per_step']:.2f} us/step"
                f" delivered_right={row.get('delivered_right')} lost={row.get('lost')}"
                f" graph_launches={tc.get('graph_launches_per_step')}"
                f" d2h={tc.get('memcpy_d2h_per_step')} hlo={row['hlo_summary']}"
                f" checks={sorted(set(row.get('checks', [])))[:2]}"
                f" handler_calls={row['handler_calls']} tc={tc}",
                flush=True,
            )
        if a.out:
            with open(a.out, "w") as f:
                json.dump(doc, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
