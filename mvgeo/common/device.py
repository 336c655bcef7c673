"""`--device` of every command line: one parser that checks the device exists before any work.

Accepted: ``cpu``, ``cuda``, ``cuda:N``, ``mps`` and ``auto`` (``cuda`` when CUDA is
available, else ``cpu``). Anything else, or a device this machine does not have
(``cuda`` on a CPU-only machine or build, ``cuda:3`` with one GPU), is an
`InputError` naming the option and what to pass instead: a command fails in a
second instead of after the first stage's computation.

torch is imported inside the function, so importing this module (and
`mvgeo.common`) stays light.
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING

from mvgeo.common.errors import InputError

if TYPE_CHECKING:
    import torch

__all__ = ["DEVICE_HELP", "DEVICE_TYPES", "resolve_device"]

#: Device types `resolve_device` accepts (``auto`` picks ``cuda`` or ``cpu``).
DEVICE_TYPES: tuple[str, ...] = ("cpu", "cuda", "mps", "auto")

#: Help text of a `--device` option.
DEVICE_HELP = "torch device: cpu, cuda, cuda:N, mps, or auto (cuda when available, else cpu)"

_DEVICE_RE = re.compile(r"(?P<type>[a-z]+)(?::(?P<index>\d+))?")


def resolve_device(text: str, *, option: str = "--device") -> torch.device:
    """Parse a device string and check that this machine has that device.

    Args:
        text: ``cpu``, ``cuda``, ``cuda:N``, ``mps`` or ``auto`` (case and surrounding
            blanks ignored).
        option: the option's name, for the message.

    Returns:
        The `torch.device` (``auto`` resolved to ``cuda`` or ``cpu``).

    Raises:
        InputError: an unknown device type or syntax, or a device that is not present.
    """
    import torch

    given = str(text).strip().lower()
    m = _DEVICE_RE.fullmatch(given)
    if m is None or m["type"] not in DEVICE_TYPES or (m["index"] is not None and m["type"] in ("auto", "mps")):
        raise InputError(f"{option} {text!r}: unknown device",
                         fix="use cpu, cuda, cuda:N (N = GPU index), mps, or auto")
    kind, index = m["type"], None if m["index"] is None else int(m["index"])
    if kind == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if kind == "cpu":
        return torch.device("cpu") if index is None else torch.device("cpu", index)
    if kind == "mps":
        if not torch.backends.mps.is_available():
            raise InputError(f"{option} mps: the Apple MPS backend is not available on this machine",
                             fix="use --device cpu (or auto)")
        return torch.device("mps")
    if not torch.cuda.is_available():
        why = "this torch build has no CUDA support" if torch.version.cuda is None else "no CUDA GPU is visible"
        raise InputError(f"{option} {given}: CUDA is not available ({why})", fix="use --device cpu (or auto)")
    count = torch.cuda.device_count()
    if index is not None and index >= count:
        raise InputError(f"{option} {given}: this machine has {count} CUDA device(s) (cuda:0..cuda:{count - 1})",
                         fix=f"use an index below {count}, or --device cuda")
    return torch.device("cuda") if index is None else torch.device("cuda", index)
