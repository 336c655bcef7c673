"""What every refused command line must guarantee, checked in one place for the bad-input tests.

`assert_refused(main, argv, capsys, inputs=..., watch=...)` runs a console entry point
in-process and checks:

- the exit code (2 unless told otherwise; an argparse usage error counts, via SystemExit);
- no "Traceback" on stderr (and no native stack dump: "*** ");
- every input file and folder is byte-identical afterwards (contents, names, symlink targets);
- no new entry appeared in the watched folders (no temporary leftovers, no half-written --out).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path


def tree_digest(paths: Iterable[str | Path]) -> dict[str, str]:
    """Relative path -> content hash (``link:TARGET`` for a symbolic link, ``dir`` for a folder)
    of every entry under each path, the paths themselves included."""
    out: dict[str, str] = {}
    for root in map(Path, paths):
        entries = [root]
        if root.is_dir() and not root.is_symlink():
            entries += sorted(root.rglob("*"))
        for p in entries:
            key = str(p)
            if p.is_symlink():
                out[key] = "link:" + os.readlink(p)
            elif p.is_dir():
                out[key] = "dir"
            elif p.is_file():
                out[key] = hashlib.sha256(p.read_bytes()).hexdigest()
            else:
                out[key] = "missing"
    return out


def listing(folders: Iterable[str | Path]) -> dict[str, list[str]]:
    """Names directly inside each folder (hidden ones included)."""
    return {str(f): sorted(os.listdir(f)) for f in map(Path, folders)}


def run_main(main: Callable[[Sequence[str]], int], argv: Sequence[str], capsys) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of an entry point; argparse's SystemExit gives its code."""
    capsys.readouterr()
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse usage errors
        code = exc.code if isinstance(exc.code, int) else 1
    captured = capsys.readouterr()
    return int(code or 0), captured.out, captured.err


def assert_refused(main: Callable[[Sequence[str]], int], argv: Sequence[str], capsys, *,
                   inputs: Iterable[str | Path], watch: Iterable[str | Path], code: int = 2,
                   message: str | Sequence[str] = ()) -> str:
    """Run `main(argv)` and check the refusal contract (module docstring).

    Args:
        inputs: files/folders that must be byte-identical afterwards.
        watch: folders in which no new entry may appear (e.g. the parent of --out).
        code: expected exit code.
        message: text(s) stderr must contain.

    Returns:
        stderr.
    """
    inputs, watch = list(inputs), list(watch)
    before, names_before = tree_digest(inputs), listing(watch)
    got, _, err = run_main(main, argv, capsys)
    assert got == code, f"exit {got} (expected {code}); stderr:\n{err}"
    assert "Traceback" not in err, err
    assert "*** " not in err, err  # a native stack dump
    for text in [message] if isinstance(message, str) else message:
        assert text in err, f"{text!r} not in stderr:\n{err}"
    assert tree_digest(inputs) == before, "an input changed"
    assert listing(watch) == names_before, f"new entries: {listing(watch)} vs {names_before}"
    return err
