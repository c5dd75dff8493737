"""The frame loop reads frame i + 1 on a worker thread while frame i is processed."""

from __future__ import annotations

import threading

import pytest

from mslam.system.run import _ReadAhead


class _Recording:
    """A stand-in sequence that records every read and fails at one index."""

    def __init__(self, n: int, bad: int | None = None) -> None:
        self.n, self.bad = n, bad
        self.reads: list[int] = []
        self.threads: set[str] = set()
        self.inside = 0
        self.overlapped = False
        self.lock = threading.Lock()

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> int:
        with self.lock:
            self.inside += 1
            self.overlapped |= self.inside > 1
        try:
            self.reads.append(i)
            self.threads.add(threading.current_thread().name)
            if i == self.bad:
                raise OSError(f"frame {i} unreadable")
            return 10 * i
        finally:
            with self.lock:
                self.inside -= 1


def test_frames_come_back_in_order_read_once_by_one_worker() -> None:
    seq = _Recording(6)
    with _ReadAhead(seq, None) as reader:
        got = [reader.get(i) for i in range(6)]
    assert got == [10 * i for i in range(6)]
    assert seq.reads == list(range(6))  # each frame read once, in order
    assert not seq.overlapped
    assert len(seq.threads) == 1 and next(iter(seq.threads)).startswith("mslam-read")


def test_a_failed_read_is_raised_for_that_frame_and_the_next_still_loads() -> None:
    seq = _Recording(4, bad=2)
    with _ReadAhead(seq, None) as reader:
        assert reader.get(1) == 10
        with pytest.raises(OSError, match="frame 2"):
            reader.get(2)
        assert reader.get(3) == 30


def test_no_reader_thread_outlives_the_loop() -> None:
    seq = _Recording(50)
    with pytest.raises(RuntimeError), _ReadAhead(seq, None) as reader:
        reader.get(0)
        raise RuntimeError("the frame's processing failed")
    assert not any(t.name.startswith("mslam-read") for t in threading.enumerate())
    assert seq.reads in ([0], [0, 1])  # at most the frame read ahead, nothing after the loop
