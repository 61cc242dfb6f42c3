"""A ring of report slots in host memory, written by the device and read by a host thread.

Layout of one ring, in little-endian uint32 words:

    [0]            the device's report counter: the `seq` of the last report it wrote
    [1:4]          padding (the slots start 16 bytes in)
    slot s         at 4 + s * (n + 2): `head`, the n payload words, `tail`

Report `seq` (1, 2, ...; 32-bit words, wrapping at 2^32) goes to slot
`((seq - 1) mod 2^32) % slots`. The writer bumps the counter,
then writes the slot's `head` = seq, the payload, and `tail` = seq, in that order, each
step visible before the next (a system-scope fence on the GPU, plain stores in order on the
host). The reader takes a slot's `tail`, then the payload, then `head`: the payload is
whole when both words equal the `seq` it expects (a seqlock). A slot rewritten while it
is read shows a newer `head`; the report it held is then lost, and counted: the next one
the reader takes has a `seq` more than one past the last it took.

The same bytes come from the GPU (a kernel writing through a device-mapped pointer to
pinned memory, `_cuda`) or from the CPU (a host function writing them in the same order),
so the reader below is the one both use.
"""

import ctypes
from typing import NamedTuple

import numpy as np

HEADER_WORDS = 4  # the counter, then padding to 16 bytes
_WORD = 4
_MASK = 2**32 - 1  # the device's words are 32 bits; seqs wrap at 2^32


def ring_words(payload_words: int, slots: int) -> int:
    """Words of a ring of `slots` slots of `payload_words` words each."""
    return HEADER_WORDS + slots * (payload_words + 2)


class Taken(NamedTuple):
    """What one look at a ring found: whole reports newer than the last taken, in order of
    `seq`, and how many reports between them were overwritten before they were seen."""

    reports: list[tuple[int, bytes]]
    lost: int
    last: int  # the newest seq taken (or given up as lost)


class Ring:
    """One ring's memory, at `address` (`ring_words(...)` words, zeroed by the owner).

    Args:
      address: where the ring's words are: pinned host memory that a device writes, or
        a host buffer that a host function writes.
      payload_words: the payload's words per report.
      slots: the number of slots.
    """

    def __init__(self, address: int, payload_words: int, slots: int):
        self.address, self.payload_words, self.slots = address, payload_words, slots
        self._stride = (payload_words + 2) * _WORD

    def counter(self) -> int:
        """The `seq` of the last report the writer started."""
        return ctypes.c_uint32.from_address(self.address).value

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

    def take(self, last: int) -> Taken:
        """The whole reports after `last` (the newest `seq` taken so far).

        A report still being written stops the look there (it and the newer ones wait for
        the next look); a report whose slot already holds a newer one is lost.
        """
        newest = last + self.unread(last)
        if newest == last:
            return Taken([], 0, last)
        reports: list[tuple[int, bytes]] = []
        lost = 0
        first = max(last + 1, newest - self.slots + 1)
        lost += first - (last + 1)  # overwritten by the time of this look
        taken = first - 1
        n = self.payload_words * _WORD
        for seq in range(first, newest + 1):
            slot = self._slot(seq)
            tail = ctypes.c_uint32.from_address(slot + _WORD + n).value
            if tail != seq & _MASK:
                if _is_newer(tail, seq) or _is_newer(self._head(slot), seq):
                    lost += 1  # rewritten by a later report already
                    taken = seq
                    continue
                break  # still being written: wait for the next look
            payload = ctypes.string_at(slot + _WORD, n)
            if self._head(slot) != seq & _MASK:  # rewritten while it was read
                lost += 1
                taken = seq
                continue
            reports.append((seq, payload))
            taken = seq
        return Taken(reports, lost, taken)

    @staticmethod
    def _head(slot: int) -> int:
        return ctypes.c_uint32.from_address(slot).value

    def write(self, payload: np.ndarray) -> int:
        """Writes one report as the device does, from the host: bumps the counter, then
        `head`, payload, `tail`, in that order. Returns its seq."""
        words = np.ascontiguousarray(payload, dtype=np.uint32)
        seq = (self.counter() + 1) & _MASK  # 32 bits, as the device's counter
        ctypes.c_uint32.from_address(self.address).value = seq
        slot = self._slot(seq)
        ctypes.c_uint32.from_address(slot).value = seq
        ctypes.memmove(slot + _WORD, words.ctypes.data, words.nbytes)
        ctypes.c_uint32.from_address(slot + _WORD + words.nbytes).value = seq
        return seq


def _is_newer(word: int, seq: int) -> bool:
    """Whether a slot's 32-bit word names a report after `seq` (so `seq`'s report is gone):
    in serial-number arithmetic, as the words wrap at 2^32."""
    return 0 < (word - seq) & _MASK < 2**31
