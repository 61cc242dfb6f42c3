"""The CUDA side of the report channel: pinned rings and the kernel that writes them.

Inside a CUDA graph's conditional node only kernels, copies, memsets and nested graphs may
run, never a host function; so a report leaves the device as a kernel that writes it
through a device-mapped pointer into pinned host memory (`_ring` has the layout), where a
host thread picks it up. The kernel is PTX text, loaded with the driver API (libcuda,
present wherever an NVIDIA GPU is), and launched from a `buffer_callback` that XLA traces
into its command buffer once: no toolkit, compiler or C extension is needed.
"""

import ctypes
import functools
import threading
from typing import Any

# One block: thread 0 bumps the ring's counter and then the device's order word (each with
# an atomic add, so that two report kernels the device runs at once never share a seq or a
# stamp; a system-scope fence between them, so that the host never sees the stamp taken
# before the ring's counter: `_ring.Merge` relies on it), and writes `head`; all threads copy
# the payload, thread 0 the stamp; each fences at system scope (so the host sees the words in
# this order), then thread 0 writes `tail`. Reports are O(metrics) words, so one block of 256
# threads is plenty.
_PTX = r"""
.version 7.0
.target sm_70
.address_size 64

.visible .entry jaxmetrics_ring_put(
    .param .u64 src_param,
    .param .u64 ring_param,
    .param .u64 order_param,
    .param .u32 words_param,
    .param .u32 slots_param
)
{
    .reg .pred %p<3>;
    .reg .b32 %r<13>;
    .reg .b64 %rd<11>;
    .shared .align 4 .b32 seq_shared;
    .shared .align 4 .b32 stamp_shared;

    ld.param.u64 %rd1, [src_param];
    ld.param.u64 %rd2, [ring_param];
    ld.param.u64 %rd9, [order_param];
    ld.param.u32 %r1, [words_param];
    ld.param.u32 %r2, [slots_param];
    mov.u32 %r3, %tid.x;
    mov.u32 %r4, %ntid.x;
    setp.ne.u32 %p1, %r3, 0;
    @%p1 bra BUMPED;
    atom.add.u32 %r5, [%rd2], 1;
    add.u32 %r5, %r5, 1;
    membar.sys;
    atom.add.u32 %r11, [%rd9], 1;
    add.u32 %r11, %r11, 1;
    st.shared.u32 [seq_shared], %r5;
    st.shared.u32 [stamp_shared], %r11;
BUMPED:
    bar.sync 0;
    ld.shared.u32 %r5, [seq_shared];
    sub.u32 %r6, %r5, 1;
    rem.u32 %r6, %r6, %r2;
    add.u32 %r7, %r1, 3;
    mul.lo.u32 %r8, %r6, %r7;
    add.u32 %r8, %r8, 4;
    mul.wide.u32 %rd3, %r8, 4;
    add.u64 %rd3, %rd2, %rd3;
    @%p1 bra HEADED;
    st.volatile.u32 [%rd3], %r5;
    membar.sys;
HEADED:
    bar.sync 0;
    add.u64 %rd4, %rd3, 8;
    @%p1 bra STAMPED;
    ld.shared.u32 %r12, [stamp_shared];
    st.volatile.u32 [%rd3+4], %r12;
STAMPED:
    mov.u32 %r9, %r3;
COPY:
    setp.ge.u32 %p2, %r9, %r1;
    @%p2 bra COPIED;
    mul.wide.u32 %rd5, %r9, 4;
    add.u64 %rd6, %rd1, %rd5;
    ld.u32 %r10, [%rd6];
    add.u64 %rd7, %rd4, %rd5;
    st.volatile.u32 [%rd7], %r10;
    add.u32 %r9, %r9, %r4;
    bra COPY;
COPIED:
    membar.sys;
    bar.sync 0;
    @%p1 bra DONE;
    mul.wide.u32 %rd8, %r1, 4;
    add.u64 %rd8, %rd4, %rd8;
    st.volatile.u32 [%rd8], %r5;
    membar.sys;
DONE:
    ret;
}
"""
_KERNEL = b"jaxmetrics_ring_put"
_THREADS = 256
_MEMHOSTALLOC_PORTABLE_DEVICEMAP = 0x1 | 0x2


class CudaError(RuntimeError):
    """A CUDA driver call failed (named in the message with its error code)."""


class Driver:
    """The few CUDA driver calls the channel makes, through ctypes."""

    def __init__(self) -> None:
        lib = ctypes.CDLL("libcuda.so.1")
        p, u, i, sz = ctypes.c_void_p, ctypes.c_uint, ctypes.c_int, ctypes.c_size_t
        pp = ctypes.POINTER(p)
        signatures: dict[str, list[Any]] = {
            "cuInit": [u],
            "cuDriverGetVersion": [ctypes.POINTER(i)],
            "cuDeviceGet": [ctypes.POINTER(i), i],
            "cuDevicePrimaryCtxRetain": [pp, i],
            "cuCtxPushCurrent_v2": [p],
            "cuCtxPopCurrent_v2": [pp],
            "cuCtxGetDevice": [ctypes.POINTER(i)],
            "cuMemHostAlloc": [pp, sz, u],
            "cuMemFreeHost": [p],
            "cuModuleLoadData": [pp, ctypes.c_char_p],
            "cuModuleGetFunction": [pp, p, ctypes.c_char_p],
            "cuLaunchKernel": [p, u, u, u, u, u, u, u, p, pp, pp],
            "cuGetErrorName": [i, ctypes.POINTER(ctypes.c_char_p)],
        }
        for name, args in signatures.items():
            fn = getattr(lib, name)
            fn.argtypes, fn.restype = args, ctypes.c_int
        self._lib = lib
        self._check(lib.cuInit(0), "cuInit")
        self._lock = threading.Lock()
        self._contexts: dict[int, ctypes.c_void_p] = {}
        self._kernels: dict[int, ctypes.c_void_p] = {}

    def _check(self, rc: int, what: str) -> None:
        if rc:
            name = ctypes.c_char_p()
            self._lib.cuGetErrorName(rc, ctypes.byref(name))
            raise CudaError(f"{what} failed: CUDA error {rc} {(name.value or b'?').decode()}")

    def version(self) -> int:
        """The driver's CUDA version, e.g. 12080 for 12.8."""
        out = ctypes.c_int()
        self._check(self._lib.cuDriverGetVersion(ctypes.byref(out)), "cuDriverGetVersion")
        return out.value

    def _context(self, ordinal: int) -> ctypes.c_void_p:
        if ordinal not in self._contexts:
            dev, ctx = ctypes.c_int(), ctypes.c_void_p()
            self._check(self._lib.cuDeviceGet(ctypes.byref(dev), ordinal), "cuDeviceGet")
            rc = self._lib.cuDevicePrimaryCtxRetain(ctypes.byref(ctx), dev)
            self._check(rc, "cuDevicePrimaryCtxRetain")
            self._contexts[ordinal] = ctx
        return self._contexts[ordinal]

    def prepare(self, ordinal: int) -> None:
        """Loads the kernel into device `ordinal`'s primary context (JAX's context), once:
        a stream being captured into a graph may not load modules."""
        with self._lock:
            if ordinal in self._kernels:
                return
            self._check(self._lib.cuCtxPushCurrent_v2(self._context(ordinal)), "cuCtxPush")
            try:
                module, kernel = ctypes.c_void_p(), ctypes.c_void_p()
                rc = self._lib.cuModuleLoadData(ctypes.byref(module), _PTX.encode())
                self._check(rc, "cuModuleLoadData")
                rc = self._lib.cuModuleGetFunction(ctypes.byref(kernel), module, _KERNEL)
                self._check(rc, "cuModuleGetFunction")
            finally:
                self._lib.cuCtxPopCurrent_v2(ctypes.byref(ctypes.c_void_p()))
            self._kernels[ordinal] = kernel

    def pinned(self, nbytes: int) -> int:
        """Zeroed page-locked host memory, mapped into every device's address space
        (portable): the kernel writes it through the same address (unified addressing)."""
        ptr = ctypes.c_void_p()
        with self._lock:
            self._check(self._lib.cuCtxPushCurrent_v2(self._context(0)), "cuCtxPush")
            try:
                rc = self._lib.cuMemHostAlloc(
                    ctypes.byref(ptr), nbytes, _MEMHOSTALLOC_PORTABLE_DEVICEMAP
                )
            finally:
                self._lib.cuCtxPopCurrent_v2(ctypes.byref(ctypes.c_void_p()))
        self._check(rc, "cuMemHostAlloc")
        assert ptr.value is not None  # allocated
        ctypes.memset(ptr.value, 0, nbytes)
        return int(ptr.value or 0)

    def free_pinned(self, address: int) -> None:
        """Frees memory of `pinned` (once nothing can write it any more)."""
        with self._lock:
            self._check(self._lib.cuCtxPushCurrent_v2(self._context(0)), "cuCtxPush")
            try:
                rc = self._lib.cuMemFreeHost(ctypes.c_void_p(address))
            finally:
                self._lib.cuCtxPopCurrent_v2(ctypes.byref(ctypes.c_void_p()))
        self._check(rc, "cuMemFreeHost")

    def current_device(self) -> int:
        """The ordinal of the device whose context is current on this thread (XLA makes its
        device's context current before it runs or traces a custom call)."""
        out = ctypes.c_int()
        self._check(self._lib.cuCtxGetDevice(ctypes.byref(out)), "cuCtxGetDevice")
        return out.value

    def put(self, stream: int, src: int, ring: int, order: int, words: int, slots: int) -> None:
        """Enqueues on `stream` the kernel that writes the `words` uint32 words at device
        address `src` into the ring at `ring` as its next report, stamped from the order
        word at `order`."""
        kernel = self._kernels[self.current_device()]
        args = (
            ctypes.c_uint64(src),
            ctypes.c_uint64(ring),
            ctypes.c_uint64(order),
            ctypes.c_uint32(words),
            ctypes.c_uint32(slots),
        )
        params = (ctypes.c_void_p * len(args))(*(ctypes.addressof(a) for a in args))
        rc = self._lib.cuLaunchKernel(
            kernel, 1, 1, 1, _THREADS, 1, 1, 0, ctypes.c_void_p(stream), params, None
        )
        self._check(rc, "cuLaunchKernel")


@functools.cache
def driver() -> Driver:
    """The process's driver (loaded once; raises OSError where there is no libcuda)."""
    return Driver()
