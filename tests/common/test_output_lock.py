"""`eval.pipeline.lock.output_lock`: one holder at a time, even when two processes race for a new lock."""

from __future__ import annotations

import os
import time

import pytest

from eval.pipeline.lock import LOCK_NAME, output_lock
from mvgeo.common.errors import InputError

# Exit codes of a racing child.
HELD, REFUSED, DOUBLE_HOLD, OTHER_ERROR = 0, 1, 3, 4


def _race_once(folder, marker, hold_s: float, lock) -> int:
    """Take the lock of `folder` and check that nobody else holds it; return an exit code above.

    While holding the lock the process creates `marker` with O_EXCL; it exists only while someone
    holds the lock, so finding it already there means two holders at once.
    """
    try:
        with lock(folder):
            try:
                os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
            except FileExistsError:
                return DOUBLE_HOLD
            time.sleep(hold_s)
            os.unlink(marker)
            return HELD
    except InputError:
        return REFUSED


def _racer(root, go_fd: int, result_fd: int, hold_s: float, lock) -> None:
    """Forked worker: for each trial number read from `go_fd`, race for that trial's lock and write
    the result code to `result_fd`; stop at end of file. Never returns."""
    code = OTHER_ERROR
    try:
        while len(msg := os.read(go_fd, 4)) == 4:
            trial = int.from_bytes(msg, "little")
            try:
                res = _race_once(root / f"t{trial}", root / f"t{trial}.held", hold_s, lock)
            except Exception:
                res = OTHER_ERROR
            os.write(result_fd, bytes([res]))
        code = 0
    finally:
        os._exit(code)


def race_trials(root, n_trials: int, *, lock=output_lock, hold_s: float = 0.001) -> dict[int, int]:
    """`n_trials` times: two processes wake up together and take the lock of a fresh folder.

    Two forked workers serve all trials (forking per trial would cost more than the trials).

    Returns:
        result code -> count over both processes and all trials (see the constants above).
    """
    workers = []
    for _ in range(2):
        go_r, go_w = os.pipe()
        res_r, res_w = os.pipe()
        pid = os.fork()
        if pid == 0:
            for fd in (go_w, res_r, *(fd for _, w, r in workers for fd in (w, r))):
                os.close(fd)  # so that each worker sees end of file when the parent closes its pipe
            _racer(root, go_r, res_w, hold_s, lock)
        os.close(go_r)
        os.close(res_w)
        workers.append((pid, go_w, res_r))
    counts: dict[int, int] = {}
    try:
        for trial in range(n_trials):
            msg = trial.to_bytes(4, "little")
            for _, go_w, _ in workers:  # both wake up at (nearly) the same moment
                os.write(go_w, msg)
            for _, _, res_r in workers:
                code = os.read(res_r, 1)[0]
                counts[code] = counts.get(code, 0) + 1
    finally:
        for _, go_w, _ in workers:
            os.close(go_w)
        for pid, _, res_r in workers:
            os.waitpid(pid, 0)
            os.close(res_r)
    return counts


def test_two_processes_never_hold_the_lock_together(tmp_path):
    counts = race_trials(tmp_path, 200)
    assert counts.get(DOUBLE_HOLD, 0) == 0, counts
    assert counts.get(OTHER_ERROR, 0) == 0, counts
    # The trials did race: in some, one process was turned away while the other held the lock
    # (otherwise this test could not see a double hold).
    assert counts.get(REFUSED, 0) > 0, counts
    assert counts.get(HELD, 0) >= 200, counts  # every trial has a holder
    assert not list(tmp_path.glob(f"t*/{LOCK_NAME}"))  # released locks leave no file behind


def _hold_in_child(folder):
    """Fork a child that holds the lock of `folder` until its stdin pipe closes; return (pid, release_fd)."""
    ready_r, ready_w = os.pipe()
    stop_r, stop_w = os.pipe()
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            os.close(ready_r)
            os.close(stop_w)
            with output_lock(folder):
                os.write(ready_w, b"1")
                os.read(stop_r, 1)
            code = 0
        finally:
            os._exit(code)
    os.close(ready_w)
    os.close(stop_r)
    assert os.read(ready_r, 1) == b"1"
    os.close(ready_r)
    return pid, stop_w


def test_live_holder_is_named_and_its_exit_releases_the_lock(tmp_path):
    out = tmp_path / "out"
    pid, stop = _hold_in_child(out)
    try:
        with pytest.raises(InputError, match=f"another run \\(pid {pid}\\) is writing this folder"):
            with output_lock(out):
                pass
    finally:
        os.close(stop)
        os.waitpid(pid, 0)
    with output_lock(out):
        assert (out / LOCK_NAME).read_text().strip() == str(os.getpid())
    assert not (out / LOCK_NAME).exists()


def test_wait_takes_the_lock_when_the_holder_lets_go(tmp_path):
    """`wait=True` (the evaluation's readers of a finished run): no error, the lock once the holder is gone."""
    import threading

    out = tmp_path / "out"
    pid, stop = _hold_in_child(out)
    released = threading.Event()

    def release_later() -> None:
        time.sleep(0.3)
        released.set()
        os.close(stop)  # the child leaves its `with` block and exits

    threading.Thread(target=release_later).start()
    try:
        with output_lock(out, wait=True):
            assert released.is_set()  # not before the holder let go
            assert (out / LOCK_NAME).read_text().strip() == str(os.getpid())
    finally:
        os.waitpid(pid, 0)
    assert not (out / LOCK_NAME).exists()


def test_killed_holder_releases_the_lock(tmp_path):
    out = tmp_path / "out"
    pid, stop = _hold_in_child(out)
    os.kill(pid, 9)
    os.waitpid(pid, 0)
    os.close(stop)
    assert (out / LOCK_NAME).exists()  # the file stays, but nobody holds it
    with output_lock(out):
        pass


def test_unheld_lock_file_is_taken_over_whatever_it_says(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    for text in ("", "0", "999999999", str(os.getppid())):
        (out / LOCK_NAME).write_text(text)  # e.g. left by a crashed run: only a held lock counts
        with output_lock(out):
            assert (out / LOCK_NAME).read_text().strip() == str(os.getpid())


@pytest.mark.parametrize("text", ["garbage", "my notes\n", "1" * 40])
def test_a_users_file_named_like_the_lock_is_neither_truncated_nor_removed(tmp_path, text):
    """What this module writes there is a pid or nothing; anything else is the user's."""
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK_NAME).write_text(text)
    with pytest.raises(InputError, match="not a lock file"), output_lock(out):
        pass
    assert (out / LOCK_NAME).read_text() == text


def test_second_holder_in_the_same_process_is_refused(tmp_path):
    with output_lock(tmp_path), pytest.raises(InputError, match="another run"):
        with output_lock(tmp_path):
            pass
