"""Property tests: NMEA logs and streams, however damaged, give counts and typed errors,
never a traceback (issue 14). The readers: `treetraits nmea info` (a log file), the parser
the service and `replay` run on the GNSS bytes (`SurveyProcessor`: splitter, sentence
decoder, epoch assembler, localiser), and `replay --nmea` (`nmea_log_messages`, then the
same parser, and a few whole replays of a real VLP-16 capture with the log).

Inputs: arbitrary bytes; the real receiver logs of tests/fixtures/nmea (PROVENANCE.md) cut
anywhere and with bytes flipped, inserted or deleted; their sentences with fields changed
and the checksum made right again, so that the damage reaches the field decoders rather
than stopping at the checksum.
"""

from __future__ import annotations

import contextlib
import io
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.helpers.fuzz import cuts, edits, mutate
from tests.helpers.paths import FIXTURES
from treetraits.cli import main
from treetraits.drivers import recording as rec
from treetraits.drivers.calibration import Calibration
from treetraits.drivers.gnss.sentences import checksum
from treetraits.errors import EXIT_DATA_LOSS, EXIT_USAGE, SourceError
from treetraits.service.config import ServiceConfig
from treetraits.service.replay import nmea_log_messages
from treetraits.service.survey import make_processor

LOGS = sorted((FIXTURES / "nmea").glob("*.nmea"))
CAPTURE = FIXTURES / "vlp16" / "lidarutils_vlp16_strongest_0x22.pcap"
FUZZ = settings(
    max_examples=120,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
_WORK = tempfile.TemporaryDirectory(prefix="treetraits-nmea-fuzz-")
WORK = Path(_WORK.name)
T0 = 1_778_605_200_000_000_000  # a host clock reading (ns), 2026-05-12


def _write(data: bytes) -> Path:
    path = WORK / "log.nmea"
    path.write_bytes(data)
    return path


def _sentence_edit(line: bytes, position: int, text: bytes, fix_checksum: bool) -> bytes:
    """`line` with `text` in place of the field at `position` (commas counted), and its
    checksum recomputed when `fix_checksum`."""
    if not line.startswith((b"$", b"!")) or b"*" not in line:
        return line
    body, _, _ = line[1:].partition(b"*")
    fields = body.split(b",")
    fields[position % len(fields)] = text
    body = b",".join(fields)
    tail = b"%02X" % checksum(body) if fix_checksum else b"00"
    return line[:1] + body + b"*" + tail + b"\r\n"


def _main(argv: list[str]) -> tuple[int, str, str]:
    """`treetraits ARGV`: its exit status, stdout and stderr (no capsys: hypothesis runs
    many examples per test)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


real_logs = st.sampled_from(LOGS).map(lambda p: p.read_bytes())
field_text = st.binary(max_size=12) | st.sampled_from(
    [b"", b"-", b"nan", b"inf", b"1e400", b"-0", b"999999.99", b"9999.9999", b"N", b"X", b"00"]
)


@st.composite
def damaged_logs(draw) -> bytes:
    """A real log, some of its sentences with a field replaced (checksum right or wrong),
    then bytes flipped, inserted or deleted and the file cut somewhere."""
    lines = draw(real_logs).splitlines(keepends=True)
    for _ in range(draw(st.integers(0, 6))):
        i = draw(st.integers(0, len(lines) - 1))
        lines[i] = _sentence_edit(
            lines[i], draw(st.integers(0, 30)), draw(field_text), draw(st.booleans())
        )
    return mutate(b"".join(lines), draw(edits), draw(cuts))


any_log = st.binary(max_size=2000) | damaged_logs()


def _feed_as_the_service_does(data: bytes, chunk: int) -> None:
    """The GNSS bytes in pieces of `chunk` (a serial port's reads) through the processor
    the service and replay share: nothing may raise."""
    processor = make_processor(ServiceConfig(), Calibration())
    for i in range(0, len(data), chunk):
        processor.feed(rec.GNSS_NMEA, data[i : i + chunk], T0 + i * 1_000_000, T0)
    processor.finish()


@FUZZ
@given(any_log, st.integers(1, 600))
def test_the_service_parser_counts_and_skips_whatever_comes(data, chunk):
    _feed_as_the_service_does(data, chunk)


@FUZZ
@given(any_log)
def test_nmea_info_reads_any_log_or_refuses_it_in_one_line(data):
    path = _write(data)
    code, out, err = _main(["nmea", "info", str(path), "--json"])
    assert "Traceback" not in err
    assert code == 0 or (code == EXIT_USAGE and err.startswith("treetraits: error: ")), err
    if code == 0:
        assert '"sentences"' in out


@FUZZ
@given(any_log, st.sampled_from([0.0, "start", 3600.0]))
def test_replay_nmea_places_any_log_or_refuses_it(data, offset):
    """`replay --nmea`'s reader: a typed refusal (no timed sentence, a log that ends
    before the capture) or messages, which the shared parser takes without raising."""
    path = _write(data)
    try:
        messages = list(nmea_log_messages(path, T0, offset, 0.05))
    except SourceError:
        return
    processor = make_processor(ServiceConfig(), Calibration())
    for topic, raw, log_time, publish_time in messages:
        assert topic == rec.GNSS_NMEA and log_time >= publish_time
        processor.feed(topic, raw, log_time, publish_time)
    processor.finish()


@settings(FUZZ, max_examples=12)
@given(damaged_logs())
def test_a_whole_replay_with_a_damaged_nmea_log(data):
    """The command itself: a real capture with a damaged log ends with a result (0, or 3
    for the capture's own cut) or one line (2), never a traceback."""
    path = _write(data)
    out = Path(tempfile.mkdtemp(dir=WORK))
    argv = ["replay", str(CAPTURE), "--nmea", str(path), "--nmea-offset", "start"]
    code, _, err = _main([*argv, "--out", str(out / "o"), "--json"])
    assert "Traceback" not in err
    assert code in (0, EXIT_DATA_LOSS) or (
        code == EXIT_USAGE and err.startswith("treetraits: error: ")
    ), err


@pytest.mark.parametrize("log", LOGS, ids=lambda p: p.stem)
def test_every_real_log_reads_whole(log):
    """The undamaged fixtures go through the service's parser in one piece and in bytes."""
    data = log.read_bytes()
    _feed_as_the_service_does(data, len(data))
    _feed_as_the_service_does(data[:3000], 1)
