"""Image file I/O at the project's boundary (see docs/conventions.md).

Arrays are H x W x 3 float32 RGB in [0, 1]. cv2 does the decoding (BGR) and
we convert once here. cv2 is imported on the first read or write, so importing
this module stays light (`tests/common/test_import_light.py`).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mvgeo.common.errors import InputError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")
#: Camera and phone photo formats OpenCV does not decode (HEIF, AVIF, raw). `list_images` refuses a folder
#: holding one without a readable file of the same name (RAW+JPEG and HEIC+JPEG pairs read the JPEG), so no
#: photo is left out silently.
UNREADABLE_PHOTO_SUFFIXES = (".heic", ".heif", ".avif", ".dng", ".cr2", ".cr3", ".nef", ".nrw", ".arw", ".raf",
                             ".orf", ".rw2", ".pef", ".srw")

_log = logging.getLogger(__name__)
#: Folders whose subfolders of images `list_images` has warned about (once per folder and process).
_warned_subfolders: set[Path] = set()


def list_images(folder: str | Path) -> list[Path]:
    """Sorted image files (by name) directly inside `folder`.

    Images in its subfolders are not used; a warning names the (non-hidden) subfolders that hold some, so
    no photo is left out without a word.

    Raises:
        InputError: the folder is missing, not a folder, holds no images, or holds a broken
            symbolic link with an image name, or an image whose file name is not UTF-8 (named), or a
            photo in a format OpenCV does not read (`UNREADABLE_PHOTO_SUFFIXES`) without a readable file of
            the same name.
    """
    folder = Path(folder)
    try:
        return _list_images(folder)
    except PermissionError as exc:  # the folder, a folder above it, or an entry (readable but not searchable)
        raise InputError(f"cannot read the folder ({exc.strerror or exc})", path=folder,
                         fix="check the permissions of the folder and those above it (readable and searchable: "
                             "`chmod u+rx`)") from exc


def _list_images(folder: Path) -> list[Path]:
    if not folder.exists():
        raise InputError("folder does not exist", path=folder, fix="pass a folder of images")
    if not folder.is_dir():
        raise InputError("not a folder", path=folder, fix="pass a folder of images")
    entries = list(folder.iterdir())
    named = sorted(p for p in entries if p.suffix.lower() in IMAGE_SUFFIXES)
    for p in named:
        try:
            p.name.encode("utf-8")
        except UnicodeEncodeError:  # bytes the file system gave undecoded: OpenCV and the records cannot take it
            raise InputError(f"image file name {os.fsencode(p.name)!r} is not UTF-8 text", path=folder,
                             fix="rename the file (e.g. `mv` it to an ASCII name)") from None
        if p.is_symlink() and not p.exists():  # a photo we would silently lose
            raise InputError("broken symbolic link: the image it points to does not exist", path=p,
                             fix=f"restore its target ({os.readlink(p)}) or remove the link")
    files = [p for p in named if p.is_file()]
    stems = {p.stem for p in files}
    unread = sorted(p.name for p in entries
                    if p.suffix.lower() in UNREADABLE_PHOTO_SUFFIXES and p.stem not in stems and p.is_file())
    if unread:
        shown = ", ".join(unread[:5]) + (f" and {len(unread) - 5} more" if len(unread) > 5 else "")
        raise InputError(f"{len(unread)} photo(s) in a format this tool does not read ({shown}); they would be "
                         "left out", path=folder,
                         fix="convert them to JPEG or PNG (e.g. `heif-convert` for HEIC, `darktable-cli` or "
                             "`dcraw` for raw files), or move them out of the folder")
    if not files:
        raise InputError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in folder", path=folder,
                         fix="put PNG/JPEG images directly in this folder")
    _warn_about_subfolders(folder, entries)
    return files


def _warn_about_subfolders(folder: Path, entries: list[Path]) -> None:
    """Warn (once per folder) about the non-hidden subfolders of `folder` that hold image files: their images
    are not used."""
    if folder in _warned_subfolders:
        return
    held = {}
    for sub in sorted(p for p in entries if not p.name.startswith(".") and p.is_dir()):
        try:
            n = sum(1 for q in sub.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES and q.is_file())
        except OSError:  # an unreadable subfolder: nothing to say about it
            continue
        if n:
            held[sub.name] = n
    if held:
        _warned_subfolders.add(folder)
        _log.warning("%s: %d image(s) in its subfolder(s) %s are not used, only the images directly in the folder "
                     "(move them up to use them)", folder, sum(held.values()),
                     ", ".join(f"{name}/ ({n})" for name, n in held.items()))


def check_distinct_stems(names: Sequence[str], *, path: str | Path) -> None:
    """Refuse file names that share a stem (`a.png` and `a.jpg`), ignoring case (`A.png` and `a.jpg`): a
    command that writes `<stem>.png` per input would write one over the other, and on a case-insensitive
    file system (macOS, Windows) `A.png` is `a.png`.

    Raises:
        InputError: naming the first two clashing names and `path`.
    """
    seen: dict[str, str] = {}
    for name in names:
        stem = Path(name).stem
        if stem.casefold() in seen:
            raise InputError(f"two images share the name {stem!r} ({seen[stem.casefold()]}, {name}); the outputs "
                             "are named by stem (case aside), so one would replace the other", path=path,
                             fix="rename or remove one of them")
        seen[stem.casefold()] = name


def jpeg_exif_orientation(data: bytes | np.ndarray) -> int:
    """The EXIF Orientation tag (1..8) of JPEG file bytes; 1 (as stored) when absent or unreadable.

    Walks the JPEG markers up to the first scan, finds the APP1 "Exif" segment, and reads tag
    0x0112 from IFD0 of its TIFF block (either byte order).
    """
    b = data if isinstance(data, bytes) else np.asarray(data, np.uint8).tobytes()
    if b[:2] != b"\xff\xd8":
        return 1
    i = 2
    while i + 4 <= len(b) and b[i] == 0xFF:
        marker, length = b[i + 1], int.from_bytes(b[i + 2:i + 4], "big")
        if marker == 0xDA or length < 2:  # start of scan: no more metadata
            return 1
        seg = b[i + 4:i + 2 + length]
        if marker == 0xE1 and seg[:6] == b"Exif\x00\x00":
            return _tiff_orientation(seg[6:])
        i += 2 + length
    return 1


def webp_exif_orientation(data: bytes | np.ndarray) -> int:
    """The EXIF Orientation tag (1..8) of WebP file bytes; 1 (as stored) when absent or unreadable.

    Walks the RIFF chunks for the "EXIF" one (its TIFF block, after an optional "Exif\\0\\0" header) and
    reads tag 0x0112 from IFD0.
    """
    b = data if isinstance(data, bytes) else np.asarray(data, np.uint8).tobytes()
    if len(b) < 12 or b[:4] != b"RIFF" or b[8:12] != b"WEBP":
        return 1
    i = 12
    while i + 8 <= len(b):
        fourcc, size = b[i:i + 4], int.from_bytes(b[i + 4:i + 8], "little")
        if fourcc == b"EXIF":
            t = b[i + 8:i + 8 + size]
            return _tiff_orientation(t[6:] if t[:6] == b"Exif\x00\x00" else t)
        i += 8 + size + (size & 1)  # chunks are padded to an even size
    return 1


def exif_orientation(data: bytes | np.ndarray) -> int:
    """The EXIF Orientation tag (1..8) `read_image` applies: a JPEG's or a WebP's (by their content, not
    their file name); 1 for any other file or without one."""
    b = data if isinstance(data, bytes) else np.asarray(data, np.uint8).tobytes()
    return jpeg_exif_orientation(b) if b[:2] == b"\xff\xd8" else webp_exif_orientation(b)


def _tiff_orientation(t: bytes) -> int:
    if len(t) < 8 or t[:2] not in (b"II", b"MM"):
        return 1
    order = "little" if t[:2] == b"II" else "big"
    ifd = int.from_bytes(t[4:8], order)
    if ifd + 2 > len(t):
        return 1
    for k in range(int.from_bytes(t[ifd:ifd + 2], order)):
        e = ifd + 2 + 12 * k
        if e + 12 > len(t):
            break
        if int.from_bytes(t[e:e + 2], order) == 0x0112:  # Orientation, type SHORT, count 1: value inline
            value = int.from_bytes(t[e + 8:e + 10], order)
            return value if 1 <= value <= 8 else 1
    return 1


def apply_exif_orientation(img: np.ndarray, orientation: int) -> np.ndarray:
    """Turn an (H, W, ...) array stored with EXIF `orientation` into the upright photo.

    1 as is, 2 mirrored left-right, 3 rotated 180, 4 mirrored top-bottom, 5 transposed,
    6 rotated 90 degrees clockwise, 7 transversed, 8 rotated 90 degrees counter-clockwise
    (the TIFF/EXIF definitions; what PIL's `ImageOps.exif_transpose` does).
    """
    ops = {
        1: lambda a: a,
        2: lambda a: a[:, ::-1],
        3: lambda a: a[::-1, ::-1],
        4: lambda a: a[::-1],
        5: lambda a: a.swapaxes(0, 1),
        6: lambda a: np.rot90(a, k=-1),
        7: lambda a: a[::-1, ::-1].swapaxes(0, 1),
        8: lambda a: np.rot90(a, k=1),
    }
    return np.ascontiguousarray(ops.get(int(orientation), ops[1])(img))


#: EXIF tags: the Exif sub-IFD pointer of IFD0, and FocalLengthIn35mmFilm (SHORT, millimetres; 0 = unknown).
_EXIF_IFD, _FOCAL_35MM = 0x8769, 0xA405


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: The PNG chunks Pillow reads EXIF from: eXIf, and the text chunks ("Raw profile type exif").
_PNG_EXIF_CHUNKS = frozenset({b"eXIf", b"tEXt", b"zTXt", b"iTXt"})


def _png_without_exif(path: str | Path) -> bool:
    """True for a well-formed PNG file none of whose chunks can carry EXIF (`_PNG_EXIF_CHUNKS`), found from
    the chunk headers alone. Pillow looks for an eXIf chunk after the image data by decoding the whole
    image (`PngImageFile.getexif` loads it): twice the decoding for `exif_focal_35mm` on every PNG. False
    (Pillow decides) for anything else: other formats, such chunks, a truncated or malformed file."""
    try:
        with open(path, "rb") as fh:
            if fh.read(8) != _PNG_SIGNATURE:
                return False
            size = os.fstat(fh.fileno()).st_size
            while True:
                head = fh.read(8)
                if len(head) != 8:
                    return False
                length, kind = int.from_bytes(head[:4], "big"), head[4:]
                if kind in _PNG_EXIF_CHUNKS:
                    return False
                if kind == b"IEND":
                    return True
                pos = fh.seek(length + 4, os.SEEK_CUR)  # the data and the CRC
                if pos > size:
                    return False
    except OSError:
        return False


def exif_focal_35mm(path: str | Path) -> float | None:
    """The photo's 35 mm-equivalent focal length in mm (EXIF FocalLengthIn35mmFilm), or None.

    Read with Pillow from the file's header (JPEG, PNG eXIf, TIFF, WebP), in the Exif sub-IFD where the
    standard puts it or in IFD0 where some writers do. None when the file has no such tag, says 0
    ("unknown"), or cannot be parsed: a photo without it is not an error.
    """
    import warnings

    if _png_without_exif(path):
        return None
    from PIL import Image, UnidentifiedImageError

    try:
        with warnings.catch_warnings():  # Pillow's pixel-count guard: only the header is read here
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                exif = im.getexif()
                value = exif.get_ifd(_EXIF_IFD).get(_FOCAL_35MM, exif.get(_FOCAL_35MM))
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError, KeyError, TypeError,
            Image.DecompressionBombError):  # over ~179 MP Pillow refuses to open: no prior, as without EXIF
        return None
    try:
        mm = float(value[0] if isinstance(value, tuple) else value)
    except (TypeError, ValueError, IndexError):
        return None
    return mm if np.isfinite(mm) and mm > 0 else None


def upright_size(path: str | Path) -> tuple[int, int] | None:
    """(W, H) of an image as `read_image` returns it, without decoding its pixels: the size from its header
    (Pillow), turned where its EXIF orientation (`exif_orientation`, the rule `read_image` applies) turns it;
    None where Pillow cannot tell (the image's own checks report it when it is read)."""
    from PIL import Image

    path = Path(path)
    try:
        with Image.open(path) as im:
            w, h = im.size
        return (h, w) if exif_orientation(path.read_bytes()) in (5, 6, 7, 8) else (w, h)
    except (OSError, ValueError, SyntaxError):  # Pillow's errors on unreadable or odd files
        return None


def read_image(path: str | Path, *, gray_to_rgb: bool = True, apply_orientation: bool = True) -> np.ndarray:
    """Read an 8/16-bit image as float32 RGB in [0, 1], shape (H, W, 3).

    Grayscale files are replicated to three channels; an alpha channel that is opaque everywhere is dropped,
    and a photo with transparent pixels is refused (their colour, often black, is not a photo of the scene:
    denoised, aligned and splatted, it would be fitted as one). A JPEG's or WebP's EXIF
    Orientation tag is applied (the array is the photo as a viewer shows it) unless `apply_orientation` is
    False: then the array is the pixels as stored, which is what cameras calibrated by COLMAP (which
    ignores the tag) describe.

    Raises:
        InputError: missing, unreadable or corrupt file, or one with transparent pixels (named).
    """
    from mvgeo.common.deps import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError("image file does not exist", path=path)
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise InputError(f"cannot read the image file ({exc.strerror or exc})", path=path,
                         fix="check the file's permissions (e.g. `chmod u+r`)") from exc
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise InputError("cannot decode image (corrupt or unsupported format)", path=path,
                         fix="re-export it as PNG or JPEG, or remove it from the folder")
    if img.dtype == np.uint8:
        scale = 255.0
    elif img.dtype == np.uint16:
        scale = 65535.0
    else:
        raise InputError(f"unsupported pixel type {img.dtype}", path=path, fix="use 8- or 16-bit images")
    if img.ndim == 2:
        img = img[:, :, None]
    if apply_orientation:
        img = apply_exif_orientation(img, exif_orientation(data))
    if img.shape[2] == 4:  # cv2 gives gray + alpha and palette + transparency as BGRA too
        transparent = int(np.count_nonzero(img[:, :, 3] < np.iinfo(img.dtype).max))
        if transparent:
            raise InputError(f"the image has transparent pixels ({transparent} of {img.shape[0] * img.shape[1]}); "
                             "their colour is not a photo of the scene and would be reconstructed as one", path=path,
                             fix="flatten it onto a background (e.g. `magick IN -background white -alpha remove "
                                 "-alpha off OUT`), or re-export the photo without transparency")
        img = img[:, :, :3]
    if img.shape[2] == 1:
        if not gray_to_rgb:
            return (img.astype(np.float32) / scale)
        img = np.repeat(img, 3, axis=2)
    else:
        img = img[:, :, ::-1]
    return np.ascontiguousarray(img.astype(np.float32) / np.float32(scale))


def to_uint(img: np.ndarray, bits: int = 8) -> np.ndarray:
    """[0, 1] float -> uint8/uint16 with rounding and clipping."""
    if bits not in (8, 16):
        raise ValueError("bits must be 8 or 16")
    maxv = 255 if bits == 8 else 65535
    dtype = np.uint8 if bits == 8 else np.uint16
    return np.clip(np.rint(np.asarray(img, dtype=np.float64) * maxv), 0, maxv).astype(dtype)


def write_image(path: str | Path, img: np.ndarray, *, bits: int = 8) -> None:
    """Write an (H, W, 3) or (H, W) float image in [0, 1] (RGB) as PNG/JPEG.

    The file is written under a temporary sibling name and renamed onto `path`: an existing file there is
    replaced, never written into, so a hard link or a symbolic link at `path` keeps what it points to.
    """
    from mvgeo.common.atomic import atomic_write_bytes
    from mvgeo.common.deps import cv2

    path = Path(path)
    arr = to_uint(img, bits)
    if arr.ndim == 3:
        arr = arr[:, :, ::-1]
    ok, buf = cv2.imencode(path.suffix or ".png", np.ascontiguousarray(arr))
    if not ok:
        raise InputError("cannot encode image", path=path)
    atomic_write_bytes(path, buf.tobytes())
