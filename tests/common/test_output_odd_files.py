"""What sits beside or inside `--out` under a leftover's name is never a reason to crash or hang, and
files named like the product's internal ones (a file's record, the lock) are the user's: refused, never
replaced or written through."""

from __future__ import annotations

import json
import os
import socket
import sys

import pytest

from eval.pipeline.lock import output_lock
from mvgeo.common.atomic import atomic_output_dir
from mvgeo.common.errors import InputError
from mvgeo.common.jsonio import read_json_object
from mvgeo.common.output import (
    LOCK_NAME,
    MANIFEST_NAME,
    OWNER_SUFFIX,
    file_record_path,
    prepare_output,
    prepare_output_file,
    stale_leftovers,
    write_manifest,
)
from tests.common._out_policy import snapshot

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX file types")

CMD = "tool write"
DEEP = "[" * 100_000 + "]" * 100_000
OWNER_DEEP = "[" * 2000 + "]" * 2000  # within the owner file's 4096 bytes


@pytest.mark.timeout(30)  # a FIFO read would block
@pytest.mark.parametrize("owner", ["fifo", "deep json", "huge pid", "negative pid"])
def test_a_users_folder_named_like_a_leftover_with_an_odd_owner_file_is_kept_without_a_crash(tmp_path, owner):
    out = tmp_path / "out"
    out.mkdir()
    name = ".tmp-0123abcd"
    (out / name).mkdir()
    (out / name / "mine.txt").write_text("mine")
    path = out / (name + OWNER_SUFFIX)
    if owner == "fifo":
        os.mkfifo(path)
    elif owner == "deep json":
        path.write_text(OWNER_DEEP)
    else:
        pid = 10**20 if owner == "huge pid" else -(10**20)
        path.write_text(json.dumps({"entry": name, "host": socket.gethostname(), "pid": pid}))
    before = snapshot(tmp_path)
    assert stale_leftovers(out) == []
    with pytest.raises(InputError):
        prepare_output(out, command=CMD)
    assert snapshot(tmp_path) == before


def test_a_users_deeply_nested_json_is_a_typed_error(tmp_path):
    path = tmp_path / "split.json"
    path.write_text(DEEP)
    with pytest.raises(InputError, match="split.json"):
        read_json_object(path, fix="fix it")


def test_a_users_deeply_nested_file_named_like_the_manifest_is_not_a_crash(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / MANIFEST_NAME).write_text(DEEP)
    with pytest.raises(InputError, match="did not write"):
        prepare_output(out, command=CMD)


@pytest.mark.parametrize("kind", ["file", "link"])
def test_a_users_file_named_like_an_output_files_record_is_refused_not_replaced(tmp_path, kind):
    mine = tmp_path / "notes.txt"
    mine.write_text("my notes")
    record = file_record_path(tmp_path / "sel.json")
    if kind == "file":
        record.write_text("my other notes")
    else:
        record.symlink_to(mine)
    before = snapshot(tmp_path)
    with pytest.raises(InputError, match="record"):
        prepare_output_file(tmp_path / "sel.json", command="denoise select")
    assert snapshot(tmp_path) == before


def test_a_stale_record_of_the_command_for_a_deleted_output_file_may_be_replaced(tmp_path):
    """Guard of the fix above: the record a command left beside a file the user deleted is its own."""
    out = tmp_path / "sel.json"
    out.write_text("{}")
    from mvgeo.common.output import write_file_record
    write_file_record(out, "denoise select")
    out.unlink()
    assert prepare_output_file(out, command="denoise select") == out.resolve()


def test_a_symbolic_link_named_like_the_lock_is_not_written_through(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    write_manifest(out, "denoise-gs run", record_files=False)
    mine = tmp_path / "precious.txt"
    mine.write_text("precious")
    (out / LOCK_NAME).symlink_to(mine)
    before = snapshot(tmp_path)
    with pytest.raises(InputError, match="lock"):
        with output_lock(out):
            pass
    assert snapshot(tmp_path) == before


def test_an_atomic_write_after_an_odd_owner_file_still_leaves_the_users_folder(tmp_path):
    """The same through `atomic_output_dir` beside `--out` (prefix scan of the parent)."""
    name = ".out.tmp-0123abcd"
    (tmp_path / name).mkdir()
    (tmp_path / name / "mine.txt").write_text("mine")
    (tmp_path / (name + OWNER_SUFFIX)).write_text(OWNER_DEEP)
    before = snapshot(tmp_path)
    with atomic_output_dir(prepare_output(tmp_path / "out", command=CMD)) as tmp:
        (tmp / "a.txt").write_text("a")
    after = snapshot(tmp_path)
    assert {k: v for k, v in after.items() if not k.startswith("out")} == before
