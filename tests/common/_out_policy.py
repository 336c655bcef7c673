"""Shared checks of the `tests/*/test_cli_out_policy.py` modules: a refused `--out` exits with code 2,
prints no traceback, leaves every file byte-identical and leaves no temporary behind."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from mvgeo.common.output import MANIFEST_NAME, write_manifest

TEMP_MARKERS = (".tmp-", ".old-", "-probe-")


def snapshot(root: Path) -> dict[str, str | None]:
    """Relative path -> sha256 of the content (None for a folder, "-> target" for a link, "special" for a
    FIFO, socket or device, which is never opened: a FIFO would block), for every entry under `root`."""
    out: dict[str, str | None] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = os.path.join(dirpath, name)
            rel = os.path.relpath(p, root)
            if os.path.islink(p):
                out[rel] = "-> " + os.readlink(p)
            elif os.path.isdir(p):
                out[rel] = None
            elif os.path.isfile(p):
                with open(p, "rb") as f:
                    out[rel] = hashlib.sha256(f.read()).hexdigest()
            else:
                out[rel] = "special"
    return out


def temporaries(root: Path) -> list[str]:
    return [p for p in snapshot(root) if any(m in os.path.basename(p) for m in TEMP_MARKERS)]


def assert_refused(main, argv: list[str], capsys, root: Path, *needles: str) -> str:
    """Run `main(argv)` in-process; check exit 2, a one-paragraph error naming `needles`, no traceback,
    nothing under `root` changed or added (inputs byte-identical, no output, no temporaries).

    Returns:
        stderr.
    """
    capsys.readouterr()
    before = snapshot(root)
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, (code, err)
    assert err.startswith("error:") and "Traceback" not in err, err
    for needle in needles:
        assert needle in err, (needle, err)
    after = snapshot(root)
    assert after == before, {k: (before.get(k), after.get(k)) for k in set(before) | set(after)
                             if before.get(k) != after.get(k)}
    assert not temporaries(root)
    return err


def fake_previous_output(folder: Path, command: str, files: dict[str, str] | None = None) -> Path:
    """A folder that looks like a previous output of `command` (its files and manifest)."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in (files or {"old.txt": "old"}).items():
        (folder / name).write_text(text)
    write_manifest(folder, command)
    assert (folder / MANIFEST_NAME).is_file()
    return folder


def readonly_access(monkeypatch, folder: Path) -> None:
    """Make `os.access` report `folder` as not writable.

    The tests run as root in CI, where permission bits are ignored and `chmod` cannot make a folder
    read-only; the output check consults `os.access` first, so this exercises its refusal.
    """
    real = os.access
    target = str(Path(folder).resolve())

    def access(path, mode, *args, **kwargs):
        if str(Path(path).resolve()) == target and mode & os.W_OK:
            return False
        return real(path, mode, *args, **kwargs)

    monkeypatch.setattr(os, "access", access)
