"""Rings of report slots in host memory, written by a device and read by a host thread, and
the merge that puts the reports of one device's rings back into the order it wrote them.

A channel has one ring per payload layout and device, and one order word per device (the
CPU's host function counts as one device). Both are little-endian uint32 words:

    order word     [0] the device's stamp counter: the stamp of the last report it started,
                   over all of the channel's rings; [1:4] padding (16 bytes)
    ring           [0] the ring's report counter: the `seq` of the last report it started;
                   [1:4] padding (the slots start 16 bytes in)
    slot s         at 4 + s * (n + 3): `head`, `stamp`, the n payload words, `tail`

Report `seq` (1, 2, ...; 32-bit words, wrapping at 2^32) of a ring goes to slot
`((seq - 1) mod 2^32) % slots`. The writer bumps the ring's counter, then the order word
(atomically: its old value plus one is the report's stamp), then writes the slot's `head` =
seq, the stamp and the payload, and `tail` = seq, in that order, each step visible before the
next (a system-scope fence on the GPU, plain stores in order under one lock on the host). The
reader takes a slot's `tail`, then the stamp and payload, then `head`: they are whole when both
words equal the `seq` it expects (a seqlock). A slot rewritten while it is read shows a newer
`head`; the report it held is then lost, and counted: the next one the reader takes has a `seq`
more than one past the last it took.

Within a ring, reports come in `seq` order; across the rings of a device, the stamps give the
order the device wrote them in (`Merge`). A report is delivered once every stamp before it is
delivered or known lost: a report whose stamp was taken but whose slot is not whole yet holds
back the later ones, and a stamp whose report was overwritten is given up once every report
its ring had started by then is taken or lost, so a lost report stalls nothing.

The same bytes come from the GPU (a kernel writing through a device-mapped pointer to
pinned memory, `_cuda`) or from the CPU (a host function writing them in the same order),
so the reader below is the one both use.
"""

import collections
import ctypes
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

HEADER_WORDS = 4  # the counter, then padding to 16 bytes
ORDER_WORDS = 4  # the order word, then padding to 16 bytes
_WORD = 4
_MASK = 2**32 - 1  # the device's words are 32 bits; seqs and stamps wrap at 2^32


def ring_words(payload_words: int, slots: int) -> int:
    """Words of a ring of `slots` slots of `payload_words` words each."""
    return HEADER_WORDS + slots * (payload_words + 3)


def _word(address: int) -> int:
    return ctypes.c_uint32.from_address(address).value


class Taken(NamedTuple):
    """What one look at a ring found: whole reports newer than the last taken, in order of
    `seq` (each `(seq, stamp, payload)`), and how many reports between them were overwritten
    before they were seen."""

    reports: list[tuple[int, int, bytes]]
    lost: int
    last: int  # the newest seq taken (or given up as lost)


class Ring:
    """One ring's memory, at `address` (`ring_words(...)` words, zeroed by the owner), and
    its reader's place in it.

    Args:
      address: where the ring's words are: pinned host memory that a device writes, or
        a host buffer that a host function writes.
      payload_words: the payload's words per report.
      slots: the number of slots.

    Attributes:
      taken: the newest `seq` the reader took or gave up as lost.
      held: reports taken from the ring but not yet delivered, `(stamp, payload)` in
        `seq` order: they wait for a report of an earlier stamp (`Merge`).
    """

    def __init__(self, address: int, payload_words: int, slots: int):
        self.address, self.payload_words, self.slots = address, payload_words, slots
        self._stride = (payload_words + 3) * _WORD
        self.taken = 0
        self.held: collections.deque[tuple[int, bytes]] = collections.deque()

    def counter(self) -> int:
        """The `seq` of the last report the writer started."""
        return _word(self.address)

    def unread(self, last: int) -> int:
        """How many reports the writer started after `last` (the newest `seq` taken). The
        device counts in 32 bits, the reader in Python ints: what the counter moved since
        `last` (modulo 2^32) is that number, so a look each 2^32 reports never misreads a
        wrap."""
        return (self.counter() - last) & _MASK

    def _slot(self, seq: int) -> int:
        # As the device computes it, from its 32-bit seq: the same slot for any `seq` and
        # `seq` + k * 2^32, whatever the number of slots.
        return (
            self.address + HEADER_WORDS * _WORD + (((seq - 1) & _MASK) % self.slots) * self._stride
        )

    def take(self, last: int, newest: int | None = None) -> Taken:
        """The whole reports after `last` (the newest `seq` taken so far), up to `newest`
        (a `seq` the counter showed; by default what it shows now).

        A report still being written stops the look there (it and the newer ones wait for
        the next look); a report whose slot already holds a newer one is lost.
        """
        if newest is None:
            newest = last + self.unread(last)
        if newest == last:
            return Taken([], 0, last)
        reports: list[tuple[int, int, bytes]] = []
        lost = 0
        first = max(last + 1, newest - self.slots + 1)
        lost += first - (last + 1)  # overwritten by the time of this look
        taken = first - 1
        n = self.payload_words * _WORD
        for seq in range(first, newest + 1):
            slot = self._slot(seq)
            tail = _word(slot + 2 * _WORD + n)
            if tail != seq & _MASK:
                if _is_newer(tail, seq) or _is_newer(_word(slot), seq):
                    lost += 1  # rewritten by a later report already
                    taken = seq
                    continue
                break  # still being written: wait for the next look
            stamped = ctypes.string_at(slot + _WORD, _WORD + n)
            if _word(slot) != seq & _MASK:  # rewritten while it was read
                lost += 1
                taken = seq
                continue
            reports.append((seq, int.from_bytes(stamped[:_WORD], "little"), stamped[_WORD:]))
            taken = seq
        return Taken(reports, lost, taken)

    def write(self, payload: np.ndarray, order: int) -> int:
        """Writes one report as the device does, from the host: bumps the counter, then the
        order word at `order`, then writes `head`, stamp, payload, `tail`, in that order.
        The caller holds the lock of every writer of that order word. Returns its seq."""
        words = np.ascontiguousarray(payload, dtype=np.uint32)
        seq = (self.counter() + 1) & _MASK  # 32 bits, as the device's counter
        ctypes.c_uint32.from_address(self.address).value = seq
        stamp = (_word(order) + 1) & _MASK
        ctypes.c_uint32.from_address(order).value = stamp
        slot = self._slot(seq)
        ctypes.c_uint32.from_address(slot).value = seq
        ctypes.c_uint32.from_address(slot + _WORD).value = stamp
        ctypes.memmove(slot + 2 * _WORD, words.ctypes.data, words.nbytes)
        ctypes.c_uint32.from_address(slot + 2 * _WORD + words.nbytes).value = seq
        return seq


class Looked(NamedTuple):
    """What one look at a device's rings delivers: whole reports in the order the device
    wrote them (each `(index of its ring, payload)`), how many were lost, and how many
    reports the rings started since the last look (taken or lost)."""

    reports: list[tuple[int, bytes]]
    lost: int
    found: int


class Merge:
    """The reader of one device's rings (one per payload layout), delivering their reports in
    the order of their stamps (`look`).

    A stamp not seen yet is either still being written or lost; which one is settled by
    looks: at each, the order word is read first, then every ring's counter, and once every
    ring has been taken up to the counter it showed then (each report whole or lost), every
    stamp up to that order word is settled. A stamp is taken after its ring's counter was
    bumped, both visible in that order, so no report with a settled stamp is still to come.

    Args:
      order: the address of the device's order word: its stamps from the next one on are
        the merge's (a fresh word is zero: from 1 on).
    """

    def __init__(self, order: int):
        self.order = order
        self._next = _word(order) + 1  # the stamp delivered next
        self._settled = self._next - 1  # every stamp up to this one is delivered, held or lost
        # Looks not yet settled: the order word they read, and each ring's counter then.
        self._looks: collections.deque[tuple[int, list[tuple[Ring, int]]]] = collections.deque()

    def _unwrap(self, word: int) -> int:
        """The stamp of 32-bit `word` nearest to the next one (stamps wrap at 2^32)."""
        return self._next + ((word - self._next + 2**31) & _MASK) - 2**31

    def look(self, rings: Sequence[Ring]) -> Looked:
        """Takes what `rings` hold now and delivers, in stamp order, every report whose
        earlier stamps are all delivered or known lost."""
        counter = self._unwrap(_word(self.order))  # before the rings' counters: see above
        newest = [ring.taken + ring.unread(ring.taken) for ring in rings]
        lost = found = 0
        for ring, n in zip(rings, newest):
            taken = ring.take(ring.taken, n)
            found += taken.last - ring.taken
            lost += taken.lost
            ring.taken = taken.last
            ring.held.extend((self._unwrap(stamp), payload) for _, stamp, payload in taken.reports)
        if not self._looks or self._looks[-1][0] != counter:  # else it settles no more
            self._looks.append((counter, list(zip(rings, newest))))
        while self._looks and all(ring.taken >= n for ring, n in self._looks[0][1]):
            self._settled = max(self._settled, self._looks.popleft()[0])
        held = {stamp for ring in rings for stamp, _ in ring.held}
        ready = self._next - 1  # every stamp up to `ready` is delivered, held or lost
        while ready + 1 in held:
            ready += 1
        ready = max(ready, self._settled)
        reports = []
        while heads := [(ring.held[0][0], i) for i, ring in enumerate(rings) if ring.held]:
            stamp, i = min(heads)
            if stamp > ready:
                break
            reports.append((i, rings[i].held.popleft()[1]))
            self._next = max(self._next, stamp + 1)
        return Looked(reports, lost, found)


def _is_newer(word: int, seq: int) -> bool:
    """Whether a slot's 32-bit word names a report after `seq` (so `seq`'s report is gone):
    in serial-number arithmetic, as the words wrap at 2^32."""
    return 0 < (word - seq) & _MASK < 2**31
