"""Bytes to framed NMEA sentences: a push splitter that resynchronises on `$`, not on lines.

A serial port delivers NMEA in arbitrary pieces, mixed with whatever else the receiver
sends (UBX or RTCM3 binary), line noise, NULs, sentences cut short by a reboot or glued to
the next one. `SentenceSplitter.push(data, t_host)` takes the bytes of one read and returns
each sentence it completed, as received; `flush()` ends the stream.

A sentence is `$` or `!`, then printable ASCII without `$ ! *`, then `*` and two hex
digits, then CR, LF or the end of the input; the line end is kept in `raw` (CR LF, LF, or a
lone CR). This is the "stream" rule of the NMEA fixtures' PROVENANCE.md, so the counts
agree with it. A new `$` or `!` always starts a new candidate: a sentence interrupted by
another is dropped (`truncated`) and the interrupting one is still found.

Sentences with a wrong checksum are returned too (`checksum_ok` False), because a recording
keeps every sentence as received; decoders must not use them. Every byte pushed ends up in
exactly one place: a returned sentence, `garbage_bytes`, or the pending tail (at most
`max_length` bytes, so memory is bounded whatever comes in).
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass

from treetraits.drivers.gnss.sentences import NMEA_MAX_LENGTH, Sentence, checksum

# Longest sentence accepted, `$` to line end. NMEA says 82; $PUBX,03 with many satellites
# or a long proprietary sentence can be several hundred, so the default leaves room.
DEFAULT_MAX_LENGTH = 1024

_START = re.compile(rb"[$!]")
_BODY = re.compile(rb"[\x20\x22\x23\x25-\x29\x2b-\x7e]*")  # printable, not $ ! *
_HEX = frozenset(b"0123456789ABCDEFabcdef")
_CR, _LF, _STAR = 0x0D, 0x0A, 0x2A


@dataclass
class SplitterStats:
    """What the splitter saw. `bytes` = bytes of returned sentences + `garbage_bytes` +
    the pending tail; each `$`/`!` that began no returned sentence is counted once in
    `truncated`, `unterminated` or `too_long`."""

    bytes: int = 0
    sentences: int = 0  # returned: good and bad checksums
    valid: int = 0  # returned with a matching checksum
    bad_checksum: int = 0  # returned with checksum_ok False
    truncated: int = 0  # cut by a new $/!, a line end, a non-printable byte or the input end
    unterminated: int = 0  # `*` not followed by two hex digits and CR/LF (glued `*1E$GP...`)
    too_long: int = 0  # longer than max_length before its checksum: dropped
    over_nmea_limit: int = 0  # returned sentences longer than NMEA's 82 characters
    garbage_bytes: int = 0  # bytes in no returned sentence (binary, text, fragments)

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class SentenceSplitter:
    """Push bytes in, get complete sentences out (see the module docstring)."""

    def __init__(self, max_length: int = DEFAULT_MAX_LENGTH):
        if max_length < 6:
            raise ValueError(f"max_length must allow at least `$*hh\\r\\n`, got {max_length}")
        self.max_length = max_length
        self.stats = SplitterStats()
        self._pending = b""  # an unfinished candidate, starting at its `$`/`!`
        self._pending_t_host = 0  # t_host of the push that left it pending

    @property
    def pending(self) -> int:
        """Bytes held back: the start of a sentence not yet complete."""
        return len(self._pending)

    def push(self, data: bytes, t_host: int) -> list[Sentence]:
        """The sentences completed by `data` (the bytes of one read, received at
        `t_host`). A sentence's t_host is that of the read holding its line end."""
        self.stats.bytes += len(data)
        return self._scan(data, t_host, final=False)

    def flush(self) -> list[Sentence]:
        """End of input: a pending sentence complete up to its checksum is returned (the
        input may end without a line end); anything else pending is counted truncated."""
        return self._scan(b"", self._pending_t_host, final=True)

    def _scan(self, data: bytes, t_host: int, *, final: bool) -> list[Sentence]:
        old = len(self._pending)
        buf = self._pending + data if old else data
        self._pending = b""
        stats = self.stats
        out: list[Sentence] = []
        size = len(buf)
        pos = 0
        while pos < size:
            start_match = _START.search(buf, pos)
            if start_match is None:
                stats.garbage_bytes += size - pos
                break
            start = start_match.start()
            stats.garbage_bytes += start - pos
            star = _BODY.match(buf, start + 1).end()
            if star + 5 - start > self.max_length:  # +5: `*hh` and CR LF
                stats.too_long += 1
                stats.garbage_bytes += star - start
                pos = star  # the rest of the body, if still to come, is garbage too
                continue
            end = self._end_of_sentence(buf, star, final)
            if end is None:  # needs more bytes
                self._pending = buf[start:]
                self._pending_t_host = t_host
                return out
            if end < 0:
                # Not a sentence: resume at the byte that ended the body (or just after a
                # `*`), where the stream rule looks for the next `$`/`!`.
                if star < size and buf[star] == _STAR:
                    stats.unterminated += 1
                    resume = star + 1
                else:
                    stats.truncated += 1
                    resume = star
                stats.garbage_bytes += resume - start
                pos = resume
                continue
            body = buf[start + 1 : star]
            ok = checksum(body) == int(buf[star + 1 : star + 3], 16)
            # The line end (or the input end) arrived with this read or an earlier one.
            when = t_host if star + 3 >= old else self._pending_t_host
            out.append(Sentence(buf[start:end], when, ok))
            stats.sentences += 1
            if ok:
                stats.valid += 1
            else:
                stats.bad_checksum += 1
            if end - start > NMEA_MAX_LENGTH:
                stats.over_nmea_limit += 1
            pos = end
        return out

    @staticmethod
    def _end_of_sentence(buf: bytes, star: int, final: bool) -> int | None:
        """Where the sentence whose body ends at `star` ends (exclusive); -1 when it is
        not a sentence; None when more bytes are needed to tell."""
        size = len(buf)
        if star >= size:
            return -1 if final else None
        if buf[star] != _STAR:
            return -1  # a new $/!, a line end or a non-printable byte before `*hh`
        for index in (star + 1, star + 2):
            if index >= size:
                return -1 if final else None
            if buf[index] not in _HEX:
                return -1
        after = star + 3
        if after >= size:
            return after if final else None
        if buf[after] == _LF:
            return after + 1
        if buf[after] != _CR:
            return -1
        if after + 1 >= size:
            return after + 1 if final else None
        return after + 2 if buf[after + 1] == _LF else after + 1
