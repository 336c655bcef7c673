"""Views rolled a quarter turn against the others (a camera held sideways): registered, and where.

Builds two folders from DTU scan24's square 384 x 384 photos (views 8-13 of `../shared/data/dtu_scan24`):
the photos as they are, and the same photos with view 10 turned a quarter counter-clockwise and view 12 a
quarter clockwise (`np.rot90`: for a square photo with its principal point at the centre, exactly the
photo a camera rolled by a quarter turn about its axis takes). Both are aligned with `mvgeo align`'s
defaults; for each view, the rolled solution's relative rotation to view 8 is compared with the unrolled
solution's after taking out the nearest quarter turn about the optical axis (0 for a view not rolled).

Usage: .venv/bin/python benchmarks/diag_rolled_views.py [--data ../shared/data] [--work DIR]
"""
import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

import mvgeo.common.deps  # noqa: F401  cv2 before pycolmap
from mvgeo.align.api import AlignConfig, align_images
from mvgeo.common.imageio import read_image, write_image
from mvgeo.metrics import rotation_error_deg

VIEWS = (8, 9, 10, 11, 12, 13)
TURNS = {10: 1, 12: 3}  # quarter turns counter-clockwise (np.rot90's k)


def _roll_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rotations(folder: Path) -> dict[str, np.ndarray]:
    res = align_images(sorted(folder.glob("*.png")), AlignConfig())
    return {im.name: im.cam_from_world[:3, :3] for im in res.sparse_model.images}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[1] / ".." / "shared" / "data")
    ap.add_argument("--work", type=Path, default=None, help="folder for the two photo folders (default: temporary)")
    args = ap.parse_args()
    src = args.data / "dtu_scan24" / "images"
    if not src.is_dir():
        print(f"error: {src} is missing (DTU scan24 from ../shared/data)", file=sys.stderr)
        return 2
    work = args.work or Path(tempfile.mkdtemp(prefix="rolled-"))
    plain, rolled = work / "plain", work / "rolled"
    for folder in (plain, rolled):
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
    for v in VIEWS:
        img = read_image(src / f"{v:06d}.png")
        write_image(plain / f"v{v:02d}.png", img)
        write_image(rolled / f"v{v:02d}.png", np.ascontiguousarray(np.rot90(img, TURNS.get(v, 0))))
    a, b = _rotations(plain), _rotations(rolled)
    print(f"registered: {len(a)}/{len(VIEWS)} as they are, {len(b)}/{len(VIEWS)} with views 10 and 12 rolled\n")
    print("| view | rolled (quarter turns) | found (deg) | off the unrolled solution (deg) |")
    print("|---|---|---|---|")
    ref = "v08.png"
    for name in sorted(a):
        if name not in b:
            print(f"| {name} | {TURNS.get(int(name[1:3]), 0)} | not registered | |")
            continue
        Z = (b[name] @ b[ref].T) @ (a[name] @ a[ref].T).T  # the roll between the two solutions' views
        turn = 90.0 * round(np.degrees(np.arctan2(Z[1, 0], Z[0, 0])) / 90.0)
        print(f"| {name} | {TURNS.get(int(name[1:3]), 0)} | {turn:+.0f} | "
              f"{float(rotation_error_deg(_roll_z(turn), Z)):.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
