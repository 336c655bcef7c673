"""What a command killed by SIGKILL leaves at `--out` (the temporary folder it wrote into, or the old output
it had renamed aside) is removed by the next command writing there, and only that: the owner file beside
each (`mvgeo.common.output.OwnerFile`) must name a process of this host that is gone, and be unlocked."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mvgeo.common.atomic import atomic_output_dir
from mvgeo.common.errors import InputError
from mvgeo.common.output import OWNER_SUFFIX, prepare_output, stale_leftovers, write_manifest

CMD = "tool write"
ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="SIGKILL")


def _killed_while_writing(out: Path, tmp_path: Path) -> None:
    """Run a command writing `out` in a child process and SIGKILL it inside the atomic block."""
    ready = tmp_path / "ready"
    _kill_when_ready(
        "import pathlib, time\n"
        "from mvgeo.common.atomic import atomic_output_dir\n"
        "from mvgeo.common.output import prepare_output\n"
        f"with atomic_output_dir(prepare_output({str(out)!r}, command={CMD!r})) as tmp:\n"
        "    (tmp / 'half.txt').write_text('half')\n"
        f"    pathlib.Path({str(ready)!r}).write_text('1')\n"
        "    time.sleep(60)\n", ready)


def _kill_when_ready(code: str, ready: Path) -> None:
    """Run `code` in a child process, SIGKILL it once it has written `ready`, then remove `ready`."""
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT)
    try:
        deadline = time.monotonic() + 60
        while not ready.exists():
            assert proc.poll() is None, "the child ended before it was killed"
            assert time.monotonic() < deadline
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        proc.kill()
    ready.unlink()


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _hidden(folder: Path) -> list[str]:
    return sorted(n for n in os.listdir(folder) if n.startswith("."))


def test_a_killed_commands_temporary_folder_beside_out_is_removed_by_the_next_one(tmp_path):
    out = tmp_path / "out"
    _killed_while_writing(out, tmp_path)
    left = _hidden(tmp_path)
    assert len(left) == 2 and left[0].startswith(".out.tmp-") and left[1] == left[0] + OWNER_SUFFIX
    with atomic_output_dir(prepare_output(out, command=CMD)) as tmp:
        (tmp / "a.txt").write_text("a")
    assert _hidden(tmp_path) == [] and (out / "a.txt").read_text() == "a"


def test_an_empty_out_holding_only_a_killed_commands_temporary_folder_counts_as_empty(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    _killed_while_writing(out, tmp_path)
    assert len(_hidden(out)) == 2
    plan = prepare_output(out, command=CMD)
    assert plan.state == "empty"
    with atomic_output_dir(plan) as tmp:
        (tmp / "a.txt").write_text("a")
    assert sorted(os.listdir(out)) == [".denoise-gs-output.json", "a.txt"]


def test_an_old_output_a_killed_overwrite_renamed_aside_is_removed(tmp_path):
    out = tmp_path / "out"
    with atomic_output_dir(prepare_output(out, command=CMD)) as tmp:
        (tmp / "a.txt").write_text("1")
    old = tmp_path / ".out.old-0123abcd"
    old.mkdir()
    (old / "a.txt").write_text("0")
    (tmp_path / (old.name + OWNER_SUFFIX)).write_text(
        json.dumps({"entry": old.name, "host": socket.gethostname(), "pid": _dead_pid()}))
    with atomic_output_dir(prepare_output(out, command=CMD, overwrite=True)) as tmp:
        (tmp / "a.txt").write_text("2")
    assert _hidden(tmp_path) == [] and (out / "a.txt").read_text() == "2"


@pytest.mark.parametrize("case", ["no owner file", "owner alive", "other host", "owner names another entry",
                                  "a symbolic link"])
def test_what_is_not_provably_a_dead_commands_leftover_is_kept(tmp_path, case):
    out = tmp_path / "out"
    name = ".out.tmp-0123abcd"
    entry = tmp_path / name
    if case == "a symbolic link":  # to the user's file: neither a folder nor a file the commands write
        (tmp_path / "mine.txt").write_text("mine")
        entry.symlink_to(tmp_path / "mine.txt")
    else:
        entry.mkdir()
        (entry / "mine.txt").write_text("mine")
    info = {"entry": name, "host": socket.gethostname(), "pid": _dead_pid()}
    if case == "owner alive":
        info["pid"] = os.getppid()
    elif case == "other host":
        info["host"] = socket.gethostname() + "-elsewhere"
    elif case == "owner names another entry":
        info["entry"] = ".out.tmp-ffffffff"
    if case != "no owner file":
        (tmp_path / (name + OWNER_SUFFIX)).write_text(json.dumps(info))
    before = _hidden(tmp_path)
    assert stale_leftovers(tmp_path) == []
    with atomic_output_dir(prepare_output(out, command=CMD)) as tmp:
        (tmp / "a.txt").write_text("a")
    assert _hidden(tmp_path) == before
    assert (entry / "mine.txt").read_text() == "mine" if not entry.is_symlink() else entry.read_text() == "mine"


def test_an_out_holding_a_leftover_of_a_live_command_is_still_refused(tmp_path):
    out = tmp_path / "out"
    (out / ".tmp-0123abcd").mkdir(parents=True)
    (out / (".tmp-0123abcd" + OWNER_SUFFIX)).write_text(
        json.dumps({"entry": ".tmp-0123abcd", "host": socket.gethostname(), "pid": os.getppid()}))
    with pytest.raises(InputError, match="temporary folder of an interrupted run"):
        prepare_output(out, command=CMD)


def test_only_the_leftovers_of_the_same_out_are_removed(tmp_path):
    """`--out a` removes a dead command's `.a.tmp-TAG`, not `.a.b.tmp-TAG` (that of `--out a.b`)."""
    pid = _dead_pid()
    for name in (".a.tmp-0123abcd", ".a.b.tmp-0123abcd"):
        (tmp_path / name).mkdir()
        (tmp_path / (name + OWNER_SUFFIX)).write_text(
            json.dumps({"entry": name, "host": socket.gethostname(), "pid": pid}))
    with atomic_output_dir(prepare_output(tmp_path / "a", command=CMD)) as tmp:
        (tmp / "x.txt").write_text("x")
    assert _hidden(tmp_path) == [".a.b.tmp-0123abcd", ".a.b.tmp-0123abcd" + OWNER_SUFFIX]


def test_a_leftover_whose_owner_file_is_locked_is_kept_even_if_its_pid_looks_gone(tmp_path):
    """A command in another pid namespace (a container sharing the folder) has a pid this one cannot see;
    its owner file's lock says it is alive."""
    import fcntl

    name = ".out.tmp-0123abcd"
    (tmp_path / name).mkdir()
    owner = tmp_path / (name + OWNER_SUFFIX)
    owner.write_text(json.dumps({"entry": name, "host": socket.gethostname(), "pid": _dead_pid()}))
    assert stale_leftovers(tmp_path) == [tmp_path / name, owner]  # unlocked: a dead command's
    with open(owner) as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        assert stale_leftovers(tmp_path) == []
        with atomic_output_dir(prepare_output(tmp_path / "out", command=CMD)) as tmp:
            (tmp / "a.txt").write_text("a")
        assert (tmp_path / name).is_dir() and owner.is_file()


def test_the_owner_file_is_locked_while_the_command_writes(tmp_path):
    from mvgeo.common.output import _owner_locked

    with atomic_output_dir(prepare_output(tmp_path / "out", command=CMD)) as tmp:
        owner = tmp.with_name(tmp.name + OWNER_SUFFIX)
        assert _owner_locked(owner)
        assert stale_leftovers(tmp_path) == []
    assert not owner.exists()


def _dead_owner(folder, name):
    (folder / (name + OWNER_SUFFIX)).write_text(
        json.dumps({"entry": name, "host": socket.gethostname(), "pid": _dead_pid()}))


def _killed_between_the_renames(folder: Path) -> None:
    """What --overwrite leaves when killed between its two renames: no `out`, the previous output (with its
    manifest) retired as `.out.old-TAG`, the unfinished new one as `.out.tmp-TAG`, both with dead owners."""
    for name in (".out.old-0123abcd", ".out.tmp-0123abcd"):
        (folder / name).mkdir()
        (folder / name / "a.txt").write_text(name)
        _dead_owner(folder, name)
    write_manifest(folder / ".out.old-0123abcd", CMD)


def test_the_only_copy_of_a_previous_output_is_put_back(tmp_path):
    """The next command writing `out` renames the retired previous output back to `out` first: it is then a
    previous output like any other (refused without --overwrite, replaced with it)."""
    _killed_between_the_renames(tmp_path)
    with pytest.raises(InputError, match="holds a previous output"):
        prepare_output(tmp_path / "out", command=CMD)
    assert (tmp_path / "out" / "a.txt").read_text() == ".out.old-0123abcd"
    assert _hidden(tmp_path) == [".out.tmp-0123abcd", ".out.tmp-0123abcd" + OWNER_SUFFIX]  # removed when writing
    with atomic_output_dir(prepare_output(tmp_path / "out", command=CMD, overwrite=True)) as tmp:
        (tmp / "b.txt").write_text("b")
    assert sorted(p.name for p in (tmp_path / "out").iterdir() if not p.name.startswith(".")) == ["b.txt"]
    assert _hidden(tmp_path) == []


def test_a_retired_output_is_not_put_back_when_it_is_not_certain(tmp_path):
    """Two retired copies (which one?), a live owner, or an `out` that exists: nothing is moved."""
    _killed_between_the_renames(tmp_path)
    (tmp_path / ".out.old-89abcdef").mkdir()
    _dead_owner(tmp_path, ".out.old-89abcdef")
    with atomic_output_dir(prepare_output(tmp_path / "out", command=CMD)) as tmp:
        (tmp / "b.txt").write_text("b")
    assert (tmp_path / ".out.old-0123abcd" / "a.txt").is_file() and (tmp_path / ".out.old-89abcdef").is_dir()
    live = tmp_path / "live"
    live.mkdir()
    (live / ".out.old-0123abcd").mkdir()
    (live / (".out.old-0123abcd" + OWNER_SUFFIX)).write_text(
        json.dumps({"entry": ".out.old-0123abcd", "host": socket.gethostname(), "pid": os.getppid()}))
    with atomic_output_dir(prepare_output(live / "out", command=CMD)) as tmp:
        (tmp / "b.txt").write_text("b")
    assert (live / ".out.old-0123abcd").is_dir() and (live / "out" / "b.txt").is_file()


def test_an_owner_file_whose_folder_was_never_made_is_removed(tmp_path):
    _dead_owner(tmp_path, ".out.tmp-0123abcd")
    with atomic_output_dir(prepare_output(tmp_path / "out", command=CMD)) as tmp:
        (tmp / "b.txt").write_text("b")
    assert _hidden(tmp_path) == []


def test_a_resumed_folder_loses_what_a_killed_command_left_inside(tmp_path):
    from mvgeo.common.output import resumable_output_dir

    out = tmp_path / "out"
    out.mkdir()
    (out / ".x.tmp-0123abcd").mkdir()
    _dead_owner(out, ".x.tmp-0123abcd")
    (out / "mine.txt").write_text("kept")  # refused as --out by the policy, so a run folder of ours instead
    write_manifest(out, CMD, record_files=False)
    with resumable_output_dir(prepare_output(out, command=CMD, resume=True)):
        pass
    assert sorted(os.listdir(out)) == [".denoise-gs-output.json", "mine.txt"]


def test_a_single_output_files_temporary_file_left_by_sigkill_is_removed_next_time(tmp_path):
    """`write_output_file` killed while writing leaves `.F.tmp-TAG` and its owner file; the next call for F
    removes both (and nothing else: a user's `.F.tmp-…` without an owner file stays)."""
    from mvgeo.common.output import prepare_output_file, write_output_file

    out = tmp_path / "scene.ply"
    ready = tmp_path / "ready"
    _kill_when_ready(
        "import pathlib, time\n"
        "from mvgeo.common.output import prepare_output_file, write_output_file\n"
        "def write(tmp):\n"
        "    tmp.write_text('half')\n"
        f"    pathlib.Path({str(ready)!r}).write_text('1')\n"
        "    time.sleep(60)\n"
        f"write_output_file(prepare_output_file({str(out)!r}, command={CMD!r}), {CMD!r}, write)\n", ready)
    left = _hidden(tmp_path)
    assert len(left) == 2 and left[0].startswith(".scene.ply.tmp-") and left[1] == left[0] + OWNER_SUFFIX
    (tmp_path / ".scene.ply.tmp-89abcdef").write_text("the user's")  # no owner file: not ours
    write_output_file(prepare_output_file(out, command=CMD), CMD, lambda tmp: tmp.write_text("whole"))
    assert out.read_text() == "whole"
    assert _hidden(tmp_path) == [".scene.ply.denoise-gs-output.json", ".scene.ply.tmp-89abcdef"]


def test_a_retired_output_behind_a_symbolic_link_is_put_back(tmp_path):
    """`--out link` whose target a killed --overwrite retired: the link is broken until the target is put back."""
    _killed_between_the_renames(tmp_path)
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "out")
    with pytest.raises(InputError, match="holds a previous output"):
        prepare_output(link, command=CMD)
    assert (link / "a.txt").read_text() == ".out.old-0123abcd"


@pytest.mark.parametrize("fallback", [True, False])
def test_rename_no_replace_never_replaces_what_is_there(tmp_path, fallback):
    """A plain rename would replace an empty folder, or a file, that appeared at the destination."""
    from mvgeo.common.output import rename_no_replace

    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "a.txt").write_text("a")
    (tmp_path / "dst").mkdir()
    with pytest.raises(FileExistsError):
        rename_no_replace(tmp_path / "src", tmp_path / "dst", fallback=fallback)
    assert (tmp_path / "src" / "a.txt").is_file() and list((tmp_path / "dst").iterdir()) == []
    (tmp_path / "user.txt").write_text("the user's")
    with pytest.raises(FileExistsError):
        rename_no_replace(tmp_path / "src" / "a.txt", tmp_path / "user.txt", fallback=fallback)
    assert (tmp_path / "user.txt").read_text() == "the user's"
    rename_no_replace(tmp_path / "src", tmp_path / "new", fallback=fallback)
    assert (tmp_path / "new" / "a.txt").is_file() and not (tmp_path / "src").exists()


def test_a_file_appearing_in_an_empty_out_while_the_output_moves_in_is_kept(tmp_path, monkeypatch):
    """`--out` was empty: the results move up from the temporary folder inside it. A file of the user's that
    appears after the last check (here: right after it) is neither replaced nor removed; exit 2."""
    import mvgeo.common.atomic as atomic

    out = tmp_path / "out"
    out.mkdir()
    listdir, seen = os.listdir, []

    def listdir_then_user_writes(p="."):
        names = listdir(p)
        if Path(p) == out and not seen:  # `_move_entries_up`'s check of --out: the user's file comes after it
            seen.append(p)
            (out / "a.txt").write_text("the user's")
        return names

    with pytest.raises(InputError, match="a.txt"):
        with atomic_output_dir(prepare_output(out, command=CMD)) as tmp:
            (tmp / "a.txt").write_text("ours")
            (tmp / "b.txt").write_text("ours")
            monkeypatch.setattr(atomic.os, "listdir", listdir_then_user_writes)
    assert (out / "a.txt").read_text() == "the user's" and seen


def _entries_moved_then(out: Path, tmp_path: Path, *, kill: bool) -> None:
    """A command writing two results into the empty `out`, interrupted after its first move up from the
    temporary folder: SIGKILLed in a child process (`kill`), or a Ctrl-C here."""
    import mvgeo.common.atomic as atomic

    if kill:
        ready = tmp_path / "ready"
        _kill_when_ready(
            "import pathlib, time\n"
            "import mvgeo.common.atomic as atomic\n"
            "from mvgeo.common.output import prepare_output\n"
            "real, calls = atomic.rename_no_replace, []\n"
            "def slow(src, dst):\n"
            "    calls.append(dst)\n"
            "    if len(calls) == 2:\n"
            f"        pathlib.Path({str(ready)!r}).write_text('1')\n"
            "        time.sleep(60)\n"
            "    real(src, dst)\n"
            "atomic.rename_no_replace = slow\n"
            f"with atomic.atomic_output_dir(prepare_output({str(out)!r}, command={CMD!r})) as tmp:\n"
            "    (tmp / 'a.txt').write_text('a')\n"
            "    (tmp / 'b.txt').write_text('b')\n", ready)
        return
    real, calls = atomic.rename_no_replace, []

    def interrupted(src, dst):
        calls.append(dst)
        if len(calls) == 2:
            raise KeyboardInterrupt
        real(src, dst)

    atomic.rename_no_replace = interrupted
    try:
        with pytest.raises(KeyboardInterrupt):
            with atomic_output_dir(prepare_output(out, command=CMD)) as tmp:
                (tmp / "a.txt").write_text("a")
                (tmp / "b.txt").write_text("b")
    finally:
        atomic.rename_no_replace = real


def test_a_command_killed_while_its_results_move_into_an_empty_out_leaves_no_finished_looking_output(tmp_path):
    """The manifest moves last: a SIGKILL between the moves leaves some results and no manifest, so the next
    command does not take the folder for a previous output (which --overwrite would replace, or a resume
    would build on); it refuses the folder, naming what is in it."""
    from mvgeo.common.output import MANIFEST_NAME

    out = tmp_path / "out"
    out.mkdir()
    _entries_moved_then(out, tmp_path, kill=True)
    assert (out / "a.txt").read_text() == "a" and MANIFEST_NAME not in os.listdir(out)
    for overwrite in (False, True):
        with pytest.raises(InputError, match=r"unfinished output \('a.txt'\)"):
            prepare_output(out, command=CMD, overwrite=overwrite)
    assert (out / "a.txt").read_text() == "a"


def test_a_ctrl_c_while_the_results_move_into_an_empty_out_takes_them_out_again(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    _entries_moved_then(out, tmp_path, kill=False)
    assert os.listdir(out) == []
    plan = prepare_output(out, command=CMD)
    assert plan.state == "empty"
    with atomic_output_dir(plan) as tmp:
        (tmp / "a.txt").write_text("a")
    assert sorted(os.listdir(out)) == [".denoise-gs-output.json", "a.txt"]
