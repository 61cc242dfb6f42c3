"""The report channel: how a report made inside a jitted program reaches the host.

Two channels carry the same payload (a pytree of small arrays) to the same host function:

- `"ring"`: the payload is written into a ring of slots in host memory by the device
  itself (on a CUDA GPU, a kernel writing through a device-mapped pointer into pinned
  memory, `_cuda`; on the CPU, a host function writing the same words), and a host thread
  takes whole reports from it (`_ring`) and hands them on in order: each payload layout
  has a ring of its own, and a stamp that every report takes from one counter per device
  puts the rings' reports back into the order the device sent them. On a GPU nothing in
  the program waits for the host: XLA records the kernel into its CUDA graph, inside the
  conditional of a period end, so a step that reports nothing costs no host round trip.
- `"io_callback"`: an ordered `io_callback`, portable. On a GPU, XLA cannot record a host
  callback into a CUDA graph, so a `lax.cond` whose branch holds one is run from the host:
  the predicate is copied back and the GPU waited for on every evaluation, reported or not.

`"auto"` takes the ring on a CUDA GPU with a driver of CUDA `MIN_CUDA_DRIVER` or later and
command buffers not turned off, where the ring passes its self-test (`self_test`: a report
sent from a jitted program comes back whole), and the `io_callback` elsewhere;
`Choice.reason` says why. The ring's primitive is built from JAX internals
(`_ring_send.private_jax`), so a JAX release that changes them is caught by the self-test, not by a
list of tested versions: the ring then falls back, with the reason.

The ring loses a report only when the host falls more than `slots` reports behind the
device; the reports after it say so (their `seq` skips), and `take_lost` counts them.

A record the host makes itself (`Logger.flush`) follows the reports of the programs
dispatched before it: `in_order` waits for those programs and delivers their reports before
the record is queued, and delivers no later one until it is.
"""

import contextlib
import logging
import os
import threading
import weakref
from collections.abc import Callable, Iterator
from typing import Any, NamedTuple

import jax
import numpy as np
from jax.experimental import io_callback

from .._core._validate import is_int
from . import _ring_send

MIN_CUDA_DRIVER = 12030
"""CUDA 12.3: the first with conditional nodes in CUDA graphs, which XLA's `lax.cond`
needs to stay inside a graph."""
CHANNELS = ("auto", "ring", "io_callback")
DEFAULT_SLOTS = 64
POLL_S = 1e-3
"""The ring reader's look interval while reports arrive: a report is lost when the device
makes more than `slots` of them between two looks."""
IDLE_POLL_S = 32e-3
"""The longest interval between looks, reached by doubling after each look that found
nothing: idle Loggers that poll at 1 kHz for the process's life take a CPU core's share and
the GIL from the program (20 of them: 26% of a core, a CPU-bound JAX loop 28% slower). At
most 32 ms of reports (64 slots: over 2,000 a second) can pile up before the reader is back
at `POLL_S`."""
SELF_TEST_TIMEOUT_S = 120.0
"""How long the self-test's round trip may take (a compile and one run) before the ring is
judged not to work."""

_log = logging.getLogger("jaxmetrics")


class Choice(NamedTuple):
    """The channel a Logger's in-graph reports take, and why."""

    kind: str  # "ring" or "io_callback"
    reason: str


def choose(requested: str) -> Choice:
    """The channel for `requested` ("auto", "ring" or "io_callback") on this process's
    default backend."""
    if requested == "io_callback":
        return Choice("io_callback", "report_channel='io_callback' was asked for")
    backend = jax.default_backend()
    if requested == "ring":
        if backend not in ("cpu", "gpu") or (backend == "gpu" and _gpu_platform() != "cuda"):
            raise ValueError(
                f"report_channel='ring' runs on CUDA GPUs and on the CPU, not on "
                f"{backend} ({_gpu_platform() if backend == 'gpu' else backend}); use "
                "report_channel='auto' or 'io_callback'."
            )
        if (failed := self_test()) is not None:
            raise RuntimeError(
                f"report_channel='ring' does not work with JAX {jax.__version__} here: "
                f"{failed}. Use report_channel='auto' (which falls back to the io_callback) "
                "or 'io_callback'."
            )
        return Choice("ring", "report_channel='ring' was asked for")
    if backend != "gpu" or _gpu_platform() != "cuda":
        return Choice("io_callback", f"the default backend is {backend}, not a CUDA GPU")
    try:
        from . import _cuda

        driver = _cuda.driver().version()
    except (ImportError, AttributeError, OSError, RuntimeError) as e:
        return Choice("io_callback", f"the ring could not load: {e}")
    if driver < MIN_CUDA_DRIVER:
        return Choice("io_callback", f"the CUDA driver is {driver}, below {MIN_CUDA_DRIVER}")
    flags = os.environ.get("XLA_FLAGS", "")
    for flag in flags.split():
        if flag.startswith("--xla_gpu_enable_command_buffer="):
            kinds = flag.split("=", 1)[1].upper().split(",")
            if "CONDITIONAL" not in kinds or "CUSTOM_CALL" not in kinds:
                return Choice(
                    "io_callback", f"{flag} leaves conditionals or custom calls out of graphs"
                )
    if (failed := self_test()) is not None:
        return Choice(
            "io_callback", f"the ring fails its self-test on JAX {jax.__version__}: {failed}"
        )
    return Choice("ring", f"CUDA driver {driver}, JAX {jax.__version__}: the self-test passed")


_SELF_TESTS: dict[str, str | None] = {}
_SELF_TEST_LOCK = threading.Lock()


def self_test() -> str | None:
    """None when the ring works on this process's default backend, else why not: a report
    sent through it from a jitted program, under a `lax.cond` as a period end sends it,
    comes back whole (`_round_trip`). Run once per backend and process, on a thread of its
    own: the caller may be tracing a program (the first `send`), into which the test's
    program would be staged instead of run."""
    backend = jax.default_backend()
    with _SELF_TEST_LOCK:
        if backend not in _SELF_TESTS:
            result: list[str | None] = []
            thread = threading.Thread(
                target=lambda: result.append(_round_trip()),
                name="jaxmetrics-ring-self-test",
                daemon=True,
            )
            thread.start()
            thread.join(SELF_TEST_TIMEOUT_S)
            _SELF_TESTS[backend] = (
                result[0] if result else f"its round trip took over {SELF_TEST_TIMEOUT_S:g} s"
            )
        return _SELF_TESTS[backend]


def _round_trip() -> str | None:
    """Sends a known report (words of every bit pattern class: high bits, zero, a float
    and an int) through a ring of its own and reads it back; None when it came back
    exactly once and whole, else what went wrong."""
    sent = (np.array([0xDEADBEEF, 0, 1, 0x80000000], np.uint32), np.float32(-2.5))
    got: list[tuple[Any, ...]] = []
    channel = Channel(lambda *_: None, lambda *p: got.append(p), "ring", slots=2)
    channel._choice = Choice("ring", "the ring's self-test")
    try:

        def program(words: jax.Array, x: jax.Array, go: jax.Array) -> jax.Array:
            jax.lax.cond(go, lambda: channel.send(words, x), lambda: None)
            return x + 1

        jax.block_until_ready(jax.jit(program)(*sent, True))
        jax.effects_barrier()
        for _ in range(1000):  # the device's writes reach the host without a wait on it
            channel.drain()
            if got:
                break
            channel._stop.wait(1e-3)
    except Exception as e:  # noqa: BLE001 - any failure means: not this channel
        return f"{type(e).__name__}: {e}"
    finally:
        channel.close()
    if len(got) != 1 or channel.take_lost():
        return f"{len(got)} reports came back of 1 sent"
    words, x = got[0]
    if words.tobytes() != sent[0].tobytes() or np.float32(x) != sent[1]:
        return f"the report came back as {got[0]}, not {sent}"
    return None


def _gpu_platform() -> str:
    """ "cuda" or "rocm" (JAX names both backends "gpu"; the version string tells them
    apart)."""
    version = jax.devices()[0].client.platform_version.lower()
    return next((p for p in ("cuda", "rocm") if p in version), version)


def check_settings(requested: Any, slots: Any) -> None:
    """Raises for a `report_channel` or `report_slots` a Logger cannot take."""
    if requested not in CHANNELS:
        raise ValueError(
            f"Logger(report_channel=...) must be one of {CHANNELS}, got {requested!r}."
        )
    if not is_int(slots) or not 1 <= slots <= 2**16:
        raise ValueError(f"Logger(report_slots=...) must be an int in [1, 65536], got {slots!r}.")


class _WeakCallback:
    """The `io_callback`'s host function as a compiled program holds it: weakly. JAX may keep
    a traced program (and so its callback) in its caches after the program itself is gone
    (JAX 0.12 does); a strong reference would keep the Logger, its writers and its spec
    alive for the process's life, one more per Logger of a sweep."""

    def __init__(self, callback: Callable[..., None]):
        self._callback = weakref.ref(callback)

    def __call__(self, *payload: Any) -> None:
        callback = self._callback()
        if callback is None:
            _log.error(
                "jaxmetrics: a report reached a Logger that no longer exists (it was garbage "
                "collected while a compiled program that reports to it was kept); the report "
                "is dropped. Keep the Logger for as long as its programs run, and close it."
            )
            return
        callback(*payload)


class Channel:
    """`send(*payload)` in-graph hands `payload` (a tuple of arrays, or pytrees of them)
    to the host, as arrays, in order.

    Args:
      callback: the `io_callback` channel's host function (the device waits for it).
      deliver: the ring's host function, called on the channel's thread (one call at a
        time, in the order each device sent the reports, whatever their layouts).
      requested: "auto", "ring" or "io_callback".
      slots: the ring's slots per layout and device: how many reports the host may fall
        behind the device before one is lost.
      on_error: where an exception of `deliver` goes (the channel's thread cannot raise).
      on_lost: called on the channel's thread when a look finds reports overwritten,
        before it delivers the (newer) reports it took.
      poll_interval_s: how long the ring's thread sleeps between looks while reports
        arrive; after a look that found none it waits twice as long, up to `IDLE_POLL_S`.

    Attributes:
      choice: the channel taken (`Choice`), decided at the first `send` traced (or the
        first look at it).
    """

    def __init__(
        self,
        callback: Callable[..., None],
        deliver: Callable[..., None],
        requested: str = "auto",
        slots: int = DEFAULT_SLOTS,
        on_error: Callable[[BaseException], None] | None = None,
        poll_interval_s: float = POLL_S,
        on_lost: Callable[[], None] | None = None,
    ):
        self._callback, self._deliver, self._requested = callback, deliver, requested
        self._weak_callback = _WeakCallback(callback)
        self._on_error, self._on_lost = on_error, on_lost
        self.slots, self.poll_interval_s = slots, poll_interval_s
        self._choice: Choice | None = None
        self._sites: dict[Any, _ring_send.Site] = {}
        self._orders = _ring_send.Orders()
        self._traced = False  # whether a `send` was traced (either kind)
        self._lock = threading.RLock()  # sites and takes; held while delivering
        self._lost = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def choice(self) -> Choice:
        if self._choice is None:
            self._choice = choose(self._requested)
            _log.debug("jaxmetrics report channel: %s (%s)", *self._choice)
        return self._choice

    @property
    def in_use(self) -> bool:
        """Whether a program was traced that sends through the ring (it may still run
        after `close`)."""
        with self._lock:
            return bool(self._sites)

    def send(self, *payload: Any) -> None:
        """In-graph: sends `payload` to the host (unordered with the program's other
        effects; ordered with this channel's other reports)."""
        self._traced = True
        if self.choice.kind == "io_callback":
            io_callback(self._weak_callback, None, *payload, ordered=True)
            return
        leaves, treedef = jax.tree.flatten(payload)
        layout = (treedef, tuple(_ring_send.Leaf.of(x) for x in leaves))
        with self._lock:
            site = self._sites.get(layout)
            if site is None:
                site = self._sites[layout] = _ring_send.Site(*layout, self.slots, self._orders)
                if jax.default_backend() == "gpu":
                    site.cuda_rings()
                self._start()
        _ring_send.send_p().bind(site.encode(leaves), site=site)

    def _start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(
                target=self._poll, name="jaxmetrics-report-channel", daemon=True
            )
            self._thread.start()

    def _poll(self) -> None:
        interval = self.poll_interval_s
        while not self._stop.wait(interval):
            found = self.take()
            interval = self.poll_interval_s if found else min(2 * interval, IDLE_POLL_S)

    def take(self) -> int:
        """Hands every whole report the rings hold now to `deliver`, in the order each
        device sent them (a report waits for those its device sent before it); returns how
        many reports the rings held since the last look (taken or lost)."""
        found = 0
        with self._lock:
            sites = list(self._sites.values())
            for device, order in list(self._orders.by_device.items()):
                rings = [(site, site.rings[device]) for site in sites if device in site.rings]
                looked = order.merge.look([ring for _, ring in rings])
                found += looked.found
                self._lost += looked.lost
                if looked.lost and self._on_lost is not None:
                    self._on_lost()
                for i, payload in looked.reports:
                    try:
                        self._deliver(*rings[i][0].decode(payload))
                    except Exception as e:  # noqa: BLE001 - kept for the caller
                        if self._on_error is None:
                            raise
                        self._on_error(e)
        return found

    def drain(self) -> None:
        """After the device work that sends has finished (`jax.effects_barrier()`): every
        report it sent is delivered (or counted as lost) when this returns."""
        if self._thread is not None:
            self.take()

    @contextlib.contextmanager
    def in_order(self) -> Iterator[None]:
        """Around a record the host queues itself (a flush): in program order, after the
        reports of every program dispatched before it, and before those of the programs
        dispatched after it.

        Where a `send` was traced, it waits for the programs dispatched so far
        (`jax.effects_barrier`: a program that sends has an effect) and delivers what they
        sent; the block then runs under the lock that delivery takes, so that no report is
        delivered until the record is queued. Reports of the `io_callback` are delivered
        by the programs themselves: the wait is all they need.
        """
        if not self._traced:
            yield
            return
        jax.effects_barrier()
        with self._lock:
            self.drain()
            yield

    def unread_check(self) -> Callable[[], int]:
        """A function that counts the reports the rings received and this channel did
        not deliver (those taken but held back for an earlier stamp included), holding
        the rings weakly and nothing of the channel (nor of what it delivers to): a ring
        nothing holds any more (no compiled program writes it) counts none."""
        with self._lock:
            sites = [weakref.ref(site) for site in self._sites.values()]

        def unread() -> int:
            count = 0
            for ref in sites:
                site = ref()
                if site is None:
                    continue
                for ring in site.rings.values():
                    count += ring.unread(ring.taken) + len(ring.held)
            return count

        return unread

    def take_lost(self) -> int:
        """Reports lost since the last call (overwritten before the host took them)."""
        with self._lock:
            lost, self._lost = self._lost, 0
        return lost

    def close(self) -> None:
        """Stops the thread (after a last `drain`). The rings' memory stays: a compiled
        program may still hold their addresses."""
        self.drain()
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
