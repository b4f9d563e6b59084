"""The checkpoint log (pd_service/service/handover/checkpoint_log.py): newest record wins, a damaged end
drops only what follows the damage, foreign files are set aside, earlier versions' files
are carried over, the file stays bounded."""

from __future__ import annotations

import logging
import os

from pd_service.service.handover import checkpoint_log
from pd_service.service.handover.checkpoint_log import LOG_NAME, MAGIC, CheckpointLog, parse, record


def names(d):
    return sorted(p.name for p in d.iterdir())


def test_the_newest_record_of_a_session_wins_and_a_removal_forgets_it(tmp_path):
    log = CheckpointLog(tmp_path)
    log.append([("a", b"a1"), ("b", b"b1")])
    log.append([("a", b"a2"), ("b", None), ("c", b"c1")])
    log.close()
    again = CheckpointLog(tmp_path)
    assert again.get("a") == b"a2" and again.get("b") is None and again.get("c") == b"c1"
    assert again.sessions() == ["a", "c"]
    buf = (tmp_path / LOG_NAME).read_bytes()
    assert buf.startswith(MAGIC)
    assert parse(buf, len(MAGIC)) == ({"a": b"a2", "c": b"c1"}, len(buf))


def test_a_damaged_end_drops_only_what_follows_it(tmp_path, caplog):
    log = CheckpointLog(tmp_path)
    log.append([("a", b"a1"), ("b", b"b1")])
    log.append([("a", b"a2-newer")])
    log.close()
    path = tmp_path / LOG_NAME
    whole = path.read_bytes()
    cut = whole[:-3]  # a crash while appending: the last record cut short
    path.write_bytes(cut)
    with caplog.at_level(logging.WARNING):
        again = CheckpointLog(tmp_path)
        assert again.get("a") == b"a1" and again.get("b") == b"b1"
    assert "checkpoint_log_damaged" in caplog.text
    assert again.damaged is not None and f"byte {len(whole) - len(record('a', b'a2-newer'))}" \
        in again.damaged
    assert CheckpointLog(tmp_path).damage() == again.damaged  # read on the way
    # a flipped byte inside a record: its CRC fails, reading stops before it
    flipped = bytearray(whole)
    flipped[len(MAGIC) + 12] ^= 0xFF  # inside the first record's name
    path.write_bytes(bytes(flipped))
    assert CheckpointLog(tmp_path).sessions() == []
    # the next append rewrites the log without the damage: everything reads to the end
    path.write_bytes(cut)
    again = CheckpointLog(tmp_path)
    again.append([("c", b"c1")])
    buf = path.read_bytes()
    assert parse(buf, len(MAGIC)) == ({"a": b"a1", "b": b"b1", "c": b"c1"}, len(buf))


def test_a_file_that_is_not_a_log_is_set_aside(tmp_path):
    (tmp_path / LOG_NAME).write_bytes(b"not a checkpoint log")
    log = CheckpointLog(tmp_path)
    assert log.sessions() == []
    assert names(tmp_path) == [LOG_NAME + ".bad"]
    assert log.damaged is not None and "no PDCKLOG1 magic" in log.damaged
    os.mkfifo(tmp_path / "x")
    (tmp_path / LOG_NAME).unlink(missing_ok=True)
    (tmp_path / LOG_NAME).symlink_to(tmp_path / "x")  # a symlink to a FIFO: never opened
    assert CheckpointLog(tmp_path).sessions() == []
    assert os.path.lexists(tmp_path / (LOG_NAME + ".bad"))


def test_earlier_versions_files_are_read_then_carried_into_the_log(tmp_path):
    (tmp_path / "old.ckpt").write_bytes(b"old-state")
    (tmp_path / "both.ckpt").write_bytes(b"stale")
    os.mkfifo(tmp_path / "fifo.ckpt")  # never read, left alone
    log = CheckpointLog(tmp_path)
    log.append([("both", b"newer")])
    log.close()
    assert names(tmp_path) == [LOG_NAME, "fifo.ckpt"]
    again = CheckpointLog(tmp_path)
    assert again.get("old") == b"old-state" and again.get("both") == b"newer"
    assert again.get("fifo") is None


def test_the_log_stays_bounded_by_its_live_states(tmp_path, monkeypatch):
    monkeypatch.setattr(checkpoint_log, "COMPACT_SLACK_BYTES", 10_000)
    log = CheckpointLog(tmp_path)
    state = b"s" * 1000
    for i in range(500):  # 500 kB written, 2 kB live
        log.append([("a", state), ("b", state + b"%d" % i)])
    size = (tmp_path / LOG_NAME).stat().st_size
    assert size <= checkpoint_log.COMPACT_FACTOR * 2_010 + 10_000 + len(record("b", state + b"499"))
    log.close()
    assert CheckpointLog(tmp_path).get("b") == state + b"499"


def test_a_failed_append_is_rewritten_before_the_next_one(tmp_path, monkeypatch):
    """A write that fails halfway (a full disk) may leave a record cut short: the next
    append rewrites the log first, so the records after it are read back."""
    log = CheckpointLog(tmp_path)
    log.append([("a", b"a1")])
    real_write = os.write
    calls = []

    def half_then_fail(fd, data):
        calls.append(1)
        real_write(fd, bytes(data[: len(data) // 2]))
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(checkpoint_log.os, "write", half_then_fail)
    try:
        log.append([("b", b"b1" * 100)])
    except OSError:
        pass
    else:
        raise AssertionError("the failed write was not reported")
    monkeypatch.setattr(checkpoint_log.os, "write", real_write)
    assert calls and log.get("b") is None  # not written: not held
    log.append([("c", b"c1")])
    log.close()
    again = CheckpointLog(tmp_path)
    assert again.get("a") == b"a1" and again.get("c") == b"c1" and again.get("b") is None
