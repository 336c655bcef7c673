"""The output policy (`mvgeo.common.output`) and the atomic folder writer on top of it."""

from __future__ import annotations

import json
import os

import pytest

from mvgeo.common.atomic import atomic_output_dir, atomic_write_text
from mvgeo.common.errors import InputError
from mvgeo.common.output import (
    LOCK_NAME,
    MANIFEST_NAME,
    file_record_path,
    prepare_output,
    prepare_output_file,
    read_manifest,
    resumable_output_dir,
    write_file_record,
    write_manifest,
    write_output_file,
)

CMD = "tool write"


def _tree(root):
    """Relative path -> bytes (None for folders, "-> target" for links) of everything under `root`."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = os.path.join(dirpath, name)
            if os.path.islink(p):
                content = "-> " + os.readlink(p)
            elif os.path.isdir(p):
                content = None
            else:
                with open(p, "rb") as f:
                    content = f.read()
            out[os.path.relpath(p, root)] = content
    return out


def _temporaries(root):
    return [p for p in _tree(root) if ".tmp-" in p or ".old-" in p or "probe" in p]


def _write(out, *, command=CMD, overwrite=False, files=("a.txt",)):
    with atomic_output_dir(prepare_output(out, command=command, overwrite=overwrite)) as tmp:
        for name in files:
            (tmp / name).write_text(name)


def test_new_folder_gets_the_outputs_and_a_manifest(tmp_path):
    out = tmp_path / "a" / "b" / "out"  # missing parents are created
    _write(out)
    assert sorted(os.listdir(out)) == [MANIFEST_NAME, "a.txt"]
    m = json.loads((out / MANIFEST_NAME).read_text())
    assert m["command"] == CMD and m["version"] and m["created_utc"].endswith("Z")
    assert not _temporaries(tmp_path)


def test_empty_folder_is_written_in_place(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    inode = out.stat().st_ino
    _write(out)
    assert out.stat().st_ino == inode  # filled, not renamed or replaced
    assert sorted(os.listdir(out)) == [MANIFEST_NAME, "a.txt"]


def test_foreign_folder_file_and_links_are_refused_untouched(tmp_path):
    user = tmp_path / "user"
    user.mkdir()
    (user / "thesis.tex").write_text("x")
    afile = tmp_path / "file.txt"
    afile.write_text("mine")
    link_dir = tmp_path / "link_dir"
    link_dir.symlink_to(user)
    broken = tmp_path / "broken"
    broken.symlink_to(tmp_path / "nowhere")
    before = _tree(tmp_path)
    for out, needle in ((user, "did not write"), (afile, "not a folder"), (link_dir, "did not write"),
                        (broken, "broken symbolic link")):
        for overwrite in (False, True):
            with pytest.raises(InputError, match=needle) as exc:
                prepare_output(out, command=CMD, overwrite=overwrite)
            assert str(out) in str(exc.value) and "fix:" in str(exc.value)
    assert _tree(tmp_path) == before
    assert broken.is_symlink() and link_dir.is_symlink()


def test_previous_output_needs_overwrite_and_the_same_command(tmp_path):
    out = tmp_path / "out"
    _write(out, files=("old.txt",))
    with pytest.raises(InputError, match="previous output") as exc:
        prepare_output(out, command=CMD)
    assert "--overwrite" in str(exc.value)
    with pytest.raises(InputError, match="output of `tool write`, not of `other cmd`"):
        prepare_output(out, command="other cmd", overwrite=True)
    _write(out, overwrite=True, files=("new.txt",))
    assert sorted(os.listdir(out)) == [MANIFEST_NAME, "new.txt"]
    assert not _temporaries(tmp_path)
    # a symbolic link to a previous output: the folder it names is replaced, the link kept
    link = tmp_path / "link"
    link.symlink_to(out)
    _write(link, overwrite=True, files=("third.txt",))
    assert link.is_symlink() and sorted(os.listdir(link)) == [MANIFEST_NAME, "third.txt"]


def test_corrupt_manifest_counts_as_foreign(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / MANIFEST_NAME).write_text("{not json")
    (out / "data.bin").write_bytes(b"1")
    with pytest.raises(InputError, match="did not write"):
        prepare_output(out, command=CMD, overwrite=True)


@pytest.mark.parametrize("where", ["equal", "inside", "contains", "dotdot", "symlink"])
def test_out_overlapping_an_input_is_refused(tmp_path, where):
    data = tmp_path / "data"
    (data / "images").mkdir(parents=True)
    (data / "images" / "v.png").write_bytes(b"png")
    (tmp_path / "alias").symlink_to(data / "images")
    inp = data / "images"
    out = {"equal": inp, "inside": inp / "out", "contains": data,
           "dotdot": data / "images" / ".." / "images", "symlink": tmp_path / "alias"}[where]
    before = _tree(tmp_path)
    with pytest.raises(InputError, match="--out (is|contains|is inside) the input"):
        prepare_output(out, command=CMD, inputs=[inp], overwrite=True)
    assert _tree(tmp_path) == before


def test_current_folder(tmp_path, monkeypatch):
    cwd = tmp_path / "work"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    _write(".")  # empty: written into, never renamed
    assert sorted(os.listdir(cwd)) == [MANIFEST_NAME, "a.txt"] and os.getcwd() == str(cwd)
    with pytest.raises(InputError, match="current folder"):  # replacing it would rename the cwd
        prepare_output(".", command=CMD, overwrite=True)
    before = _tree(tmp_path)
    (cwd / "sub").mkdir()
    monkeypatch.chdir(cwd / "sub")
    with pytest.raises(InputError, match="current folder"):  # an ancestor of the cwd
        prepare_output("..", command=CMD, overwrite=True)
    (cwd / "sub").rmdir()
    assert _tree(tmp_path) == before


def test_read_only_parent_fails_before_any_work(tmp_path, monkeypatch):
    # Running as root ignores permission bits, so `chmod` cannot make a folder read-only here; the
    # check is exercised through `os.access`, which is what it consults first.
    parent = tmp_path / "ro"
    parent.mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if os.fspath(p) == str(parent)
                        else real_access(p, mode, **kw))
    with pytest.raises(InputError, match="not writable") as exc:
        prepare_output(parent / "a" / "out", command=CMD)  # nearest existing parent: ro
    assert "fix:" in str(exc.value)
    with pytest.raises(InputError, match="not writable"):
        prepare_output_file(parent / "sel.json", command=CMD)
    assert os.listdir(parent) == []


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores permission bits: chmod cannot make a folder read-only")
def test_read_only_parent_by_chmod(tmp_path):
    parent = tmp_path / "ro"
    parent.mkdir()
    parent.chmod(0o555)
    try:
        with pytest.raises(InputError, match="not writable"):
            prepare_output(parent / "out", command=CMD)
    finally:
        parent.chmod(0o755)


def test_parent_that_is_a_file(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(InputError, match="is not a folder"):
        prepare_output(tmp_path / "f" / "out", command=CMD)


def test_error_in_the_block_leaves_nothing(tmp_path):
    out = tmp_path / "new" / "deeper" / "out"
    with pytest.raises(RuntimeError), atomic_output_dir(prepare_output(out, command=CMD)) as tmp:
        (tmp / "half.txt").write_text("1")
        raise RuntimeError("boom")
    assert os.listdir(tmp_path) == []  # the parents it created are gone too
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(RuntimeError), atomic_output_dir(prepare_output(empty, command=CMD)) as tmp:
        (tmp / "half.txt").write_text("1")
        raise RuntimeError("boom")
    assert os.listdir(empty) == []


def test_something_appearing_at_out_during_the_work_is_kept(tmp_path):
    out = tmp_path / "out"
    plan = prepare_output(out, command=CMD)
    with pytest.raises(InputError, match="did not write"), atomic_output_dir(plan) as tmp:
        (tmp / "a.txt").write_text("1")
        out.mkdir()
        (out / "user.txt").write_text("user")
    assert sorted(os.listdir(tmp_path)) == ["out"] and os.listdir(out) == ["user.txt"]


def test_resumable_folder(tmp_path):
    out = tmp_path / "o" / "x"
    plan = prepare_output(out, command="run cmd", resume=True)
    with pytest.raises(InputError), resumable_output_dir(plan) as path:
        assert read_manifest(path)["command"] == "run cmd"
        raise InputError("bad scene file")
    assert os.listdir(tmp_path) == []  # a failed first run leaves no empty folder behind
    with resumable_output_dir(prepare_output(out, command="run cmd", resume=True)) as path:
        (path / "round1").mkdir()
    plan = prepare_output(out, command="run cmd", resume=True)  # resumed without --overwrite
    assert plan.state == "previous"
    with pytest.raises(InputError), resumable_output_dir(plan):
        raise InputError("later failure")
    assert sorted(os.listdir(out)) == [MANIFEST_NAME, "round1"]  # a resumed folder is kept
    with pytest.raises(InputError, match="not of `other cmd`"):
        prepare_output(out, command="other cmd", resume=True)


def test_a_folder_without_manifest_is_never_taken_for_a_resumable_output(tmp_path):
    # Entries named like the run's own ("round1", "report.md") do not make a folder ours: only the
    # manifest does (a user's folder of that shape was once resumed into and its files deleted).
    old = tmp_path / "old"
    (old / "round1").mkdir(parents=True)
    (old / "report.md").write_text("r")
    with pytest.raises(InputError, match="did not write"):
        prepare_output(old, command="run cmd", resume=True)
    locked = tmp_path / "locked"
    locked.mkdir()
    (locked / LOCK_NAME).write_text("123")
    assert prepare_output(locked, command="run cmd", resume=True).state == "empty"


@pytest.mark.parametrize("added", ["top.txt", "sub/nested.txt", "emptydir/", "link", "a.txt (changed)"])
def test_overwrite_refuses_a_previous_output_holding_what_it_did_not_write(tmp_path, added):
    out = tmp_path / "out"
    _write(out, files=("a.txt",))
    (out / "sub").mkdir()  # after the manifest: not the command's either
    if added == "top.txt":
        (out / "top.txt").write_text("mine")
    elif added == "sub/nested.txt":
        (out / "sub" / "nested.txt").write_text("mine")
    elif added == "emptydir/":
        (out / "sub").rmdir()
        (out / "emptydir").mkdir()
    elif added == "link":
        (out / "sub").rmdir()
        (out / "link").symlink_to(tmp_path)
    else:
        (out / "sub").rmdir()
        (out / "a.txt").write_text("edited by the user")
    before = _tree(tmp_path)
    with pytest.raises(InputError, match="did not write or that changed since"):
        _write(out, overwrite=True, files=("b.txt",))
    assert _tree(tmp_path) == before


def test_overwrite_replaces_an_unchanged_previous_output(tmp_path):
    out = tmp_path / "out"
    with atomic_output_dir(prepare_output(out, command=CMD)) as tmp:
        (tmp / "sub").mkdir()
        (tmp / "sub" / "x.bin").write_bytes(b"x" * 10)
        (tmp / "link").symlink_to("sub/x.bin")
    m = json.loads((out / MANIFEST_NAME).read_text())
    assert m["dirs"] == ["sub"] and set(m["files"]) == {"sub/x.bin", "link"}
    assert m["files"]["link"] == {"link": "sub/x.bin"}
    os.utime(out / "sub" / "x.bin", ns=(1, 1))  # a copy that kept the content: still the command's file
    _write(out, overwrite=True, files=("b.txt",))
    assert sorted(os.listdir(out)) == [MANIFEST_NAME, "b.txt"]


def test_an_edit_of_the_same_size_with_its_time_set_back_is_still_an_edit(tmp_path):
    out = tmp_path / "out"
    _write(out, files=("a.txt",))
    st = (out / "a.txt").stat()
    (out / "a.txt").write_text("A.txt")  # same size
    os.utime(out / "a.txt", ns=(st.st_atime_ns, st.st_mtime_ns))
    with pytest.raises(InputError, match="changed since"):
        _write(out, overwrite=True)
    assert (out / "a.txt").read_text() == "A.txt"


def test_overwrite_refuses_a_manifest_that_lists_no_files(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.txt").write_text("a")
    (out / MANIFEST_NAME).write_text(json.dumps({"command": CMD, "version": "0", "format": 1}))
    with pytest.raises(InputError, match="does not list its files"):
        _write(out, overwrite=True)
    assert (out / "a.txt").read_text() == "a"


def test_a_leftover_temporary_folder_is_named_as_such(tmp_path):
    out = tmp_path / "out"
    (out / ".tmp-3f368950").mkdir(parents=True)
    with pytest.raises(InputError, match="temporary folder of an interrupted run"):
        prepare_output(out, command=CMD)


def test_output_file_policy(tmp_path):
    (tmp_path / "dir").mkdir()
    with pytest.raises(InputError, match=r"(?s)is a folder.*dir/sel\.json"):
        prepare_output_file(tmp_path / "dir", command=CMD, example_name="sel.json")
    f = tmp_path / "sel.json"
    f.write_text("{}")
    with pytest.raises(InputError, match="--overwrite"):
        prepare_output_file(f, command=CMD)
    # A file the command did not write is never replaced, --overwrite or not.
    with pytest.raises(InputError, match="no record"):
        prepare_output_file(f, command=CMD, overwrite=True)
    write_file_record(f, CMD)
    assert file_record_path(f).name == ".sel.json" + MANIFEST_NAME
    assert prepare_output_file(f, command=CMD, overwrite=True) == f.resolve()
    with pytest.raises(InputError, match="does not say `other cmd` wrote it"):
        prepare_output_file(f, command="other cmd", overwrite=True)
    os.utime(f, ns=(1, 1))  # same content, new time: still ours
    assert prepare_output_file(f, command=CMD, overwrite=True) == f.resolve()
    f.write_text('{"edited": 1}')
    with pytest.raises(InputError, match="changed since"):
        prepare_output_file(f, command=CMD, overwrite=True)
    with pytest.raises(InputError, match="is inside the input"):
        prepare_output_file(tmp_path / "dir" / "s.json", command=CMD, inputs=[tmp_path / "dir"])


def test_output_file_through_a_link_needs_the_targets_record(tmp_path):
    target = tmp_path / "real" / "t.splat"
    target.parent.mkdir()
    target.write_bytes(b"user data")
    link = tmp_path / "link.splat"
    link.symlink_to(target)
    with pytest.raises(InputError, match="no record"):
        prepare_output_file(link, command=CMD, overwrite=True)
    write_file_record(target, CMD)
    assert prepare_output_file(link, command=CMD, overwrite=True) == target.resolve()


def test_atomic_write_text_leaves_no_temporary_on_failure(tmp_path):
    (tmp_path / "d").mkdir()
    with pytest.raises(IsADirectoryError):
        atomic_write_text(tmp_path / "d", "x")
    assert os.listdir(tmp_path) == ["d"] and os.listdir(tmp_path / "d") == []


def test_manifest_roundtrip_and_garbage(tmp_path):
    write_manifest(tmp_path, "a b")
    assert read_manifest(tmp_path)["command"] == "a b"
    (tmp_path / MANIFEST_NAME).write_text(json.dumps({"command": 3}))
    assert read_manifest(tmp_path) is None


@pytest.mark.parametrize("name", [LOCK_NAME, MANIFEST_NAME + ".tmp-notes"])
def test_overwrite_counts_files_named_like_internal_ones(tmp_path, name):
    # A previous output of a command that writes at once never holds a lock or a manifest temporary:
    # a file with such a name is the user's.
    out = tmp_path / "out"
    _write(out)
    (out / name).write_text("the user's")
    with pytest.raises(InputError, match="did not write"):
        _write(out, overwrite=True)
    assert (out / name).read_text() == "the user's"


def test_a_users_file_named_like_the_lock_is_not_a_lock(tmp_path):
    folder = tmp_path / "f"
    folder.mkdir()
    (folder / LOCK_NAME).write_text("precious notes")
    with pytest.raises(InputError, match="did not write"):
        prepare_output(folder, command="run cmd", resume=True)
    (folder / LOCK_NAME).write_text("12345\n")  # what a killed run leaves: a pid
    assert prepare_output(folder, command="run cmd", resume=True).state == "empty"


def test_a_file_name_too_long_for_its_record_is_refused_up_front(tmp_path):
    with pytest.raises(InputError, match="too long"):
        prepare_output_file(tmp_path / ("a" * 230 + ".splat"), command=CMD)
    assert os.listdir(tmp_path) == []


def test_a_run_that_loses_the_lock_leaves_the_winners_manifest(tmp_path):
    out = tmp_path / "out"
    plan = prepare_output(out, command="run cmd", resume=True)
    with pytest.raises(InputError, match="another run"):
        with resumable_output_dir(plan):
            (out / LOCK_NAME).write_text("999\n")  # the winner's lock, taken meanwhile
            raise InputError("another run (pid 999) is writing this folder")
    assert sorted(os.listdir(out)) == [MANIFEST_NAME, LOCK_NAME]


def _leftovers(folder) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".tmp-" in p.name)


def test_output_file_written_new_and_replaced_when_ours(tmp_path):
    out = prepare_output_file(tmp_path / "a.json", command=CMD)
    write_output_file(out, CMD, lambda tmp: tmp.write_text("one"))
    assert out.read_text() == "one" and file_record_path(out).is_file() and _leftovers(tmp_path) == []
    out = prepare_output_file(tmp_path / "a.json", command=CMD, overwrite=True)
    write_output_file(out, CMD, lambda tmp: tmp.write_text("two"))
    assert out.read_text() == "two" and _leftovers(tmp_path) == []
    # a file system without hard links: checked, then renamed
    out.unlink()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(os, "link", lambda *a, **k: (_ for _ in ()).throw(PermissionError(1, "no links")))
        write_output_file(out, CMD, lambda tmp: tmp.write_text("three"))
    assert out.read_text() == "three" and _leftovers(tmp_path) == []


def test_output_file_that_appears_or_changes_while_the_output_is_made_is_never_replaced(tmp_path):
    """`prepare_output_file` checks --out before the work; `write_output_file` after it. A file the user put
    at --out, or changed there, in between is kept, byte for byte, and the command stops with a typed error."""
    out = prepare_output_file(tmp_path / "b.json", command=CMD)

    def make(tmp):
        tmp.write_text("ours")
        out.write_text("the user's")  # appears while the output is being made

    with pytest.raises(InputError, match="changed while the output was being made: it has no record"):
        write_output_file(out, CMD, make)
    assert out.read_text() == "the user's" and not file_record_path(out).exists() and _leftovers(tmp_path) == []
    # ... or at the last moment, after the check and before the hard link (with and without hard links)
    real_link = os.link

    def link_late(src, dst):
        out.write_text("the user's, late")
        real_link(src, dst)

    def no_link_late(src, dst):
        out.write_text("the user's, late")
        raise PermissionError(1, "no links")

    def no_link_late_before_the_claim(src, dst):  # appears after the no-link check, before the claim
        raise PermissionError(1, "no links")

    real_open = os.open

    def open_late(p, flags, *a):
        if flags & os.O_EXCL and os.fspath(p) == os.fspath(out):
            out.write_text("the user's, late")
        return real_open(p, flags, *a)

    out.unlink()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(os, "link", no_link_late_before_the_claim)
        mp.setattr(os, "open", open_late)
        with pytest.raises(InputError, match="a file appeared there"):
            write_output_file(out, CMD, lambda tmp: tmp.write_text("ours"))
    assert out.read_text() == "the user's, late" and _leftovers(tmp_path) == []
    for link in (link_late, no_link_late):
        out.unlink()
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(os, "link", link)
            with pytest.raises(InputError, match="a file appeared there"):
                write_output_file(out, CMD, lambda tmp: tmp.write_text("ours"))
        assert out.read_text() == "the user's, late" and _leftovers(tmp_path) == []
    # ours when planned, edited by the user before the rename
    out.unlink()
    write_output_file(out, CMD, lambda tmp: tmp.write_text("ours"))
    out = prepare_output_file(out, command=CMD, overwrite=True)

    def edit(tmp):
        tmp.write_text("ours again")
        out.write_text("edited by the user")

    with pytest.raises(InputError, match="changed while the output was being made: it changed since"):
        write_output_file(out, CMD, edit)
    assert out.read_text() == "edited by the user" and _leftovers(tmp_path) == []


def test_output_file_whose_record_cannot_be_written_is_a_typed_error(tmp_path, monkeypatch):
    import mvgeo.common.output as output

    out = prepare_output_file(tmp_path / "c.json", command=CMD)

    def full(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(output, "write_file_record", full)
    with pytest.raises(InputError, match="its record could not be") as exc:
        write_output_file(out, CMD, lambda tmp: tmp.write_text("ours"))
    assert "c.json" in str(exc.value) and _leftovers(tmp_path) == []


def test_output_file_in_a_folder_still_to_be_made(tmp_path):
    """`prepare_output_file` accepts `NEW/SUB/F` under a writable folder; `write_output_file` makes the folders
    (and takes them away again when the write fails)."""
    out = prepare_output_file(tmp_path / "new" / "sub" / "a.json", command=CMD)
    write_output_file(out, CMD, lambda tmp: tmp.write_text("one"))
    assert out.read_text() == "one" and _leftovers(out.parent) == []
    bad = prepare_output_file(tmp_path / "other" / "sub" / "b.json", command=CMD)

    def fail(tmp):
        raise RuntimeError("the content could not be made")

    with pytest.raises(RuntimeError):
        write_output_file(bad, CMD, fail)
    assert not (tmp_path / "other").exists()


def test_a_name_too_long_for_the_temporary_folder_beside_it_is_refused_up_front(tmp_path):
    # The temporary sibling `.<name>.tmp-XXXXXXXX` and its owner file add 20 bytes to the name; the file system
    # takes 255. The longest name that fits is written; one byte more is refused before any work.
    longest = 255 - len(".") - len(".tmp-") - 8 - len(".owner")
    plan = prepare_output(tmp_path / ("a" * longest), command=CMD)
    with atomic_output_dir(plan) as tmp:
        (tmp / "x.txt").write_text("x")
    assert (tmp_path / ("a" * longest) / "x.txt").is_file()
    with pytest.raises(InputError, match="too long"):
        prepare_output(tmp_path / ("b" * (longest + 1)), command=CMD)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a" * longest]
    empty = tmp_path / ("c" * 250)  # an existing empty folder is written in place: no sibling, no limit
    empty.mkdir()
    with atomic_output_dir(prepare_output(empty, command=CMD)) as tmp:
        (tmp / "y.txt").write_text("y")
    assert (empty / "y.txt").is_file()
